"""The physics of a rig's twin (:mod:`galvo_driver.twin`): the simulator rendering the
exposure of each trigger edge at the galvo board's DAC outputs, and the render log.

It runs in the twin camera's process (``python -m galvo_driver.fake_camera --render``). No
rclpy here.
"""

from __future__ import annotations

import dataclasses
import threading
import zlib
from pathlib import Path

import numpy as np

#: AD5754R output range select codes -> (lowest, highest) output [V] (Analog Devices,
#: AD5724R/AD5734R/AD5754R data sheet Rev. E, "Output Range Select Register", Table 26).
AD5754R_RANGES = {0: (0.0, 5.0), 1: (0.0, 10.0), 2: (0.0, 10.8), 3: (-5.0, 5.0),
                  4: (-10.0, 10.0), 5: (-10.8, 10.8)}
#: The DAC's bits.
AD5754R_BITS = 16
def ad5754r_volts(codes, powered: int, range_code: int) -> np.ndarray:
    """The AD5754R's output voltages for the codes in its DAC registers.

    Offset-binary coding (BIN/2sCOMP strapped low, as on the galvo board): code 0 is the
    range's lowest voltage, each code one span / 2**16 above (data sheet, "Transfer
    function", offset binary). A channel powered down outputs 0 V (its output is tied to
    AGND through a resistor).

    Parameters
    ----------
    codes : sequence of 4 int
        DAC output codes of channels A..D (U1_pan, U1_tilt, U2_pan, U2_tilt).
    powered : int
        Bit mask of the powered-up channels (bit 0: channel A).
    range_code : int
        The output range select code (:data:`AD5754R_RANGES`; the board sets 4, +-10 V).

    Raises
    ------
    ValueError
        Not 4 codes, a code outside 0..65535 or an unknown range code.
    """
    c = np.asarray(codes, dtype=np.int64)
    if c.shape != (4,) or np.any((c < 0) | (c > 0xFFFF)):
        raise ValueError(f'codes: expected 4 codes in 0..65535, got {codes}')
    if int(range_code) not in AD5754R_RANGES:
        raise ValueError(f'range code {range_code}: not an AD5754R output range')
    lo, hi = AD5754R_RANGES[int(range_code)]
    volts = lo + (hi - lo) * c / float(1 << AD5754R_BITS)
    on = np.array([(int(powered) >> i) & 1 for i in range(4)], dtype=bool)
    return np.where(on, volts, 0.0)


@dataclasses.dataclass(frozen=True)
class RenderRecord:
    """One frame a twin's camera rendered: ``edge_ns`` (the trigger edge's instant,
    CLOCK_REALTIME [ns]), ``cycle`` (the edge's CPU cycle in the board's log), ``index`` (the
    simulator's frame index), ``codes`` (the DAC output codes the mirrors were set from),
    ``laser_on``, ``exposure_s``, ``crc`` (CRC-32 of the image's bytes as sent)."""

    edge_ns: int
    cycle: int
    index: int
    codes: tuple
    laser_on: bool
    exposure_s: float
    crc: int


def image_crc(image) -> int:
    """CRC-32 of an image's bytes (how a published image is found in the render log)."""
    return zlib.crc32(np.ascontiguousarray(image).tobytes())


def renders_by_image(renders: dict) -> dict[int, RenderRecord]:
    """The records of :func:`read_render_log` by image CRC (:func:`image_crc`)."""
    return {r.crc: r for r in renders.values()}


def read_render_log(path) -> dict[int, RenderRecord]:
    """A render log (one line per frame: edge ns, cycle, index, 4 codes, laser, exposure
    [us], image CRC-32), by edge instant."""
    out = {}
    text = Path(path).read_text(encoding='ascii') if Path(path).exists() else ''
    for line in text.splitlines():
        f = line.split()
        if len(f) != 10:
            continue  # a line being written
        rec = RenderRecord(int(f[0]), int(f[1]), int(f[2]), tuple(int(x) for x in f[3:7]),
                           f[7] == '1', float(f[8]) * 1e-6, int(f[9]))
        out[rec.edge_ns] = rec
    return out


