"""The galvo board firmware (``firmware/``) running in simavr, as a board the host can use.

The C harness ``firmware/build/galvo_harness`` runs the firmware's ELF in simavr with the
board around it: the AD5754R DAC on the SPI (with /LDAC), the trigger, laser and interlock
pins, and a cycle-stamped log of all of it (format in ``firmware/harness/galvo_harness.c``).
Two ways to drive it:

* :class:`SimavrBoard`: the firmware's UART on a pty, simulated time locked to the wall
  clock, so that :class:`~galvo_driver.serial_link.backend.SerialBackend` (or any host)
  opens :attr:`SimavrBoard.port` exactly like a board's USB serial port. Interlock, reset
  and unplug are commands to the harness.
* :func:`run_script`: a scripted host in *simulated* time, free-running (several times
  faster than real time, and deterministic): the bytes to send and the pin changes at given
  board times, then the log. :class:`Script` writes such scripts with the protocol module.

:func:`parse_log` turns a log into a :class:`HarnessLog`: DAC output updates, trigger edges,
laser and interlock levels, and every frame in both directions, each with its CPU cycle
(16 MHz). Build the harness and firmware with ``make firmware`` (or :func:`build`).

No rclpy here.
"""

from __future__ import annotations

import bisect
import os
import select
import struct
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from galvo_driver.serial_link import protocol as p

#: CPU clock of the simulated ATmega2560 [Hz].
F_CPU = 16_000_000
#: The harness's datagram for each rising trigger edge (``--edge-udp``; the layout is in
#: ``galvo_harness.c``): edge instant [ns, CLOCK_REALTIME], the four DAC output codes, the
#: powered-channel mask, the output range code, the laser level, 5 pad bytes, the CPU cycle.
EDGE_FORMAT = struct.Struct('<Q4HBBB5xQ')


def firmware_dir() -> Path:
    """The repository's ``firmware/`` directory (or ``$GALVOSCAN_FIRMWARE_DIR``)."""
    env = os.environ.get('GALVOSCAN_FIRMWARE_DIR')
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[4] / 'firmware'


