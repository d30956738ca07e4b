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
"""

from __future__ import annotations

import time

from galvo_driver.backend import BackendError, GalvoBackend
from galvoscan_common.frame import STATUS_SETTLED, Frame, check_voltages


class SimBackend(GalvoBackend):
    name = 'sim'

    def __init__(self, rig='reference', scene='stair_block', seed=0, max_frames_per_poll=1):
        self.rig_name, self.scene_name, self.seed = rig, scene, int(seed)
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
        self._volts = self.sim.rig.dac.quantize(volts)
        self._index, self._laser = 0, bool(laser_on)
        self._period = 1.0 / float(frame_rate)
        self._t_wall, self._t_mono = time.time(), time.monotonic()
        return volts.shape[0]

    @property
    def running(self) -> bool:
        return self._volts is not None and self._index < self._volts.shape[0]

    def poll(self, timeout: float = 0.0):
        out = []
        if not self.running:
            return out
        due = int((time.monotonic() - self._t_mono) / self._period) + 1
        exposure = self.sim.rig.image.exposure
        while self.running and self._index < due and len(out) < self.max_frames_per_poll:
            i = self._index
            frame = (self.sim.render(self._volts[i]) if self._laser
                     else self.sim.calibration_frame(self._volts[i]))
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
