"""System test: ``galvoscan run`` on a rig with the laser beside the camera scans correctly
with nothing set for it.

A family rig with the laser left of the camera (the stripe along the image columns, moved
sideways by G2) on the ``sim`` backend, facing a matt wall at its working point, its
reconstructor given the rig's calibration; the parameters file names neither the
extractor's ``orientation`` nor the driver's ``raster_g1_axis``. The bring-up reads them from
the calibration, so the synchronised raster (``galvoscan scan --pattern raster``) steps G1's
pan with G2, the extractor takes one centre per image row, and the cloud on ``points/scan``
lies on the wall, spread over the pan range.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from galvoscan.simulated_rig import truth_calibration
from galvoscan_common import cdr
from galvoscan_sim.rig import rig_from_dict
from galvoscan_sim.rig_family import draw_rig, working_point
from reconstructor import calibration_file
from reconstructor.cloud import xyz
from reconstructor.model import v0_T_v
from reconstructor.planning import aim_laser

pytestmark = pytest.mark.dds
GALVOSCAN = [sys.executable, '-m', 'galvoscan.cli']
PAN = (-0.4, 0.4)   # G1 pan range of the raster [V]
#: A stripe of ~500 rows in each of the raster's 24 frames (one centre per row: the
#: columns' way).
MIN_POINTS = 24 * 300


def test_a_laser_beside_rig_scans_a_wall_with_nothing_set_for_it(spawn, ros_env, tmp_path):
    data = draw_rig(3, 0.45, build={'sensor': 'IMX287', 'bit_depth': 8, 'laser': 'left'})
    rig_file = tmp_path / 'beside.yaml'
    rig_file.write_text(yaml.safe_dump(data))
    cal = truth_calibration(rig_from_dict(data, 'beside'))
    cal_file = tmp_path / 'cal.yaml'
    calibration_file.save(cal, cal_file)
    depth = float(working_point(data)[2])
    scene = tmp_path / 'wall.yaml'
    scene.write_text('format_version: 1\nname: wall\nobjects:\n  - type: plane\n'
                     f'    name: wall\n    pose: {{translation: [0, 0, {depth:.6f}]}}\n'
                     '    size: [3.0, 3.0]\n    albedo: 0.5\n')
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': str(rig_file),
                                             'scene': str(scene)}},
        'reconstructor': {'ros__parameters': {'calibration_file': str(cal_file)}}}))
    # the G2 tilt that keeps the stripe on the view's axis at either end of the pan range
    g2 = [aim_laser(cal.model, pan, 0.0, depth) for pan in PAN]

    graph = spawn([*GALVOSCAN, 'run', '--params', params, '--log-dir', tmp_path / 'logs'],
                  name='galvoscan_run')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('beside_listener', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    clouds = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(PointCloud2, 'points/scan',
                             lambda raw: clouds.append(xyz(cdr.parse_point_cloud(raw)[1])),
                             latched, raw=True)
    try:
        deadline = time.monotonic() + 90
        while node.count_subscribers('camera/image_raw') == 0 or \
                node.count_publishers('points/scan') == 0:
            assert time.monotonic() < deadline and graph.poll() is None, \
                graph.log_path.read_text()
            ex.spin_once(timeout_sec=0.2)
        assert 'the stripe runs along the image columns' in graph.log_path.read_text()
        scan_args = [*GALVOSCAN, 'scan', '--pattern', 'raster', '--g1-pan', *map(str, PAN),
                     '--g1-tilt', '-0.2', '0.2', '--g2-tilt', *map(str, g2),
                     '--steps-pan', '12', '--steps-tilt', '2']
        # the first frames may meet a cold extractor: no cloud, or a cloud short of frames
        for _attempt in range(3):
            scan = subprocess.run([str(a) for a in scan_args], env=ros_env,
                                  capture_output=True, text=True, timeout=120)
            assert scan.returncode == 0, scan.stdout + scan.stderr
            reported = re.search(r'points/scan: (\d+) points in frame v0', scan.stdout)
            if reported and int(reported.group(1)) >= MIN_POINTS:
                break
        assert reported, scan.stdout + scan.stderr + graph.log_path.read_text()[-3000:]
        deadline = time.monotonic() + 10
        n = int(reported.group(1))
        while not any(len(c) == n for c in clouds) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
        p = next(c for c in clouds if len(c) == n)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    assert n >= MIN_POINTS, scan.stdout
    centre = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
    residual = (p - centre) @ vt[2]
    assert np.sqrt(np.mean(residual ** 2)) < 2e-4, 'the points do not lie on the wall'
    # spread along x by the pan steps (the frames' stripes side by side), as far as G1's
    # view axis moves over the pan range
    ends = []
    for pan in PAN:
        T = v0_T_v(cal.model, pan, 0.0)
        ends.append(T[:3, 3] + (depth - T[2, 3]) / T[2, 2] * T[:3, 2])
    span = abs(ends[1][0] - ends[0][0])
    assert span > 0.01 and np.ptp(p[:, 0]) > 0.8 * span, (np.ptp(p, axis=0), span)
