"""The driver node on the serial backend, against the firmware emulator in another process.

A scan's frames carry the board's voltages over DDS, and SIGINT or SIGTERM to the driver
leaves the board at 0 V with the laser off, commanded by the driver itself (not by the
watchdog, which is the SIGKILL path).
"""

import json
import signal
import sys
import time

import numpy as np
import pytest
import rclpy
from galvoscan_msgs.msg import GalvoState
from galvoscan_msgs.srv import GetScanProgress, StartScan
from rclpy.node import Node

from galvo_driver.serial_link.protocol import codes_to_volts, volts_to_codes
from galvoscan_common.executor import call_service

pytestmark = pytest.mark.dds


def _wait_line(path, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = path.read_text() if path.exists() else ''
        if '\n' in text:
            return text.splitlines()[0].strip()
        time.sleep(0.05)
    raise AssertionError(f'no output in {path}')


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_driver_scan_then_signal_leaves_board_safe(spawn, ros_env, tmp_path, sig):
    emu_log = tmp_path / 'emu.jsonl'
    # 0.5 s: ten heartbeat periods. At 0.15 s a busy 2-core machine (a full test run beside
    # other work) starved the heartbeat thread long enough to trip it in mid-scan.
    emu = spawn([sys.executable, '-m', 'galvo_driver.serial_link.emulator', '--pty',
                 '--watchdog', '0.5', '--log', emu_log], name='emulator')
    port = _wait_line(emu.log_path)
    driver = spawn([sys.executable, '-m', 'galvo_driver.driver_node', '--ros-args',
                    '-p', 'backend:=serial', '-p', f'serial_port:={port}'], name='driver')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('driver_serial_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    states = []
    try:
        node.create_subscription(GalvoState, 'galvo/state', states.append, 500)
        rng = np.random.default_rng(3)
        volts = rng.uniform(-9.5, 9.5, size=(400, 4))
        req = StartScan.Request(pattern='custom', voltages=volts.ravel().tolist(),
                                frame_rate=200.0, laser_on=True)
        progress_client = node.create_client(GetScanProgress, 'scan/progress')
        resp = call_service(ex, node.create_client(StartScan, 'scan/start'), req, timeout=20.0,
                            resend=True)
        assert resp.success, resp.message + driver.log_path.read_text()
        assert resp.frames_total == 400
        deadline = time.monotonic() + 20
        while len(states) < 100 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert len(states) >= 100, driver.log_path.read_text()
        progress = call_service(ex, progress_client, GetScanProgress.Request(), timeout=20.0,
                                resend=True)
        assert progress.state == 'running' and progress.frames_total == 400

        # every received frame carries exactly the DAC-quantised voltages of its row
        quantised = codes_to_volts(volts_to_codes(volts))
        seqs = np.array([s.seq for s in states])
        got = np.array([[s.g1_pan_voltage, s.g1_tilt_voltage, s.g2_pan_voltage,
                         s.g2_tilt_voltage] for s in states])
        index = seqs - seqs.min()  # first scan of this driver: seq counts triggers
        np.testing.assert_array_equal(got, quantised[index])
        assert all(s.laser_on for s in states)

        driver.send_signal(sig)
        assert driver.wait(timeout=15) is not None
        time.sleep(0.5)  # the emulator logs what it applied
        entries = [json.loads(line) for line in emu_log.read_text().splitlines()]
        last = entries[-1]
        assert last['volts'] == [0.0, 0.0, 0.0, 0.0] and last['laser'] is False, last
        # the driver's own shutdown path made it safe, before any watchdog trip
        reasons = [e['reason'] for e in entries]
        assert 'safe' in reasons
        assert 'watchdog' not in reasons[:reasons.index('safe') + 1]
        assert emu.poll() is None
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
