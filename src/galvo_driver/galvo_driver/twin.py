"""The hardware-in-the-loop twin of a rig: every part real but the physics.

A :class:`Twin` is what the ``rig`` backend opens in place of a real galvo board and a real
camera:

* the galvo board is the firmware (``firmware/``) in simavr, locked to the wall clock
  (:class:`~galvo_driver.serial_link.simavr_board.SimavrBoard`): its UART on a pty that
  the driver opens as a serial port, the AD5754R DAC modelled on its SPI, its timer firing
  the trigger output;
* the trigger wire goes from that output to the camera's ``Line0`` input (a UDP datagram
  per rising edge, sent by the harness at the edge);
* the camera is Aravis' GigE Vision fake camera (:class:`~galvo_driver.fake_camera.FakeCamera`)
  on loopback, speaking GVCP/GVSP and GenICam to the driver, with the simulator's rendered
  exposure as each triggered frame's payload;
* the physics, and only the physics, is the simulator (:class:`Renderer`): the galvos
  turn to the DAC's output voltages at the edge (the AD5754R's transfer function applied to
  the codes in its output registers, which the edge's datagram carries: the drive voltage on
  the galvo drivers' inputs), the laser shines if its enable pin is high, and the camera
  exposes the scene.

The host never tells the twin what it commanded: the voltages an image is rendered at are
the DAC model's outputs at the trigger edge, so a frame the driver tags with the wrong
EVENT has an image of other voltages. Every rendered frame is logged (:func:`read_render_log`)
with its edge, the DAC codes and the CRC-32 of its image: the truth a test finds a published
image by (:func:`renders_by_image`) and checks the driver's tag against. The image itself is
the simulator's, untouched.

What the twin does not model: the galvos' settling (the image is rendered at the outputs'
final angles; the firmware gives them half a trigger period), the camera's Gain (the rig's
sensor gain is used) and exposure for laser-off frames (the rig's board exposure under room
light, as the ``sim`` backend takes them). The renderer is slower than a real camera, so the
twin runs at a reduced frame rate (tens of Hz for 720 x 540 frames on a shared 2-core
machine); frames are delayed by the render time, never lost to it.

No rclpy here.
"""

from __future__ import annotations

import dataclasses
import tempfile
import threading
import zlib
from pathlib import Path

import numpy as np

from galvo_driver.fake_camera import _PIXEL_DEPTH, FakeCamera
from galvo_driver.serial_link.simavr_board import SimavrBoard

#: AD5754R output range select codes -> (lowest, highest) output [V] (Analog Devices,
#: AD5724R/AD5734R/AD5754R data sheet Rev. E, "Output Range Select Register", Table 26).
AD5754R_RANGES = {0: (0.0, 5.0), 1: (0.0, 10.0), 2: (0.0, 10.8), 3: (-5.0, 5.0),
                  4: (-10.0, 10.0), 5: (-10.8, 10.8)}
#: The DAC's bits.
AD5754R_BITS = 16
#: How long the driver waits for a scan's last frames [s]: the renderer delays each frame
#: by its render time (a board frame takes 0.1-0.2 s on a loaded 2-core machine).
FRAME_TIMEOUT_S = 3.0
#: The board's simulation slips when it falls this far behind the wall clock [ms] (a loaded
#: machine stalling it) rather than catching up in a burst that would trip its watchdog.
MAX_LAG_MS = 10.0


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
            (Width, Height, OffsetX, OffsetY, PixelFormat) of the camera: the image is cut
            to that region and scaled to that pixel format's bits.
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
            w, h, ox, oy, pixel_format = (int(v) for v in roi)
            image = image[oy:oy + h, ox:ox + w]
            depth = _PIXEL_DEPTH.get(pixel_format, 8)
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


