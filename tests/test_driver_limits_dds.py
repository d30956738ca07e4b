"""A scan request too large to carry out is refused with its limit named, and the driver
stays alive to carry out the next one; a resent start (its answer lost) is answered again
and starts nothing (the driver as its own process, over DDS)."""

import sys
import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from galvoscan_msgs.srv import GetScanProgress, StartScan
from rclpy.node import Node

from galvoscan_common.executor import call_service

pytestmark = pytest.mark.dds


def _call(ex, client, request, timeout=90.0):
    # generous: on a fresh clone the driver's first scan compiles the simulator's kernels
    return call_service(ex, client, request, timeout, resend=True)


def _driver(spawn, ros_env):
    proc = spawn([sys.executable, '-m', 'galvo_driver.driver_node', '--ros-args',
                  '-p', 'backend:=sim', '-p', 'scene:=plane'], name='driver')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('limits_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    start = node.create_client(StartScan, 'scan/start')
    progress = node.create_client(GetScanProgress, 'scan/progress')
    assert start.wait_for_service(timeout_sec=60), proc.log_path.read_text()
    deadline = time.monotonic() + 30
    while 'active' not in proc.log_path.read_text():
        assert time.monotonic() < deadline, proc.log_path.read_text()
        time.sleep(0.1)
    return proc, ctx, node, ex, start, progress


def _until_done(ex, progress, timeout=30.0):
    deadline = time.monotonic() + timeout
    while True:
        p = _call(ex, progress, GetScanProgress.Request())
        if p.state != 'running':
            return p
        assert time.monotonic() < deadline, p.message
        time.sleep(0.1)


def test_huge_scans_are_refused_and_the_next_completes(spawn, ros_env, tmp_path):
    proc, ctx, node, ex, start, progress = _driver(spawn, ros_env)
    try:
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
        p = _until_done(ex, progress)
        assert p.state == 'done' and p.frames_done == 20 and p.frames_dropped == 0
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


def test_a_resent_start_is_answered_again_and_starts_nothing(spawn, ros_env):
    proc, ctx, node, ex, start, progress = _driver(spawn, ros_env)

    def sweep(request_id, steps=20):
        return StartScan.Request(pattern='g2_sweep', g2_tilt_min=-0.1, g2_tilt_max=0.1,
                                 steps_tilt=steps, frame_rate=200.0, laser_on=True,
                                 request_id=request_id)

    def once(request):  # each call here is what a resend after a lost answer looks like
        return call_service(ex, start, request, timeout=90.0, resend=True)

    try:
        first = once(sweep('a1'))
        assert first.success and first.frames_total == 20, first.message
        again = once(sweep('a1'))  # while the scan runs: not "still running"
        assert (again.success, again.scan_id, again.frames_total, again.message) == (
            True, first.scan_id, first.frames_total, first.message)
        p = _until_done(ex, progress)
        assert (p.state, p.scan_id, p.frames_done) == ('done', first.scan_id, 20)
        again = once(sweep('a1'))  # after it ended: still the first answer, no new scan
        assert again.success and again.scan_id == first.scan_id
        assert _call(ex, progress, GetScanProgress.Request()).state == 'done'
        other = once(sweep('a1', steps=30))  # the same id for another request
        assert not other.success and 'already used' in other.message, other.message
        assert _call(ex, progress, GetScanProgress.Request()).state == 'done'
        huge = once(sweep('x' * 100_000))  # an absurd id: refused, not kept, nothing started
        assert not huge.success and '100000 characters' in huge.message, huge.message
        assert _call(ex, progress, GetScanProgress.Request()).scan_id == first.scan_id
        # a new id is a new scan
        second = once(sweep('a2'))
        assert second.success and second.scan_id != first.scan_id, second.message
        p = _until_done(ex, progress)
        assert (p.scan_id, p.frames_done) == (second.scan_id, 20)
        assert "'a1' resent" in proc.log_path.read_text()
        assert proc.poll() is None
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
