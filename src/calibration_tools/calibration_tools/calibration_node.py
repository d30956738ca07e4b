"""``calibration_node``: every calibration stage as ROS services.

Services
    calibration/capture  galvoscan_msgs/CaptureCalibration: run the stage's capture plan
                         with its operator: each target placement is asked for on
                         ``calibration/instruction``; after "placed" the scanner searches
                         for the target, measures its pose from its own detections, plans
                         the views around it (``scan/start`` for each) and records
                         ``camera/image_raw`` + ``galvo/state`` into one rosbag2 directory
                         per step under ``data_dir`` (search and check views under
                         ``search/`` and ``checks/``; the measured poses in
                         ``measured_poses.yaml``). See docs/calibrate-real-rig.md.
    calibration/operator galvoscan_msgs/OperatorAction: the operator's answer to the
                         instruction: placed, undo, skip or done.
    calibration/compute  galvoscan_msgs/ComputeCalibration: run the stage on captured bags,
                         merge the result into the active calibration and save it
                         atomically to ``calibration_file``.
    calibration/load     galvoscan_msgs/LoadCalibration
    calibration/save     galvoscan_msgs/SaveCalibration

Publications
    calibration/instruction  galvoscan_msgs/CalibrationInstruction, latched (transient
                         local, depth 1): what the operator must do now, with the stage's
                         feedback (placements, views kept and rejected by reason).

Subscriptions (spun only while a capture runs)
    robot/flange_pose    geometry_msgs/PoseStamped (``robot_pose_topic``): the robot's flange
                         in its base frame, for the hand-eye stage when ``robot_poses`` is
                         empty. Then each ``calibration/capture`` of that stage is one robot
                         pose: the node takes the latest pose (refused if stamped longer than
                         ``robot_pose_max_age`` ago), captures the artefact from it and, after
                         every capture step, refuses the pose if the stream went stale or the
                         flange moved beyond ``robot_still_m`` / ``robot_still_rad`` (the
                         robot must hold still while the scanner measures). Accepted poses
                         accumulate in one run folder with its ``robot_poses.yaml`` until a
                         ``calibration/compute`` of the stage succeeds; a refused one leaves
                         nothing behind.

Long stages log their progress (counts and an ETA). The stage maths lives in the pure
modules (``stage_runner``, ``capture_plans`` and the stage modules); this node only moves
data between ROS and them.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
from galvoscan_msgs.msg import CalibrationInstruction, CalibrationProgress, GalvoState
from galvoscan_msgs.srv import (
    CaptureCalibration,
    ComputeCalibration,
    GetScanProgress,
    LoadCalibration,
    OperatorAction,
    SaveCalibration,
    StartScan,
)
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image

from calibration_tools import operator_flow, robot_poses, stage_runner, stopping
from calibration_tools.registry import OVERRIDABLE, plan
from calibration_tools.registry import stage as stage_entry
from calibration_tools.stages import KNOWN_STAGES, CaptureStep, apply_result
from galvoscan_bag.writer import BagWriter
from galvoscan_common.boundary import CallbackErrors, guard_service, guard_subscription
from galvoscan_common.diagnostics import publish_periodically
from galvoscan_common.executor import call_service
from galvoscan_common.logbridge import forward_python_logging
from reconstructor import calibration_file


class _Capture(Node):
    """The node that talks to the driver and records, spun only while a capture runs."""

    def __init__(self, context, errors: CallbackErrors, pose_topic: str):
        super().__init__('calibration_capture', context=context)
        self.writer = None
        self.frames = 0
        self.states = 0
        self.dropped = 0  # messages that arrived while nothing was recorded
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        log = self.get_logger()
        self.create_subscription(Image, 'camera/image_raw', guard_subscription(
            'camera/image_raw', self._on_image, log, errors), qos, raw=True)
        self.create_subscription(GalvoState, 'galvo/state', guard_subscription(
            'galvo/state', self._on_state, log, errors), qos, raw=True)
        self.clients_ = {n: self.create_client(t, n) for n, t in (
            ('scan/start', StartScan), ('scan/progress', GetScanProgress))}
        self.actions = []  # (action, placement) answered on calibration/operator
        self.expect = None  # (placement index, states accepted for 'placed') or None
        self.create_service(OperatorAction, 'calibration/operator', guard_service(
            'calibration/operator', self._on_action, log, errors))
        self.pose_topic = pose_topic
        self.watch = robot_poses.PoseWatch(1.0, 1e-4, 2e-4)  # limits set per capture
        self.create_subscription(PoseStamped, pose_topic, guard_subscription(
            pose_topic, self._on_pose, log, errors), qos_profile_sensor_data)

    def now(self) -> float:
        """This node's clock [s], the one pose stamps are judged on."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_pose(self, msg):
        p, q = msg.pose.position, msg.pose.orientation
        try:
            T = robot_poses.pose_matrix((p.x, p.y, p.z), (q.x, q.y, q.z, q.w), 'pose')
            frame = robot_poses.frame_name(msg.header.frame_id, 'header.frame_id')
        except ValueError as exc:
            self.watch.reject(str(exc))  # a measurement it falls in is refused
            raise
        self.watch.add(T, msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, frame)

    def _on_action(self, req, resp):
        action = req.action.strip().lower()
        if action not in ('placed', 'undo', 'skip', 'done'):
            resp.accepted = False
            resp.message = f"unknown action '{req.action}'; one of placed, undo, skip, done"
        elif self.expect is None:
            resp.accepted, resp.message = False, 'no capture is waiting for the operator'
        elif action in ('placed', 'skip') and req.placement != self.expect:
            resp.accepted = False
            resp.message = (f'the instruction asks for placement {self.expect}, not '
                            f'{req.placement}')
        else:
            self.actions.append(action)
            resp.accepted, resp.message = True, f'{action}: received'
        return resp

    def _on_image(self, data):
        if self.writer is not None:
            self.writer.write('/camera/image_raw', data, time.time_ns())
            self.frames += 1
        else:
            self.dropped += 1

    def _on_state(self, data):
        if self.writer is not None:
            self.writer.write('/galvo/state', data, time.time_ns())
            self.states += 1
        else:
            self.dropped += 1


