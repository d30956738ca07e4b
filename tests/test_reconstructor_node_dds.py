"""The reconstructor node as a real process: clouds in V0, bad input skipped, scan saving."""

import math
import sys
import time

import numpy as np
import open3d as o3d
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from galvoscan_msgs.msg import StripeCenters
from galvoscan_msgs.srv import LoadCalibration, SaveScan
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2

from galvoscan_common.executor import call_service
from reconstructor import calibration_file
from reconstructor.cloud import CLOUD_DTYPE
from reconstructor.model import (
    laser_plane_v0,
    nominal_example_rig,
    predict_pixels,
    transform_plane,
    v0_T_v,
)

pytestmark = pytest.mark.dds


def stripe_points(model, volts, n=40, depth=0.65):
    """V0 points on the laser plane, seen by the camera at ``volts``."""
    T = v0_T_v(model, volts[0], volts[1])
    a, b, c, e = transform_plane(T, laser_plane_v0(model, volts[3]))
    x = np.linspace(-0.02, 0.02, n)
    y = -(a * x + c * depth + e) / b
    p_v = np.column_stack([x, y, np.full(n, depth), np.ones(n)])
    return (T @ p_v.T).T[:, :3]


def centers_msg(model, volts, seq, points):
    uv, ok = predict_pixels(model, points, volts[0], volts[1])
    assert ok.all()
    msg = StripeCenters()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 100 + seq, 0
    msg.header.frame_id = 'camera_optical'
    g = msg.galvo
    g.header = msg.header
    g.seq = seq
    g.g1_pan_voltage, g.g1_tilt_voltage, g.g2_pan_voltage, g.g2_tilt_voltage = volts
    g.laser_on = True
    msg.image_width, msg.image_height = 720, 540
    msg.u = uv[:, 0].astype(np.float32).tolist()
    msg.v = uv[:, 1].astype(np.float32).tolist()
    msg.width = [4.7] * len(points)
    msg.strength = [float(i) for i in range(len(points))]
    msg.method = 'steger'
    return msg


def cloud_points(msg):
    return np.frombuffer(bytes(msg.data), CLOUD_DTYPE)


