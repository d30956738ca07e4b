"""System test: the README's tour gives a cloud, and a first run says which calibration it uses.

``galvoscan run`` with no parameters (the simulated reference rig) in separate processes,
then the tour's ``galvoscan scan --pattern raster ...`` exactly as the README shows it. The
calibration that ``galvoscan calibrate`` wrote last is recorded in a private state directory
(the simulator's true calibration stands in for the one ``make demo`` computes, which takes
minutes). A listener of its own checks that the cloud on ``points/scan`` holds the points the
scan client reports, and a Foxglove client (Foxglove's own WebSocket protocol and ROS 2 CDR
libraries, ``tools/foxglove_client``) connected to ``galvoscan view`` draws that cloud.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from galvoscan import bringup, calibration_memory
from galvoscan_common import cdr

pytestmark = pytest.mark.dds
GALVOSCAN = [sys.executable, '-m', 'galvoscan.cli']
TOUR_SCAN = ['scan', '--pattern', 'raster', '--g1-pan', '-1', '1', '--g1-tilt', '-0.3', '0.3',
             '--g2-tilt', '-0.2', '0.4', '--steps-pan', '3', '--steps-tilt', '12']
FOXGLOVE_CLIENT = Path(__file__).resolve().parents[1] / 'tools' / 'foxglove_client'


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture
def state_dir(tmp_path, monkeypatch):
    state = tmp_path / 'state'
    monkeypatch.setenv('GALVOSCAN_STATE_DIR', str(state))
    return state


def test_the_readme_tour_gives_a_cloud_on_points_scan(spawn, ros_env, tmp_path, state_dir):
    from galvoscan.simulated_rig import truth_calibration
    from galvoscan_sim import load_rig
    from reconstructor import calibration_file

    cal = tmp_path / 'cal.yaml'
    calibration_file.save(truth_calibration(load_rig('reference')), cal)
    assert calibration_memory.remember_from_command(
        'calibrate', ['all', '--sim', '--calibration', str(cal)]) is not None

    graph = spawn([*GALVOSCAN, 'run', '--log-dir', tmp_path / 'logs'], name='galvoscan_run',
                  env={'GALVOSCAN_STATE_DIR': str(state_dir)})
    ws_port = _free_port()
    view = spawn([*GALVOSCAN, 'view', '--ws-port', ws_port, '--no-browser-page'],
                 name='galvoscan_view')
    env = {**ros_env, 'GALVOSCAN_STATE_DIR': str(state_dir)}

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('tour_listener', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    clouds = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(
        PointCloud2, 'points/scan',
        lambda raw: clouds.append(cdr.parse_point_cloud(raw)[1].shape[0]), latched, raw=True)
    try:
        # the extractor subscribes once its kernels are compiled
        deadline = time.monotonic() + 90
        while node.count_subscribers('camera/image_raw') == 0 or \
                node.count_publishers('points/scan') == 0:
            assert time.monotonic() < deadline and graph.poll() is None, \
                graph.log_path.read_text()
            ex.spin_once(timeout_sec=0.2)
        said = graph.log_path.read_text()
        assert f'reconstructor uses the calibration galvoscan calibrate wrote last: {cal}' \
            in said, said
        # the first frames after start-up may meet a cold extractor: scan until points come
        for _attempt in range(3):
            scan = subprocess.run([*GALVOSCAN, *TOUR_SCAN], env=env, capture_output=True,
                                  text=True, timeout=120)
            assert scan.returncode == 0, scan.stdout + scan.stderr
            reported = re.search(r'points/scan: (\d+) points in frame v0', scan.stdout)
            if reported:
                break
            assert 'points/scan: no cloud came back' in scan.stderr, scan.stderr
        assert reported, scan.stdout + scan.stderr + graph.log_path.read_text()[-3000:]
        deadline = time.monotonic() + 10
        while int(reported.group(1)) not in clouds and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
        assert int(reported.group(1)) in clouds and int(reported.group(1)) > 0, clouds
        assert '36/36 frames' in scan.stdout

        # a Foxglove client on galvoscan view draws the same cloud
        assert shutil.which('node') and (FOXGLOVE_CLIENT / 'node_modules').is_dir(), \
            'node and tools/foxglove_client/node_modules come with make setup'
        assert view.poll() is None, view.log_path.read_text()
        png = tmp_path / 'foxglove_cloud.png'
        drawn = subprocess.run(
            ['node', FOXGLOVE_CLIENT / 'draw_cloud.mjs', '--url', f'ws://127.0.0.1:{ws_port}',
             '--topic', 'points/scan', '--png', png, '--timeout', '30',
             '--min-points', reported.group(1)],
            capture_output=True, text=True, timeout=60)
        assert drawn.returncode == 0, drawn.stdout + drawn.stderr + view.log_path.read_text()
        seen = json.loads(drawn.stdout.splitlines()[-1])
        assert seen['points'] == int(reported.group(1)) == seen['finite'], seen
        assert seen['frame_id'] == 'v0' and seen['schema'] == 'sensor_msgs/msg/PointCloud2'
        assert seen['pixels_drawn'] > 1000, seen      # the stair's surfaces, not a few dots
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_a_scan_with_no_reconstructor_says_so(spawn, ros_env, tmp_path, state_dir):
    graph = spawn([*GALVOSCAN, 'run', '--nodes', 'galvo_driver'], name='driver_only')
    scan = subprocess.run([*GALVOSCAN, 'scan', '--pattern', 'g2_sweep', '--steps-tilt', '3',
                           '--cloud-timeout', '2'],
                          env=ros_env, capture_output=True, text=True, timeout=120)
    assert scan.returncode == 0, scan.stdout + scan.stderr + graph.log_path.read_text()
    assert 'points/scan: no cloud came back within 2 s: no reconstructor answered' \
        in scan.stderr, scan.stderr


def test_the_reconstructor_starts_from_the_last_calibration_of_its_rig_or_design_values(
        tmp_path, state_dir, caplog):
    import yaml

    cal = tmp_path / 'out' / 'calibration.yaml'
    cal.parent.mkdir()
    cal.write_text('format_version: 1\n')
    nodes = list(bringup.DEFAULT_NODES)

    def started_with(params):
        path = bringup.with_reconstructor_calibration(params, nodes, tmp_path / 'run')
        return yaml.safe_load(open(path))['reconstructor']['ros__parameters']['calibration_file']

    # nothing made yet: the design values, and it says so
    with caplog.at_level('INFO', logger='galvoscan.bringup'):
        design = started_with(None)
    assert design.endswith('design_values.yaml') and 'design values of sim rig reference' \
        in caplog.text
    # after `galvoscan demo`: its calibration, for the rig it was made for only
    assert calibration_memory.remember_from_command('demo', ['--out', str(tmp_path / 'out')])
    assert started_with(None) == str(cal.resolve())
    other = tmp_path / 'other.yaml'
    other.write_text(yaml.safe_dump({'galvo_driver': {'ros__parameters': {'rig': 'ideal'}}}))
    assert started_with(other).endswith('design_values.yaml')
    # a calibration named in the parameters is used as it is
    given = tmp_path / 'given.yaml'
    given.write_text(yaml.safe_dump({'reconstructor': {'ros__parameters': {
        'calibration_file': '/cal/of/the/user.yaml'}}}))
    assert bringup.with_reconstructor_calibration(given, nodes, tmp_path / 'run') == given
    # a file that has gone is not used
    cal.unlink()
    assert started_with(None).endswith('design_values.yaml')
    # a real rig gets nothing it did not ask for
    real = tmp_path / 'real.yaml'
    real.write_text(yaml.safe_dump({'galvo_driver': {'ros__parameters': {'backend': 'rig'}}}))
    assert bringup.with_reconstructor_calibration(real, nodes, tmp_path / 'run') == real


def test_a_nodes_warnings_and_errors_reach_the_console(tmp_path):
    import io
    import threading

    log = tmp_path / 'reconstructor.log'
    log.write_bytes(b'[INFO] [0.9] [reconstructor]: from an earlier run\n')
    start = log.stat().st_size
    done = threading.Event()
    console = io.StringIO()
    follower = threading.Thread(target=bringup.follow_log, args=(
        log, start, 'reconstructor', done.is_set, console, 0.01))
    follower.start()
    with open(log, 'ab') as node:               # the node writes as it goes, half lines too
        for chunk in (b'[INFO] [1.0] [reconstructor]: loaded\n[ERROR] [1.1] [recon',
                      b'structor]: no calibration_file given\n',
                      b'[WARN] [1.2] [reconstructor]: skipping frame: laser_off\n',
                      b'Traceback (most recent call last):\n  File "x.py", line 1'):
            node.write(chunk)
            node.flush()
            time.sleep(0.05)
    done.set()
    follower.join(5)
    assert not follower.is_alive()
    assert console.getvalue().splitlines() == [
        '[reconstructor] [ERROR] [1.1] [reconstructor]: no calibration_file given',
        '[reconstructor] [WARN] [1.2] [reconstructor]: skipping frame: laser_off',
        '[reconstructor] Traceback (most recent call last):',
        '[reconstructor]   File "x.py", line 1']


def test_a_nodes_error_reaches_the_console_and_the_scan_says_why_no_points_came(
        spawn, ros_env, tmp_path):
    import yaml

    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'reconstructor': {'ros__parameters': {
        'calibration_file': str(tmp_path / 'no_such_calibration.yaml')}}}))
    run = spawn([*GALVOSCAN, 'run', '--nodes', 'galvo_driver,reconstructor', '--params', params,
                 '--log-dir', tmp_path / 'logs'], name='galvoscan_run')
    deadline = time.monotonic() + 60
    line = re.compile(r'^\[reconstructor\] \[(ERROR|WARN)\].*no_such_calibration', re.M)
    while not line.search(run.log_path.read_text()):
        assert time.monotonic() < deadline and run.poll() is None, run.log_path.read_text()
        time.sleep(0.2)
    assert 'no_such_calibration' in (tmp_path / 'logs' / 'reconstructor.log').read_text()
    assert '[reconstructor] [INFO]' not in run.log_path.read_text()

    scan = subprocess.run([*GALVOSCAN, 'scan', '--pattern', 'g2_sweep', '--steps-tilt', '3',
                           '--cloud-timeout', '3'],
                          env=ros_env, capture_output=True, text=True, timeout=120)
    assert scan.returncode == 0, scan.stdout + scan.stderr
    assert 'points/scan: no cloud came back within 3 s: the reconstructor has no calibration ' \
        'loaded' in scan.stderr, scan.stderr + run.log_path.read_text()
