"""The ``sim`` backend: the physical rig simulator behind the driver interface (no rclpy).

Laser-on frames are stripe frames (the rig's laser exposure); laser-off frames are fully
textured calibration frames under room light (the rig's calibration exposure), which is
what the calibration stages image boards with. The voltages reported with a frame are the
DAC-quantised ones the board outputs.

Frames are stamped on a virtual clock: frame ``i`` of a scan has the stamp
``t_start + i / frame_rate + exposure / 2`` (the middle of its exposure), where
``t_start`` is the wall time the scan started. Frames are handed out as they fall due at
the requested rate; when rendering is slower than that rate, they come out as fast as the
simulator renders them, stamps unchanged. One frame is handed out per poll by default:
a burst of 720x540 images overflows Fast DDS's default shared-memory segment and a
best-effort subscriber then loses frames. Sequence numbers run on across scans.

Exposure: laser frames use ``exposure`` [s] (0: the rig's) and ``laser_power`` (relative to
the rig's laser). With ``auto_exposure`` a laser scan first renders a short pre-scan of
``auto_exposure_frames`` frames spread over its voltages (not published) and sets the
scan's exposure from their stripe level (:func:`pre_scan_exposure`), within the camera's
shortest exposure and the frame period; where even the longest is too short, the laser
power is raised up to ``max_laser_power`` (relative to the rig's; at most what the
laser is rated for; the default 1 never raises it). With ``hdr_ratio`` > 1 every position
of a laser scan is taken twice, at the scan's exposure and at that over ``hdr_ratio``
(twice the frames; the extractor's ``hdr_pairs`` merges each pair into one stripe).
"""

from __future__ import annotations

import time

import numpy as np

from galvo_driver.backend import BackendError, GalvoBackend
from galvoscan_common.frame import STATUS_SETTLED, Frame, check_voltages

#: Shortest exposure of the simulated camera [s] (assumed for a global-shutter industrial
#: camera of the rig's class, whose GenICam ExposureTime minimum is a few tens of us).
MIN_EXPOSURE = 20e-6


def exposure_limits(frame_rate: float) -> tuple[float, float]:
    """(shortest, longest) exposure [s] at ``frame_rate`` [Hz]."""
    from stripe_extractor.exposure import exposure_limits as limits

    return limits(float(frame_rate), MIN_EXPOSURE)


def pre_scan_exposure(sim, voltages, frame_rate: float, frames: int = 5,
                      exposure: float | None = None, laser_power: float = 1.0,
                      index0: int = 10_000_000, max_laser_power: float | None = None):
    """The exposure [s] a scan over ``voltages`` (n, 4) should use, from ``frames``
    pre-scan frames spread over it (rendered at ``exposure``, the rig's by default, and
    ``laser_power``), and their (saturated fraction, peak level) pairs. A clipped pre-scan
    is repeated once at the exposure it suggests.

    With ``max_laser_power`` (> ``laser_power``) the third value returned is the laser
    power for the scan: raised, up to that, by what the exposure could not give within the
    frame period. Returns (exposure, levels) without it, (exposure, levels, power) with.
    """
    from stripe_extractor.exposure import CLIPPED_SHARE, auto_exposure, frame_levels

    v = np.asarray(voltages, dtype=np.float64)
    idx = np.unique(np.linspace(0, len(v) - 1, max(int(frames), 1)).round().astype(int))
    t = sim.rig.image.exposure if exposure is None else float(exposure)
    limits = exposure_limits(frame_rate)
    white = sim.rig.image.white_level
    bg = sim.rig.image.black_level / float(white)
    levels = []
    for attempt in range(2):
        imgs = [sim.render(v[i], exposure=t, laser_power=laser_power,
                           frame_index=index0 + 100 * attempt + k).image
                for k, i in enumerate(idx)]
        levels = [frame_levels(im, white) for im in imgs]
        new = auto_exposure(imgs, t, limits, background=bg, white=white)
        clipped = max(s for s, _ in levels) > CLIPPED_SHARE
        measured_at, t = t, new
        if not clipped:
            break
    if max_laser_power is None:
        return t, levels
    power = laser_power
    if t >= limits[1] * (1 - 1e-9) and max_laser_power > laser_power:
        from stripe_extractor.exposure import TARGET_PEAK

        peak = max(p for _, p in levels)  # as auto_exposure reads the pre-scan
        ideal = measured_at * (TARGET_PEAK - bg) / max(peak - bg, 1e-6)
        power = float(min(max_laser_power, laser_power * ideal / t))
    return t, levels, power


