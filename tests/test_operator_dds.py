"""The operator interface over real DDS: the calibration node asks for each placement on
``calibration/instruction`` and waits for ``calibration/operator``; the simulated operator
(its own process context) answers. A target nudged during its capture is caught by the
motion gate and its views are retaken; a board put 80 mm off and turned 10 deg is found by
the search; bad answers are refused without harm; the captured bags re-solve offline
(``galvoscan calibrate intrinsics --bags``) to the same intrinsics."""

import io
import sys
import time

import pytest
import rclpy
import yaml
from galvoscan_msgs.msg import CalibrationInstruction, CalibrationProgress
from galvoscan_msgs.srv import CaptureCalibration, ComputeCalibration, OperatorAction
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from galvoscan.offline import main
from galvoscan.operator import SimulatedOperator, console, progress_text
from galvoscan_common.executor import ServiceClients
from reconstructor import calibration_file

pytestmark = pytest.mark.dds


def test_operator_places_the_scanner_finds_a_moved_target_is_retaken(spawn, ros_env,
                                                                      tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': 'reference', 'seed': 2}},
        'calibration': {'ros__parameters': {'calibration_file': str(tmp_path / 'cal.yaml'),
                                            'quick': True,
                                            'data_dir': str(tmp_path / 'data')}},
    }))
    proc = spawn([sys.executable, '-m', 'galvoscan.cli', 'run', '--params', params,
                  '--nodes', 'galvo_driver,calibration'], name='graph')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('operator_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    seen = []
    node.create_subscription(CalibrationInstruction, 'calibration/instruction', seen.append,
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    progress = []
    node.create_subscription(CalibrationProgress, 'calibration/progress', progress.append,
                             QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    services = ServiceClients(node, ex, on_error=lambda exc: AssertionError(
        f'{exc}\n' + proc.log_path.read_text()))

    def call(srv, name, req, timeout=300.0, resend=False):
        return services.call(srv, name, req, timeout, resend)

    # no capture runs: an answer is refused, and so is nonsense
    resp = call(OperatorAction, 'calibration/operator',
                OperatorAction.Request(action='placed', placement=0), resend=True)
    assert not resp.accepted and 'no capture' in resp.message
    resp = call(OperatorAction, 'calibration/operator',
                OperatorAction.Request(action='juggle'), resend=True)
    assert not resp.accepted and 'unknown action' in resp.message
    # a person at the console: what they type is checked and sent, the answer printed
    typed, shown = io.StringIO('x\np\n'), io.StringIO()
    assert console(int(ros_env['ROS_DOMAIN_ID']), typed, shown) == 1  # input ended
    assert "'x'? p(laced)" in shown.getvalue()
    assert 'no capture is waiting' in shown.getvalue(), shown.getvalue()
    t_end = time.monotonic() + 10.0
    while not seen and time.monotonic() < t_end:  # latched: the idle instruction is there
        ex.spin_once(timeout_sec=0.1)
    assert seen and seen[-1].state == 'idle'

    # the first board is nudged 4 mm while its views are taken; the second is put 80 mm
    # off and turned 10 deg
    operator = SimulatedOperator(int(ros_env['ROS_DOMAIN_ID']), seed=4, mistakes=[
        'moved_during_capture', ((0.08, 0.0, 0.0), 0.1745)], log_fn=print).start()
    try:
        cap = call(CaptureCalibration, 'calibration/capture',
                   CaptureCalibration.Request(stage='intrinsics', max_frames=5))
        assert cap.success, cap.message + proc.log_path.read_text()[-3000:]
        assert cap.poses == 5 and cap.frames_recorded == 5, cap.message
        assert 'views rejected: moved' in cap.message, cap.message
        comp = call(ComputeCalibration, 'calibration/compute',
                    ComputeCalibration.Request(stage='intrinsics'))
        assert comp.success and comp.samples_used == 5, comp.message
        assert comp.reprojection_rms < 0.2
        # the bags re-solve offline to the same intrinsics
        offline = tmp_path / 'offline.yaml'
        assert main(['intrinsics', '--bags', cap.bag_path, '--rig', 'reference',
                     '--calibration', str(offline)]) == 0
        got = calibration_file.load(offline).model.intrinsics
        want = calibration_file.load(tmp_path / 'cal.yaml').model.intrinsics
        assert (got.fx, got.fy, got.cx, got.cy, *got.dist) == pytest.approx(
            (want.fx, want.fy, want.cx, want.cy, *want.dist), rel=1e-9, abs=1e-12)
        ex.spin_once(timeout_sec=0.2)
        states = [m.state for m in seen]
        for state in ('place', 'search', 'capture', 'done'):
            assert state in states, states
        first = next(m for m in seen if m.state == 'place')
        assert first.stage == 'intrinsics' and first.target == 'checkerboard'
        assert first.header.frame_id == 'v0' and first.hold_still
        assert list(first.extents) == pytest.approx([0.06, 0.06, 0.06])
        assert 'square' in yaml.safe_load(first.target_spec)
        retake = [m for m in seen if m.state == 'place' and 'moved during' in m.text]
        assert retake
        done = [m for m in seen if m.state == 'done'][-1]
        assert done.placements_done == 5 and done.placements_planned == 5
        assert dict(zip(done.rejected_reasons, done.rejected_counts, strict=True))['moved'] >= 1
        assert [m.sequence for m in seen] == sorted({m.sequence for m in seen})
        assert operator.stats['mistakes']['moved_during_capture'] == 1
        # calibration/progress: the sigma table against its targets, the coverage, the
        # advice and every view's detections with its verdict
        mine = [m for m in progress if m.stage == 'intrinsics']
        last = mine[-1]
        assert last.placements_done == 5 and last.placements_max == 5
        assert list(last.parameter_names[:4]) == ['fx', 'fy', 'cx', 'cy']
        assert len(last.sigma) == len(last.sigma_target) == len(last.parameter_units) == \
            len(last.parameter_names)
        assert all(s > 0 for s in last.sigma) and all(t > 0 for t in last.sigma_target)
        assert last.image_grid_rows * last.image_grid_cols == len(last.image_coverage)
        assert sum(last.image_coverage) >= 5 * 88 and sum(last.voltage_coverage) >= 5
        assert last.voltage_axes == 'u1x,u1y' and last.header.frame_id == 'v0'
        views = [m for m in mine if m.view_points_u]
        assert any(m.view_accepted and len(m.view_points_u) == 88 for m in views)
        assert all(len(m.view_points_u) == len(m.view_points_v) for m in views)
        assert all(m.view_accepted == (m.view_reason == '') for m in views)
        assert 'fx' in progress_text(last) and last.advice in progress_text(last)
        assert proc.poll() is None
    finally:
        operator.stop()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
