"""Hand-eye through the calibration node over real DDS, robot poses from a PoseStamped topic.

The sim driver and the calibration node run in their own processes; this process is the
robot: it streams its flange pose on ``robot/flange_pose`` at 20 Hz. The ideal-image rig's
world frame W is the flange (its true mounting ``W_T_V0``); every ``calibration/capture`` of
``hand_eye`` is one robot pose. A pose is recorded per capture (and written beside the
bags), a stale, moving or unreadable one is refused and leaves nothing behind, and the
poses recorded give the true mounting through ``calibration/compute``, and the same offline
(``galvoscan calibrate hand_eye --bags RUN --robot-poses RUN/robot_poses.yaml``).
"""

import dataclasses
import sys
import time

import numpy as np
import pytest
import rclpy
import yaml
from galvoscan_msgs.srv import CaptureCalibration, ComputeCalibration
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from scipy.spatial.transform import Rotation

from galvoscan.operator import EXACT, SimulatedOperator
from galvoscan_common.executor import ServiceClients
from galvoscan_sim import load_rig
from reconstructor import calibration_file

pytestmark = pytest.mark.dds

LAYOUT = [[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.10, 0.0], [0.11, 0.09, 0.03]]


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


BASE_T_TARGET = pose([0.0, 0.0, 0.3], [1.1, 0.2, 0.05])


def flange_poses(W_T_V0, n, seed=0):
    """A robot program: flange poses that show the artefact at ~0.6 m, tilted ~15 deg."""
    rng = np.random.default_rng(seed)
    return [BASE_T_TARGET @ np.linalg.inv(pose(
        rng.uniform(-0.25, 0.25, 3) + [np.pi, 0, 0],
        [rng.uniform(-0.12, 0.0), rng.uniform(-0.1, 0.0), rng.uniform(0.55, 0.7)]))
        @ np.linalg.inv(W_T_V0) for _ in range(n)]


class Robot:
    """Streams the flange pose at 20 Hz: ``pose``, stamped ``lag`` s ago, moving ``drift`` m
    per message, or with a broken quaternion."""

    def __init__(self, node):
        self.pose, self.lag, self.drift, self.broken, self.sent = None, 0.0, 0.0, False, 0
        self.node = node
        self.pub = node.create_publisher(PoseStamped, 'robot/flange_pose', 10)
        node.create_timer(0.05, self.tick)

    def tick(self):
        if self.pose is None:
            return
        if self.drift:
            self.pose = self.pose.copy()
            self.pose[0, 3] += self.drift
        msg = PoseStamped()
        msg.header.frame_id = 'base_link'
        stamp = self.node.get_clock().now().nanoseconds * 1e-9 - self.lag
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp), int(stamp % 1 * 1e9)
        p = self.pose[:3, 3]
        q = Rotation.from_matrix(self.pose[:3, :3]).as_quat()
        if self.broken:
            q = np.zeros(4)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = map(float, q)
        self.pub.publish(msg)
        self.sent += 1


