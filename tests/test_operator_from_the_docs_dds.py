"""An operator written from the documentation alone drives a calibration over real DDS.

``DocsOperator`` below knows only what ``docs/calibrate-real-rig.md`` states about the
operator interface (the ``calibration/instruction`` topic, the ``calibration/operator``
service, their fields and states) and what ``docs/simulator.md`` and the shipped scene
files state about scenes: it imports nothing of galvoscan's own, only rclpy, the message
packages, numpy and yaml. It plays the operator's hands on the simulated rig: each target
exactly where and as asked, put into the scene through ``sim/set_scene``, then *placed*;
a ``move`` instruction is followed as it says. It calibrates the intrinsics (checkerboard)
and captures the laser plane (circle grid, on the laser line), so the interface a robot
program or another front end would use is enough to calibrate, as documented.
"""

import sys
import threading
import time

import numpy as np
import pytest
import rclpy
import yaml
from galvoscan_msgs.msg import CalibrationInstruction
from galvoscan_msgs.srv import CaptureCalibration, ComputeCalibration, OperatorAction, SetScene
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

pytestmark = pytest.mark.dds


def rotation_vector(q) -> list:
    """Rotation vector of a unit quaternion (x, y, z, w)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q) * (1.0 if q[3] >= 0.0 else -1.0)
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return [0.0, 0.0, 0.0]
    return (q[:3] / s * 2.0 * np.arctan2(s, q[3])).tolist()


def board_object(target: str, spec: dict, translation, rotvec) -> dict:
    """The scene object of a kit board (docs/calibrate-real-rig.md, 'The kit' and the scene
    objects of docs/simulator.md): a checkerboard's ``cols`` x ``rows`` inner corners are
    (cols + 1) x (rows + 1) squares with one square of white margin; a circle grid is a
    circle board without sub-patterns (every circle the same) with half a pitch of margin."""
    pose = {'translation': [float(v) for v in translation], 'rotation_vector': rotvec}
    if target == 'checkerboard':
        nx, ny, sq = spec['cols'] + 1, spec['rows'] + 1, spec['square']
        return {'type': 'checkerboard', 'name': 'board', 'pose': pose,
                'size': [(nx + 2) * sq, (ny + 2) * sq], 'thickness': 0.003,
                'squares': [nx, ny], 'square_size': sq, 'albedo': 0.85, 'dark_albedo': 0.05}
    if target == 'circle_grid':
        p, d = spec['pitch'], spec['diameter']
        return {'type': 'circle_board', 'name': 'board', 'pose': pose,
                'size': [(spec['cols'] + 1) * p, (spec['rows'] + 1) * p], 'thickness': 0.003,
                'grid': [spec['cols'], spec['rows']], 'pitch': p, 'sub_pattern': 1,
                'small_diameter': d, 'big_diameter': d, 'albedo': 0.85,
                'circle_albedo': 0.05}
    raise ValueError(f'this operator has no {target} in its kit')


class DocsOperator:
    """Places each target exactly as instructed, in its own ROS context and thread."""

    def __init__(self, domain_id: int):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = Node('docs_operator', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.scene = self.node.create_client(SetScene, 'sim/set_scene')
        self.answer = self.node.create_client(OperatorAction, 'calibration/operator')
        self.node.create_subscription(
            CalibrationInstruction, 'calibration/instruction', self.on_instruction,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.last_sequence, self.pose = -1, None
        self.seen, self.errors, self.placed, self.retries = [], [], 0, 0
        self.moves = []
        self.running = True
        self.thread = threading.Thread(target=self.spin, daemon=True)

    def spin(self):
        while self.running:
            self.executor.spin_once(timeout_sec=0.05)

    def on_instruction(self, msg):
        self.seen.append(msg)
        if msg.sequence == self.last_sequence or msg.state not in ('place', 'move'):
            return
        self.last_sequence = msg.sequence
        spec = yaml.safe_load(msg.target_spec) or {}
        if msg.state == 'place' or self.pose is None or not np.any(msg.move):
            self.pose = (np.array(msg.centre, dtype=np.float64), list(msg.orientation))
        else:  # a displacement to apply, V0 [m]
            self.moves.append(msg.direction)
            self.pose = (self.pose[0] + np.asarray(msg.move), self.pose[1])
        scene = {'format_version': 1, 'name': 'operator',
                 'objects': [board_object(msg.target, spec, self.pose[0],
                                          rotation_vector(self.pose[1]))]}
        self.put(yaml.safe_dump(scene), msg.placement, time.monotonic() + 30.0)

    def put(self, text, placement, deadline):
        future = self.scene.call_async(SetScene.Request(scene_yaml=text))
        future.add_done_callback(lambda f: self.after_scene(f, text, placement, deadline))

    def after_scene(self, future, text, placement, deadline):
        resp = future.result()
        if not resp.success and 'during a scan' in resp.message and \
                time.monotonic() < deadline:  # the simulator changes no scene mid-scan
            self.retries += 1
            time.sleep(0.02)
            self.put(text, placement, deadline)
            return
        if not resp.success:
            self.errors.append(resp.message)
            return
        self.placed += 1
        self.answer.call_async(OperatorAction.Request(action='placed', placement=placement))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.running = False
        self.thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def test_an_operator_written_from_the_docs_calibrates(spawn, ros_env, tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': 'reference', 'seed': 5}},
        'calibration': {'ros__parameters': {'calibration_file': str(tmp_path / 'cal.yaml'),
                                            'quick': True,
                                            'data_dir': str(tmp_path / 'data')}},
    }))
    proc = spawn([sys.executable, '-m', 'galvoscan.cli', 'run', '--params', params,
                  '--nodes', 'galvo_driver,calibration'], name='graph')
    domain = int(ros_env['ROS_DOMAIN_ID'])
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('docs_operator_test', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def call(srv, name, req, timeout=300.0):
        client = node.create_client(srv, name)
        t_end = time.monotonic() + timeout
        while not client.wait_for_service(timeout_sec=0.5):
            assert proc.poll() is None and time.monotonic() < t_end, \
                proc.log_path.read_text()[-3000:]
        future = client.call_async(req)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        assert future.done(), f'{name}: no answer in {timeout} s'
        return future.result()

    try:
        with DocsOperator(domain) as operator:
            cap = call(CaptureCalibration, 'calibration/capture',
                       CaptureCalibration.Request(stage='intrinsics', max_frames=5))
            assert cap.success, cap.message + proc.log_path.read_text()[-3000:]
            assert cap.poses == 5, cap.message
            comp = call(ComputeCalibration, 'calibration/compute',
                        ComputeCalibration.Request(stage='intrinsics'))
            assert comp.success and comp.samples_used == 5, comp.message
            assert comp.reprojection_rms < 0.2
            cap = call(CaptureCalibration, 'calibration/capture',
                       CaptureCalibration.Request(stage='laser_plane'))
            assert cap.success, cap.message + proc.log_path.read_text()[-3000:]
            assert cap.poses >= 2, cap.message
            assert not operator.errors, operator.errors
            states = {m.state for m in operator.seen}
            assert {'place', 'search', 'capture', 'done'} <= states, states
            asked = [m for m in operator.seen if m.state == 'place']
            assert {m.target for m in asked} == {'checkerboard', 'circle_grid'}
            assert any(m.on_laser_line for m in asked if m.target == 'circle_grid')
            assert operator.placed >= 5 + 2
        assert proc.poll() is None
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
