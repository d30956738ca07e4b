"""A scan request too large to carry out is refused with its limit named, and the driver
stays alive to carry out the next one (the driver as its own process, over DDS)."""

import sys
import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from galvoscan_msgs.srv import GetScanProgress, StartScan
from rclpy.node import Node

pytestmark = pytest.mark.dds


def _call(ex, client, request, timeout=90.0):
    # generous: on a fresh clone the driver's first scan compiles the simulator's kernels
    fut = client.call_async(request)
    ex.spin_until_future_complete(fut, timeout_sec=timeout)
    assert fut.result() is not None, 'no answer'
    return fut.result()


def test_huge_scans_are_refused_and_the_next_completes(spawn, ros_env, tmp_path):
    proc = spawn([sys.executable, '-m', 'galvo_driver.driver_node', '--ros-args',
                  '-p', 'backend:=sim', '-p', 'scene:=plane'], name='driver')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('limits_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        start = node.create_client(StartScan, 'scan/start')
        progress = node.create_client(GetScanProgress, 'scan/progress')
        assert start.wait_for_service(timeout_sec=60), proc.log_path.read_text()
        deadline = time.monotonic() + 30
        while 'active' not in proc.log_path.read_text():
            assert time.monotonic() < deadline, proc.log_path.read_text()
            time.sleep(0.1)
        # 4e9 x 4e9 steps: 1.6e19 frames, a table of 5e20 bytes if it were built
        huge = StartScan.Request(pattern='raster', steps_pan=4_000_000_000,
                                 steps_tilt=4_000_000_000, g1_pan_min=-1.0, g1_pan_max=1.0,
                                 frame_rate=500.0, laser_on=True)
        resp = _call(ex, start, huge)
        assert not resp.success and 'max_scan_frames' in resp.message, resp.message
        # under the frame limit but 2e6 frames at 1 Hz last 23 days
        slow = StartScan.Request(pattern='g1_grid', steps_pan=1000, steps_tilt=2000,
                                 frame_rate=1.0)
        resp = _call(ex, start, slow)
        assert not resp.success and 'max_scan_duration' in resp.message, resp.message
        bad = StartScan.Request(pattern='g2_sweep', steps_tilt=0, frame_rate=10.0)
        resp = _call(ex, start, bad)
        assert not resp.success and 'steps_tilt' in resp.message, resp.message
        assert proc.poll() is None
        ok = StartScan.Request(pattern='g2_sweep', g2_tilt_min=-0.1, g2_tilt_max=0.1,
                               steps_tilt=20, frame_rate=200.0, laser_on=True)
        resp = _call(ex, start, ok)
        assert resp.success and resp.frames_total == 20, resp.message
        deadline = time.monotonic() + 30
        while True:
            p = _call(ex, progress, GetScanProgress.Request())
            if p.state == 'done':
                break
            assert time.monotonic() < deadline, p.message
            time.sleep(0.1)
        assert p.frames_done == 20 and p.frames_dropped == 0
        # the driver's diagnostics count what it published; refusals are answers, not failures
        diag = []
        node.create_subscription(DiagnosticArray, 'diagnostics', diag.append, 10)
        deadline = time.monotonic() + 10
        while not diag and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
        values = {kv.key: kv.value for kv in diag[0].status[0].values}
        assert diag[0].status[0].name == 'galvo_driver: galvo driver'
        assert values['frames_published'] == '20' and values['scans'] == '1', values
        assert values['callback_errors'] == '0' and values['scan/state'] == 'done', values
        assert proc.poll() is None
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
