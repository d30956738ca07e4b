"""``galvo_driver``: the lifecycle node in front of a galvo backend (sim, serial, replay, rig).

Topics (published reliable; consumers subscribe with sensor-data QoS):
    camera/image_raw   sensor_msgs/Image (mono8; mono16 for Mono10/12/16), stamp = middle of
                       the exposure
    camera/camera_info sensor_msgs/CameraInfo, same stamp (from ``calibration_file`` when
                       given, else from the simulator's rig)
    galvo/state        galvoscan_msgs/GalvoState, same stamp and the frame's sequence number
Services:
    scan/start     galvoscan_msgs/StartScan; a request whose ``request_id`` the driver has
                   answered before (its answer lost on the way, the caller resent it) gets
                   that answer again and starts nothing; the same id with another request
                   is refused
    scan/stop      galvoscan_msgs/StopScan
    scan/progress  galvoscan_msgs/GetScanProgress
    sim/set_scene  galvoscan_msgs/SetScene (sim backend only; not offered by a driver
                   started on ``rig``)

Camera parameters (backend ``rig``), GenICam features by their SFNC names and units, as
camera_aravis2 has them: ``ExposureTime`` [us], ``Gain``, ``PixelFormat``, ``Width``,
``Height``, ``OffsetX``, ``OffsetY`` [px], ``AcquisitionFrameRate`` [Hz]; 0 (or '') keeps
the camera's own value. While configured, a change is written to the camera after it is
checked against the camera's own range; a refused value is reported with the camera's
reason and nothing changes. Size and pixel format change only while inactive.

Lifecycle: configure opens the backend (rig: the board, with its protocol version checked,
and the camera), activate arms it (rig: the camera starts acquiring, waiting for trigger
edges), deactivate/error/shutdown drive the galvos to 0 V with the laser off (rig: and stop
the camera). ``autostart`` (default true) configures and activates at
start-up. ``main`` puts the hardware in the safe state in its ``finally``, since rclpy does
not run ``on_shutdown`` on SIGINT/SIGTERM.
"""

from __future__ import annotations

import collections
import hashlib
import time

import numpy as np
import rclpy
from galvoscan_msgs.msg import GalvoState
from galvoscan_msgs.srv import GetScanProgress, SetScene, StartScan, StopScan
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from galvo_driver import patterns
from galvo_driver.backend import BackendError
from galvoscan_common import cdr, intra
from galvoscan_common.boundary import CallbackErrors, guard_service
from galvoscan_common.diagnostics import publish_periodically
from galvoscan_common.logbridge import forward_python_logging
from galvoscan_common.runtime import freeze_startup_heap, tune_this_process

BACKENDS = ('sim', 'serial', 'replay', 'rig')
#: StartScan answers kept for resends, by request_id (the newest ones)
ANSWERED_STARTS_KEPT = 64
#: Longest StartScan request_id [characters]: a uuid is 36; the answers kept hold their ids
REQUEST_ID_MAX_CHARS = 256
#: Camera parameters of the rig backend: GenICam feature name -> (default meaning "keep the
#: camera's value", descriptor range, description).
CAMERA_PARAMS = {
    'ExposureTime': (0.0, (0.0, 10_000_000.0), 'rig: camera exposure [us] (0: keep)'),
    'Gain': (0.0, (0.0, 1000.0), "rig: camera gain, in the camera's unit (usually dB)"),
    'PixelFormat': ('', None, "rig: Mono8, Mono10, Mono12 or Mono16 ('': keep)"),
    'Width': (0, (0, 65535), 'rig: region of interest width [px] (0: keep)'),
    'Height': (0, (0, 65535), 'rig: region of interest height [px] (0: keep)'),
    'OffsetX': (0, (0, 65535), 'rig: region of interest left column [px]'),
    'OffsetY': (0, (0, 65535), 'rig: region of interest top row [px]'),
    'AcquisitionFrameRate': (0.0, (0.0, 100_000.0),
                             'rig: free-running frame rate limit [Hz] (0: keep)'),
}
PIXEL_FORMATS = ('Mono8', 'Mono10', 'Mono12', 'Mono16')
#: Parameters that only change while unconfigured.
_CONFIGURE_ONLY = ('rig', 'scene', 'seed', 'exposure', 'laser_power', 'auto_exposure',
                   'auto_exposure_frames', 'max_laser_power', 'hdr_ratio', 'backend',
                   'serial_port',
                   'replay_bag',
                   'camera_serial', 'camera_user_id', 'trigger_source', 'camera_clock',
                   'frame_timeout', 'calibration_file')
