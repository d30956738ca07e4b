"""``calibration_node``: every calibration stage as ROS services.

Services
    calibration/capture  galvoscan_msgs/CaptureCalibration: run the stage's capture plan
                         on the driver (``sim/set_scene`` to place boards and the sphere in
                         the simulator, ``scan/start`` for each pattern) and record
                         ``camera/image_raw`` + ``galvo/state`` into one rosbag2 directory
                         per pose under ``data_dir``.
    calibration/compute  galvoscan_msgs/ComputeCalibration: run the stage on captured bags,
                         merge the result into the active calibration and save it
                         atomically to ``calibration_file``.
    calibration/load     galvoscan_msgs/LoadCalibration
    calibration/save     galvoscan_msgs/SaveCalibration

Long stages log their progress (counts and an ETA). The stage maths lives in the pure
modules (``stage_runner``, ``capture_plans`` and the stage modules); this node only moves
data between ROS and them.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import rclpy
from galvoscan_msgs.msg import GalvoState
from galvoscan_msgs.srv import (
    CaptureCalibration,
    ComputeCalibration,
    GetScanProgress,
    LoadCalibration,
    SaveCalibration,
    SetScene,
    StartScan,
)
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from calibration_tools import stage_runner
from calibration_tools.registry import plan
from calibration_tools.stages import KNOWN_STAGES, apply_result
from galvoscan_bag.writer import BagWriter
from galvoscan_common.boundary import CallbackErrors, guard_service, guard_subscription
from galvoscan_common.diagnostics import publish_periodically
from galvoscan_common.executor import call_service
from reconstructor import calibration_file


class _Capture(Node):
    """The node that talks to the driver and records, spun only while a capture runs."""

    def __init__(self, context, errors: CallbackErrors):
        super().__init__('calibration_capture', context=context)
        self.writer = None
        self.frames = 0
        self.states = 0
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        log = self.get_logger()
        self.create_subscription(Image, 'camera/image_raw', guard_subscription(
            'camera/image_raw', self._on_image, log, errors), qos, raw=True)
        self.create_subscription(GalvoState, 'galvo/state', guard_subscription(
            'galvo/state', self._on_state, log, errors), qos, raw=True)
        self.clients_ = {n: self.create_client(t, n) for n, t in (
            ('scan/start', StartScan), ('scan/progress', GetScanProgress),
            ('sim/set_scene', SetScene))}

    def _on_image(self, data):
        if self.writer is not None:
            self.writer.write('/camera/image_raw', data, time.time_ns())
            self.frames += 1

    def _on_state(self, data):
        if self.writer is not None:
            self.writer.write('/galvo/state', data, time.time_ns())
            self.states += 1


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
        self.declare_parameter('cell_reference', '', ParameterDescriptor(
            description='cell_extrinsic: YAML of the robot-reported sphere positions in the '
                        'cell frame (calibration_tools.cell_extrinsic.read_reference)'))
        self._last_bags = {}
        self.calibration = self._initial()
        self.callback_errors = CallbackErrors()
        self.counters = {'captures': 0, 'computes': 0, 'frames_recorded': 0}
        for srv_type, name, callback in (
                (CaptureCalibration, 'calibration/capture', self._on_capture),
                (ComputeCalibration, 'calibration/compute', self._on_compute),
                (LoadCalibration, 'calibration/load', self._on_load),
                (SaveCalibration, 'calibration/save', self._on_save)):
            self.create_service(srv_type, name, guard_service(
                name, callback, self.get_logger(), self.callback_errors))
        publish_periodically(
            self, 'calibration', lambda: self.counters, self.callback_errors,
            message=lambda: ('calibration loaded' if self.calibration is not None
                             else 'no calibration loaded'))
        self._cap_executor = SingleThreadedExecutor(context=self.context)
        self._cap = _Capture(self.context, self.callback_errors)
        self._cap_executor.add_node(self._cap)

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
        return call_service(self._cap_executor, self._cap.clients_[name], request, timeout)

    def _record_step(self, step, bag_dir):
        cap = self._cap
        if step.scene_yaml:
            resp = self._call('sim/set_scene', SetScene.Request(scene_yaml=step.scene_yaml))
            if not resp.success:
                raise RuntimeError(f'sim/set_scene: {resp.message}')
        # drop frames of earlier scans still queued in the subscriptions
        quiet = time.monotonic() + 0.2
        while time.monotonic() < quiet:
            self._cap_executor.spin_once(timeout_sec=0.02)
        writer = BagWriter(bag_dir)
        writer.open()
        writer.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        writer.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
        cap.writer, cap.frames, cap.states = writer, 0, 0
        try:
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
        try:
            steps = plan(stage, self.calibration, quick=self.get_parameter('quick').value,
                         inputs=self._inputs(stage))
            if req.max_frames:
                steps = _cap_frames(steps, req.max_frames)
            root = Path(req.output_dir or self.get_parameter('data_dir').value)
            run_dir = root / f"{stage}_{time.strftime('%Y%m%d-%H%M%S')}"
            bags, frames, wanted = [], 0, 0
            total = sum(len(s.voltages) for s in steps)
            for i, step in enumerate(steps):
                bag = run_dir / f'pose{step.pose_index:03d}_step{i:03d}'
                got, n = self._record_step(step, bag)
                bags.append(str(bag))
                frames, wanted = frames + got, wanted + n
                elapsed = time.monotonic() - t0
                eta = elapsed / max(frames, 1) * (total - frames)
                self.get_logger().info(f'capture {stage}: step {i + 1}/{len(steps)}, '
                                       f'{frames}/{total} frames, ETA {eta:.0f} s')
        except (RuntimeError, ValueError, OSError) as exc:
            resp.success, resp.message = False, f'capture {stage} failed: {exc}'
            self.get_logger().error(resp.message)
            return resp
        self._last_bags[stage] = bags
        self.counters['captures'] += 1
        self.counters['frames_recorded'] += frames
        resp.success = frames > 0
        resp.bag_path, resp.frames_recorded = str(run_dir), frames
        resp.poses = len({s.pose_index for s in steps})
        resp.duration = time.monotonic() - t0
        resp.message = (f'{stage}: recorded {frames}/{wanted} frames in {len(bags)} bags '
                        f'under {run_dir}')
        self.get_logger().info(resp.message)
        return resp

    def _inputs(self, stage: str) -> dict:
        """What the operator supplies for ``stage`` (node parameters named as its inputs)."""
        from calibration_tools.registry import stage as stage_entry

        return {k: self.get_parameter(k).value for k in stage_entry(stage).inputs}

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
            views = stage_runner.views_from_bags(bags)
            result = stage_runner.compute(stage, views, self.calibration, progress=progress,
                                          inputs=self._inputs(stage))
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
