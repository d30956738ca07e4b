"""System test: /tf_static and /tf from the reconstructor, read as a tf2 listener would.

`galvoscan run --one-process` on the simulator (reference rig, a plane 650 mm from the
scanner in the simulator's world W) with a calibration file whose ``cell_T_v0`` places W
in a robot cell. A separate process (this test) joins late: its /tf_static subscription
starts after the reconstructor has published. `galvoscan scan` runs a short raster. The
listener fills :class:`galvoscan_common.tf_tree.TfBuffer` and maps the received clouds into
``world``: they must agree with the file's transform and lie on the simulated plane.
"""

import sys
import time

import numpy as np
import pytest
import rclpy
from galvoscan_msgs.msg import GalvoState
from galvoscan_msgs.srv import LoadCalibration
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage

from galvoscan.simulated_rig import truth_calibration
from galvoscan_common.executor import call_service
from galvoscan_common.tf_tree import TfBuffer, stamp_ns
from galvoscan_sim import load_rig
from reconstructor import calibration_file
from reconstructor.cloud import CLOUD_DTYPE
from reconstructor.model import v0_T_v
from reconstructor.planning import aim_laser

pytestmark = pytest.mark.dds
SEED = 11
PLANE_Z_W = 0.65  # scenes/plane.yaml: the plane z = 0.65 m of the simulator's world


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


#: where the simulated world sits in the cell (a scanner mounted 1.2 m up, turned)
CELL_T_W = pose([0.3, -0.2, 1.1], [0.8, -0.4, 1.2])