def build() -> tuple[Path, Path]:
    """Run ``make -C firmware`` (a no-op when up to date); return (harness, elf).

    Raises
    ------
    RuntimeError
        The build failed (the message holds make's output), e.g. gcc-avr or libsimavr-dev
        missing: they come from tools/apt-packages.txt.
    """
    fw = firmware_dir()
    proc = subprocess.run(['make', '-s', '-C', str(fw), 'all'], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        raise RuntimeError(f'make -C {fw} failed:\n{proc.stdout}\n{proc.stderr}')
    return fw / 'build' / 'galvo_harness', fw / 'build' / 'galvo_board.elf'


# ---------------------------------------------------------------------------------------
# The log
# ---------------------------------------------------------------------------------------

@dataclass
class HarnessLog:
    """Everything the simulated board did, with CPU cycles (see the module docstring).

    Attributes
    ----------
    outputs : list of (cycle, codes, powered, range_code)
        DAC output updates: codes of (U1_pan, U1_tilt, U2_pan, U2_tilt), the bit mask of
        powered channels and the output range code (4: +-10 V).
    trigger : list of (cycle, level)
    laser : list of (cycle, level)
    interlock : list of (cycle, is_open)
    tx : list of (cycle, frame bytes)
        Frames the firmware sent (with their 0x00 delimiter), at their last byte.
    rx : list of (cycle, bytes)
        Bytes handed to the firmware's UART receiver.
    resets : list of cycle
    crashed : bool
    end : int
        The last simulated cycle.
    """

    outputs: list = field(default_factory=list)
    trigger: list = field(default_factory=list)
    laser: list = field(default_factory=list)
    interlock: list = field(default_factory=list)
    tx: list = field(default_factory=list)
    rx: list = field(default_factory=list)
    resets: list = field(default_factory=list)
    frame_errors: int = 0
    crashed: bool = False
    end: int = 0

    def rising_edges(self) -> np.ndarray:
        """Cycles of the trigger's rising edges."""
        return np.array([c for c, v in self.trigger if v], dtype=np.int64)

    def codes_at(self, cycle: int) -> tuple:
        """DAC output codes in effect at ``cycle``."""
        cycles = [o[0] for o in self.outputs]
        i = bisect.bisect_right(cycles, cycle) - 1
        if i < 0:
            raise ValueError(f'no DAC output before cycle {cycle}')
        return self.outputs[i][1]

    def level_at(self, series: list, cycle: int, default: int = 0) -> int:
        """Level of a (cycle, level) series at ``cycle``."""
        cycles = [s[0] for s in series]
        i = bisect.bisect_right(cycles, cycle) - 1
        return default if i < 0 else series[i][1]

    def packets(self) -> list[tuple[int, p.Packet]]:
        """Every packet the firmware sent, decoded (bad frames are left out and counted
        by the decoder they went through: :attr:`decode_errors`)."""
        dec = p.FrameDecoder()
        out = []
        for cycle, frame in self.tx:
            out += [(cycle, pkt) for pkt in dec.feed(frame)]
        self.decode_errors = dec.error_count
        return out

    def events(self) -> list[tuple[int, p.Event]]:
        return [(c, pk.msg) for c, pk in self.packets() if isinstance(pk.msg, p.Event)]


def parse_log(path) -> HarnessLog:
    """Read a harness log file (see the module docstring)."""
    log = HarnessLog()
    with open(path, encoding='ascii') as fh:
        for line in fh:
            if line.startswith('#'):
                continue
            f = line.split()
            if len(f) < 2:
                continue
            cycle, what = int(f[0]), f[1]
            log.end = cycle
            if what == 'out':
                log.outputs.append((cycle, tuple(int(x) for x in f[2:6]), int(f[6]),
                                    int(f[7])))
            elif what == 'trig':
                log.trigger.append((cycle, int(f[2])))
            elif what == 'laser':
                log.laser.append((cycle, int(f[2])))
            elif what == 'interlock':
                log.interlock.append((cycle, f[2] == 'open'))
            elif what == 'tx':
                log.tx.append((cycle, bytes.fromhex(f[2])))
            elif what == 'rx':
                log.rx.append((cycle, bytes.fromhex(f[2])))
            elif what == 'reset':
                log.resets.append(cycle)
            elif what == 'dac-frame-error':
                log.frame_errors += 1
            elif what == 'crashed':
                log.crashed = True
    return log


# ---------------------------------------------------------------------------------------
# Scripted host, simulated time
# ---------------------------------------------------------------------------------------

class Script:
    """A scripted host: lines of (board time [us], action) for :func:`run_script`.

    Commands get consecutive sequence numbers from 1, as the serial backend numbers them.
    """

    def __init__(self):
        self.lines: list[tuple[float, str]] = []
        self.seq = 0
        self.sent: dict[int, p.Message] = {}

    def raw(self, t_us: float, frame: bytes) -> None:
        """Send raw bytes (a frame with its delimiter, or anything else)."""
        self.lines.append((t_us, 'tx ' + bytes(frame).hex()))

    def send(self, t_us: float, msg: p.Message, seq: int | None = None) -> int:
        """Send one message; returns its seq (0 for HEARTBEAT)."""
        if seq is None:
            if isinstance(msg, p.Heartbeat):
                seq = 0
            else:
                self.seq = self.seq % 0xFFFF + 1
                seq = self.seq
        self.sent[seq] = msg
        self.raw(t_us, p.encode_frame(seq, msg))
        return seq

    def heartbeats(self, t0_us: float, t1_us: float, period_us: float = 50_000) -> None:
        """HEARTBEAT every ``period_us`` from ``t0_us`` up to ``t1_us``."""
        for t in np.arange(t0_us, t1_us, period_us):
            self.send(float(t), p.Heartbeat())

    def upload_scan(self, t_us: float, scan_id: int, codes: np.ndarray, period_us: int,
                    laser: bool = True, gap_us: float = 8000.0) -> float:
        """SCAN_BEGIN, the SCAN_DATA chunks and SCAN_START from ``t_us``, one command every
        ``gap_us`` (a full SCAN_DATA frame takes 2.7 ms at 1 Mbaud, 11 bits a byte in simavr
        1.6, which always counts a parity bit); returns the time of SCAN_START."""
        codes = np.asarray(codes, dtype=np.uint16)
        self.send(t_us, p.ScanBegin(scan_id, len(codes)))
        for off in range(0, len(codes), p.ROWS_PER_CHUNK):
            t_us += gap_us
            rows = tuple(tuple(int(c) for c in r) for r in codes[off:off + p.ROWS_PER_CHUNK])
            self.send(t_us, p.ScanData(scan_id, off, rows))
        t_us += gap_us
        self.send(t_us, p.ScanStart(scan_id, len(codes), period_us, laser,
                                    p.table_crc(codes)))
        return t_us

    def at(self, t_us: float, action: str) -> None:
        """A harness action: 'interlock open', 'interlock closed', 'reset'."""
        self.lines.append((t_us, action))

    def text(self, end_us: float) -> str:
        lines = sorted(self.lines, key=lambda x: x[0])
        return ''.join(f'{t:.3f} {a}\n' for t, a in lines) + f'{end_us:.3f} end\n'


def run_script(script: Script, end_us: float, *, boot_count: int = 1, workdir=None,
               timeout: float = 120.0) -> HarnessLog:
    """Run the firmware free-running against a scripted host until board time ``end_us``;
    return its log.

    Raises
    ------
    RuntimeError
        The harness failed or did not finish within ``timeout`` [s] of wall time.
    """
    harness, elf = build()
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        script_path = Path(tmp) / 'script.txt'
        log_path = Path(tmp) / 'board.log'
        script_path.write_text(script.text(end_us))
        try:
            proc = subprocess.run([str(harness), '--log', str(log_path), '--script',
                                   str(script_path), '--boot-count', str(boot_count),
                                   str(elf)], capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired as err:
            raise RuntimeError(f'the harness did not finish in {timeout} s') from err
        if proc.returncode != 0:
            raise RuntimeError(f'galvo_harness failed: {proc.stderr}')
        return parse_log(log_path)


def answers(log: HarnessLog) -> dict[int, list[p.Message]]:
    """The ACK/NAK answers in a log, by the seq they answer."""
    out: dict[int, list[p.Message]] = {}
    for _, pkt in log.packets():
        if isinstance(pkt.msg, (p.Ack, p.Nak)):
            out.setdefault(pkt.msg.acked_seq, []).append(pkt.msg)
    return out


# ---------------------------------------------------------------------------------------
# Host in the loop: pty, real time
# ---------------------------------------------------------------------------------------

class SimavrBoard:
    """The firmware in simavr behind a pty, in real time (module docstring).

    Parameters
    ----------
    log_path : str, optional
        Where the harness writes its log (default: a temporary file).
    boot_count : int
        EEPROM boot counter before power-up (so that runs differ in their boot id).
    rate : float
        Simulated seconds per wall-clock second (1: real time). Below 1 the board's
        watchdog (150 ms of board time) gives a host that a loaded machine stalls more
        wall-clock time; board times (trigger stamps) stay exact.
    edge_udp_port : int, optional
        The board's trigger output wired to a camera's trigger input on this UDP port of
        127.0.0.1: each rising edge sends one datagram, stamped with the edge's wall-clock
        instant and carrying the DAC outputs and the laser level at that edge (the galvos'
        and the laser's drive, for a simulated rig's physics: :data:`EDGE_FORMAT`). The
        edges' instants follow the board's crystal from power-up (a camera clock of its own).
    max_lag_ms : float, optional
        When the harness falls this far behind the wall clock (the machine stalled it), it
        slips instead of catching up in a burst, which would hand the firmware the host's
        bytes of the stall at once and then run its watchdog out in fast-forward. The board
        clock then runs behind the host's by the slips (a clock step for the host; the
        serial backend resyncs before each scan). None: always catch up.
    """

    def __init__(self, log_path: str | None = None, boot_count: int = 1, rate: float = 1.0,
                 edge_udp_port: int | None = None, max_lag_ms: float | None = None):
        if not (np.isfinite(rate) and 0 < rate <= 1):
            raise ValueError(f'rate: expected 0 < rate <= 1, got {rate}')
        if edge_udp_port is not None and not 1 <= int(edge_udp_port) <= 65535:
            raise ValueError(f'edge_udp_port: expected 1..65535, got {edge_udp_port}')
        self.edge_udp_port = None if edge_udp_port is None else int(edge_udp_port)
        if max_lag_ms is not None and not (np.isfinite(max_lag_ms) and max_lag_ms > 0):
            raise ValueError(f'max_lag_ms: expected > 0 ms, got {max_lag_ms}')
        self.max_lag_ms = max_lag_ms
        self.rate = float(rate)
        self._tmp = None
        if log_path is None:
            self._tmp = tempfile.TemporaryDirectory()
            log_path = str(Path(self._tmp.name) / 'board.log')
        self.log_path = log_path
        self.boot_count = int(boot_count)
        self.port: str | None = None
        self._proc: subprocess.Popen | None = None
        self._out = b''

    def start(self) -> SimavrBoard:
        """Start the harness; :attr:`port` is the pty to open."""
        harness, elf = build()
        self._proc = subprocess.Popen(
            [str(harness), '--pty', '--realtime', '--rate', repr(self.rate), '--log',
             self.log_path,
             '--boot-count', str(self.boot_count),
             *(['--edge-udp', str(self.edge_udp_port)] if self.edge_udp_port else []),
             *(['--max-lag', repr(float(self.max_lag_ms))] if self.max_lag_ms else []),
             str(elf)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            bufsize=0)
        # unbuffered reads: a buffered reader would swallow the pty line that select waits for
        out = b''
        fd = self._proc.stdout.fileno()
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            ready, _, _ = select.select([fd], [], [], 0.5)
            if ready:
                chunk = os.read(fd, 4096)
                if not chunk:
                    break
                out += chunk
                for line in out.decode('ascii', 'replace').splitlines():
                    if line.startswith('pty ') and out.endswith(b'\n'):
                        self.port = line.split(None, 1)[1].strip()
                        return self
        self.stop()
        raise RuntimeError('galvo_harness did not report its pty')

    def _command(self, line: str) -> None:
        if self._proc is None or self._proc.poll() is not None:
            raise RuntimeError('the harness is not running')
        self._proc.stdin.write((line + '\n').encode('ascii'))

    def set_interlock(self, is_open: bool) -> None:
        """Open or close the interlock loop."""
        self._command('interlock open' if is_open else 'interlock closed')

    def reset(self, after_event: int | None = None, hold_s: float = 0.0) -> None:
        """Reset the MCU now, or right after it has sent the EVENT of trigger index
        ``after_event``; ``hold_s`` [s of wall-clock time] keeps it in reset that long first
        (as the Mega's bootloader delays the firmware after a reset)."""
        if hold_s > 0:
            self._command(f'hold-reset {round(hold_s * 1e3)}')
        else:
            self._command('reset' if after_event is None
                          else f'reset-after-event {after_event}')

    def unplug(self) -> None:
        """Cut the serial link both ways (the board runs on)."""
        self._command('unplug')

    def replug(self) -> None:
        self._command('replug')

    def log(self) -> HarnessLog:
        """The log up to now (the harness flushes it on request first)."""
        self._command('sync')
        fd = self._proc.stdout.fileno()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if b'sync ' in self._out:
                self._out = self._out[self._out.index(b'sync ') + 5:]
                break
            ready, _, _ = select.select([fd], [], [], 0.5)
            if ready:
                chunk = os.read(fd, 4096)
                if not chunk:
                    raise RuntimeError('the harness exited')
                self._out += chunk
        else:
            raise RuntimeError('the harness did not answer sync')
        return parse_log(self.log_path)

    def trigger_codes(self) -> list[tuple]:
        """DAC output codes at each trigger's rising edge so far."""
        log = self.log()
        return [log.codes_at(int(c)) for c in log.rising_edges()]

    def output_codes(self) -> tuple:
        """The DAC output codes now."""
        return self.log().outputs[-1][1]

    def laser_on(self) -> bool:
        log = self.log()
        return bool(log.laser[-1][1]) if log.laser else False

    def faults(self) -> list[int]:
        """Codes of the FAULT messages the board has sent."""
        return [pk.msg.code for _, pk in self.log().packets() if isinstance(pk.msg, p.Fault)]

    def is_safe(self) -> bool:
        """All channels at code 32768 (0 V) and the laser off, now."""
        log = self.log()
        laser = log.laser[-1][1] if log.laser else 0
        return bool(log.outputs) and log.outputs[-1][1] == (p.CODE_ZERO,) * 4 and not laser

    def wait_until(self, predicate, timeout: float = 2.0) -> bool:
        """Poll ``predicate(board)`` every 20 ms until true or ``timeout`` [s]."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.02)
        return bool(predicate(self))

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                proc.stdin.write(b'quit\n')
            except (BrokenPipeError, ValueError, OSError):
                pass
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            for stream in (proc.stdin, proc.stdout):
                try:
                    stream.close()
                except OSError:
                    pass

    def close(self) -> None:
        self.stop()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> SimavrBoard:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
