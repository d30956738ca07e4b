"""The driver node on the ``rig`` backend in its own process: the galvo board emulator on a
pty and the fake GigE Vision camera, the board's trigger output wired to the camera's
``Line0`` input. A subscriber in this process checks every published frame's GalvoState
against the emulator's record of the trigger that exposed that frame's image.

The truth of an image is the instant of the line edge that exposed it, which the fake
camera writes into the image's first bytes (``fake_camera.edge_of``); the test recorded
which trigger sent that edge. So a frame the driver tagged with the wrong trigger's
voltages fails here, however the driver paired it.
"""

import gc
import sys
import time

import numpy as np
import pytest
import rclpy
from galvoscan_msgs.msg import GalvoState
from galvoscan_msgs.srv import GetScanProgress, StartScan
from rclpy.node import Node
from sensor_msgs.msg import Image

from galvo_driver.fake_camera import FakeCamera, edge_at, edge_of
from galvo_driver.serial_link.emulator import FirmwareEmulator
from galvo_driver.serial_link.protocol import codes_to_volts

pytestmark = pytest.mark.dds

SERIAL = 'GSRIGDDS'
ROWS, RATE = 300, 200.0  # [1], [Hz]


def _call(node, ex, srv_type, name, request, timeout=20.0):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=timeout), name
    fut = client.call_async(request)
    ex.spin_until_future_complete(fut, timeout_sec=timeout)
    assert fut.result() is not None, name
    return fut.result()


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_rig_driver_publishes_frames_tagged_with_their_triggers(spawn, ros_env):
    edges = {}  # edge instant [ns] -> emulator trigger time t
    gc.collect()  # the emulator runs in this process: see test_rig_backend.fake
    gc.freeze()
    try:
        _run(spawn, ros_env, edges)
    finally:
        gc.unfreeze()


def _run(spawn, ros_env, edges):
    with FakeCamera(SERIAL, width=64, height=32) as fake:
        def wire(index, t):  # the board's trigger output -> the camera's Line0
            edge = edge_at(t)
            edges[edge] = t
            fake.pulse_line(edge)

        emu = FirmwareEmulator('pty', seed=11, on_trigger=wire, watchdog=1.0)
        with emu:
            driver = spawn([sys.executable, '-m', 'galvo_driver.driver_node', '--ros-args',
                            '-p', 'backend:=rig', '-p', f'serial_port:={emu.port}',
                            '-p', f'camera_serial:={SERIAL}', '-p', 'camera_clock:=host',
                            '-p', 'ExposureTime:=300.0', '-p', 'PixelFormat:=Mono8'],
                           name='driver')
            _scan_and_check(driver, emu, edges, ros_env)


def _scan_and_check(driver, emu, edges, ros_env):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('rig_dds_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    states, images = {}, {}
    try:
        node.create_subscription(GalvoState, 'galvo/state',
                                 lambda m: states.__setitem__(_stamp(m), m), 1000)
        node.create_subscription(Image, 'camera/image_raw',
                                 lambda m: images.__setitem__(_stamp(m), m), 1000)
        volts = np.random.default_rng(5).uniform(-9.0, 9.0, (ROWS, 4))
        req = StartScan.Request(pattern='custom', voltages=volts.ravel().tolist(),
                                frame_rate=RATE, laser_on=True)
        resp = _call(node, ex, StartScan, 'scan/start', req, timeout=30.0)
        assert resp.success, resp.message + driver.log_path.read_text()
        deadline = time.monotonic() + ROWS / RATE + 15.0
        state = 'running'
        while state == 'running' and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
            state = _call(node, ex, GetScanProgress, 'scan/progress',
                          GetScanProgress.Request()).state
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # the last messages on their way
            ex.spin_once(timeout_sec=0.05)
        log = driver.log_path.read_text()
        assert state == 'done', state + log

        records = {r.t: r for r in emu.triggers()}
        assert images and set(images) <= set(states), log  # every image has its state
        checked = 0
        for stamp, img in images.items():
            assert img.encoding == 'mono8' and (img.height, img.width) == (32, 64)
            edge = edge_of(np.frombuffer(bytes(img.data), np.uint8))
            rec = records[edges[edge]]
            st = states[stamp]
            got = [st.g1_pan_voltage, st.g1_tilt_voltage, st.g2_pan_voltage,
                   st.g2_tilt_voltage]
            np.testing.assert_array_equal(got, codes_to_volts(np.array(rec.codes)))
            assert st.seq == rec.index and st.laser_on == rec.laser_on
            checked += 1
        # a loaded machine makes the fake camera miss triggers; a few must come through
        assert checked >= 10, log
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