#: Poll period of the backend while a scan runs [s] (frames at up to 1 kHz).
SCAN_POLL_PERIOD = 0.001
#: Poll period while no scan runs [s]: backend faults are still seen within 0.1 s, and an
#: idle driver costs next to no CPU.
IDLE_POLL_PERIOD = 0.1


def make_backend(name: str, params: dict):
    """Instantiate a backend by name from the node's parameter values."""
    if name == 'sim':
        from galvo_driver.sim_backend import SimBackend
        return SimBackend(rig=params['rig'], scene=params['scene'], seed=params['seed'],
                          exposure=params.get('exposure', 0.0),
                          laser_power=params.get('laser_power', 1.0),
                          auto_exposure=params.get('auto_exposure', False),
                          auto_exposure_frames=params.get('auto_exposure_frames', 5),
                          max_laser_power=params.get('max_laser_power', 1.0),
                          hdr_ratio=params.get('hdr_ratio', 1.0))
    if name == 'serial':
        from galvo_driver.serial_link.backend import SerialBackend
        return SerialBackend(params['serial_port'])
    if name == 'replay':
        from galvo_driver.replay_backend import ReplayBackend
        return ReplayBackend(params['replay_bag'], rate=params['replay_rate'])
    if name == 'rig':
        from galvo_driver.rig_backend import RigBackend
        features = {k: params[k] for k in CAMERA_PARAMS
                    if k in params and params[k] not in (0, 0.0, '')}
        if params.get('OffsetX') or params.get('OffsetY'):  # 0 is a real offset once asked
            features.update(OffsetX=params.get('OffsetX', 0), OffsetY=params.get('OffsetY', 0))
        return RigBackend(params['serial_port'], camera_serial=params.get('camera_serial'),
                          camera_user_id=params.get('camera_user_id'), features=features,
                          trigger_source=params.get('trigger_source', 'Line0'),
                          camera_clock=params.get('camera_clock', 'camera'),
                          frame_timeout=params.get('frame_timeout', 0.3),
                          auto_exposure=params.get('auto_exposure', False),
                          auto_exposure_frames=params.get('auto_exposure_frames', 5),
                          hdr_ratio=params.get('hdr_ratio', 1.0))
    raise ValueError(f"backend: unknown '{name}'; known: {', '.join(BACKENDS)}")


def _stamp(frame) -> tuple[int, int]:
    """(sec, nanosec) of a frame's stamp."""
    ns = frame.stamp_ns if frame.stamp_ns is not None else int(round(frame.stamp * 1e9))
    return divmod(ns, 1_000_000_000)