class Listener:
    """A tf2-listener-like node in this process, on the graph's domain."""

    def __init__(self, domain):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = Node('tf_listener_test', context=self.ctx)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.buffer = TfBuffer(cache_time=1000 * 10**9)  # the whole test
        self.statics, self.tf, self.clouds, self.states = [], [], [], {}
        tf_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(TFMessage, '/tf', self._on_tf, tf_qos)
        self.node.create_subscription(PointCloud2, 'points', self.clouds.append, 100)
        self.node.create_subscription(GalvoState, 'galvo/state', self._on_state, 100)

    def join_static(self):
        """tf2's static listener QoS: reliable, transient local, so a late joiner gets it."""
        self.node.create_subscription(
            TFMessage, '/tf_static', self._on_static,
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def _on_static(self, msg):
        self.statics.append(msg)
        self.buffer.set_message(msg.transforms, static=True)

    def _on_tf(self, msg):
        self.tf.append(msg)
        self.buffer.set_message(msg.transforms)

    def _on_state(self, msg):
        self.states[stamp_ns(msg.header.stamp)] = (msg.g1_pan_voltage, msg.g1_tilt_voltage)

    def spin_until(self, done, timeout, proc, what):
        deadline = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < deadline, f'timed out waiting for {what}\n' + \
                proc.log_path.read_text()[-3000:]
            assert proc.poll() is None, proc.log_path.read_text()[-3000:]
            self.ex.spin_once(timeout_sec=0.05)

    def spin_for(self, seconds, proc):
        end = time.monotonic() + seconds
        self.spin_until(lambda: time.monotonic() > end, seconds + 5, proc, 'a pause')

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def cloud_xyz(msg):
    pts = np.frombuffer(bytes(msg.data), CLOUD_DTYPE)
    return np.column_stack([pts['x'], pts['y'], pts['z']]).astype(np.float64)


def apply(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def test_tf_static_and_tf_place_the_clouds_in_the_cell(spawn, ros_env, tmp_path,
                                                        sim_graph_params):
    rig = load_rig('reference')
    cal = truth_calibration(rig)
    cal.cell_T_v0 = CELL_T_W @ rig.W_T_V0
    cal_path = tmp_path / 'truth_in_cell.yaml'
    calibration_file.save(cal, cal_path)
    model = calibration_file.load(cal_path).model
    params = sim_graph_params(scene='plane', seed=SEED, calibration=cal_path,
                              extractor={'line_width_px': 4.0},
                              reconstructor={'scan_end_timeout': 1.0, 'tf_rate_max': 100.0})
    graph = spawn([sys.executable, '-m', 'galvoscan.cli', 'run', '--params', params,
                   '--one-process'], name='galvoscan')
    tilt = (-0.5, 0.5)
    g2 = [f'{aim_laser(model, 0.0, t, PLANE_Z_W):.6f}' for t in tilt]
    scan_args = [sys.executable, '-m', 'galvoscan.cli', 'scan', '--pattern', 'raster',
                 '--g1-pan', '-1', '1', '--g1-tilt', *map(str, tilt), '--g2-tilt', *g2,
                 '--steps-pan', '2', '--steps-tilt', '6', '--rate', '25']

    lis = Listener(int(ros_env['ROS_DOMAIN_ID']))
    try:
        lis.spin_until(lambda: lis.node.count_publishers('/tf_static') > 0
                       and lis.node.count_publishers('points') > 0, 90, graph,
                       'the reconstructor')
        lis.spin_for(0.5, graph)  # the static message went out before we listen
        lis.join_static()
        lis.spin_until(lambda: lis.statics, 20, graph, 'the latched /tf_static')
        assert len(lis.statics) == 1
        assert {(t.header.frame_id, t.child_frame_id) for t in lis.statics[0].transforms} == \
            {('world', 'v0'), ('v', 'camera_optical')}
        np.testing.assert_allclose(lis.buffer.lookup('world', 'v0'), cal.cell_T_v0,
                                   atol=1e-12)

        # the extractor's numba kernels warm up at start: scan until clouds with points come
        for _attempt in range(4):
            scan = spawn(scan_args, name='scan')
            lis.spin_until(lambda p=scan: p.poll() is not None, 60, graph, 'galvoscan scan')
            assert scan.returncode == 0, scan.log_path.read_text()
            lis.spin_for(1.5, graph)  # the last frames
            if any(len(c.data) for c in lis.clouds):
                break
        check_tf_and_clouds(lis, graph, model, cal.cell_T_v0)
        check_updates(lis, graph, cal, cal_path)
        assert graph.poll() is None
    finally:
        lis.close()


def check_tf_and_clouds(lis, graph, model, cell_T_v0):
    """Every /tf pose is the model's at its frame; every cloud lands on the plane in world."""
    clouds = [c for c in lis.clouds if len(c.data)]
    assert clouds and lis.tf, graph.log_path.read_text()[-3000:]

    # /tf: v0 -> v at each frame's stamp, equal to the model at that frame's voltages
    for msg in lis.tf:
        (tf,) = msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ('v0', 'v')
        stamp = stamp_ns(tf.header.stamp)
        assert stamp in lis.states, 'a /tf stamp that is no frame stamp'
        np.testing.assert_allclose(lis.buffer.lookup('v0', 'v', stamp),
                                   v0_T_v(model, *lis.states[stamp]), atol=1e-9)
    # frames reach the reconstructor 40 ms apart on average, in bursts at times; the
    # rate limit (10 ms here) holds back some, never the last pose of a scan
    tf_stamps = {stamp_ns(m.transforms[0].header.stamp) for m in lis.tf}
    assert len(tf_stamps) >= 0.5 * len(lis.states), (len(tf_stamps), len(lis.states))
    assert max(lis.states) in tf_stamps

    n_points, off_plane = 0, 0.0
    for msg in clouds:
        assert msg.header.frame_id == 'v0'
        p_v0 = cloud_xyz(msg)
        world_T_cloud = lis.buffer.lookup('world', msg.header.frame_id)
        p_world = apply(world_T_cloud, p_v0)
        np.testing.assert_allclose(p_world, apply(cell_T_v0, p_v0), atol=1e-9)
        # on the simulated plane, seen from the cell
        p_w = apply(np.linalg.inv(CELL_T_W), p_world)
        off_plane = max(off_plane, np.abs(p_w[:, 2] - PLANE_Z_W).max())
        assert off_plane < 1e-3
        # the dynamic chain at the cloud's stamp: the camera frame is where V was
        stamp = stamp_ns(msg.header.stamp)
        if stamp in tf_stamps:
            np.testing.assert_allclose(
                lis.buffer.lookup('world', 'camera_optical', stamp),
                cell_T_v0 @ v0_T_v(model, *lis.states[stamp]), atol=1e-9)
        n_points += len(p_v0)
    assert n_points > 100
    print(f'\n{len(lis.tf)} /tf for {len(lis.states)} frames, {n_points} points in '
          f'{len(clouds)} clouds mapped to world, at most {off_plane * 1e6:.0f} um off the '
          f'plane')


def check_updates(lis, graph, cal, cal_path):
    """Parameter sets refused with a reason or re-sending /tf_static; a reload too."""
    # parameters: a bad extrinsic or a clashing name is refused with the reason ...
    params_client = lis.node.create_client(SetParameters, 'reconstructor/set_parameters')

    def set_parameter(param):  # setting a value again is harmless: safe to resend
        resp = call_service(lis.ex, params_client,
                            SetParameters.Request(parameters=[param.to_parameter_msg()]),
                            timeout=20.0, resend=True)
        (result,) = resp.results
        return result

    mirror = (np.diag([1.0, 1.0, -1.0, 1.0])).ravel().tolist()
    for param, reason in ((Parameter('cell_T_v0', value=mirror), 'determinant -1'),
                          (Parameter('cell_frame', value='v0'), 'must differ'),
                          (Parameter('cell_T_v0', value=[1.0] * 3), '4x4')):
        result = set_parameter(param)
        assert not result.successful and reason in result.reason, result.reason
    # ... a good one re-sends /tf_static whole (the file's extrinsic still wins)
    assert set_parameter(Parameter('cell_frame', value='robot_cell')).successful
    lis.spin_until(lambda: len(lis.statics) == 2, 10, graph, 'the new /tf_static')
    assert {(t.header.frame_id, t.child_frame_id) for t in lis.statics[1].transforms} == \
        {('robot_cell', 'v0'), ('v', 'camera_optical')}
    np.testing.assert_allclose(lis.buffer.lookup('robot_cell', 'v0'), cal.cell_T_v0,
                               atol=1e-12)

    # reloading a calibration with another extrinsic re-sends it too
    cal.cell_T_v0 = pose([0.0, 0.0, 0.5], [2.0, 0.0, 0.0])
    calibration_file.save(cal, cal_path)
    reload = lis.node.create_client(LoadCalibration, 'reconstructor/reload_calibration')
    assert reload.wait_for_service(timeout_sec=10)
    resp = call_service(lis.ex, reload, LoadCalibration.Request(path=str(cal_path)),
                        timeout=10.0, resend=True)
    assert resp.success, resp.message
    lis.spin_until(lambda: len(lis.statics) == 3, 10, graph, 'the reloaded /tf_static')
    np.testing.assert_allclose(lis.buffer.lookup('robot_cell', 'v0'), cal.cell_T_v0,
                               atol=1e-12)
