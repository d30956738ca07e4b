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
* the physics, and only the physics, is the simulator
  (:class:`~galvo_driver.twin_render.Renderer`): the galvos
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

import tempfile
from pathlib import Path

from galvo_driver.fake_camera import FakeCamera
from galvo_driver.serial_link.simavr_board import SimavrBoard
from galvo_driver.twin_render import (  # noqa: F401 - the twin's physics, named here too
    AD5754R_BITS,
    AD5754R_RANGES,
    Renderer,
    RenderRecord,
    ad5754r_volts,
    image_crc,
    read_render_log,
    renders_by_image,
)

#: How long the driver waits for a scan's last frames [s]: the renderer delays each frame
#: by its render time (a board frame takes 0.1-0.2 s on a loaded 2-core machine).
FRAME_TIMEOUT_S = 3.0
#: The board's simulation slips when it falls this far behind the wall clock [ms] (a loaded
#: machine stalling it) rather than catching up in a burst that would trip its watchdog.
MAX_LAG_MS = 10.0



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