class GalvoDriverNode(LifecycleNode):
    """Lifecycle node publishing frames and galvo states from one backend."""

    def __init__(self, **kwargs):
        super().__init__('galvo_driver', **kwargs)
        d = self._declare
        d('backend', 'sim', f"frame source: {', '.join(BACKENDS)}")
        d('rig', 'reference', 'sim: rig description (name of a shipped rig or a YAML path)')
        d('scene', 'stair_block', 'sim: scene (name of a shipped scene or a YAML path)')
        d('seed', 0, 'sim: random seed for noise and jitter', ints=(0, 2 ** 31 - 1))
        d('exposure', 0.0, "sim: laser-frame exposure [s] (0: the rig's)", floats=(0.0, 1.0))
        d('laser_power', 1.0, "sim: laser power relative to the rig's [1]",
          floats=(0.0, 100.0))
        d('auto_exposure', False, 'sim, rig: set each laser scan\'s exposure from a short '
          'pre-scan (stripe peak at 0.7 of full scale, within the camera\'s limits and the '
          'frame period; rig: ExposureTime within its own bounds and increment)')
        d('auto_exposure_frames', 5, 'sim, rig: pre-scan frames of auto_exposure [1]',
          ints=(1, 100))
        d('max_laser_power', 1.0, 'sim: auto_exposure may raise the laser power up to this '
          "(relative to the rig's) where the longest exposure within the frame period is "
          'too short [1]', floats=(0.0, 100.0))
        d('hdr_ratio', 1.0, 'sim, rig: HDR, every laser-scan position taken twice, at the '
          'exposure and at the exposure over this (1: off; the extractor\'s hdr_pairs merges '
          'them; rig: a long pass then a short one, frames handed out in pairs) [1]',
          floats=(1.0, 1000.0))
        d('serial_port', '', 'serial, rig: pyserial port or URL of the DAC board')
        d('camera_serial', '', 'rig: DeviceSerialNumber of the camera (arv-tool-0.8 lists it)')
        d('camera_user_id', '', 'rig: DeviceUserID of the camera')
        d('trigger_source', 'Line0', 'rig: camera input wired to the board trigger output')
        d('camera_clock', 'camera', "rig: 'host' if the camera stamps in host time (PTP), "
          "else 'camera'")
        d('frame_timeout', 0.3, "rig: how long the scan's frames are waited for after the "
          "board's last trigger and the camera's last frame [s]", floats=(0.01, 60.0))
        d('calibration_file', '', 'camera_info from this calibration file (the '
          "reconstructor's calibration_file); '': from the simulator's rig (sim)")
        for name, (default, rng, text) in CAMERA_PARAMS.items():
            d(name, default, text, **({} if rng is None else
                                      {'floats' if isinstance(default, float) else 'ints': rng}))
        d('replay_bag', '', 'replay: rosbag2 directory to publish')
        d('replay_rate', 1.0, 'replay: speed factor (0 = as fast as possible)',
          floats=(0.0, 100.0))
        d('frame_rate', 500.0, 'default scan frame rate [Hz]', floats=(1.0, 2000.0))
        d('camera_frame_id', 'camera_optical', 'frame_id of images and camera info')
        d('output_frame_id', 'v0', 'frame_id of galvo states (the fixed output frame)')
        d('autostart', True, 'configure and activate at start-up')
        d('max_scan_frames', patterns.MAX_SCAN_FRAMES,
          'largest scan accepted [frames]; the voltage table takes 32 bytes per frame',
          ints=(1, 100_000_000))
        d('max_scan_duration', patterns.MAX_SCAN_DURATION,
          'longest scan accepted at its frame rate [s]', floats=(1.0, 7 * 86400.0))
        d('raster_g1_axis', 'tilt', "the G1 axis a raster scan steps with G2 tilt, the one "
          "that moves the view across the stripe: 'tilt' (laser below or above the camera) "
          "or 'pan' (laser beside it); galvoscan's bring-up sets it from the calibration")
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.backend = None
        self._pubs = ()
        self._timer = None
        self._poll_period = None
        self.callback_errors = CallbackErrors()
        self._scan = {'scan_id': '', 'state': 'idle', 'total': 0, 'done': 0, 'dropped': 0,
                      't0': 0.0, 'last_seq': None}
        self._scan_count = 0
        #: request_id -> (the request's digest, the answer given), newest last
        self._answered_starts = collections.OrderedDict()
        services = [(StartScan, 'scan/start', self._on_start),
                    (StopScan, 'scan/stop', self._on_stop),
                    (GetScanProgress, 'scan/progress', self._on_progress)]
        # a rig has no simulator scene; a rig's twin serves sim/set_scene where it renders
        if self.get_parameter('backend').value != 'rig':
            services.append((SetScene, 'sim/set_scene', self._on_set_scene))
        for srv_type, name, callback in services:
            self.create_service(srv_type, name, guard_service(
                name, callback, self.get_logger(), self.callback_errors))
        #: totals over the node's life (the scan's own counts are in self._scan)
        self._totals = {'frames_published': 0, 'frames_dropped': 0, 'faults': 0}
        publish_periodically(
            self, 'galvo driver', self._counters, self.callback_errors,
            message=lambda: (f"{self._scan['state']}"
                             + (f" {self._scan['scan_id']}: {self._scan['done']}/"
                                f"{self._scan['total']} frames" if self._scan['scan_id'] else '')
                             + ('' if self.backend is not None else '; not configured')),
            warn=('faults', 'frames_dropped'))
        if self.get_parameter('autostart').value:
            self.trigger_configure()
            if self.backend is not None:
                self.trigger_activate()

    # -- parameters -------------------------------------------------------------------
    def _declare(self, name, default, description, floats=None, ints=None):
        desc = ParameterDescriptor(description=description)
        if floats:
            desc.floating_point_range = [FloatingPointRange(
                from_value=floats[0], to_value=floats[1], step=0.0)]
        if ints:
            desc.integer_range = [IntegerRange(from_value=ints[0], to_value=ints[1], step=1)]
        self.declare_parameter(name, default, desc)

    def _on_set_parameters(self, params):
        for p in params:
            if p.name == 'backend' and p.value not in BACKENDS:
                return SetParametersResult(
                    successful=False, reason=f"backend must be one of {', '.join(BACKENDS)}")
            if p.name == 'camera_clock' and p.value not in ('camera', 'host'):
                return SetParametersResult(successful=False,
                                           reason="camera_clock must be 'camera' or 'host'")
            if p.name == 'PixelFormat' and p.value not in ('',) + PIXEL_FORMATS:
                return SetParametersResult(
                    successful=False,
                    reason=f"PixelFormat must be one of {', '.join(PIXEL_FORMATS)}")
            if p.name in _CONFIGURE_ONLY and self.backend is not None:
                return SetParametersResult(
                    successful=False, reason=f'{p.name} can only change while unconfigured')
        for p in params:
            if p.name in CAMERA_PARAMS and getattr(self.backend, 'name', '') == 'rig':
                reason = self._set_camera_feature(p.name, p.value)
                if reason:
                    return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _set_camera_feature(self, name: str, value) -> str:
        """Write a camera parameter to the configured rig camera; '' or why it was refused."""
        from galvo_driver.genicam_camera import CameraError

        if value in (0, 0.0, '') and name not in ('OffsetX', 'OffsetY'):
            return f"{name}: 0 / '' (keep the camera's value) only applies at configure"
        try:
            got = self.backend.set_feature(name, value)
        except (CameraError, ValueError) as exc:
            return f'{name} = {value!r} refused: {exc}'
        self.get_logger().info(f'camera {name} = {got!r}')
        return ''

    def _params(self):
        return {n: self.get_parameter(n).value for n in (
            'backend', 'rig', 'scene', 'seed', 'exposure', 'laser_power', 'auto_exposure',
            'auto_exposure_frames', 'max_laser_power', 'hdr_ratio', 'serial_port',
            'replay_bag', 'replay_rate',
            'camera_serial', 'camera_user_id', 'trigger_source', 'camera_clock',
            'frame_timeout', *CAMERA_PARAMS)}

    # -- lifecycle --------------------------------------------------------------------
    def on_configure(self, state):
        params = self._params()
        try:
            self.backend = make_backend(params['backend'], params)
            self.backend.open()
        except (BackendError, ValueError, OSError) as exc:
            self.get_logger().error(f'configure failed: {exc}')
            self.backend = None
            return TransitionCallbackReturn.FAILURE
        try:
            self._camera_info = self._make_camera_info()
        except (ValueError, OSError) as exc:
            self.get_logger().error(f'configure failed: calibration_file: {exc}')
            self._close()
            return TransitionCallbackReturn.FAILURE
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # images and states go out as CDR bytes, handed directly to in-process subscribers
        # (galvoscan run --one-process) and over DDS to everyone else
        bus = intra.bus_for(self.context)
        self._pubs = (
            intra.HandOffPublisher(self.create_lifecycle_publisher(
                Image, 'camera/image_raw', qos), bus, self._on_handoff_error),
            self.create_lifecycle_publisher(CameraInfo, 'camera/camera_info', qos),
            intra.HandOffPublisher(self.create_lifecycle_publisher(
                GalvoState, 'galvo/state', qos), bus, self._on_handoff_error))
        self.get_logger().info(f'configured backend {self.backend.name}')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        try:
            self.backend.arm()
        except BackendError as exc:
            self.get_logger().error(f'activate failed, staying inactive in the safe state: {exc}')
            self.make_safe()
            return TransitionCallbackReturn.FAILURE
        self._set_poll_period(IDLE_POLL_PERIOD)
        self.get_logger().info('active')
        return super().on_activate(state)

    def on_deactivate(self, state):
        self._stop_timer()
        self.make_safe()
        return super().on_deactivate(state)

    def on_cleanup(self, state):
        self._close()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state):
        self._stop_timer()
        self._close()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state):
        self._stop_timer()
        self.make_safe()
        return TransitionCallbackReturn.SUCCESS

    def _stop_timer(self):
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
            self._poll_period = None

    def _set_poll_period(self, period: float) -> None:
        """Poll the backend every ``period`` seconds (fast while scanning, slow when idle)."""
        if self._timer is not None and self._poll_period == period:
            return
        self._stop_timer()
        self._timer = self.create_timer(period, self._tick_boundary)
        self._poll_period = period

    def _close(self):
        if self.backend is not None:
            self.make_safe()
            try:
                self.backend.close()
            except Exception as exc:  # noqa: BLE001 - closing must not raise
                self.get_logger().error(f'closing backend: {exc}')
            self.backend = None

    def make_safe(self) -> bool:
        """Galvos to 0 V, laser off. Safe to call at any time, never raises.

        Returns False when the backend could not be put in its safe state (logged).
        """
        ok = True
        if self.backend is not None:
            try:
                self.backend.safe()
            except Exception as exc:  # noqa: BLE001 - the safe path must not raise
                self.get_logger().error(f'safe state failed: {exc}')
                ok = False
        if self._scan['state'] == 'running':
            self._scan['state'] = 'stopped'
        return ok

    # -- frames -----------------------------------------------------------------------
    def _make_camera_info(self):
        info = CameraInfo()
        path = self.get_parameter('calibration_file').value
        cam = self._calibration_camera(path) if path else \
            getattr(self.backend, 'camera_info', None)
        if cam:
            info.width, info.height = int(cam['width']), int(cam['height'])
            info.distortion_model = 'plumb_bob'
            info.d = [float(x) for x in cam['dist']]
            info.k = [float(x) for x in np.asarray(cam['K'], float).ravel()]
            info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            k = info.k
            info.p = [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
        info.header.frame_id = self.get_parameter('camera_frame_id').value
        return info

    def _calibration_camera(self, path: str) -> dict:
        """Camera intrinsics of a calibration file (the reconstructor's format); warns when
        the calibrated image size is not the camera's."""
        from reconstructor import calibration_file

        intr = calibration_file.load(path).model.intrinsics
        size = getattr(self.backend, 'image_size', None)
        if size is not None and tuple(size) != (intr.width, intr.height):
            self.get_logger().warning(
                f'{path}: calibrated for {intr.width}x{intr.height} px, the camera gives '
                f'{size[0]}x{size[1]} px: camera_info does not fit the images')
        return {'width': intr.width, 'height': intr.height, 'K': intr.matrix(),
                'dist': list(intr.dist)}

    def _counters(self) -> dict:
        out = {**self._totals, 'scans': self._scan_count,
               'backend': self.backend.name if self.backend is not None else '',
               'scan': {k: self._scan[k] for k in ('state', 'done', 'total', 'dropped')}}
        if getattr(self.backend, 'name', '') == 'rig':
            out['rig'] = self.backend.stats  # pairing/<drop kind>, drift_ppm, camera, board
            if self.backend.scan_exposure:
                levels = self.backend.pre_scan_levels
                out['rig'].update(
                    scan_exposure_s=self.backend.scan_exposure,
                    pre_scan_saturated_fraction=max((s for s, _ in levels), default=0.0),
                    pre_scan_peak_level=max((p for _, p in levels), default=0.0))
        elif getattr(self.backend, 'name', '') == 'serial':
            out['serial'] = self.backend.stats  # lost_events, ..., clock_drift_ppm
        elif getattr(self.backend, 'name', '') == 'sim' and self.backend.scan_exposure:
            levels = self.backend.pre_scan_levels
            out['sim'] = {'scan_exposure_s': self.backend.scan_exposure,
                          'scan_laser_power': self.backend.scan_laser_power,
                          'pre_scan_saturated_fraction': max((s for s, _ in levels),
                                                             default=0.0),
                          'pre_scan_peak_level': max((p for _, p in levels), default=0.0)}
        return out

    def _tick_boundary(self):
        """The poll timer as a boundary: anything unexpected puts the galvos in safe state."""
        try:
            self._tick()
        except Exception as exc:  # noqa: BLE001 - a node never dies; the rig goes safe
            n = self.callback_errors.add('poll')
            self._totals['faults'] += 1
            self.get_logger().error(f'poll failed, going safe: {exc!r} (failure {n})')
            self._scan['state'] = 'fault'
            self.make_safe()

    def _tick(self):
        if self.backend is None:
            return
        try:
            frames = self.backend.poll(0.0)
        except BackendError as exc:
            self.get_logger().error(f'backend fault, going safe: {exc}')
            self._scan['state'] = 'fault'
            self._totals['faults'] += 1
            self.make_safe()
            return
        for frame in frames:
            self._publish(frame)
        fault = getattr(self.backend, 'fault', None)
        if fault and self._scan['state'] == 'running':
            self.get_logger().error(f'backend fault, scan aborted in safe state: {fault}')
            self._scan['state'] = 'fault'
            self._totals['faults'] += 1
            self.make_safe()
        if self._scan['state'] == 'running' and not self.backend.running:
            self._scan['state'] = 'done'
            done, total = self._scan['done'], self._scan['total']
            missing = (f"; {total - done} not published ({self._scan['dropped']} of them in "
                       "sequence gaps; the backend's log says why)" if total > done else '')
            self.get_logger().info(f"scan {self._scan['scan_id']} done: {done} of {total} "
                                   f"frames published{missing}")
        if self._scan['state'] != 'running' and not self.backend.running \
                and self._timer is not None:
            self._set_poll_period(IDLE_POLL_PERIOD)

    def _publish(self, frame):
        img_pub, info_pub, state_pub = self._pubs
        scan = self._scan
        if scan['last_seq'] is not None and frame.seq != scan['last_seq'] + 1:
            gap = frame.seq - scan['last_seq'] - 1
            scan['dropped'] += max(gap, 0)
            self._totals['frames_dropped'] += max(gap, 0)
            self.get_logger().warning(f"sequence gap: {scan['last_seq']} -> {frame.seq}")
        scan['last_seq'] = frame.seq
        scan['done'] += 1
        self._totals['frames_published'] += 1
        sec, nanosec = _stamp(frame)
        state = cdr.GalvoState(
            cdr.Header(sec, nanosec, self.get_parameter('output_frame_id').value),
            int(frame.seq), *(float(v) for v in frame.voltages), bool(frame.laser_on),
            int(frame.status))
        if frame.image is not None:
            img_pub.publish(cdr.serialize_image(frame.image, cdr.Header(
                sec, nanosec, self.get_parameter('camera_frame_id').value)))
            stamp = self._camera_info.header.stamp
            stamp.sec, stamp.nanosec = sec, nanosec
            info_pub.publish(self._camera_info)
        state_pub.publish(cdr.serialize_galvo_state(state))

    def _on_handoff_error(self, exc: BaseException) -> None:
        self.get_logger().error(f'an in-process subscriber failed on a frame: {exc!r}',
                                throttle_duration_sec=5.0)

    # -- services ---------------------------------------------------------------------
    def _on_start(self, req, resp):
        key = req.request_id
        if len(key) > REQUEST_ID_MAX_CHARS:
            resp.success = False
            resp.message = (f'scan refused: request_id is {len(key)} characters long, at most '
                            f'{REQUEST_ID_MAX_CHARS} (a uuid is 36)')
            self.get_logger().warning(resp.message)
            return resp
        if key:
            body = _request_digest(req)
            seen = self._answered_starts.get(key)
            if seen is not None:
                if seen[0] != body:
                    resp.success = False
                    resp.message = (f'scan refused: request_id {key!r} was already used for '
                                    'another request')
                    self.get_logger().warning(resp.message)
                    return resp
                self.get_logger().info(f'scan/start {key!r} resent: answered again, '
                                       'nothing started')
                return seen[1]
        self._start(req, resp)
        if key:
            self._answered_starts[key] = (body, resp)
            while len(self._answered_starts) > ANSWERED_STARTS_KEPT:
                self._answered_starts.popitem(last=False)
        return resp

    def _start(self, req, resp):
        if self.backend is None or self._timer is None:
            resp.success, resp.message = False, 'driver is not active'
            return resp
        if self.backend.running:
            resp.success, resp.message = False, f"scan {self._scan['scan_id']} still running"
            return resp
        try:
            rate = req.frame_rate or self.get_parameter('frame_rate').value
            if not (np.isfinite(rate) and 0 < rate <= 2000):
                raise ValueError(f'frame_rate: {rate} Hz outside (0, 2000]')
            # sized before anything is allocated
            patterns.check_scan_size(req, rate, self.get_parameter('max_scan_frames').value,
                                     self.get_parameter('max_scan_duration').value)
            axis = self.get_parameter('raster_g1_axis').value
            if axis not in patterns.RASTER_G1_AXES:
                raise ValueError(f'raster_g1_axis: {axis!r} is not one of '
                                 f'{patterns.RASTER_G1_AXES}')
            voltages = patterns.from_request(req, axis)
            total = self.backend.start(voltages, rate, bool(req.laser_on))
        except (ValueError, BackendError) as exc:
            resp.success, resp.message = False, f'scan refused: {exc}'
            self.get_logger().warning(resp.message)
            return resp
        self._scan_count += 1
        scan_id = req.scan_id or f'scan{self._scan_count:04d}'
        self._scan.update(scan_id=scan_id, state='running', total=total, done=0, dropped=0,
                          t0=time.monotonic(), last_seq=None)
        self._set_poll_period(SCAN_POLL_PERIOD)
        resp.success, resp.scan_id, resp.frames_total = True, scan_id, total
        resp.expected_duration = total / rate
        resp.message = f"{req.pattern} scan '{scan_id}': {total} frames at {rate:g} Hz"
        self.get_logger().info(resp.message)
        return resp

    def _on_stop(self, req, resp):
        scan = self._scan
        running = self.backend is not None and self.backend.running
        if self.backend is not None:
            self.backend.stop()
        if running:
            scan['state'] = 'stopped'
        resp.success = True
        resp.scan_id = scan['scan_id'] if running else ''
        resp.frames_done = scan['done']
        resp.message = (f"stopped {scan['scan_id']} after {scan['done']} frames" if running
                        else 'no scan was running; galvos at 0 V, laser off')
        return resp

    def _on_progress(self, req, resp):
        scan = self._scan
        resp.success = True
        resp.scan_id, resp.state = scan['scan_id'], scan['state']
        resp.frames_done, resp.frames_total = scan['done'], scan['total']
        resp.frames_dropped = scan['dropped']
        resp.elapsed = time.monotonic() - scan['t0'] if scan['t0'] else 0.0
        rate = scan['done'] / resp.elapsed if resp.elapsed > 0 else 0.0
        left = max(scan['total'] - scan['done'], 0)
        resp.remaining = left / rate if rate > 0 else float('nan') if left else 0.0
        resp.message = f"{scan['state']}: {scan['done']}/{scan['total']} frames"
        if self.callback_errors.total:
            resp.message += f'; {self.callback_errors.total} failed service calls'
        return resp

    def _on_set_scene(self, req, resp):
        set_scene = getattr(self.backend, 'set_scene', None)
        if set_scene is None:
            resp.success, resp.message = False, 'set_scene needs the sim backend, configured'
            return resp
        if self.backend.running:
            resp.success, resp.message = False, 'cannot change the scene during a scan'
            return resp
        try:
            resp.objects = set_scene(path=req.scene_path or None, text=req.scene_yaml or None)
        except (ValueError, OSError) as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        resp.success, resp.message = True, f'scene set: {resp.objects} objects'
        return resp


def _request_digest(req) -> bytes:
    """A digest of the StartScan request's fields but its ``request_id``: what a resend repeats.

    From the values, not the CDR bytes: serialisation leaves its alignment padding
    uninitialised, so two equal requests can serialise differently.
    """
    h = hashlib.sha256()
    for name in req.get_fields_and_field_types():
        if name == 'request_id':
            continue
        value = getattr(req, name)
        h.update(name.encode())
        h.update(np.asarray(value, dtype=np.float64).tobytes() if name == 'voltages'
                 else repr(value).encode())
    return h.digest()


def main(args=None):
    tune_this_process()
    rclpy.init(args=args)
    node = GalvoDriverNode()
    forward_python_logging(node.get_logger())  # the backends' and serial link's logging
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    freeze_startup_heap()
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node.make_safe():
            node.get_logger().info('shutting down in the safe state: galvos at 0 V, laser off')
        node._close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