def test_hand_eye_poses_from_the_topic(spawn, ros_env, tmp_path):
    from galvoscan.simulated_rig import truth_calibration

    rig = load_rig('ideal')
    truth = rig.W_T_V0
    start = tmp_path / 'start.yaml'
    calibration_file.save(dataclasses.replace(truth_calibration(rig), source='calibrated'),
                          start)
    artefact = tmp_path / 'artefact.yaml'
    nominal = truth @ pose(np.radians([0.4, -0.3, 0.5]), [0.002, -0.001, 0.001])
    artefact.write_text(yaml.safe_dump({
        'unit': 'm', 'sphere_radius': 0.01, 'layout': LAYOUT,
        'base_T_target': BASE_T_TARGET.tolist(), 'nominal_flange_T_v0': nominal.tolist()}))
    cal_path, data = tmp_path / 'calibration.yaml', tmp_path / 'data'
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': 'ideal', 'seed': 0}},
        'calibration': {'ros__parameters': {
            'calibration_file': str(cal_path), 'initial_calibration': str(start),
            'quick': True, 'data_dir': str(data), 'hand_eye_artefact': str(artefact),
            'robot_pose_max_age': 0.5}},
    }))
    proc = spawn([sys.executable, '-m', 'galvoscan.cli', 'run', '--params', params,
                  '--nodes', 'galvo_driver,calibration'], name='graph')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('robot', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    robot = Robot(node)
    programme = flange_poses(truth, 6)

    services = ServiceClients(node, ex, on_error=lambda exc: AssertionError(
        f'{exc}\n' + proc.log_path.read_text()))
    # the simulator's scene follows the robot: the simulated operator, playing the robot's
    # side of the instructions, puts the artefact where each robot pose shows it
    operator = SimulatedOperator(int(ros_env['ROS_DOMAIN_ID']), person=EXACT).start()

    def call(srv, name, req, timeout=120.0, resend=False):
        return services.call(srv, name, req, timeout, resend)

    def capture():
        t0 = time.monotonic()
        resp = call(CaptureCalibration, 'calibration/capture',
                    CaptureCalibration.Request(stage='hand_eye'))
        return resp, time.monotonic() - t0

    def settle(seconds=0.7):  # the stream runs on in the new mode before the next capture
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)

    def recorded():
        runs = sorted(data.glob('hand_eye_*'))
        assert len(runs) == 1, runs
        poses = yaml.safe_load((runs[0] / 'robot_poses.yaml').read_text())
        return runs[0], poses

    try:
        # pose 0: recorded, with its bags, in the series' poses file
        robot.pose = programme[0]
        first, seconds = capture()
        assert first.success, first.message + proc.log_path.read_text()
        assert first.poses == 1 and 'robot pose 0 recorded' in first.message, first.message
        run, poses = recorded()
        assert (poses['base_frame'], poses['flange_frame'], poses['unit']) == \
            ('base_link', 'tool0', 'm')
        got = poses['poses'][0]
        np.testing.assert_allclose(got['position'], programme[0][:3, 3], atol=1e-9)
        R = Rotation.from_quat(got['orientation']).as_matrix()
        np.testing.assert_allclose(R, programme[0][:3, :3], atol=1e-9)
        bags = sorted(p.name for p in run.iterdir() if p.is_dir())
        assert bags == [f'pose{k:03d}_step{k:03d}' for k in range(4)], bags
        print(f'\none robot pose (4 sphere sweeps) captured in {seconds:.1f} s')

        # refused: stale, moving, unreadable; each leaves the series as it was
        robot.pose, robot.lag = programme[1], 3.0
        settle()
        stale, _ = capture()
        assert not stale.success and 'robot pose 1 refused' in stale.message
        assert 'stamped 3.0' in stale.message and 'robot_pose_max_age 0.5' in stale.message, \
            stale.message
        robot.lag, robot.drift = 0.0, 5e-4
        settle()
        moving, _ = capture()
        assert not moving.success and 'the robot moved by' in moving.message, moving.message
        robot.drift, robot.broken = 0.0, True
        settle()
        broken, _ = capture()
        assert not broken.success and 'could not be read' in broken.message, broken.message
        assert len(recorded()[1]['poses']) == 1
        assert sorted(p.name for p in run.iterdir() if p.is_dir()) == bags
        assert proc.poll() is None

        # too few poses: compute says so; then five more, and the mounting comes out
        robot.broken = False
        too_few = call(ComputeCalibration, 'calibration/compute',
                       ComputeCalibration.Request(stage='hand_eye'), resend=True)  # refused
        assert not too_few.success and 'at least 5' in too_few.message, too_few.message
        for k in range(1, 6):
            robot.pose = programme[k]
            settle(0.3)
            resp, _ = capture()
            assert resp.success and resp.poses == k + 1, resp.message
        comp = call(ComputeCalibration, 'calibration/compute',
                    ComputeCalibration.Request(stage='hand_eye'))
        assert comp.success, comp.message + proc.log_path.read_text()
        assert comp.samples_used == 6 and comp.residual_rms < 0.05e-3, comp.message
        cal = calibration_file.load(cal_path)
        dt = np.linalg.norm(cal.cell_T_v0[:3, 3] - truth[:3, 3])
        turn = Rotation.from_matrix(cal.cell_T_v0[:3, :3] @ truth[:3, :3].T).magnitude()
        print(f'hand_eye through the node, poses from the topic: {dt * 1e3:.4f} mm, '
              f'{np.degrees(turn):.5f} deg from the true mounting')
        assert dt < 0.1e-3 and np.degrees(turn) < 0.01
        entry = cal.stages['hand_eye']
        assert entry['cell_frame'] == 'tool0' and entry['poses'] == list(range(6))
        assert len(entry['bags']) == 24
        # the same series offline, from its bags and the poses file the node wrote
        from galvoscan.offline import main

        offline = tmp_path / 'offline.yaml'
        assert main(['hand_eye', '--bags', str(run), '--robot-poses',
                     str(run / 'robot_poses.yaml'), '--artefact', str(artefact),
                     '--initial', str(start), '--calibration', str(offline)]) == 0
        np.testing.assert_allclose(calibration_file.load(offline).cell_T_v0, cal.cell_T_v0,
                                   atol=1e-9)
        # computed: the series is closed, the next capture starts a new one in a new folder
        again, _ = capture()
        assert again.success and again.poses == 1 and again.bag_path != str(run), \
            again.message
        assert proc.poll() is None
    finally:
        operator.stop()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