class Rig:
    """A reconstructor process with a truth calibration, and a test node talking to it."""

    def __init__(self, spawn, ros_env, tmp_path, *params):
        self.model = nominal_example_rig()
        self.cal_path = tmp_path / 'truth_for_tests.yaml'
        calibration_file.save(
            calibration_file.Calibration(model=self.model, source='simulator_truth'),
            self.cal_path)
        args = ['-p', f'calibration_file:={self.cal_path}', '-p', 'scan_end_timeout:=0.4']
        for param in params:
            args += ['-p', param]
        self.proc = spawn([sys.executable, '-m', 'reconstructor.reconstructor_node',
                           '--ros-args', *args], name='reconstructor')
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
        self.node = Node('reconstructor_test', context=self.ctx)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.pub = self.node.create_publisher(
            StripeCenters, 'stripe/centers',
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.clouds = []
        self.node.create_subscription(PointCloud2, 'points', self.clouds.append, 50)
        deadline = time.monotonic() + 20
        while self.pub.get_subscription_count() == 0 or \
                self.node.count_publishers('points') == 0:
            assert time.monotonic() < deadline and self.proc.poll() is None, self.log()
            self.ex.spin_once(timeout_sec=0.1)

    def log(self):
        return self.proc.log_path.read_text()

    def spin_until(self, done, timeout):
        deadline = time.monotonic() + timeout
        while not done() and time.monotonic() < deadline:
            self.ex.spin_once(timeout_sec=0.1)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture
def rig(spawn, ros_env, tmp_path):
    rigs = []

    def _start(*params):
        rigs.append(Rig(spawn, ros_env, tmp_path, *params))
        return rigs[-1]

    yield _start
    for r in rigs:
        r.close()


def test_reconstructor_node(rig, tmp_path):
    r = rig()
    model, proc, node, ex, pub, clouds = r.model, r.proc, r.node, r.ex, r.pub, r.clouds
    cal_path = r.cal_path
    frames = [(0.0, 0.0, 0.0, 0.0), (3.0, -2.0, 0.0, -1.5), (-6.0, 7.5, 0.0, 5.0)]
    truth = []
    bad = []
    for seq, volts in enumerate(frames):
        pts = stripe_points(model, volts)
        truth.append(pts)
        pub.publish(centers_msg(model, volts, seq, pts))
        # bad input between good frames: each must be skipped without harm
        m = centers_msg(model, volts, 100 + seq, pts)
        if seq == 0:
            m.v = m.v[:-1]  # length mismatch
        elif seq == 1:
            m.galvo.g1_tilt_voltage = math.nan
        else:
            m.galvo.g2_tilt_voltage = 12.0  # out of range
        bad.append(m)
        pub.publish(m)
        # and a truncated CDR message, as a faulty writer could send it
        pub.publish(serialize_message(m)[:60 + 40 * seq])
    deadline = time.monotonic() + 15
    while len(clouds) < len(frames) and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.1)
    assert len(clouds) == len(frames), proc.log_path.read_text()
    for msg, pts, seq in zip(clouds, truth, range(len(frames)), strict=True):
        assert msg.header.frame_id == 'v0'
        assert msg.header.stamp.sec == 100 + seq
        assert msg.point_step == 20 and msg.row_step == 20 * msg.width and msg.is_dense
        got = cloud_points(msg)
        assert got.shape[0] == pts.shape[0]
        xyz = np.column_stack([got['x'], got['y'], got['z']])
        # float32 pixels and coordinates: ~1e-5 m is the representation limit here
        np.testing.assert_allclose(xyz, pts, atol=2e-5)
        np.testing.assert_array_equal(got['intensity'], np.arange(pts.shape[0]))
    assert proc.poll() is None
    deadline = time.monotonic() + 5          # the truncated messages were logged, not fatal
    while 'skipping frame: malformed_cdr' not in proc.log_path.read_text():
        assert time.monotonic() < deadline, proc.log_path.read_text()
        time.sleep(0.1)
    # ... and counted in the node's diagnostics, which turn WARN
    diag = []
    node.create_subscription(DiagnosticArray, 'diagnostics', diag.append, 10)
    r.spin_until(lambda: any(s.name == 'reconstructor: reconstruction' for m in diag
                             for s in m.status), 10)
    status = next(s for m in diag for s in m.status if s.name == 'reconstructor: reconstruction')
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.WARN, values
    assert values['frames'] == '3' and values['callback_errors'] == '0', values
    for cause, n in (('array_length_mismatch', 1), ('nonfinite_voltage', 1),
                     ('voltage_out_of_range', 1), ('malformed_cdr', 3)):
        assert values[f'skipped/{cause}'] == str(n), values

    # the accumulated scan arrives on the latched topic, also for a late subscriber
    time.sleep(0.8)
    scans = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(PointCloud2, 'points/scan', scans.append, latched)
    deadline = time.monotonic() + 10
    while not scans and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.1)
    assert scans and scans[0].width == sum(len(p) for p in truth)

    save = node.create_client(SaveScan, 'reconstructor/save_scan')
    assert save.wait_for_service(timeout_sec=10)
    for name, ok in (('scan.ply', True), ('scan.pcd', True), ('scan.xyz', False)):
        resp = call_service(ex, save, SaveScan.Request(path=str(tmp_path / name)),
                            timeout=10.0, resend=True)
        assert resp.success is ok, resp.message
        if ok:
            pcd = o3d.io.read_point_cloud(str(tmp_path / name))
            assert len(pcd.points) == scans[0].width

    reload = node.create_client(LoadCalibration, 'reconstructor/reload_calibration')
    assert reload.wait_for_service(timeout_sec=10)
    broken = tmp_path / 'broken.yaml'
    broken.write_text(cal_path.read_text().replace('l: 0.08345', 'l: 83.45'))
    resp = call_service(ex, reload, LoadCalibration.Request(path=str(broken)), timeout=10.0,
                        resend=True)
    assert not resp.success and 'model.l' in resp.message
    # the previous calibration is still active
    clouds.clear()
    pub.publish(centers_msg(model, frames[1], 50, truth[1]))
    deadline = time.monotonic() + 10
    while not clouds and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.1)
    assert clouds and cloud_points(clouds[0]).shape[0] == truth[1].shape[0]
    log = proc.log_path.read_text()
    for cause in ('array_length_mismatch', 'nonfinite_voltage', 'voltage_out_of_range'):
        assert cause in log


