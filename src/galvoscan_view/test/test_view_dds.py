"""System test: ``galvoscan view`` joins a running graph over DDS and serves it to Foxglove.

Real processes on a private ROS domain: the simulated graph (``galvoscan run
--one-process``), ``galvoscan view`` on an ephemeral port, scans started with
``galvoscan scan``; a raw WebSocket client offering only the older subprotocol name
subscribes to the cloud and the galvo state as Lichtblick would, and decodes what arrives.
"""

import json
import signal
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from websockets.sync.client import connect

from galvoscan_common import cdr
from galvoscan_common.cdr import parse_point_cloud
from galvoscan_sim import load_rig, patterns
from galvoscan_view.view_node import cloud_xyz

pytestmark = pytest.mark.dds
SEED = 7
GALVOSCAN = [sys.executable, '-m', 'galvoscan.cli']


def _graph_params(tmp_path, sim_graph_params):
    params = sim_graph_params(seed=SEED, reconstructor={'scan_end_timeout': 0.5})
    scan = tmp_path / 'scan.csv'
    np.savetxt(scan, patterns.synchronised(load_rig('reference'), [0.0, 0.4], -0.3, steps=6,
                                           tilt_step=0.05), delimiter=',')
    return params, scan


def _messages(ws, subs, until):
    """messageData payloads by topic, read until ``until`` (monotonic) passes."""
    got = {t: [] for t in subs.values()}
    while time.monotonic() < until:
        try:
            frame = ws.recv(timeout=0.2)
        except TimeoutError:
            continue
        if isinstance(frame, bytes) and frame[0] == 1:
            sub = struct.unpack_from('<I', frame, 1)[0]
            got[subs[sub]].append(frame[13:])
    return got


def test_view_serves_the_clouds_of_a_scan_to_a_websocket_client(spawn, ros_env, tmp_path,
                                                                 sim_graph_params,
                                                                 logged_port):
    params, scan_csv = _graph_params(tmp_path, sim_graph_params)
    graph = spawn([*GALVOSCAN, 'run', '--one-process', '--params', params], name='graph')
    view = spawn([*GALVOSCAN, 'view', '--host', '127.0.0.1', '--ws-port', '0',
                  '--no-browser-page'], name='view')
    port = logged_port(view, 'Foxglove WebSocket')
    with connect(f'ws://127.0.0.1:{port}', subprotocols=['foxglove.websocket.v1'],
                 max_size=None, open_timeout=30) as ws:
        assert ws.subprotocol == 'foxglove.websocket.v1'
        assert json.loads(ws.recv(timeout=30))['op'] == 'serverInfo'
        advertise = json.loads(ws.recv(timeout=30))
        assert advertise['op'] == 'advertise'
        channels = {c['topic']: c for c in advertise['channels']}
        assert channels['/points']['schemaName'] == 'sensor_msgs/msg/PointCloud2'
        subs = {1: '/points', 2: '/galvo/state'}
        ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': i, 'channelId': channels[t]['id']} for i, t in subs.items()]}))

        # discovery takes its time: short scans until the clouds come through the view
        got = {'/points': []}
        deadline = time.monotonic() + 120
        while not any(got['/points']):
            assert time.monotonic() < deadline, (view.log_path.read_text(),
                                                 graph.log_path.read_text())
            assert graph.poll() is None and view.poll() is None
            scan = subprocess.run([*GALVOSCAN, 'scan', '--pattern', 'custom', '--voltages',
                                   scan_csv, '--rate', '25', '--timeout', '30'],
                                  env=ros_env, capture_output=True, text=True, timeout=90)
            got = _messages(ws, subs, time.monotonic() + 2.0)
    assert scan.returncode == 0, scan.stdout + scan.stderr

    header, points = parse_point_cloud(max(got['/points'], key=len))
    xyz, _ = cloud_xyz(points)
    assert header.frame_id == 'v0'
    assert len(xyz) > 0 and np.isfinite(xyz).all()
    # the stair block lies 0.5 to 0.8 m in front of the scanner
    assert 0.5 < np.median(xyz[:, 2]) < 0.8, np.median(xyz[:, 2])
    states = [cdr.parse_galvo_state(d) for d in got['/galvo/state']]
    assert states and all(s.laser_on for s in states)

    view.send_signal(signal.SIGTERM)
    assert view.wait(timeout=20) == 0, view.log_path.read_text()
    assert 'Traceback' not in view.log_path.read_text()