class Twin:
    """The twin's board and camera, started together (a context manager).

    Parameters
    ----------
    rig, scene : str
        Simulator rig and scene.
    seed : int
        Simulator seed.
    serial : str
        The camera's serial number (the driver's ``camera_serial``).
    boot_count : int
        The board's EEPROM boot counter (its boot id).
    rate : float
        The board's simulated seconds per wall-clock second (:class:`SimavrBoard`): below 1
        a host that a loaded machine stalls has more wall-clock time before the board's
        150 ms watchdog trips (the trigger rate in wall-clock time is ``rate`` times the
        scan's). The camera keeps the board's crystal time.
    workdir : str, optional
        Where the board log (``board.log``) and the render log (``render.log``) go
        (default: a temporary directory, removed at :meth:`close`).

    Attributes
    ----------
    board : SimavrBoard
    camera : FakeCamera
    """

    def __init__(self, rig: str = 'reference', scene: str = 'stair_block', seed: int = 0,
                 serial: str = 'GSTWIN0', boot_count: int = 1, workdir: str | None = None,
                 rate: float = 1.0):
        self.rig, self.scene, self.seed = str(rig), str(scene), int(seed)
        self.rate = float(rate)
        self.serial = serial
        self.boot_count = int(boot_count)
        self._tmp = None
        if workdir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix='galvoscan-twin-')
            workdir = self._tmp.name
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.render_log = self.workdir / 'render.log'
        self.board_log = self.workdir / 'board.log'
        self.camera: FakeCamera | None = None
        self.board: SimavrBoard | None = None

    def start(self) -> Twin:
        """Start the camera (the renderer loads and compiles first), then the board wired
        to its trigger input.

        Raises
        ------
        RuntimeError
            Either part did not start (the other is stopped).
        ValueError
            Bad rig or scene.
        """
        self.render_log.unlink(missing_ok=True)
        self.camera = FakeCamera(self.serial, start_timeout_s=180.0, render={
            'rig': self.rig, 'scene': self.scene, 'seed': self.seed,
            'log': str(self.render_log)})
        self.camera.replug()
        try:
            self.board = SimavrBoard(str(self.board_log), boot_count=self.boot_count,
                                     edge_udp_port=self.camera.line_port,
                                     max_lag_ms=MAX_LAG_MS, rate=self.rate).start()
        except BaseException:
            self.close()
            raise
        return self

    @property
    def port(self) -> str:
        """The board's serial port (the driver's ``serial_port``)."""
        if self.board is None or self.board.port is None:
            raise RuntimeError('the twin is not started')
        return self.board.port

    def exposure_us(self) -> float:
        """The rig's laser-frame exposure [us] (the camera's ExposureTime a scan of it
        should use)."""
        from galvoscan_sim import load_rig

        return load_rig(self.rig).image.exposure * 1e6

    def driver_parameters(self) -> dict:
        """``galvo_driver`` parameters of a ``rig`` backend on this twin: the board's pty,
        the camera's serial, the rig's exposure, Mono8. The camera stamps frames on a clock of
        its own (``camera_clock: camera``): the board crystal's time since power-up, which
        a loaded machine's slips (:data:`MAX_LAG_MS`) put behind the host's. The frames'
        render delay asks for a longer ``frame_timeout`` (:data:`FRAME_TIMEOUT_S`)."""
        return {'backend': 'rig', 'serial_port': self.port, 'camera_serial': self.serial,
                'camera_clock': 'camera', 'ExposureTime': float(self.exposure_us()),
                'PixelFormat': 'Mono8', 'frame_timeout': FRAME_TIMEOUT_S}

    def set_scene(self, text: str) -> int:
        """Replace the rendered scene (scene YAML); returns its number of objects.

        Raises
        ------
        ValueError
            Malformed scene (the scene stays).
        """
        if self.camera is None:
            raise RuntimeError('the twin is not started')
        return self.camera.set_scene(text)

    def renders(self) -> dict[int, RenderRecord]:
        """Every frame rendered so far, by edge instant."""
        return read_render_log(self.render_log)

    def close(self) -> None:
        """Stop the board and the camera."""
        if self.board is not None:
            self.board.stop()
            self.board = None
        if self.camera is not None:
            self.camera.close()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> Twin:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
