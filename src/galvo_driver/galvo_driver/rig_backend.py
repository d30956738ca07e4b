"""The ``rig`` driver backend: the galvo board on a serial port and a GenICam camera.

The board (:class:`~galvo_driver.serial_link.backend.SerialBackend`) drives the galvos and
fires the camera through its trigger output, wired to the camera's trigger input
(``TriggerSource`` ``Line0`` by default); it reports every trigger as an EVENT (board clock
time, trigger index, DAC codes). The camera
(:class:`~galvo_driver.genicam_camera.GenICamCamera`) delivers frames with its own frame id
and clock. :class:`~galvo_driver.trigger_pairing.TriggerPairer` pairs the two streams;
every pair becomes one :class:`~galvoscan_common.frame.Frame`:

* ``image``: the camera image (uint8 for Mono8, uint16 for Mono10/12/16);
* ``voltages``, ``laser_on``: decoded from the DAC codes in the CRC-checked EVENT of the
  trigger that exposed the frame (STATUS_FAULT and an ERROR log if they differ from the
  commanded row);
* ``seq``: (trigger indices of previous scans) + the trigger index, so every trigger that
  produced no frame (event lost, frame lost, frame dropped as ambiguous) is a gap in ``seq``;
* ``stamp``: the middle of the exposure in the host's ``time.time()`` base [s] (the ROS
  time of a node on the system clock): the camera's exposure start plus half the exposure,
  mapped to the board clock by the pairer's clock fit, then to the host by the board offset.

A frame the pairer cannot assign to exactly one trigger is dropped and counted, never
guessed; :attr:`RigBackend.stats` has every count (``pairing/<kind>``, see
:data:`~galvo_driver.trigger_pairing.DROP_KINDS`).

Faults (each ends the scan with an ERROR log; the board is commanded to 0 V with the laser
off and the camera stopped; :attr:`RigBackend.fault` says why until :meth:`RigBackend.arm`):

* the board: a reset, a lost link, a watchdog trip (:class:`SerialBackend` detects them);
* the camera: control lost (unplugged, powered off), its stream failing, or no frame for
  ``max_missing_frames`` consecutive triggers;
* the pairing: ``max_unpaired_frames`` consecutive frames dropped as unpairable (the
  two clocks no longer agree in a way the pairer can explain; see its documented limits).

Lost events, lost frames, duplicated events, clock drift and clock steps are recovered by
the pairer within the scan (the frames concerned are dropped and counted).

Exposure (laser scans only; the pure logic is :mod:`stripe_extractor.exposure`, shared with
the simulator's backend):

* ``auto_exposure``: before the scan, a pre-scan of ``auto_exposure_frames`` triggers spread
  over the scan's rows, laser on, is run through the board and the camera (its frames are
  not handed out; the sequence numbers continue as if it had not run). Their saturated
  fraction and peak level set ``ExposureTime`` so that the median column's peak sits at
  0.7 of the white level (:func:`~stripe_extractor.exposure.auto_exposure`); a clipped
  pre-scan is repeated once at the exposure it suggests. The exposure stays within the
  camera's own ``ExposureTime`` bounds, on its increment, and within 0.9 of the frame
  period (and 50 us short of it). The board switches the laser only on and off, so the
  exposure is the only handle.
* ``hdr_ratio`` > 1: every row is exposed twice, at the scan's exposure and at that over
  ``hdr_ratio``. A GenICam camera cannot change its exposure from one trigger to the next
  without a vendor sequencer, so the board runs the rows twice, the long pass then the
  short one (``ExposureTime`` written between them), and the backend hands each row's two
  frames out together, long then short, with consecutive sequence numbers (the
  extractor's ``hdr_pairs`` merges them). The long pass's frames are held until their
  short ones come: at most :data:`HDR_MAX_HELD_BYTES` of images, so longer scans are
  refused. A row whose partner is missing is handed out alone.

Camera reconnection follows camera_ros' pattern: the camera's error flag, then, while no
scan runs, :meth:`RigBackend.poll` tries every ``reconnect_period`` to reopen the same
device (restoring its features); :meth:`RigBackend.arm` restarts the acquisition.

No rclpy here.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque

import numpy as np

from galvo_driver.backend import BackendError, GalvoBackend
from galvo_driver.genicam_camera import CameraError, GenICamCamera, pixel_format_info
from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link.backend import SerialBackend
from galvo_driver.trigger_pairing import DROP_KINDS, PairedFrame, TriggerPairer
from galvoscan_common.frame import STATUS_FAULT, Frame, check_voltages
from stripe_extractor.exposure import (
    CLIPPED_SHARE,
    auto_exposure,
    exposure_limits,
    frame_levels,
    on_increment,
)

log = logging.getLogger(__name__)

#: Camera features the driver exposes as parameters, in the order they are applied
#: (GenICam SFNC names and units: ExposureTime [us], AcquisitionFrameRate [Hz], sizes [px]).
CAMERA_FEATURES = ('PixelFormat', 'Width', 'Height', 'OffsetX', 'OffsetY', 'ExposureTime',
                   'Gain', 'AcquisitionFrameRate')
#: Trigger inputs a board can be wired to, and the edge that triggers.
TRIGGER_SOURCES = ('Line0', 'Line1', 'Line2', 'Line3', 'Software')
TRIGGER_ACTIVATIONS = ('RisingEdge', 'FallingEdge')
#: Time base of the camera's frame timestamps.
CAMERA_CLOCKS = ('camera', 'host')
#: Kinds of drops on the trigger side (a trigger index without a frame).
EVENT_SIDE = ('event_lost', 'event_without_frame')
#: Time an exposure must leave free in the trigger period [us].
EXPOSURE_MARGIN_US = 50.0
#: Auto exposure: pre-scans run before giving up when one gives no frame (the first scan
#: after arming may pair none: the pairer locks on the two clocks from its first frames).
PRE_SCAN_TRIES = 3
#: HDR: most image bytes the long pass may hold until its short pass comes [B].
HDR_MAX_HELD_BYTES = 512 * 1024 * 1024


class _ScanState:
    """What the backend tracks of the running scan."""

    def __init__(self, n: int, codes: np.ndarray, seq_base: int):
        self.n = n
        self.codes = codes  # (n, 4) uint16, as commanded
        self.seq_base = seq_base
        self.decided: set[int] = set()  # trigger indices paired or dropped
        self.board_done_at: float | None = None
        self.last_frame_at = time.monotonic()
        self.events_since_frame = 0
        self.frames_since_pair = 0  # frames dropped since the last pair
        self.paired = 0


class RigBackend(GalvoBackend):
    """The galvo board (serial) and a GenICam camera, frames paired with trigger events.

    Parameters
    ----------
    port : str
        Serial port or pyserial URL of the galvo board.
    camera_serial, camera_user_id : str, optional
        The camera's DeviceSerialNumber / DeviceUserID (see :class:`GenICamCamera`); neither:
        the first camera found.
    features : dict, optional
        Camera features to apply at :meth:`open`, name -> value in GenICam units (names from
        :data:`CAMERA_FEATURES`); the others keep the camera's own settings.
    trigger_source : str
        The camera input the board's trigger output is wired to (:data:`TRIGGER_SOURCES`).
    trigger_activation : str
        The edge of the board's trigger pulse that starts the exposure.
    camera_clock : {'camera', 'host'}
        'host' when the camera stamps frames in the host's ``time.time()`` base (a PTP-
        synchronised camera and host, or the fake camera): the pairer then also checks
        each new pairing hypothesis on the host clock, which catches a camera that missed
        the first triggers of a scan. 'camera': a free-running camera clock.
    trigger_delay_us : float
        The camera's delay from the trigger edge to the exposure start [us] (its datasheet
        latency plus any TriggerDelay); it shifts the stamps, never a pairing.
    frame_id_wrap : int or None
        Frame ids wrap after this (GigE Vision 1.x block ids: 65536); None: 64-bit ids.
    frame_timeout : float
        How long after the board's last trigger (and the camera's last frame) the scan's
        frames are waited for [s].
    max_missing_frames : int
        Consecutive trigger events without any camera frame that make a camera fault, if
        no frame came for ``camera_timeout`` either.
    camera_timeout : float
        See ``max_missing_frames`` [s].
    max_unpaired_frames : int
        Consecutive frames the pairer could not pair that stop the scan (pairing lost).
    n_buffers : int
        Camera stream buffers.
    reconnect_period : float
        Time between two attempts to reopen a lost camera while idle [s].
    baudrate : int
        Serial baud rate [bit/s] (ignored by ptys and sockets).
    auto_exposure : bool
        Set ``ExposureTime`` before every laser scan from a pre-scan (module docstring).
    auto_exposure_frames : int
        Triggers of the pre-scan, >= 1.
    hdr_ratio : float
        1: off; > 1 (up to 1000): every row of a laser scan exposed twice, the second time
        at the exposure over this (module docstring).
    """

    name = 'rig'

    def __init__(self, port: str, *, camera_serial: str | None = None,
                 camera_user_id: str | None = None, features: dict | None = None,
                 trigger_source: str = 'Line0', trigger_activation: str = 'RisingEdge',
                 camera_clock: str = 'camera', trigger_delay_us: float = 0.0,
                 frame_id_wrap: int | None = 65536, frame_timeout: float = 0.3,
                 max_missing_frames: int = 50, camera_timeout: float = 1.0,
                 max_unpaired_frames: int = 100,
                 n_buffers: int = 64,
                 reconnect_period: float = 1.0, baudrate: int = 921600,
                 auto_exposure: bool = False, auto_exposure_frames: int = 5,
                 hdr_ratio: float = 1.0):
        features = dict(features or {})
        unknown = sorted(set(features) - set(CAMERA_FEATURES))
        if unknown:
            raise ValueError(f'features: unknown {unknown}; known: {", ".join(CAMERA_FEATURES)}')
        if trigger_source not in TRIGGER_SOURCES:
            raise ValueError(f'trigger_source: {trigger_source!r} not one of {TRIGGER_SOURCES}')
        if trigger_activation not in TRIGGER_ACTIVATIONS:
            raise ValueError(f'trigger_activation: {trigger_activation!r} not one of '
                             f'{TRIGGER_ACTIVATIONS}')
        if camera_clock not in CAMERA_CLOCKS:
            raise ValueError(f'camera_clock: {camera_clock!r} not one of {CAMERA_CLOCKS}')
        for name, value in (('frame_timeout', frame_timeout), ('camera_timeout', camera_timeout),
                            ('reconnect_period', reconnect_period)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f'{name}: must be a positive time in s, got {value}')
        if int(max_missing_frames) < 1:
            raise ValueError(f'max_missing_frames: must be >= 1, got {max_missing_frames}')
        if not (math.isfinite(trigger_delay_us) and trigger_delay_us >= 0):
            raise ValueError(f'trigger_delay_us: must be >= 0 us, got {trigger_delay_us}')
        if isinstance(auto_exposure_frames, bool) or not 1 <= int(auto_exposure_frames) <= 100:
            raise ValueError(f'auto_exposure_frames: expected 1..100, got {auto_exposure_frames}')
        if not (math.isfinite(hdr_ratio) and 1.0 <= hdr_ratio <= 1000.0):
            raise ValueError(f'hdr_ratio: expected 1 (off) .. 1000, got {hdr_ratio}')
        self.auto_exposure = bool(auto_exposure)
        self.auto_exposure_frames = int(auto_exposure_frames)
        self.hdr_ratio = float(hdr_ratio)
        #: The laser-frame exposure of the last scan [s] (None before the first laser scan)
        #: and its pre-scan's (saturated fraction, peak level) per frame.
        self.scan_exposure: float | None = None
        self.pre_scan_levels: list[tuple[float, float]] = []
        #: HDR scan in progress: the rows, rate, exposures, pass, held long frames
        self._hdr: dict | None = None
        self.board = SerialBackend(port, baudrate=baudrate)
        self.camera = GenICamCamera(serial=camera_serial or None,
                                    user_id=camera_user_id or None)
        self.features = features
        self.trigger_source = trigger_source
        self.trigger_activation = trigger_activation
        self.camera_clock = camera_clock
        self.trigger_delay_us = float(trigger_delay_us)
        self.frame_id_wrap = frame_id_wrap
        self.frame_timeout = float(frame_timeout)
        self.max_missing_frames = int(max_missing_frames)
        self.camera_timeout = float(camera_timeout)
        if int(max_unpaired_frames) < 1:
            raise ValueError(f'max_unpaired_frames: must be >= 1, got {max_unpaired_frames}')
        self.max_unpaired_frames = int(max_unpaired_frames)
        self.n_buffers = int(n_buffers)
        self.reconnect_period = float(reconnect_period)
        self.pairer: TriggerPairer | None = None
        self._msgs: deque = deque()  # board messages, from the serial reader thread
        self._frames: deque = deque()  # camera frames, from the grab thread
        self._wake = threading.Event()
        self._grab_thread: threading.Thread | None = None
        self._grab_stop = threading.Event()
        self._grab_error: str | None = None
        self._scan: _ScanState | None = None
        self._seq_base = 0
        self._out: list[Frame] = []
        self._fault: str | None = None
        self._camera_lost = False  # a camera fault: the device is reopened before use
        self._exposure_s = 0.0
        self._last_reconnect = 0.0
        self._reconnect_thread: threading.Thread | None = None
        self._counters = {'scans': 0, 'frames': 0, 'mismatched_codes': 0, 'camera_faults': 0,
                          'reconnects': 0, 'pre_scans': 0, 'pre_scan_frames': 0,
                          'hdr_pairs': 0, 'hdr_unpaired': 0}
        self.board.add_listener(self._on_board_message)

    # ------------------------------------------------------------------ properties
    @property
    def running(self) -> bool:
        """True from :meth:`start` until every frame of the scan (of both HDR passes) is
        paired or dropped."""
        return self._scan is not None or self._hdr is not None

    @property
    def fault(self) -> str | None:
        """Why the backend is in FAULT (board or camera), or None."""
        return self.board.fault or self._fault

    @property
    def exposure(self) -> float:
        """The camera's exposure time as last read (arm, start) [s]."""
        return self._exposure_s

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the images [px], None while the camera is not open."""
        if not self.camera.is_open or self.camera.error:
            return None
        try:
            return int(self.camera.get('Width')), int(self.camera.get('Height'))
        except CameraError:
            return None

    @property
    def stats(self) -> dict:
        """Counters for diagnostics: ``pairing`` (the pairer's counts by kind, drift_ppm),
        ``board`` (the serial link), ``camera`` (stream buffers), and the backend's own."""
        out = dict(self._counters)
        if self.pairer is not None:
            out['pairing'] = self.pairer.stats()
        out['board'] = self.board.stats
        try:
            out['camera'] = self.camera.statistics()
        except Exception:  # noqa: BLE001 - statistics of a lost device: none
            out['camera'] = {}
        out['camera_error'] = self.camera.error or ''
        return out

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the board (handshake, protocol version check) and the camera (features,
        trigger set-up).

        Raises
        ------
        BackendError
            Either device cannot be opened, or a feature is refused (both are closed).
        """
        self.board.open()
        try:
            self.camera.open()
            for name in CAMERA_FEATURES:
                if name in self.features:
                    self.camera.set(name, self.features[name])
            pixel_format_info(self.camera.get('PixelFormat'))
            self._setup_trigger()
            self._exposure_s = float(self.camera.get('ExposureTime')) * 1e-6
        except CameraError as err:
            self.camera.close()
            self.board.close()
            raise BackendError(f'camera: {err}') from err
        info = self.board.board_info
        log.info('rig: board %r (protocol %d) on %s, %s, %s, exposure %.1f us', info.firmware_id,
                 info.version, self.board.port, self.camera.device_id,
                 self.camera.get('PixelFormat'), self._exposure_s * 1e6)

    def _setup_trigger(self) -> None:
        """One frame per trigger edge on ``trigger_source``."""
        cam = self.camera
        if 'FrameStart' in self._entries('TriggerSelector'):
            cam.set('TriggerSelector', 'FrameStart')
        cam.set('TriggerMode', 'On')
        cam.set('TriggerSource', self.trigger_source)
        if self._entries('TriggerActivation'):
            cam.set('TriggerActivation', self.trigger_activation)

    def _entries(self, feature: str) -> tuple:
        try:
            return self.camera.feature_range(feature)
        except CameraError:
            return ()  # the camera has no such feature

    def arm(self) -> None:
        """Re-establish the board session, clear a fault, reopen a lost camera and start
        its acquisition (it waits for trigger edges).

        Raises
        ------
        BackendError
            The board does not answer, or the camera cannot be reopened or started.
        """
        self._join_reconnect()
        self.board.arm()
        try:
            if self._camera_lost or self.camera.error is not None or not self.camera.is_open:
                if not self.camera.reopen():
                    raise CameraError(self.camera.error or 'reopen failed')
                self._counters['reconnects'] += 1
                self._camera_lost = False
                self._setup_trigger()
            self._exposure_s = float(self.camera.get('ExposureTime')) * 1e-6
            self._stop_grab()
            self.camera.start(self.n_buffers)
        except CameraError as err:
            raise BackendError(f'camera: {err}') from err
        self.pairer = TriggerPairer(
            exposure_s=self._exposure_s, board_to_host=self.board.board_to_host,
            trigger_delay_us=self.trigger_delay_us, frame_id_wrap=self.frame_id_wrap,
            camera_to_host=(lambda ns: ns * 1e-9) if self.camera_clock == 'host' else None)
        self._msgs.clear()
        self._frames.clear()
        self._start_grab()
        self._fault = None

    def set_feature(self, name: str, value):
        """Write one of :data:`CAMERA_FEATURES` on the camera, checked against its limits.

        Returns
        -------
        object
            The value the camera reports afterwards.

        Raises
        ------
        ValueError
            Not an exposed feature, or a scan is running.
        CameraError
            The camera refused the value (nothing changed); the message says why.
        """
        if name not in CAMERA_FEATURES:
            raise ValueError(f'{name}: not a camera parameter ({", ".join(CAMERA_FEATURES)})')
        if self.running:
            raise ValueError(f'{name}: cannot change during a scan')
        self.camera.set(name, value)
        self.features[name] = value
        if name == 'ExposureTime':
            self._exposure_s = float(self.camera.get('ExposureTime')) * 1e-6
        return self.camera.get(name)

    def start(self, voltages: np.ndarray, frame_rate: float, laser_on: bool = True) -> int:
        """Upload the scan to the board and start triggering; frames come from :meth:`poll`.

        Parameters
        ----------
        voltages : ndarray, shape (n, 4), volts
            One row of (U1_pan, U1_tilt, U2_pan, U2_tilt) per trigger.
        frame_rate : float
            Trigger rate [Hz]; the period must exceed the camera's exposure.
        laser_on : bool

        Returns
        -------
        int
            n, the number of triggers.

        With ``auto_exposure`` a laser scan first runs its pre-scan (blocking, a few
        frame periods plus ``frame_timeout``); with ``hdr_ratio`` > 1 it runs twice (long,
        short) and n is twice the rows.

        Raises
        ------
        ValueError
            Bad voltages or frame rate, an exposure that does not fit the frame period, an
            HDR scan too long to hold (nothing is sent).
        BackendError
            In FAULT, the camera not acquiring (not armed), a scan running, the board
            refused, or the auto exposure's pre-scan gave no frame.
        """
        arr = check_voltages(voltages)
        rate = float(frame_rate)
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f'frame_rate: must be a positive rate in Hz, got {frame_rate}')
        period_us = round(1e6 / rate)
        if self.fault is not None:
            raise BackendError(f'backend in FAULT ({self.fault}); arm() (activate) to clear it')
        if self.running:
            raise BackendError('a scan is already running; stop() it first')
        if not self.camera.acquiring or self.camera.error is not None or self.pairer is None:
            raise BackendError('the camera is not acquiring: arm() (activate the driver) first')
        hdr = laser_on and self.hdr_ratio > 1.0
        if hdr:
            size = self.image_size or (0, 0)
            held = arr.shape[0] * size[0] * size[1] * (2 if self._white_level() > 255 else 1)
            if held > HDR_MAX_HELD_BYTES:
                raise ValueError(f'HDR: {arr.shape[0]} rows would hold {held / 2**20:.0f} MiB '
                                 f'of images between the passes (at most '
                                 f'{HDR_MAX_HELD_BYTES / 2**20:.0f} MiB): split the scan')
        if laser_on and self.auto_exposure:
            try:
                self._auto_expose(arr, rate)
            except CameraError as err:
                raise BackendError(f'auto exposure: camera: {err}') from err
        elif self._exposure_s * 1e6 + EXPOSURE_MARGIN_US > period_us:
            raise ValueError(f'frame_rate: {rate:g} Hz leaves {period_us} us per frame, not '
                             f'more than the exposure ({self._exposure_s * 1e6:.0f} us) + '
                             f'{EXPOSURE_MARGIN_US:.0f} us')
        if laser_on:
            self.scan_exposure = self._exposure_s
        if hdr:
            lo = self._exposure_limits(rate)[0]
            self._hdr = {'rows': arr, 'rate': rate, 'long': self._exposure_s,
                         'short': max(self._exposure_s / self.hdr_ratio, lo), 'pass': 1,
                         'held': {}, 'base': self._seq_base, 'n': arr.shape[0]}
            try:
                return 2 * self._begin(arr, rate, laser_on)
            except BaseException:
                self._hdr = None
                raise
        return self._begin(arr, rate, laser_on)

    def _begin(self, arr: np.ndarray, rate: float, laser_on: bool, pump: bool = True) -> int:
        """Start one board scan of ``arr`` and its pairing; the number of triggers."""
        period_us = round(1e6 / rate)
        if pump:
            self._pump()  # frames and events of before this scan are outside it
        n = self.board.start(arr, rate, laser_on)
        self.pairer.exposure_ns = self._exposure_s * 1e9
        self._scan = _ScanState(n, p.volts_to_codes(arr), self._seq_base)
        self._take(self.pairer.begin_scan(self.board.boot_id, self.board.scan_id, period_us,
                                          n_rows=n, seq_base=self._seq_base))
        self._counters['scans'] += 1
        return n

    def poll(self, timeout: float = 0.0) -> list[Frame]:
        """Frames paired since the last call; waits up to ``timeout`` [s] for one while a
        scan runs. While idle, retries a lost camera every ``reconnect_period``."""
        deadline = time.monotonic() + max(float(timeout), 0.0)
        while True:
            self._wake.clear()
            self._pump()
            left = deadline - time.monotonic()
            if self._out or not self.running or left <= 0:
                break
            self._wake.wait(min(left, 0.005))
        if self._scan is None:
            self._maybe_reconnect()
        out, self._out = self._out, []
        return out

    def stop(self) -> None:
        """Abort the scan: the board goes to 0 V with the laser off (the camera keeps
        acquiring, ready for the next scan).

        Raises
        ------
        BackendError
            The board did not confirm the safe state (logged).
        """
        try:
            self.board.stop()
        finally:
            self._end_scan('stopped')

    def safe(self) -> None:
        """Best effort, never raises: galvos to 0 V, laser off, scan ended, camera stopped."""
        try:
            self.board.safe()
        except Exception as err:  # noqa: BLE001 - must never raise
            log.error('safe(): board: %s', err)
        try:
            self._end_scan('safe state')
        except Exception as err:  # noqa: BLE001
            log.error('safe(): ending the pairing: %s', err)
        self._stop_grab()
        if self._camera_lost:
            return  # the device is gone or in doubt: it is dropped and reopened by arm()
        try:
            self.camera.stop()
        except Exception as err:  # noqa: BLE001
            log.error('safe(): camera: %s', err)

    def close(self) -> None:
        """Safe state, then close the camera and the board."""
        self.safe()
        self._join_reconnect()
        try:
            self.camera.close()
        except Exception as err:  # noqa: BLE001 - closing a lost device
            log.error('closing the camera: %s', err)
        self.board.close()

    # ------------------------------------------------------------------ threads
    def _on_board_message(self, msg) -> None:
        """Serial reader thread: queue the message for :meth:`_pump`."""
        self._msgs.append(msg)
        self._wake.set()

    def _start_grab(self) -> None:
        self._grab_stop.clear()
        self._grab_error = None
        self._grab_thread = threading.Thread(target=self._grab_loop, name='rig-camera-grab',
                                             daemon=True)
        self._grab_thread.start()

    def _stop_grab(self) -> None:
        self._grab_stop.set()
        th, self._grab_thread = self._grab_thread, None
        if th is not None and th is not threading.current_thread():
            th.join(timeout=2.0)

    def _grab_loop(self) -> None:
        cam = self.camera
        while not self._grab_stop.is_set():
            try:
                frame = cam.grab(0.05)
            except CameraError as err:
                if not self._grab_stop.is_set():
                    self._grab_error = str(err)
                    self._wake.set()
                return
            if frame is not None:
                self._frames.append(frame)
                self._wake.set()
            elif cam.error is not None:
                self._wake.set()
                return

    # ------------------------------------------------------------------ pairing
    def _pump(self) -> None:
        """Give the pairer what arrived on both sides; check the scan's end and faults."""
        pairer = self.pairer
        if pairer is None:
            return
        self.board.poll(0.0)  # the board's own image-less frames: not used here
        scan = self._scan
        while self._msgs:
            msg = self._msgs.popleft()
            if isinstance(msg, p.Event):
                if scan is not None and msg.scan_id == self.board.scan_id:
                    scan.events_since_frame += 1
                self._take(pairer.add_event(msg))
            elif isinstance(msg, p.Boot):
                self._take(pairer.board_reset(msg.info.boot_id))
            elif isinstance(msg, p.Status) and msg.status.boot_id != self.board.boot_id:
                self._take(pairer.board_reset(msg.status.boot_id))
        while self._frames:
            frame = self._frames.popleft()
            if scan is not None:
                scan.events_since_frame = 0
                scan.last_frame_at = time.monotonic()
            self._take(pairer.add_frame(frame))
        if scan is not None:
            self._check_scan(scan)

    def _check_scan(self, scan: _ScanState) -> None:
        now = time.monotonic()
        camera_fault = self.camera.error or self._grab_error
        if camera_fault is None and scan.events_since_frame > self.max_missing_frames \
                and now - scan.last_frame_at > self.camera_timeout:
            camera_fault = (f'no camera frame for {scan.events_since_frame} consecutive '
                            f'triggers (is the board trigger output wired to '
                            f'{self.trigger_source}?)')
        if camera_fault is not None:
            self._counters['camera_faults'] += 1
            self._camera_lost = True
            self._fault = f'camera: {camera_fault}'
            log.error('camera fault during the scan (%s): scan aborted, galvos to 0 V, laser '
                      'off; activate the driver again (arm) once the camera is back',
                      camera_fault)
            self.board.safe()
            self._end_scan('camera fault')
            return
        if self.board.fault is not None:
            self._end_scan(f'board fault: {self.board.fault}')
            return
        if scan.frames_since_pair > self.max_unpaired_frames:
            self._fault = (f'pairing lost: {scan.frames_since_pair} consecutive frames could '
                           'not be paired with a trigger unambiguously')
            log.error('%s: scan aborted, galvos to 0 V, laser off (no frame was tagged by '
                      'guess); activate the driver again (arm) to clear it', self._fault)
            self.board.safe()
            self._end_scan('pairing lost')
            return
        if self.board.running:
            return
        if scan.board_done_at is None:
            scan.board_done_at = now
        if len(scan.decided) >= scan.n and self.pairer.pending == (0, 0):
            self._end_scan('complete')
        elif now - max(scan.board_done_at, scan.last_frame_at) > self.frame_timeout:
            self._end_scan('complete')

    def _end_scan(self, why: str) -> None:
        scan = self._scan
        if scan is None or self.pairer is None:
            return
        self._take(self.pairer.end_scan())
        self._scan = None
        self._seq_base = scan.seq_base + scan.n
        c = self.pairer.counters
        dropped = {k: v for k, v in c.items() if v and k in DROP_KINDS}
        level = logging.INFO if why in ('complete', 'stopped') else logging.ERROR
        log.log(level, 'scan %d %s: %d of %d triggers paired with a frame; drops so far: %s',
                self.board.scan_id or 0, why, scan.paired, scan.n, dropped or 'none')
        if self._hdr is not None:
            self._hdr_pass_done(why)

    # ------------------------------------------------------------------ exposure
    def _white_level(self) -> int:
        """The camera's top code at its pixel format [DN]."""
        return (1 << pixel_format_info(self.camera.get('PixelFormat'))[1]) - 1

    def _exposure_limits(self, rate: float) -> tuple[float, float]:
        """(shortest, longest) exposure [s]: the camera's ExposureTime bounds, within
        the frame period at ``rate`` [Hz] (:func:`~stripe_extractor.exposure.exposure_limits`)
        and :data:`EXPOSURE_MARGIN_US` short of it."""
        lo_us, hi_us = self.camera.feature_range('ExposureTime')
        free_us = 1e6 / rate - EXPOSURE_MARGIN_US
        if free_us < lo_us:
            raise ValueError(f'frame_rate: {rate:g} Hz leaves no room for the camera\'s '
                             f'shortest exposure ({lo_us:g} us) + {EXPOSURE_MARGIN_US:.0f} us')
        return exposure_limits(rate, lo_us * 1e-6, min(hi_us, free_us) * 1e-6)

    def _write_exposure(self, seconds: float) -> float:
        """Write ExposureTime [s], on the camera's increment; the exposure it reports [s]."""
        lo_us = self.camera.feature_range('ExposureTime')[0]
        inc_us = self.camera.feature_increment('ExposureTime')
        us = on_increment(seconds * 1e6, lo_us, inc_us)
        self.camera.set('ExposureTime', us)
        self._exposure_s = float(self.camera.get('ExposureTime')) * 1e-6
        return self._exposure_s

    def _auto_expose(self, arr: np.ndarray, rate: float) -> None:
        """Set ExposureTime from a pre-scan of rows spread over ``arr`` (module docstring)."""
        lo, hi = self._exposure_limits(rate)
        white = self._white_level()
        idx = np.unique(np.linspace(0, arr.shape[0] - 1, self.auto_exposure_frames)
                        .round().astype(int))
        t = self._exposure_s
        if not lo <= t <= hi:
            t = self._write_exposure(min(max(t, lo), hi))
        levels: list = []
        for _attempt in range(2):
            images = []
            for _ in range(PRE_SCAN_TRIES):
                images = self._capture(arr[idx], rate)
                if images:
                    break
            if not images:
                raise BackendError(f'auto exposure: {PRE_SCAN_TRIES} pre-scans of {len(idx)} '
                                   'triggers gave no frame (is the trigger wired? see the '
                                   'pairing counts)')
            levels = [frame_levels(im, white) for im in images]
            measured_at = t
            t = self._write_exposure(auto_exposure(images, t, (lo, hi), white=white))
            if max(s for s, _ in levels) <= CLIPPED_SHARE:
                break
        self.pre_scan_levels = levels
        log.info('auto exposure: %d pre-scan frames at %.0f us, peak level %.3f, saturated '
                 '%.3f: ExposureTime %.0f us (limits %.0f..%.0f us at %g Hz)', len(levels),
                 measured_at * 1e6, max(p for _, p in levels), max(s for s, _ in levels),
                 t * 1e6, lo * 1e6, hi * 1e6, rate)

    def _capture(self, rows: np.ndarray, rate: float) -> list:
        """Run ``rows`` with the laser on and return the images of the frames (not handed
        out; the sequence numbers of the next scan continue as if this had not run)."""
        base = self._seq_base
        self._counters['pre_scans'] += 1
        self._begin(rows, rate, True)
        frames: list[Frame] = []
        deadline = time.monotonic() + rows.shape[0] / rate + self.frame_timeout + 2.0
        try:
            while self._scan is not None and time.monotonic() < deadline:
                frames += self.poll(0.02)
            if self._scan is not None:
                self.stop()
            frames += self.poll(0.0)
        finally:
            self._seq_base = base
        if self.fault is not None:
            raise BackendError(f'auto exposure: the pre-scan failed: {self.fault}')
        self._counters['pre_scan_frames'] += len(frames)
        return [f.image for f in frames if f.laser_on and f.image is not None]

    def _deliver(self, frame: Frame, index: int) -> None:
        """Hand a paired frame out; in an HDR scan, hold the long pass's frames and hand
        each out with its short one (sequence numbers base + 2 index, + 1 for the short)."""
        h = self._hdr
        if h is None:
            self._out.append(frame)
            return
        frame.seq = h['base'] + 2 * index + (h['pass'] - 1)
        if h['pass'] == 1:
            h['held'][index] = frame
            return
        for i in sorted(i for i in h['held'] if i < index):
            self._out.append(h['held'].pop(i))
            self._counters['hdr_unpaired'] += 1
        long = h['held'].pop(index, None)
        if long is not None:
            self._out.append(long)
            self._counters['hdr_pairs'] += 1
        else:
            self._counters['hdr_unpaired'] += 1
        self._out.append(frame)

    def _hdr_pass_done(self, why: str) -> None:
        """After the long pass: the short one; after it (or a failure): the held frames
        out, the long exposure back."""
        h = self._hdr
        if h['pass'] == 1 and why == 'complete' and self.fault is None:
            try:
                self._write_exposure(h['short'])
                h['pass'] = 2
                self._begin(h['rows'], h['rate'], True, pump=False)
                return
            except (CameraError, BackendError, ValueError) as err:
                log.error('HDR: the short pass did not start (%s); the long frames go out '
                          'alone', err)
        self._hdr = None
        for i in sorted(h['held']):
            self._out.append(h['held'][i])
            self._counters['hdr_unpaired'] += 1
        self._seq_base = h['base'] + 2 * h['n']
        try:
            self._write_exposure(h['long'])
        except (CameraError, ValueError) as err:
            log.error('HDR: the long exposure could not be restored: %s', err)

    def _take(self, results) -> None:
        scan = self._scan
        for r in results:
            if isinstance(r, PairedFrame):
                if scan is not None:
                    scan.decided.add(r.index)
                    scan.paired += 1
                    scan.frames_since_pair = 0
                self._deliver(self._frame(r, scan), r.event.index)
            elif scan is not None and r.kind in EVENT_SIDE and r.index is not None:
                scan.decided.add(r.index)
                log.debug('trigger %s without a frame: %s', r.index, r.detail)
            elif r.frame is not None:
                if scan is not None:
                    scan.frames_since_pair += 1
                log.debug('frame %s dropped (%s): %s', r.frame.frame_id, r.kind, r.detail)

    def _frame(self, pair: PairedFrame, scan: _ScanState | None) -> Frame:
        ev = pair.event
        status = ev.status
        if scan is not None and tuple(int(c) for c in scan.codes[ev.index]) != tuple(ev.codes):
            self._counters['mismatched_codes'] += 1
            status = STATUS_FAULT
            log.error('trigger %d: board output codes %s, commanded %s', ev.index, ev.codes,
                      tuple(int(c) for c in scan.codes[ev.index]))
        self._counters['frames'] += 1
        return Frame(seq=pair.seq, stamp=pair.stamp,
                     voltages=p.codes_to_volts(np.array(ev.codes, dtype=np.int64)),
                     laser_on=bool(ev.laser_on), status=int(status), image=pair.frame.image)

    def _maybe_reconnect(self) -> None:
        """camera_ros' pattern: while the camera's error flag is up, try to reopen it every
        ``reconnect_period``, in a thread of its own (discovery takes a while)."""
        if not (self._camera_lost or self.camera.error) or self.camera.device_id is None:
            return
        th = self._reconnect_thread
        now = time.monotonic()
        if (th is not None and th.is_alive()) or now - self._last_reconnect < \
                self.reconnect_period:
            return
        self._last_reconnect = now
        self._reconnect_thread = threading.Thread(target=self._reconnect, daemon=True,
                                                  name='rig-camera-reconnect')
        self._reconnect_thread.start()

    def _reconnect(self) -> None:
        self._stop_grab()
        if self.camera.reopen():
            self._camera_lost = False
            self._counters['reconnects'] += 1
            log.info('camera %s reopened; activate the driver (arm) to acquire again',
                     self.camera.device_id)
        else:
            log.warning('camera still lost: %s', self.camera.error)

    def _join_reconnect(self) -> None:
        th, self._reconnect_thread = self._reconnect_thread, None
        if th is not None:
            th.join(timeout=15.0)