class Renderer:
    """The twin camera's physics: the simulator rendering each trigger edge's exposure.

    Parameters
    ----------
    rig, scene : str
        Simulator rig and scene (shipped names or YAML paths).
    seed : int
        Seeds the simulator (jitter, noise, speckle); frames are numbered from 0 in the
        order they are rendered.
    log_path : str, optional
        Render log (:func:`read_render_log`).

    Raises
    ------
    ValueError
        The rig or scene cannot be read, or the rig's DAC is not the board's.
    """

    def __init__(self, rig: str = 'reference', scene: str = 'stair_block', seed: int = 0,
                 log_path: str | None = None):
        from galvoscan_sim import ConfigError, Simulator, load_rig, load_scene

        try:
            r = load_rig(rig)
            s = load_scene(scene)
        except (ConfigError, OSError) as err:
            raise ValueError(str(err)) from err
        if r.dac.bits != AD5754R_BITS or abs(r.dac.full_scale - 10.0) > 1e-12:
            raise ValueError(f'rig {r.name}: its DAC ({r.dac.bits} bits, +-{r.dac.full_scale} '
                             'V) is not the galvo board\'s AD5754R (16 bits, +-10 V)')
        self.sim = Simulator(r, s, seed=int(seed))
        self._lock = threading.Lock()
        self.index = 0
        self._log = open(log_path, 'a', encoding='ascii') if log_path else None  # noqa: SIM115
        self.sim.render(np.zeros(4), frame_index=1 << 30)  # compile and warm up

    @classmethod
    def from_spec(cls, spec: dict) -> Renderer:
        """From the ``render`` dict of :class:`~galvo_driver.fake_camera.FakeCamera`."""
        return cls(str(spec.get('rig', 'reference')), str(spec.get('scene', 'stair_block')),
                   int(spec.get('seed', 0)), spec.get('log') or None)

    @property
    def size(self) -> tuple[int, int]:
        """The rig camera's sensor (width, height) [px]."""
        return self.sim.rig.camera.width, self.sim.rig.camera.height

    def set_scene(self, text: str) -> int:
        """Replace the scene with scene YAML; returns its number of objects.

        Raises
        ------
        ValueError
            Malformed scene (nothing changes).
        """
        from galvoscan_sim import ConfigError, load_scene_text

        try:
            scene = load_scene_text(text)
        except ConfigError as err:
            raise ValueError(str(err)) from err
        with self._lock:
            self.sim.set_scene(scene)
        return len(scene.objects)

    def render(self, edge_ns: int, codes, powered: int, range_code: int, laser_on: bool,
               exposure_s: float, roi=None, cycle: int = 0) -> np.ndarray:
        """The image of one trigger edge.

        Parameters
        ----------
        edge_ns : int
            The edge's instant (logged with the frame).
        codes, powered, range_code
            The DAC's output state at the edge (:func:`ad5754r_volts`).
        laser_on : bool
            The laser enable pin at the edge.
        exposure_s : float
            The camera's ExposureTime [s] (laser frames; laser-off frames are board frames
            at the rig's board exposure).
        roi : tuple, optional
            (Width, Height, OffsetX, OffsetY, bits per pixel) of the camera: the image is
            cut to that region and scaled to those bits.
        cycle : int
            The edge's CPU cycle (logged).

        Raises
        ------
        ValueError
            Voltages outside the galvo drivers' +-10 V input, or a bad exposure.
        """
        volts = ad5754r_volts(codes, powered, range_code)
        if np.any(np.abs(volts) > self.sim.rig.dac.full_scale):
            raise ValueError(f'DAC outputs {volts.tolist()} V beyond the galvo drivers\' +-'
                             f'{self.sim.rig.dac.full_scale} V input')
        if not (np.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f'exposure {exposure_s} s')
        with self._lock:
            index = self.index
            self.index += 1
            if laser_on:
                frame = self.sim.render(volts, exposure=exposure_s, frame_index=index)
            else:
                frame = self.sim.calibration_frame(volts, frame_index=index)
        image = frame.image
        if roi is not None:
            w, h, ox, oy, depth = (int(v) for v in roi)
            image = image[oy:oy + h, ox:ox + w]
            src = self.sim.rig.image.bit_depth
            if depth != 8 or image.dtype != np.uint8:
                wide = image.astype(np.uint32)
                wide = wide << (depth - src) if depth >= src else wide >> (src - depth)
                image = wide.astype(np.uint8 if depth == 8 else '<u2')
        image = np.ascontiguousarray(image)
        if self._log is not None:
            c = ' '.join(str(int(x)) for x in codes)
            self._log.write(f'{int(edge_ns)} {int(cycle)} {index} {c} {int(bool(laser_on))} '
                            f'{exposure_s * 1e6:.3f} {image_crc(image)}\n')
            self._log.flush()
        return image

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None