class SimBackend(GalvoBackend):
    name = 'sim'

    def __init__(self, rig='reference', scene='stair_block', seed=0, max_frames_per_poll=1,
                 exposure=0.0, laser_power=1.0, auto_exposure=False, auto_exposure_frames=5,
                 max_laser_power=1.0, hdr_ratio=1.0):
        self.rig_name, self.scene_name, self.seed = rig, scene, int(seed)
        if not (exposure >= 0 and laser_power >= 0 and int(auto_exposure_frames) >= 1
                and max_laser_power >= 0):
            raise ValueError(f'exposure {exposure} s, laser_power {laser_power}, '
                             f'auto_exposure_frames {auto_exposure_frames}, max_laser_power '
                             f'{max_laser_power}: out of range')
        self.max_laser_power = float(max_laser_power)
        if not (hdr_ratio >= 1.0 and hdr_ratio <= 1000.0):
            raise ValueError(f'hdr_ratio: expected 1 (off) .. 1000, got {hdr_ratio}')
        self.hdr_ratio = float(hdr_ratio)
        self._hdr = False
        self.exposure = float(exposure) or None
        self.laser_power = float(laser_power)
        self.auto_exposure = bool(auto_exposure)
        self.auto_exposure_frames = int(auto_exposure_frames)
        #: The laser-frame exposure of the running (last) scan [s] and the pre-scan's
        #: (saturated fraction, peak level) per frame.
        self.scan_exposure = None
        self.scan_laser_power = self.laser_power
        self.pre_scan_levels = []
        self.max_frames_per_poll = int(max_frames_per_poll)
        self.sim = None
        self._volts = None
        self._index = 0
        self._seq = 0
        self._laser = True

    def open(self) -> None:
        from galvoscan_sim import ConfigError, Simulator, load_rig, load_scene

        try:
            self.sim = Simulator(load_rig(self.rig_name), load_scene(self.scene_name),
                                 seed=self.seed)
        except (ConfigError, OSError, ValueError) as exc:
            raise BackendError(f'simulator: {exc}') from exc

    @property
    def camera_info(self) -> dict:
        cam = self.sim.rig.camera
        return {'width': cam.width, 'height': cam.height, 'K': cam.K,
                'dist': [float(x) for x in cam.distortion]}

    def set_scene(self, path=None, text=None) -> int:
        """Replace the scene from a file or YAML text; returns the number of objects."""
        from galvoscan_sim import ConfigError, load_scene, load_scene_text

        if self.sim is None:
            raise ValueError('simulator not open')
        try:
            scene = load_scene_text(text) if text else load_scene(path)
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc
        self.sim.set_scene(scene)
        return len(scene.objects)

    def start(self, voltages, frame_rate, laser_on=True) -> int:
        if self.sim is None:
            raise BackendError('simulator not open')
        volts = check_voltages(voltages)
        if not frame_rate > 0:
            raise ValueError(f'frame_rate: must be > 0 Hz, got {frame_rate}')
        quantized = self.sim.rig.dac.quantize(volts)
        exposure = self.exposure or self.sim.rig.image.exposure
        lo, hi = exposure_limits(frame_rate)
        if laser_on and self.auto_exposure:
            exposure, self.pre_scan_levels, self.scan_laser_power = pre_scan_exposure(
                self.sim, quantized, frame_rate, self.auto_exposure_frames, exposure,
                self.laser_power, max_laser_power=self.max_laser_power)
        elif laser_on and self.exposure is not None and not lo <= exposure <= hi:
            raise ValueError(f'exposure {exposure * 1e6:.0f} us outside [{lo * 1e6:.0f}, '
                             f'{hi * 1e6:.0f}] us at {frame_rate:g} Hz')
        if not (laser_on and self.auto_exposure):
            self.scan_laser_power = self.laser_power
        self.scan_exposure = exposure
        self._hdr = bool(laser_on) and self.hdr_ratio > 1.0
        # HDR: every position twice, the long exposure, then the short one
        self._volts = np.repeat(quantized, 2, axis=0) if self._hdr else quantized
        self._index, self._laser = 0, bool(laser_on)
        self._period = 1.0 / float(frame_rate)
        self._t_wall, self._t_mono = time.time(), time.monotonic()
        return self._volts.shape[0]

    @property
    def running(self) -> bool:
        return self._volts is not None and self._index < self._volts.shape[0]

    def poll(self, timeout: float = 0.0):
        out = []
        if not self.running:
            return out
        due = int((time.monotonic() - self._t_mono) / self._period) + 1
        exposure = self.scan_exposure if self._laser else self.sim.rig.image.exposure
        custom = (self.scan_exposure != self.sim.rig.image.exposure
                  or self.scan_laser_power != 1.0 or self._hdr)
        while self.running and self._index < due and len(out) < self.max_frames_per_poll:
            i = self._index
            if not self._laser:
                frame = self.sim.calibration_frame(self._volts[i])
            elif custom:
                t = exposure
                if self._hdr and i % 2:
                    t = max(exposure / self.hdr_ratio, MIN_EXPOSURE)
                frame = self.sim.render(self._volts[i], exposure=t,
                                        laser_power=self.scan_laser_power)
            else:
                frame = self.sim.render(self._volts[i])
            out.append(Frame(seq=self._seq, stamp=self._t_wall + i * self._period + exposure / 2,
                             voltages=self._volts[i].copy(), laser_on=self._laser,
                             status=STATUS_SETTLED, image=frame.image,
                             truth={'sim': frame.truth}))
            self._index += 1
            self._seq += 1
        return out

    def stop(self) -> None:
        self._volts = None

    def safe(self) -> None:
        """The simulated galvos have no state to protect: stop the scan."""
        self._volts = None