@dataclass
class _PoseSeries:
    """Robot poses recorded from the pose topic for one stage, and their bags (one folder)."""

    root: Path
    run_dir: Path
    flange_frame: str
    base_frame: str = ''
    poses: list = field(default_factory=list)
    bags: list = field(default_factory=list)


def _ranged(description: str, low: float, high: float) -> ParameterDescriptor:
    return ParameterDescriptor(description=description, floating_point_range=[
        FloatingPointRange(from_value=low, to_value=high)])


class CalibrationNode(Node):
    def __init__(self, **kwargs):
        super().__init__('calibration', **kwargs)
        self.declare_parameter('calibration_file', 'calibration.yaml', ParameterDescriptor(
            description='calibration YAML the stages merge into (written atomically)'))
        self.declare_parameter('initial_calibration', '', ParameterDescriptor(
            description='starting (nominal) calibration file: the rig\'s design values; '
                        'empty: none until calibration/load (galvoscan run writes one for '
                        'a simulated rig)'))
        self.declare_parameter('data_dir', 'calibration_data', ParameterDescriptor(
            description='where captured bags go'))
        self.declare_parameter('quick', False, ParameterDescriptor(
            description='reduced capture plans (tests)'))
        self.declare_parameter('model', '', ParameterDescriptor(
            description="model form the dynamic_camera stage fits: 'physical' (each mirror a "
                        "plane on its own axis) or 'paper' (the paper's model as published); "
                        "'' the stage's default (physical)"))
        self.declare_parameter('cell_reference', '', ParameterDescriptor(
            description='cell_extrinsic: YAML of the robot-reported sphere positions in the '
                        'cell frame (calibration_tools.cell_extrinsic.read_reference)'))
        self.declare_parameter('robot_poses', '', ParameterDescriptor(
            description='hand_eye: YAML or CSV file of the robot\'s flange poses '
                        '(calibration_tools.robot_poses.read_robot_poses); empty: record them '
                        'from robot_pose_topic, one robot pose per calibration/capture'))
        self.declare_parameter('hand_eye_artefact', '', ParameterDescriptor(
            description='hand_eye: YAML of the artefact\'s sphere layout and where it stands '
                        '(calibration_tools.hand_eye.read_artefact)'))
        self.declare_parameter('robot_pose_topic', 'robot/flange_pose', ParameterDescriptor(
            description='hand_eye: geometry_msgs/PoseStamped of the flange in the robot\'s '
                        'base frame (header.frame_id), streamed by the robot driver',
            read_only=True))
        self.declare_parameter('robot_flange_frame', 'tool0', ParameterDescriptor(
            description='hand_eye: the frame the pose topic\'s poses are of (the flange); '
                        'the result\'s cell_frame'))
        self.declare_parameter('robot_pose_max_age', 0.5, _ranged(
            'hand_eye: a robot pose stamped longer ago than this is refused [s]', 0.01, 60.0))
        self.declare_parameter('robot_still_m', 1e-4, _ranged(
            'hand_eye: the flange may move this far while the scanner measures [m]',
            1e-7, 0.01))
        self.declare_parameter('robot_still_rad', 2e-4, _ranged(
            'hand_eye: the flange may turn this far while the scanner measures [rad]',
            1e-7, 0.1))
        self.declare_parameter('operator_timeout', 900.0, _ranged(
            'how long a capture waits for the operator\'s answer to an instruction [s]',
            1.0, 86400.0))
        self.declare_parameter('max_moves', 6, ParameterDescriptor(
            description='instructions to move a target (not found, out of reach, off the '
                        'laser line, moved during capture) before a placement is skipped'))
        self._last_bags = {}
        self._series: dict[str, _PoseSeries] = {}
        self._instruction = self.create_publisher(
            CalibrationInstruction, 'calibration/instruction',
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._progress = self.create_publisher(
            CalibrationProgress, 'calibration/progress',
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._sequence = 0
        self.operator_stats: dict[str, dict] = {}
        self.calibration = self._initial()
        self.callback_errors = CallbackErrors()
        self.counters = {'captures': 0, 'computes': 0, 'frames_recorded': 0,
                         'robot_poses_recorded': 0, 'robot_poses_refused': 0}
        for srv_type, name, callback in (
                (CaptureCalibration, 'calibration/capture', self._on_capture),
                (ComputeCalibration, 'calibration/compute', self._on_compute),
                (LoadCalibration, 'calibration/load', self._on_load),
                (SaveCalibration, 'calibration/save', self._on_save)):
            self.create_service(srv_type, name, guard_service(
                name, callback, self.get_logger(), self.callback_errors))
        publish_periodically(
            self, 'calibration', lambda: {
                **self.counters, 'robot_pose_messages': self._cap.watch.received,
                'robot_pose_messages_unreadable': self._cap.watch.rejected},
            self.callback_errors,
            message=lambda: ('calibration loaded' if self.calibration is not None
                             else 'no calibration loaded'))
        self._cap_executor = SingleThreadedExecutor(context=self.context)
        self._cap = _Capture(self.context, self.callback_errors,
                             self.get_parameter('robot_pose_topic').value)
        self._cap_executor.add_node(self._cap)
        # between captures the operator service still answers (that nothing waits)
        self.create_timer(0.1, lambda: self._cap_executor.spin_once(timeout_sec=0.0))
        self._publish(CalibrationInstruction(state='idle', text='no capture running'))
        idle = CalibrationProgress()
        idle.header.stamp = self.get_clock().now().to_msg()
        idle.header.frame_id = 'v0'
        self._progress.publish(idle)

    def _initial(self):
        path = self.get_parameter('initial_calibration').value
        if not path:
            self.get_logger().warning(
                'no initial_calibration: load a starting calibration (calibration/load) '
                'before capturing')
            return None
        try:
            return calibration_file.load(path)
        except (ValueError, OSError) as exc:
            self.get_logger().error(f'no starting calibration: {exc}')
            return None

    # -- capture ----------------------------------------------------------------------
    def _call(self, name, request, timeout=60.0):
        # scene, start (by its request_id) and progress are all safe to resend
        return call_service(self._cap_executor, self._cap.clients_[name], request, timeout,
                            resend=True)

    def _record_step(self, step, bag_dir):
        cap = self._cap
        if step.scene_yaml:  # targets are placed by the operator, never by the node
            raise ValueError(f'a capture step that places a target itself: {step.note}')
        # drop frames of earlier scans still queued in the subscriptions: until a spin
        # finds none (at most 0.2 s)
        quiet = time.monotonic() + 0.2
        while time.monotonic() < quiet:
            before = cap.dropped
            self._cap_executor.spin_once(timeout_sec=0.005)
            if cap.dropped == before:
                break
        writer = BagWriter(bag_dir)
        writer.open()
        writer.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        writer.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
        cap.writer, cap.frames, cap.states = writer, 0, 0
        try:
            self._wait_scan_ended()
            resp = self._call('scan/start', StartScan.Request(
                pattern='custom', voltages=np.asarray(step.voltages).ravel().tolist(),
                frame_rate=step.frame_rate, laser_on=step.laser_on))
            if not resp.success:
                raise RuntimeError(f'scan/start: {resp.message}')
            n, last, t_end = resp.frames_total, time.monotonic(), time.monotonic() + 600
            while cap.frames < n and time.monotonic() < t_end:
                before = cap.frames
                self._cap_executor.spin_once(timeout_sec=0.05)
                if cap.frames != before:
                    last = time.monotonic()
                elif time.monotonic() - last > 5.0:
                    state = self._call('scan/progress', GetScanProgress.Request()).state
                    if state != 'running':
                        break
                    last = time.monotonic()
            t_quiet = time.monotonic() + 2.0  # the last states may trail their images
            while cap.states < cap.frames and time.monotonic() < t_quiet:
                self._cap_executor.spin_once(timeout_sec=0.05)
        finally:
            cap.writer = None
            writer.close()
        return cap.frames, n

    def _wait_scan_ended(self, timeout: float = 10.0) -> None:
        """Wait while the driver still runs a scan: its last frames arrive before it marks
        the scan done, and under load the next step's scan/start came first (refused with
        'still running'; a drawn rig lost its 1000 mm re-set to it)."""
        deadline = time.monotonic() + timeout
        while self._call('scan/progress', GetScanProgress.Request()).state == 'running':
            if time.monotonic() > deadline:
                return  # scan/start answers with the driver's reason
            self._cap_executor.spin_once(timeout_sec=0.05)

    def _on_capture(self, req, resp):
        t0 = time.monotonic()
        stage = req.stage
        if stage not in KNOWN_STAGES:
            resp.success = False
            resp.message = f"unknown stage '{stage}'; one of {', '.join(KNOWN_STAGES)}"
            return resp
        if self.calibration is None:
            resp.success, resp.message = False, 'no starting calibration (see the log)'
            return resp
        if self._pose_topic_input(stage):
            return self._capture_robot_pose(stage, req, resp, t0)
        try:
            steps = plan(stage, self.calibration, quick=self.get_parameter('quick').value,
                         inputs=self._inputs(stage))
            if req.max_frames:
                steps = _cap_frames(steps, req.max_frames)
            root = Path(req.output_dir or self.get_parameter('data_dir').value)
            run_dir = _new_run_dir(root, stage)
            bags = []
            frames, wanted, placed = self._operator_capture(
                stage, steps, run_dir, t0, bags, by_robot=bool(stage_entry(stage).inputs))
        except (RuntimeError, ValueError, OSError) as exc:
            resp.success, resp.message = False, f'capture {stage} failed: {exc}'
            self.get_logger().error(resp.message)
            self._publish(CalibrationInstruction(stage=stage, state='failed',
                                                 text=resp.message))
            return resp
        # in name order, as an offline re-solve of the run folder reads them (the stage
        # asks for its placements in the order that helps most, not the plan's)
        self._last_bags[stage] = sorted(bags, key=lambda b: Path(b).name)
        self.counters['captures'] += 1
        self.counters['frames_recorded'] += frames
        resp.success = frames > 0
        resp.bag_path, resp.frames_recorded = str(run_dir), frames
        resp.poses = placed
        resp.duration = time.monotonic() - t0
        resp.message = (f'{stage}: recorded {frames}/{wanted} frames of {placed} placement(s) '
                        f'in {len(bags)} bags under {run_dir}; operator: '
                        + operator_flow.stats_line(self.operator_stats[stage]))
        self.get_logger().info(resp.message)
        return resp

    # -- the operator -----------------------------------------------------------------
    def _publish(self, msg):
        self._sequence += 1
        msg.sequence = self._sequence
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = msg.header.frame_id or 'v0'
        self._instruction.publish(msg)

    def _publish_progress(self, progress, stats, assessment, view=None):
        """``calibration/progress``: the stage's standard errors against their targets, its
        coverage, the advice and (``view``: (features (n, 2) px or None, kept, reason[,
        stamp s])) the last view."""
        msg = CalibrationProgress()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = 'v0'
        msg.stage = progress.stage
        msg.placements_done = int(stats['placed'])
        msg.placements_max = int(progress.most)
        a = assessment
        msg.parameter_names, msg.parameter_units = list(a.names), list(a.units)
        msg.sigma = [float(x) for x in a.sigma]
        msg.sigma_target = [float(x) for x in a.target]
        msg.targets_met = a.targets_met
        msg.advice = a.advice
        img, volt = progress.image_coverage(), progress.voltage_coverage()
        msg.image_grid_rows, msg.image_grid_cols = (int(x) for x in img.shape)
        msg.image_coverage = [int(x) for x in img.ravel()]
        msg.voltage_axes = progress.axes
        msg.voltage_extent = [float(x) for x in progress.extent]
        msg.voltage_grid_rows, msg.voltage_grid_cols = (int(x) for x in volt.shape)
        msg.voltage_coverage = [int(x) for x in volt.ravel()]
        if view is not None:
            pts, ok, why = view[:3]
            if len(view) > 3 and view[3]:
                sec = int(view[3])
                msg.view_stamp.sec, msg.view_stamp.nanosec = sec, int((view[3] - sec) * 1e9)
            else:
                msg.view_stamp = msg.header.stamp
            if pts is not None:
                q = np.asarray(pts, np.float64).reshape(-1, 2)
                msg.view_points_u = [float(x) for x in q[:, 0]]
                msg.view_points_v = [float(x) for x in q[:, 1]]
            msg.view_accepted, msg.view_reason = bool(ok), str(why)
        self._progress.publish(msg)

    def _instruct(self, stats, p, state, text, move=None):
        fields = operator_flow.instruction_fields(
            p, state, text, None if move is None else move.move,
            '' if move is None else move.words)
        msg = CalibrationInstruction(**fields)
        if p.by_robot:
            msg.header.frame_id = 'robot'
        msg.placements_planned = stats['planned']
        msg.placements_done = stats['placed']
        msg.views_captured = stats['views']
        msg.views_rejected = sum(stats['rejected'].values())
        msg.rejected_reasons = list(stats['rejected'])
        msg.rejected_counts = [int(v) for v in stats['rejected'].values()]
        msg.searches = stats['search_views']
        stats['instructions'] += 1
        self._publish(msg)
        if state in ('place', 'move'):
            self.get_logger().info(f'{p.stage} placement {p.index + 1}/{stats["planned"]}: '
                                   f'{text}')

    def _wait_action(self, placement: int) -> str:
        """The operator's next answer to the instruction of ``placement``."""
        cap = self._cap
        cap.actions.clear()
        cap.expect = placement
        timeout = self.get_parameter('operator_timeout').value
        t_end = time.monotonic() + timeout
        try:
            while not cap.actions:
                if time.monotonic() > t_end:
                    raise RuntimeError(f'no answer from the operator within {timeout:.0f} s '
                                       '(calibration/operator)')
                self._cap_executor.spin_once(timeout_sec=0.05)
            return cap.actions.pop(0)
        finally:
            cap.expect = None

    def _look(self, p, volts, bag, note, laser_on=False):
        """Record frames at ``volts`` (laser off unless ``laser_on``) into ``bag`` and read
        them back."""
        step = CaptureStep(p.index, None, volts, laser_on, frame_rate=50.0, note=note)
        self._record_step(step, bag)
        return stage_runner.views_from_bags([bag])

    def _search(self, p, model, targets, run_dir, stats):
        """Find the target after "placed" (:func:`operator_flow.search`), each look recorded
        under ``run_dir/search``."""
        def look(volts):
            n = stats['search_scans']
            stats['search_scans'] += 1
            stats['search_views'] += len(volts)
            return self._look(p, volts, run_dir / 'search' / f'place{p.index:03d}_{n:03d}',
                              f'{p.stage}: search for placement {p.index}')

        def note(volts, loc):
            self.get_logger().info(f'{p.stage} placement {p.index}: search of {len(volts)} '
                                   f'view(s): {loc.note}')

        def look_lit(volts):
            n = stats['search_scans']
            stats['search_scans'] += 1
            return self._look(p, volts, run_dir / 'search' / f'place{p.index:03d}_{n:03d}',
                              f'{p.stage}: laser line on placement {p.index}', laser_on=True)

        return operator_flow.search(model, p, targets, look, note, look_lit)

    def _operator_capture(self, stage, steps, run_dir, t0, bags, by_robot=False,
                          after_step=None, first=0):
        """The plan's placements through the operator (see the module), until the stage's
        standard errors meet their targets (:mod:`calibration_tools.stopping`), its most
        placements are kept or the operator says done; returns (frames, frames wanted,
        placements kept)."""
        from calibration_tools import capture_plans as cp

        model = cp.current_model(self.calibration)
        targets = getattr(steps, 'targets', None) or cp.choose_targets(model)
        from reconstructor.planning import stripe_layout

        places = operator_flow.placements(stage, steps, by_robot,
                                          across=stripe_layout(model).across)
        stats = operator_flow.new_stats(len(places))
        most = stopping.stage_max(stage, len(places))
        least = stopping.stage_min(stage, len(places))
        stats['placements_max'] = most
        self.operator_stats[stage] = stats
        max_moves = int(self.get_parameter('max_moves').value)
        kept, measured = [], {}
        order = list(range(len(places)))  # placements still to ask for, next first

        def skip(p, why: str) -> None:
            """Leave out placement ``p``, the next one first: the operator moved it
            ``max_moves`` times without a view the gates keep."""
            self.get_logger().warning(f'{stage} placement {p.index} skipped after {why}')
            stats['skipped'] += 1
            order.pop(0)
        progress = stopping.Progress(stage, model, most)
        assessment = self._assess(stage, model, targets, places, kept, order, progress)
        self._publish_progress(progress, stats, assessment)
        moves, frames, wanted, counter = 0, 0, 0, first
        state, text, move = 'place', '', None
        t_start = time.monotonic()
        while order and stats['placed'] < most:
            p = places[order[0]]
            if state == 'place':
                self._instruct(stats, p, 'place', operator_flow.describe(p, text))
            else:
                self._instruct(stats, p, 'move', text, move)
            action = self._wait_action(p.index)
            if action == 'done':
                stats['done_early'] = True
                break
            if action in ('skip', 'undo'):
                if action == 'skip':
                    stats['skipped'] += 1
                    order.pop(0)
                elif kept:
                    q, mine, got, n, _, _ = kept.pop()
                    for bag in mine:
                        shutil.rmtree(bag, ignore_errors=True)
                        bags.remove(bag)
                    frames, wanted = frames - got, wanted - n
                    measured.pop(q.index, None)
                    stats['placed'] -= 1
                    stats['undone'] += 1
                    order.insert(0, places.index(q))
                    progress.forget(q.index)
                    assessment = self._assess(stage, model, targets, places, kept, order, progress)
                    self._publish_progress(progress, stats, assessment)
                state, text, moves = 'place', 'Undone: ' if action == 'undo' else '', 0
                continue
            T, why, views, loc = None, None, p.plan_steps, None
            if not p.by_robot:
                self._instruct(stats, p, 'search', 'Searching for the target: keep it still.')
                loc, why = self._search(p, model, targets, run_dir, stats)
                T = None if loc is None else loc.V0_T_target
                if loc is not None and loc.features is not None:
                    self._publish_progress(progress, stats, assessment,
                                           (loc.features, why is None, '' if why is None
                                            else why.reason, loc.stamp))
                if why is None:
                    try:
                        views = operator_flow.views_for(model, p, T, targets)
                    except ValueError as exc:
                        why = operator_flow.reach_move(model, p, T[:3, 3], str(exc))
            if why is not None:
                stats['refused'][why.reason] = stats['refused'].get(why.reason, 0) + 1
                moves += 1
                if moves > max_moves:
                    skip(p, f'{max_moves} moves: {why.words}')
                    state, text, moves = 'place', '', 0
                    continue
                state, text, move = 'move', why.words, why
                continue
            mine = []
            try:
                self._instruct(stats, p, 'capture', 'Capturing: hold it still.')
                got, n = self._run_steps(stage, views, run_dir, t0, mine, after_step,
                                         first=counter)
                counter += len(views)
                shift, reason, seen, fits, at = 0.0, '', [], [], None
                if not p.by_robot:
                    after, still = self._check(p, loc.check_voltages, run_dir, counter)
                    shift = operator_flow.feature_shift_px(loc.features, after)
                    reason, seen, fits, at = self._gate(model, p, mine, still, progress,
                                                        stats, assessment)
            except BaseException:
                for bag in mine:
                    shutil.rmtree(bag, ignore_errors=True)
                raise
            if shift > operator_flow.MOVED_PX or reason:
                for bag in mine:
                    shutil.rmtree(bag, ignore_errors=True)
                if shift > operator_flow.MOVED_PX:
                    reason = 'moved'
                    stats['rejected']['moved'] = stats['rejected'].get('moved', 0) + got
                moves += 1
                if moves > max_moves:  # a gate that rejects every retake: leave it out
                    skip(p, f'{max_moves} retakes: {reason}')
                    state, text, moves = 'place', '', 0
                    continue
                state, move = 'place', None
                text = {'moved': f'The target moved during the capture ({shift:.1f} px): '
                                 'its views are retaken. ',
                        'motion_blur': 'A view was blurred by motion: hold the target '
                                       'still; its views are retaken. ',
                        'reprojection_outlier': 'Its pattern did not fit one flat board '
                                                '(warped, covered or misdetected): '
                                                'its views are retaken. '}.get(
                    reason, f'A view was rejected ({reason}): its views are retaken. ')
                self.get_logger().warning(f'{stage} placement {p.index}: {text}')
                continue
            bags += mine
            frames, wanted = frames + got, wanted + n
            kept.append((p, mine, got, n, T, at))
            if T is not None:
                measured[p.index] = T
            progress.keep(p.index, seen, [v.voltages for v in views], fits)
            stats['placed'] += 1
            stats['views'] += got
            order.pop(0)
            state, text, moves = 'place', '', 0
            assessment = self._assess(stage, model, targets, places, kept, order, progress)
            self._publish_progress(progress, stats, assessment)
            if stats['placed'] >= least and assessment.targets_met:
                stats['targets_met'] = True
                self.get_logger().info(f'{stage}: every standard error meets its target '
                                       f'after {stats["placed"]} placements')
                break
            if assessment.best is not None and order:
                order.insert(0, order.pop(assessment.best))
        stats['seconds'] = time.monotonic() - t_start
        stats['targets_met'] = bool(assessment.targets_met)
        if measured:
            operator_flow.write_measured_poses(run_dir / operator_flow.MEASURED_POSES, measured)
        done = CalibrationInstruction(stage=stage, state='done', text=(
            f'{stage}: {stats["placed"]} of {len(places)} placements captured; '
            + operator_flow.stats_line(stats)))
        done.placements_planned, done.placements_done = len(places), stats['placed']
        done.views_captured = stats['views']
        done.views_rejected = sum(stats['rejected'].values())
        done.rejected_reasons = list(stats['rejected'])
        done.rejected_counts = [int(v) for v in stats['rejected'].values()]
        done.searches = stats['search_views']
        self._publish(done)
        self._publish_progress(progress, stats, assessment)
        return frames, wanted, stats['placed']

    def _assess(self, stage, model, targets, places, kept, order, progress):
        """The stage's standard errors against its targets and the advice (the placements
        still to ask for are the candidates)."""
        try:
            from calibration_tools.dynamic_camera import intrinsics_standard_errors

            return stopping.assess(stage, model, targets,
                                   [(q, T, at) for q, _, _, _, T, at in kept if T is not None],
                                   [places[k] for k in order], places,
                                   noise_px=progress.feature_noise_px(),
                                   prior_sigma=intrinsics_standard_errors(self.calibration))
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.get_logger().warning(f'{stage}: standard errors not predicted: {exc}')
            return stopping.assess('', model, targets, [], [places[k] for k in order])

    def _gate(self, model, p, bags, still, progress, stats, assessment):
        """The reprojection and motion-blur gates on the placement's laser-off views (read
        back from ``bags``); each view is published on calibration/progress. Returns (the
        first rejection's reason or '', the kept views' features, their boards' reprojection
        RMS [px], the G1 voltages (n, 2) of the views that showed the target)."""
        seen, reason, fits, at = [], '', [], []
        try:
            views = [v for v in stage_runner.views_from_bags(bags) if not v.laser_on]
        except ValueError:
            return '', seen, fits, None
        for v in views:
            pts, why, rms = operator_flow.gate_view(model, p, v.image, still)
            if not why and math.isfinite(rms):
                fits.append(rms)
            if why == 'not_detected' and p.kind in ('circle_board', 'sphere'):
                why = ''  # a raster view off the board, or the sphere's: the stage judges
            if why:
                stats['rejected'][why] = stats['rejected'].get(why, 0) + 1
                reason = reason or why
            elif pts is not None:
                seen.append(pts)
                at.append(np.asarray(v.voltages, dtype=np.float64)[:2])
            self._publish_progress(progress, stats, assessment,
                                   (pts, not why, why, v.stamp))
        return reason, seen, fits, np.array(at).reshape(-1, 2)

    def _check(self, p, voltages, run_dir, counter):
        """The motion gate's view of the target after its views: its features, and how far
        its edges spread when still (the motion-blur gate's reference)."""
        step = operator_flow.check_step(p, voltages)
        got = self._look(p, step.voltages, run_dir / 'checks' /
                         f'place{p.index:03d}_{counter:03d}', step.note)
        if not got:
            return None, math.nan
        pts = operator_flow.features(p, got[0].image)
        return pts, (operator_flow.edge_spread_px(got[0].image, pts) if pts is not None
                     else math.nan)

    def _run_steps(self, stage, steps, run_dir, t0, bags: list, after_step=None, first=0):
        """Record every step into its own bag under ``run_dir`` (numbered from ``first``),
        appending each bag's path to ``bags`` as it starts; ``after_step(i, step)`` may refuse
        what was just recorded (raise). Returns (frames, frames wanted)."""
        frames, wanted = 0, 0
        total = sum(len(s.voltages) for s in steps)
        for i, step in enumerate(steps):
            bag = run_dir / f'pose{step.pose_index:03d}_step{first + i:03d}'
            bags.append(str(bag))
            got, n = self._record_step(step, bag)
            frames, wanted = frames + got, wanted + n
            if after_step is not None:
                after_step(i, step)
            elapsed = time.monotonic() - t0
            eta = elapsed / max(frames, 1) * (total - frames)
            self.get_logger().info(f'capture {stage}: step {i + 1}/{len(steps)}, '
                                   f'{frames}/{total} frames, ETA {eta:.0f} s')
        return frames, wanted

    # -- robot poses from the pose topic ----------------------------------------------
    def _pose_topic_input(self, stage: str) -> str:
        """The stage input recorded from the pose topic ('' when the stage has none or the
        operator gave it as a parameter)."""
        name = stage_entry(stage).pose_topic_input
        return name if name and not self.get_parameter(name).value else ''

    def _hold_robot_pose(self):
        """Wait (up to robot_pose_max_age) for a fresh robot pose and hold it."""
        cap, watch = self._cap, self._cap.watch
        watch.release()
        watch.set_limits(*(self.get_parameter(n).value for n in (
            'robot_pose_max_age', 'robot_still_m', 'robot_still_rad')))
        t_end = time.monotonic() + watch.max_age + 0.5
        while True:
            self._cap_executor.spin_once(timeout_sec=0.02)
            try:
                return watch.hold(cap.now(), cap.pose_topic)
            except ValueError:
                if time.monotonic() > t_end:
                    raise

    def _capture_robot_pose(self, stage, req, resp, t0):
        """One robot pose of a stage whose poses come from the pose topic (see the module)."""
        cap, name = self._cap, self._pose_topic_input(stage)
        root = Path(req.output_dir or self.get_parameter('data_dir').value)
        series = self._series.get(stage)
        if series is None or series.root != root:
            series = _PoseSeries(root, _new_run_dir(root, stage),
                                 self.get_parameter('robot_flange_frame').value)
        number, bags = len(series.poses), []
        try:
            T, _, base = self._hold_robot_pose()
            if series.base_frame and base != series.base_frame:
                raise ValueError(f'the pose is in frame {base}, the series\' earlier poses in '
                                 f'{series.base_frame}')
            poses = robot_poses.RobotPoses(base, series.flange_frame, T[None], (number,),
                                           cap.pose_topic)
            steps = plan(stage, self.calibration, quick=self.get_parameter('quick').value,
                         inputs={**self._inputs(stage), name: poses})
            if req.max_frames:
                steps = _cap_frames(steps, req.max_frames)

            def still(i, step):
                cap.watch.check_still(cap.now(), f'robot pose {number}, step {i + 1}/'
                                      f'{len(steps)} ({step.note})', cap.pose_topic)

            frames, wanted, _ = self._operator_capture(
                stage, steps, series.run_dir, t0, bags, by_robot=True, after_step=still,
                first=len(series.bags))
            recorded = robot_poses.RobotPoses(
                base, series.flange_frame, np.stack([*series.poses, T]),
                tuple(range(number + 1)), cap.pose_topic)
            robot_poses.write_robot_poses(recorded, series.run_dir / RECORDED_POSES)
        except (RuntimeError, ValueError, OSError) as exc:
            for bag in bags:  # a refused pose leaves nothing behind
                shutil.rmtree(bag, ignore_errors=True)
            self.counters['robot_poses_refused'] += 1
            resp.success = False
            resp.message = f'capture {stage}: robot pose {number} refused: {exc}'
            self.get_logger().error(resp.message)
            return resp
        finally:
            cap.watch.release()
        series.poses.append(T)
        series.bags += bags
        series.base_frame = base
        self._series[stage] = series
        self._last_bags[stage] = list(series.bags)
        self.counters['captures'] += 1
        self.counters['frames_recorded'] += frames
        self.counters['robot_poses_recorded'] += 1
        resp.success = frames > 0
        resp.bag_path, resp.frames_recorded = str(series.run_dir), frames
        resp.poses = len(series.poses)
        resp.duration = time.monotonic() - t0
        resp.message = (f'{stage}: robot pose {number} recorded from {cap.pose_topic} '
                        f'({base} -> {series.flange_frame} at '
                        f'{np.round(T[:3, 3], 4).tolist()} m), {frames}/{wanted} frames in '
                        f'{len(bags)} bags under {series.run_dir}; {len(series.poses)} robot '
                        f'poses in this series (compute needs at least '
                        f'{robot_poses.MIN_POSES})')
        self.get_logger().info(resp.message)
        return resp

    def _inputs(self, stage: str) -> dict:
        """What the operator supplies for ``stage`` (node parameters named as its inputs)."""
        entry = stage_entry(stage)
        out = {k: self.get_parameter(k).value for k in entry.inputs}
        out.update({k: self.get_parameter(k).value for k in OVERRIDABLE
                    if k in entry.options and self.has_parameter(k)})
        return out

    # -- compute ----------------------------------------------------------------------
    def _on_compute(self, req, resp):
        resp.reprojection_rms = resp.residual_rms = float('nan')
        stage = req.stage
        bags = list(req.bag_paths) or self._last_bags.get(stage, [])
        if stage not in KNOWN_STAGES or not bags or self.calibration is None:
            resp.success = False
            resp.message = (f"unknown stage '{stage}'" if stage not in KNOWN_STAGES else
                            'no bags given and none captured for this stage'
                            if not bags else 'no starting calibration')
            return resp
        t0 = time.monotonic()

        def progress(done, total, note=''):
            eta = (time.monotonic() - t0) / max(done, 1) * (total - done)
            self.get_logger().info(f'compute {stage}: {done}/{total} {note} ETA {eta:.0f} s')

        try:
            inputs = self._inputs(stage)
            name = self._pose_topic_input(stage)
            if name:  # the poses recorded with these bags
                inputs[name] = str(_recorded_poses(bags))
            if 'measured_poses' in stage_entry(stage).options:
                inputs['measured_poses'] = operator_flow.read_measured_poses(bags)
            views = stage_runner.views_from_bags(bags)
            result = stage_runner.compute(stage, views, self.calibration, progress=progress,
                                          inputs=inputs)
            sources = [{'path': b, 'sha256': stage_runner.bag_digest(b)} for b in bags]
            new = apply_result(self.calibration, result, sources)
            path = self.get_parameter('calibration_file').value
            calibration_file.save(new, path)
        except (RuntimeError, ValueError, OSError) as exc:
            resp.success, resp.message = False, f'compute {stage} failed: {exc}'
            self.get_logger().error(resp.message)
            return resp
        self.calibration = new
        self.counters['computes'] += 1
        series = self._series.get(stage)
        if series is not None and name and Path(inputs[name]).parent == series.run_dir:
            del self._series[stage]  # computed: the next capture starts a new series
        resp.success = True
        resp.samples_used, resp.samples_rejected = result.samples_used, result.samples_rejected
        r = result.residuals
        resp.reprojection_rms = float(r.get('reprojection_rms_px', float('nan')))
        metric = [v for k, v in r.items() if k.endswith('_m') and 'rms' in k]
        resp.residual_rms = float(metric[0]) if metric else float('nan')
        flat = stage_runner.flatten(result.updates)
        resp.parameter_names = list(flat)
        resp.parameter_values = [float(v) for v in flat.values()]
        resp.calibration_path = new.path
        resp.message = (f'{stage}: {result.samples_used} used, {result.samples_rejected} '
                        f'rejected; ' + ', '.join(f'{k}={v:.4g}' for k, v in r.items()))
        if 'coverage' in result.extra:  # views used, voltage ranges spanned, residuals
            resp.message += '\n' + stage_runner.coverage_line(stage, result.extra['coverage'])
        try:  # the calibration as it now stands: good, or which stage to redo and where
            resp.message += '\nverdict: ' + stage_runner.verdict(new)
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            resp.message += f'\nverdict: not formed ({exc})'
        self.get_logger().info(resp.message)
        return resp

    # -- file -------------------------------------------------------------------------
    def _on_load(self, req, resp):
        try:
            cal = calibration_file.load(req.path)
        except ValueError as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        self.calibration = cal
        resp.success, resp.path, resp.content_hash = True, cal.path, cal.content_hash
        resp.stages = list(cal.stages)
        resp.message = f'loaded {cal.path}'
        return resp

    def _on_save(self, req, resp):
        if self.calibration is None:
            resp.success, resp.message = False, 'no calibration to save'
            return resp
        path = req.path or self.get_parameter('calibration_file').value
        try:
            resp.content_hash = calibration_file.save(self.calibration, path)
        except (ValueError, OSError) as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        resp.success, resp.path, resp.message = True, self.calibration.path, f'saved {path}'
        return resp

    def destroy_node(self):
        self._cap_executor.shutdown()
        self._cap.destroy_node()
        return super().destroy_node()


#: The file a series of robot poses recorded from the pose topic is written to, beside its
#: bags (the offline command reads it with --robot-poses).
RECORDED_POSES = 'robot_poses.yaml'


def _new_run_dir(root: Path, stage: str) -> Path:
    """``root/<stage>_<time>``, with a suffix if a capture of this second already has it."""
    base = root / f"{stage}_{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir, n = base, 1
    while run_dir.exists():
        n += 1
        run_dir = base.with_name(f'{base.name}_{n}')
    return run_dir


def _recorded_poses(bags) -> Path:
    """The robot poses file the node wrote beside ``bags`` (all in one run folder)."""
    folders = {Path(b).parent for b in stage_runner.expand_bag_dirs(bags)}
    found = sorted(f / RECORDED_POSES for f in folders if (f / RECORDED_POSES).is_file())
    if len(found) != 1 or len(folders) != 1:
        raise ValueError(f'the bags are not one series recorded from the robot pose topic '
                         f'(folders {sorted(str(f) for f in folders)}, {len(found)} with '
                         f'{RECORDED_POSES}); or set the robot_poses parameter to a poses file')
    return found[0]


def _cap_frames(steps, max_frames):
    out, left = [], int(max_frames)
    for step in steps:
        if left <= 0:
            break
        out.append(step if len(step.voltages) <= left else step.truncated(left))
        left -= len(out[-1].voltages)
    return out


def main(args=None):
    rclpy.init(args=args)
    node = CalibrationNode()
    forward_python_logging(node.get_logger())  # the stages' coverage lines and warnings
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