def test_scan_cloud_is_bounded_by_scan_max_points(rig):
    """Continuous scanning: a scan cloud holding scan_max_points is published and the scan
    goes on in a new one, so memory stays bounded and no point is lost or repeated."""
    r = rig('scan_max_points:=1000')
    scans = []
    r.node.create_subscription(
        PointCloud2, 'points/scan', scans.append,
        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    r.spin_until(lambda: r.node.count_publishers('points/scan') > 0, 10)
    volts = (1.0, -0.5, 0.0, 0.5)
    pts = stripe_points(r.model, volts, n=300)
    for seq in range(7):                        # 2100 points: two splits, then the pause
        r.pub.publish(centers_msg(r.model, volts, seq, pts))
    r.spin_until(lambda: len(scans) >= 3, 15)
    assert [s.width for s in scans] == [900, 900, 300], r.log()
    got = np.concatenate([cloud_points(s) for s in scans])
    np.testing.assert_array_equal(got['intensity'], np.tile(np.arange(300), 7))
    # the node logs after it publishes: under load the line reaches its log a little later
    r.spin_until(lambda: 'scan ended: 300 points' in r.log(), 10)
    assert r.log().count('reached scan_max_points') == 2
    assert r.log().count('scan ended: 300 points') == 1


def _broken_calibrations(tmp_path, good_text):
    """20 calibration files a user could hand the node by mistake, each with its reason."""
    cases = [
        ('l: 0.08345', 'l: 83.45', 'model.l'),                        # millimetres
        ('format_version: 1', 'format_version: 7', 'format_version'),
        ('l: 0.08345', 'l: .nan', 'l'),
        ('d: 0.02214', 'd: 22.14', 'model.d'),
        ('format_version: 1\n', '', 'format_version'),                # key missing
    ]
    files = []
    for i, (old, new, reason) in enumerate(cases):
        assert old in good_text, old
        files.append((tmp_path / f'broken{i}.yaml', good_text.replace(old, new, 1), reason))
    files.append((tmp_path / 'binary.yaml', b'\x89PNG\r\n\x1a\n\x00\x00', 'not UTF-8'))
    files.append((tmp_path / 'utf16.yaml', good_text.encode('utf-16'), 'UTF-16'))
    files.append((tmp_path / 'yaml.yaml', 'model: [unclosed', 'not valid YAML'))
    files.append((tmp_path / 'list.yaml', '- 1\n- 2\n', 'mapping'))
    files.append((tmp_path / 'missing.yaml', None, 'cannot read'))
    out = []
    for k in range(20):
        path, content, reason = files[k % len(files)]
        path = path.with_name(f'{k:02d}_{path.name}')
        if isinstance(content, bytes):
            path.write_bytes(content)
        elif content is not None:
            path.write_text(content)
        out.append((path, reason))
    return out


def test_alternating_broken_and_good_reloads(rig, tmp_path):
    """20 broken and 20 good reloads, alternating: each broken one is refused with its reason,
    each good one taken, the node lives, and the clouds use the last good calibration."""
    r = rig()
    good_text = r.cal_path.read_text()
    assert 'l: 0.08345' in good_text and 'd: 0.02214' in good_text
    reload = r.node.create_client(LoadCalibration, 'reconstructor/reload_calibration')
    assert reload.wait_for_service(timeout_sec=10)

    def call(path):
        try:
            return call_service(r.ex, reload, LoadCalibration.Request(path=str(path)),
                                timeout=10.0, resend=True)
        except RuntimeError as exc:
            raise AssertionError(f'{exc}:\n' + r.log()) from exc

    goods = []
    for k, ls in enumerate(np.linspace(0.080, 0.086, 20)):
        path = tmp_path / f'good{k:02d}.yaml'
        path.write_text(good_text.replace('l: 0.08345', f'l: {ls:.6f}', 1))
        goods.append((path, ls))
    for (bad, reason), (good, _) in zip(_broken_calibrations(tmp_path, good_text), goods,
                                        strict=True):
        resp = call(bad)
        assert not resp.success and reason in resp.message, (bad.name, resp.message)
        resp = call(good)
        assert resp.success, (good.name, resp.message)
        assert r.proc.poll() is None, r.log()
    # the last good one (l = 0.086) is in use after one more broken reload
    assert not call(tmp_path / 'no_such_file.yaml').success
    import dataclasses

    last = dataclasses.replace(r.model, l=float(goods[-1][1]))
    volts = (3.0, -2.0, 0.0, -1.5)
    pts = stripe_points(last, volts)
    r.pub.publish(centers_msg(last, volts, 0, pts))
    r.spin_until(lambda: r.clouds, 10)
    assert r.clouds, r.log()
    got = cloud_points(r.clouds[-1])
    np.testing.assert_allclose(np.column_stack([got['x'], got['y'], got['z']]), pts, atol=2e-5)
    assert r.proc.poll() is None
    assert 'Logger severity' not in r.log() and 'Traceback' not in r.log()


def test_multi_view_filter_drops_a_reflection_and_keeps_the_stripe(rig):
    """Two views of one stripe (same G2 tilt, G1 pan -0.3 / +0.3 V): the stripe's points
    triangulate to the same place in both and are kept; light reflected 10 mm off the laser
    plane triangulates to places ~0.13 mm apart and is dropped from both. A frame without
    a second view is published unfiltered when the scan ends."""
    r = rig('multi_view_tolerance:=0.00005')
    model = r.model
    a, b = (-0.3, 0.0, 0.0, 0.0), (0.3, 0.0, 0.0, 0.0)
    true = stripe_points(model, (0.0, 0.0, 0.0, 0.0), n=20, depth=0.65)
    plane = laser_plane_v0(model, 0.0)
    ghost = true[10] + 0.010 * plane[:3] / np.linalg.norm(plane[:3])  # lit, off the plane
    pts = np.vstack([true, ghost])
    r.pub.publish(centers_msg(model, a, 0, pts))
    r.pub.publish(centers_msg(model, b, 1, pts))
    single = (0.0, 0.0, 0.0, 0.3)
    r.pub.publish(centers_msg(model, single, 2, stripe_points(model, single, n=15)))
    r.spin_until(lambda: len(r.clouds) >= 3, 15)
    assert len(r.clouds) == 3, r.log()
    for msg in r.clouds[:2]:
        got = cloud_points(msg)
        assert got.shape[0] == len(true)                    # the ghost is gone
        np.testing.assert_allclose(np.column_stack([got['x'], got['y'], got['z']]), true,
                                   atol=2e-5)
    assert cloud_points(r.clouds[2]).shape[0] == 15         # unpaired: kept as it is
