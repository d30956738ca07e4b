"""Firmware emulator of the galvo DAC board, speaking the real protocol over real bytes.

The emulator runs in a thread and serves one byte transport:

* ``'pty'``: a pseudo-terminal pair from ``os.openpty()``; the host opens the slave path
  (:attr:`FirmwareEmulator.port`, e.g. ``/dev/pts/7``) with pyserial exactly like a USB
  serial adapter.
* ``'tcp'``: a TCP server on 127.0.0.1; the host opens ``socket://127.0.0.1:<port>`` with
  ``serial.serial_for_url``.

It keeps a log of every DAC output and laser state it applied (:meth:`applied`), with the
emulator's ``time.monotonic()`` time and the reason, so tests can check what the "hardware"
did, and it injects faults on demand: lost bytes and corrupted bits in outgoing frames
(by message kind), corrupted or shortened incoming frames, lost ACKs, a DAC glitch (a row
output one LSB off), a reset (at once or right after a given trigger), an unplug (the
transport is closed; the board keeps running and its watchdog makes it safe), duplicated
trigger events, a drifting microsecond clock (ppm) and a clock step. Its interlock input
opens and closes on demand (:meth:`FirmwareEmulator.set_interlock`).

It follows ``docs/board-protocol.md`` as the board firmware (``firmware/``) does; where the
two could differ, the firmware is the reference and the emulator follows it (the scan
timing included: first edge half a period after SCAN_START, laser off and STATUS DONE half
a period after the last edge).

Every trigger is also recorded with its boot id, scan id, index and board timestamp
(:meth:`FirmwareEmulator.triggers`), and an ``on_trigger`` hook is called at each trigger
instant, so a test can fire a camera's software trigger from the board's trigger, as the
trigger output wired to the camera's line in does on a rig.

Run it as a separate process for driver tests::

    python -m galvo_driver.serial_link.emulator --pty --log /tmp/emu.jsonl

prints the port to open on its first stdout line, appends every applied output to the log
file as one JSON object per line (``t`` [s, monotonic], ``codes``, ``volts`` [V], ``laser``,
``reason``) and exits cleanly on SIGTERM or SIGINT.

No rclpy here.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import random
import select
import signal
import socket
import sys
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from galvo_driver.serial_link import protocol as p

#: Message kinds accepted by the outgoing fault injectors.
TX_KINDS = {'any': None, 'ack': p.ACK, 'nak': p.NAK, 'event': p.EVENT, 'boot': p.BOOT,
            'status': p.STATUS, 'fault': p.FAULT}

_ZERO_CODES = (p.CODE_ZERO,) * p.N_CHANNELS
#: Longest trigger period a board accepts [us] (docs/board-protocol.md).
MAX_PERIOD_US = 60_000_000


@dataclass(frozen=True)
class AppliedOutput:
    """One output state the board applied.

    Attributes
    ----------
    t : float
        Emulator ``time.monotonic()`` when it was applied [s].
    codes : tuple of 4 int
        DAC codes of (U1_pan, U1_tilt, U2_pan, U2_tilt).
    laser_on : bool
    reason : str
        'boot', 'reset', 'set', 'laser', 'trigger', 'scan_done', 'stop', 'safe', 'watchdog',
        'interlock'.
    """

    t: float
    codes: tuple
    laser_on: bool
    reason: str

    @property
    def voltages(self) -> np.ndarray:
        """shape (4,), volts."""
        return p.codes_to_volts(np.array(self.codes))

    @property
    def is_safe(self) -> bool:
        """All channels at exactly 0 V and the laser off."""
        return self.codes == _ZERO_CODES and not self.laser_on

    def as_dict(self) -> dict:
        return {'t': self.t, 'codes': list(self.codes),
                'volts': [float(v) for v in self.voltages], 'laser': self.laser_on,
                'reason': self.reason}


@dataclass(frozen=True)
class TriggerRecord:
    """One trigger the board fired: the truth a pairing is checked against.

    Attributes
    ----------
    boot_id, scan_id, index : int
        As in the trigger's EVENT.
    t : float
        Emulator ``time.monotonic()`` of the trigger instant [s].
    timestamp_us : int
        The board clock at that instant, as the EVENT reports it [us] (with the injected
        drift and steps).
    codes : tuple of 4 int
        DAC codes output from this trigger until the next output change.
    laser_on : bool
    """

    boot_id: int
    scan_id: int
    index: int
    t: float
    timestamp_us: int
    codes: tuple
    laser_on: bool


class _PtyTransport:
    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line editing before the host configures it
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)

    def fds(self):
        return [self.master]

    def on_readable(self, fd) -> bytes:
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b''
        except OSError as err:
            if err.errno == errno.EIO:  # no slave open at the moment
                return b''
            raise

    def write(self, data: bytes) -> int:
        try:
            return os.write(self.master, data)
        except (BlockingIOError, OSError):
            return 0

    def close(self):
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class _TcpTransport:
    def __init__(self, port: int = 0):
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(('127.0.0.1', port))
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.conn: socket.socket | None = None
        self.port = f'socket://127.0.0.1:{self.listener.getsockname()[1]}'

    def fds(self):
        return [self.listener.fileno()] + ([self.conn.fileno()] if self.conn else [])

    def on_readable(self, fd) -> bytes:
        if fd == self.listener.fileno():
            try:
                conn, _ = self.listener.accept()
            except BlockingIOError:
                return b''
            if self.conn is not None:  # one host at a time: the newest wins
                self.conn.close()
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.conn = conn
            return b''
        try:
            data = self.conn.recv(4096)
        except BlockingIOError:
            return b''
        except OSError:
            data = b''
        if not data:  # the host closed the connection
            self.conn.close()
            self.conn = None
        return data

    def write(self, data: bytes) -> int:
        if self.conn is None:
            return 0
        try:
            return self.conn.send(data)
        except (BlockingIOError, OSError):
            return 0

    def close(self):
        for s in (self.conn, self.listener):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self.conn = None


class FirmwareEmulator:
    """The board's firmware, in a thread, on a pty or a TCP socket.

    Parameters
    ----------
    transport : {'pty', 'tcp'}
    watchdog : float
        Heartbeat watchdog time [s]; after this long without a valid host packet the board
        goes safe.
    protocol_version : int
        Version reported in HELLO/BOOT (set another one to test the host's version check).
    firmware_id : str
        Up to 16 ASCII characters.
    max_scan_rows : int
    min_period_us : int
        Shortest trigger period the board accepts [us].
    log_path : str, optional
        Append every applied output as a JSON line to this file.
    tcp_port : int
        TCP port for ``transport='tcp'`` (0: any free port).
    seed : int, optional
        Seed of the boot-id and fault-position generator.
    log_maxlen : int
        Applied outputs and trigger records kept in memory.
    on_trigger : callable, optional
        ``on_trigger(index, t)``, called in the emulator thread at each trigger instant,
        after the output is applied and before its EVENT is sent, with the trigger index and
        the instant's ``time.monotonic()`` [s]. Keep it short: it delays the EVENT. An
        exception it raises is counted in ``stats['hook_errors']`` (the message kept in
        :attr:`hook_error`) and does not stop the board.
    clock_drift_ppm : float
        Rate error of the board's crystal [ppm] (within +-1000): its microsecond clock and
        its trigger timer; see :meth:`set_clock_drift`.
    """

    def __init__(self, transport: str = 'pty', *, watchdog: float = 0.15,
                 protocol_version: int = p.PROTOCOL_VERSION,
                 firmware_id: str = 'galvoscan-emu', max_scan_rows: int = 1 << 20,
                 min_period_us: int = 100, log_path: str | None = None, tcp_port: int = 0,
                 seed: int | None = None, log_maxlen: int = 200_000,
                 on_trigger: Callable[[int, float], None] | None = None,
                 clock_drift_ppm: float = 0.0):
        if transport not in ('pty', 'tcp'):
            raise ValueError(f"transport: expected 'pty' or 'tcp', got {transport!r}")
        if not (np.isfinite(watchdog) and watchdog > 0):
            raise ValueError(f'watchdog: must be a positive time in s, got {watchdog}')
        if len(firmware_id.encode('ascii')) > 16:
            raise ValueError('firmware_id: at most 16 ASCII characters')
        self.watchdog = float(watchdog)
        self.protocol_version = int(protocol_version)
        self.firmware_id = firmware_id
        self.max_scan_rows = int(max_scan_rows)
        self.min_period_us = int(min_period_us)
        self._rng = random.Random(seed)
        self._lock = threading.RLock()
        self._log: deque[AppliedOutput] = deque(maxlen=log_maxlen)
        self._trigger_log: deque[TriggerRecord] = deque(maxlen=log_maxlen)
        if on_trigger is not None and not callable(on_trigger):
            raise ValueError('on_trigger: expected a callable(index, t) or None')
        self.on_trigger = on_trigger
        #: Message of the last exception raised by ``on_trigger``, or None.
        self.hook_error: str | None = None
        self._drift_ppm = self._check_drift(clock_drift_ppm)
        self._clock_step_at: tuple[int, int] | None = None  # (trigger index, step [us])
        self._dup_events: list[int] = [0, 0]  # [remaining, skip]
        self._log_file = open(log_path, 'a', encoding='utf-8') if log_path else None
        self._transport = _PtyTransport() if transport == 'pty' else _TcpTransport(tcp_port)
        self.port: str = self._transport.port
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._unplugged = False
        # fault injection requests
        self._tx_faults: list[list] = []  # [action, kind_type, remaining, skip]
        self._drop_acks = 0
        self._rx_faults: list[list] = []  # [action, remaining]
        self._glitches = 0
        self._reset_request = False
        self._reset_at_trigger: int | None = None
        self._unplug_request = False
        self._interlock = False  # the input's level survives resets: it is wiring
        self._interlock_request: bool | None = None
        self._ignored_rx = 0  # board-type packets sent to the board (not rx errors)
        # statistics
        self.stats = {'rx_frames': 0, 'rx_errors': 0, 'tx_frames': 0, 'tx_dropped_bytes': 0,
                      'duplicates': 0, 'late_triggers': 0, 'resets': 0, 'hook_errors': 0,
                      'duplicated_events': 0, 'clock_steps': 0}
        #: (time of the last host packet, time the watchdog made the board safe) [s, monotonic]
        self.watchdog_trips: list[tuple[float, float]] = []
        self._decoder = p.FrameDecoder(on_error=self._on_rx_error)
        self._power_up()

    # -------------------------------------------------------------------- public API
    def start(self) -> FirmwareEmulator:
        """Start the firmware thread (it announces itself with BOOT)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name='galvo-emulator',
                                            daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the transport and the log file."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            self._transport.close()
            for fd in (self._wake_r, self._wake_w):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._wake_r = self._wake_w = -1
            if self._log_file is not None:
                self._log_file.close()
                self._log_file = None

    def __enter__(self) -> FirmwareEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def applied(self) -> list[AppliedOutput]:
        """Every output state applied so far, oldest first."""
        with self._lock:
            return list(self._log)

    def triggers(self) -> list[TriggerRecord]:
        """Every trigger fired so far (of every boot and scan), oldest first."""
        with self._lock:
            return list(self._trigger_log)

    def last_applied(self) -> AppliedOutput:
        with self._lock:
            return self._log[-1]

    def snapshot(self) -> dict:
        """Board state now: boot_id, state, scan_id, triggers, codes, laser_on, last_rx."""
        with self._lock:
            return {'boot_id': self._boot_id, 'state': self._state, 'scan_id': self._scan_id,
                    'triggers': self._triggers, 'codes': self._codes, 'laser_on': self._laser,
                    'session': self._session, 'last_rx': self._last_rx}

    def wait_until(self, predicate, timeout: float = 2.0) -> bool:
        """Poll ``predicate(emulator)`` every 2 ms until it is true or ``timeout`` [s]."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.002)
        return bool(predicate(self))

    # fault injection ------------------------------------------------------------------
    def drop_bytes(self, n_frames: int = 1, kind: str = 'any', skip: int = 0) -> None:
        """Lose one byte from the middle of each of the next ``n_frames`` outgoing frames
        of ``kind`` ('any', 'ack', 'nak', 'event', 'boot', 'status', 'fault'), after
        letting ``skip`` frames of that kind pass."""
        self._add_tx_fault('drop', n_frames, kind, skip)

    def corrupt_frames(self, n_frames: int = 1, kind: str = 'any', skip: int = 0) -> None:
        """Flip one bit in each of the next ``n_frames`` outgoing frames of ``kind``,
        after letting ``skip`` frames of that kind pass."""
        self._add_tx_fault('flip', n_frames, kind, skip)

    def drop_acks(self, n: int = 1) -> None:
        """Execute the next ``n`` commands but lose their ACK/NAK entirely."""
        with self._lock:
            self._drop_acks += int(n)

    def corrupt_rx(self, n_chunks: int = 1) -> None:
        """Flip one bit in each of the next ``n_chunks`` chunks of bytes received."""
        with self._lock:
            self._rx_faults.append(['flip', int(n_chunks)])

    def drop_rx_bytes(self, n_chunks: int = 1) -> None:
        """Lose one byte of each of the next ``n_chunks`` chunks of bytes received."""
        with self._lock:
            self._rx_faults.append(['drop', int(n_chunks)])

    def glitch_output(self, n_triggers: int = 1) -> None:
        """Output the next ``n_triggers`` scan rows one LSB off on channel 0 (a DAC fault);
        the events report the codes really output, as the firmware reads them back."""
        with self._lock:
            self._glitches += int(n_triggers)

    def reset(self, at_trigger: int | None = None) -> None:
        """Reset the board now, or right after it emits trigger index ``at_trigger``."""
        with self._lock:
            if at_trigger is None:
                self._reset_request = True
            else:
                self._reset_at_trigger = int(at_trigger)
        self._wake()

    def unplug(self) -> None:
        """Close the transport, as if the cable were pulled; the board keeps running."""
        with self._lock:
            self._unplug_request = True
        self._wake()

    def set_interlock(self, is_open: bool) -> None:
        """Open (True) or close the interlock loop. Opening switches the laser off, stops any
        scan, parks the galvos at 0 V and sends FAULT INTERLOCK and STATUS."""
        with self._lock:
            self._interlock_request = bool(is_open)
        self._wake()

    def duplicate_events(self, n: int = 1, skip: int = 0) -> None:
        """Send each of the next ``n`` trigger EVENTs twice (the copy with the next frame
        sequence number, as a firmware that re-emits an event), after letting ``skip``
        events pass."""
        if int(n) < 0 or int(skip) < 0:
            raise ValueError(f'n and skip must be >= 0, got {n}, {skip}')
        with self._lock:
            self._dup_events = [int(n), int(skip)]

    def set_clock_drift(self, ppm: float) -> None:
        """Make the board's crystal run ``ppm`` parts per million fast (negative: slow) from
        now on: its microsecond clock (continuously, no jump) and its trigger timer, whose
        period stays exact in board microseconds. It keeps the rate across resets."""
        ppm = self._check_drift(ppm)
        with self._lock:
            t = time.monotonic()
            self._clock_base = (t, self._board_us_exact(t))
            self._drift_ppm = ppm

    def step_clock(self, step_us: int, at_trigger: int | None = None) -> None:
        """Step the board's microsecond clock by ``step_us`` [us] (negative: back) now, or
        right before trigger index ``at_trigger`` of the running scan is timestamped."""
        step_us = int(step_us)
        with self._lock:
            if at_trigger is None:
                self._apply_clock_step(step_us)
            else:
                self._clock_step_at = (int(at_trigger), step_us)

    @property
    def clock_drift_ppm(self) -> float:
        """Rate error of the board clock [ppm]."""
        return self._drift_ppm

    def board_clock_us(self, t: float) -> float:
        """The board clock [us] at emulator ``time.monotonic()`` ``t`` [s] (exact; the
        firmware truncates it to whole microseconds), for ``t`` after the last clock change."""
        with self._lock:
            return self._board_us_exact(t)

    # -------------------------------------------------------------------- internals
    def _add_tx_fault(self, action: str, n: int, kind: str, skip: int) -> None:
        if kind not in TX_KINDS:
            raise ValueError(f'kind: expected one of {sorted(TX_KINDS)}, got {kind!r}')
        with self._lock:
            self._tx_faults.append([action, TX_KINDS[kind], int(n), int(skip)])

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b'x')
        except OSError:
            pass

    def _now(self) -> float:
        return time.monotonic()

    @staticmethod
    def _check_drift(ppm) -> float:
        ppm = float(ppm)
        if not (np.isfinite(ppm) and abs(ppm) <= 1000):
            raise ValueError(f'clock drift: expected -1000..1000 ppm, got {ppm}')
        return ppm

    def _board_us_exact(self, t: float) -> float:
        t_base, us_base = self._clock_base
        return us_base + (t - t_base) * 1e6 * (1.0 + self._drift_ppm * 1e-6)

    def _apply_clock_step(self, step_us: int) -> None:
        t = time.monotonic()
        self._clock_base = (t, self._board_us_exact(t) + step_us)
        self.stats['clock_steps'] += 1

    def _uptime_us(self) -> int:
        return int(self._board_us_exact(time.monotonic()))

    def _power_up(self) -> None:
        self._boot_id = self._rng.getrandbits(32) or 1
        self._boot_t0 = time.monotonic()
        self._clock_base = (self._boot_t0, 0.0)  # (monotonic [s], board clock [us]) there
        self._tx_seq = 0
        self._session = False
        self._host_version: int | None = None
        self._last_cmd: tuple[int, p.Message] | None = None
        self._state = p.STATE_IDLE
        self._scan_id = 0
        self._table: np.ndarray | None = None
        self._filled: np.ndarray | None = None
        self._period = 0.0
        self._scan_laser = False
        self._index = 0
        self._triggers = 0
        self._next_trigger = 0.0
        self._end_at: float | None = None
        self._last_rx: float | None = None
        self._wd_armed = False
        self._wd_flag = False
        self._decoder.reset()
        self._codes = _ZERO_CODES
        self._laser = False

    def _apply(self, codes, laser: bool, reason: str, t: float | None = None) -> None:
        self._codes = tuple(int(c) for c in codes)
        self._laser = bool(laser)
        entry = AppliedOutput(time.monotonic() if t is None else t, self._codes, self._laser,
                              reason)
        self._log.append(entry)
        if self._log_file is not None:
            self._log_file.write(json.dumps(entry.as_dict()) + '\n')
            self._log_file.flush()

    def _info(self) -> p.BoardInfo:
        return p.BoardInfo(self.protocol_version, self.firmware_id, p.DAC_BITS, p.N_CHANNELS,
                           self._boot_id, self._uptime_us(), self.max_scan_rows,
                           self.min_period_us)

    def _status(self) -> p.BoardStatus:
        flags = ((p.FLAG_WATCHDOG if self._wd_flag else 0)
                 | (p.FLAG_INTERLOCK if self._interlock else 0))
        return p.BoardStatus(self._boot_id, self._uptime_us(), self._state, flags, self._laser,
                             self._codes, self._scan_id, self._triggers,
                             self._decoder.error_count - self._ignored_rx)

    def _send(self, msg: p.Message) -> None:
        frame = bytearray(p.encode_frame(self._tx_seq, msg))
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF
        if msg.TYPE in (p.ACK, p.NAK) and self._drop_acks > 0:
            self._drop_acks -= 1
            return
        for fault in self._tx_faults:
            action, kind, remaining, skip = fault
            if remaining > 0 and (kind is None or kind == msg.TYPE):
                if skip > 0:
                    fault[3] -= 1
                    continue
                fault[2] -= 1
                pos = self._rng.randrange(1, len(frame) - 1)
                if action == 'drop':
                    del frame[pos]
                else:
                    bit = 1 << self._rng.randrange(8)
                    if frame[pos] ^ bit == 0:  # keep the framing: corrupt, do not split
                        bit = 0x80 if bit != 0x80 else 0x40
                    frame[pos] ^= bit
                break
        self._tx_faults = [f for f in self._tx_faults if f[2] > 0]
        self._write(bytes(frame))
        self.stats['tx_frames'] += 1

    def _write(self, data: bytes) -> None:
        if self._unplugged:
            return
        sent = 0
        while sent < len(data):
            n = self._transport.write(data[sent:])
            if n <= 0:
                self.stats['tx_dropped_bytes'] += len(data) - sent
                return
            sent += n

    def _on_rx_error(self, err: p.ProtocolError) -> None:
        if err.seq is not None and err.msg_type is not None and err.msg_type >= 0x80:
            self._ignored_rx += 1  # a board-type packet: ignored, not a receive error
            return
        self.stats['rx_errors'] += 1
        if err.seq is not None and err.msg_type is not None and err.msg_type < 0x80:
            self._respond(err.seq, p.Nak(err.seq, p.NAK_BAD_MESSAGE))

    def _rx_fault(self, data: bytes) -> bytes:
        if not self._rx_faults or not data:
            return data
        fault = self._rx_faults[0]
        positions = [i for i, b in enumerate(data) if b != 0]
        if not positions:
            return data
        pos = self._rng.choice(positions)
        buf = bytearray(data)
        if fault[0] == 'drop':
            del buf[pos]
        else:
            bit = 1 << self._rng.randrange(8)
            if buf[pos] ^ bit == 0:
                bit = 0x80 if bit != 0x80 else 0x40
            buf[pos] ^= bit
        fault[1] -= 1
        if fault[1] <= 0:
            self._rx_faults.pop(0)
        return bytes(buf)

    def _respond(self, seq: int, resp: p.Message) -> None:
        self._last_cmd = (seq, resp)
        self._send(resp)

    def _go_safe(self, reason: str) -> None:
        self._state = p.STATE_IDLE
        self._apply(_ZERO_CODES, False, reason)

    def _handle(self, pkt: p.Packet) -> None:
        msg, seq = pkt.msg, pkt.seq
        if msg.TYPE >= 0x80:  # a board message sent back to the board: ignored
            return
        self.stats['rx_frames'] += 1
        self._last_rx = time.monotonic()
        self._wd_armed = True
        if isinstance(msg, p.Heartbeat):
            self._send(p.Status(self._status()))
            self._wd_flag = False
            return
        if isinstance(msg, p.Hello):
            self._host_version = msg.version
            self._session = msg.version == self.protocol_version
            self._wd_flag = False
            self._respond(seq, p.Ack(seq, self._info().pack()))
            return
        if self._last_cmd is not None and self._last_cmd[0] == seq:
            self.stats['duplicates'] += 1
            self._send(self._last_cmd[1])
            return
        self._respond(seq, self._execute(msg, seq))

    def _execute(self, msg: p.Message, seq: int) -> p.Message:
        def nak(reason):
            return p.Nak(seq, reason)

        if isinstance(msg, p.Safe):
            self._go_safe('safe')
            return p.Ack(seq)
        if isinstance(msg, p.GetStatus):
            return p.Ack(seq, self._status().pack())
        if not self._session:
            mismatch = (self._host_version is not None
                        and self._host_version != self.protocol_version)
            return nak(p.NAK_VERSION if mismatch else p.NAK_NO_SESSION)
        scanning = self._state == p.STATE_SCANNING
        if isinstance(msg, p.ScanStop):
            if scanning or self._laser:
                self._state = p.STATE_IDLE
                self._apply(self._codes, False, 'stop')
            return p.Ack(seq)
        if isinstance(msg, p.Laser):
            if msg.on and scanning:
                return nak(p.NAK_BUSY)
            if msg.on and self._interlock:
                return nak(p.NAK_INTERLOCK)
            self._apply(self._codes, msg.on, 'laser')
            return p.Ack(seq)
        if scanning:
            return nak(p.NAK_BUSY)
        if isinstance(msg, p.SetVolts):
            if self._interlock:
                return nak(p.NAK_INTERLOCK)
            self._apply(msg.codes, self._laser, 'set')
            return p.Ack(seq)
        if isinstance(msg, p.ScanBegin):
            if msg.n_rows > self.max_scan_rows:
                return nak(p.NAK_BAD_ARGUMENT)
            self._table = np.zeros((msg.n_rows, p.N_CHANNELS), np.uint16)
            self._filled = np.zeros(msg.n_rows, bool)
            self._scan_id = msg.scan_id
            self._state = p.STATE_LOADED
            self._triggers = 0
            return p.Ack(seq)
        if isinstance(msg, p.ScanData):
            if (self._table is None or msg.scan_id != self._scan_id
                    or msg.offset + len(msg.rows) > len(self._table)):
                return nak(p.NAK_BAD_ARGUMENT)
            self._table[msg.offset:msg.offset + len(msg.rows)] = msg.rows
            self._filled[msg.offset:msg.offset + len(msg.rows)] = True
            return p.Ack(seq)
        if isinstance(msg, p.ScanStart):
            if (self._table is None or msg.scan_id != self._scan_id
                    or msg.n_rows != len(self._table) or not self._filled.all()
                    or p.table_crc(self._table) != msg.table_crc):
                return nak(p.NAK_TABLE_MISMATCH)
            if not self.min_period_us <= msg.period_us <= MAX_PERIOD_US:
                return nak(p.NAK_BAD_ARGUMENT)
            if msg.laser_on and self._interlock:
                return nak(p.NAK_INTERLOCK)
            self._period = msg.period_us * 1e-6
            self._scan_laser = msg.laser_on
            self._index = 0
            self._triggers = 0
            self._state = p.STATE_SCANNING
            self._end_at = None
            self._next_trigger = time.monotonic() + 0.5 * self._period  # as the firmware
            return p.Ack(seq)
        return nak(p.NAK_BAD_MESSAGE)

    def _trigger(self) -> None:
        row = self._table[self._index]
        if self._glitches > 0:
            self._glitches -= 1
            row = row.copy()
            row[0] = row[0] + 1 if row[0] < p.CODE_MAX else row[0] - 1
        if self._clock_step_at is not None and self._index >= self._clock_step_at[0]:
            self._apply_clock_step(self._clock_step_at[1])
            self._clock_step_at = None
        t = time.monotonic()  # the trigger instant: output applied and timestamped together
        self._apply(row, self._scan_laser, 'trigger', t)
        stamp_us = int(self._board_us_exact(t))
        self._trigger_log.append(TriggerRecord(self._boot_id, self._scan_id, self._index, t,
                                               stamp_us, self._codes, self._laser))
        self._call_hook(self._index, t)
        event = p.Event(self._boot_id, self._scan_id, self._index, stamp_us, self._codes,
                        self._laser, p.EVENT_SETTLED)
        self._send(event)
        if self._dup_events[0] > 0:
            if self._dup_events[1] > 0:
                self._dup_events[1] -= 1
            else:
                self._dup_events[0] -= 1
                self.stats['duplicated_events'] += 1
                self._send(event)
        index = self._index
        self._index += 1
        self._triggers += 1
        # the trigger timer counts the same (drifting) crystal as the microsecond clock
        self._next_trigger += self._period / (1.0 + self._drift_ppm * 1e-6)
        if self._reset_at_trigger is not None and index >= self._reset_at_trigger:
            self._reset_at_trigger = None
            self._reset()
            return
        if self._index >= len(self._table):
            # the laser stays on through the last exposure: off half a period later
            self._end_at = t + 0.5 * self._period

    def _end_scan(self) -> None:
        self._end_at = None
        self._state = p.STATE_DONE
        self._apply(self._codes, False, 'scan_done')
        self._send(p.Status(self._status()))

    def _interlock_change(self, is_open: bool) -> None:
        was = self._interlock
        self._interlock = is_open
        if is_open and not was:
            self._end_at = None
            self._state = p.STATE_IDLE
            self._apply(_ZERO_CODES, False, 'interlock')
            self._send(p.Fault(p.FAULT_INTERLOCK, self._uptime_us()))
            self._send(p.Status(self._status()))

    def _call_hook(self, index: int, t: float) -> None:
        if self.on_trigger is None:
            return
        try:
            self.on_trigger(index, t)
        except Exception as err:  # noqa: BLE001 - a test hook must not stop the firmware
            self.stats['hook_errors'] += 1
            self.hook_error = f'{type(err).__name__}: {err}'

    def _reset(self) -> None:
        self.stats['resets'] += 1
        self._power_up()
        self._apply(_ZERO_CODES, False, 'reset')
        self._send(p.Boot(self._info()))

    def _do_unplug(self) -> None:
        self._unplugged = True
        self._transport.close()

    def _check_watchdog(self, now: float) -> None:
        if self._wd_armed and now - self._last_rx > self.watchdog:
            self._wd_armed = False
            self._wd_flag = True
            self._go_safe('watchdog')
            self.watchdog_trips.append((self._last_rx, self._log[-1].t))
            self._send(p.Fault(p.FAULT_WATCHDOG, self._uptime_us()))
            self._send(p.Status(self._status()))

    def _run(self) -> None:
        with self._lock:
            self._apply(_ZERO_CODES, False, 'boot')
            self._send(p.Boot(self._info()))
        while not self._stop.is_set():
            with self._lock:
                now = time.monotonic()
                timeout = 0.05
                if self._state == p.STATE_SCANNING:
                    timeout = min(timeout, (self._next_trigger if self._end_at is None
                                            else self._end_at) - now)
                if self._wd_armed:
                    timeout = min(timeout, self._last_rx + self.watchdog - now + 0.001)
                fds = [] if self._unplugged else self._transport.fds()
            try:
                readable, _, _ = select.select(fds + [self._wake_r], [], [], max(timeout, 0))
            except (OSError, ValueError):
                readable = []
            with self._lock:
                if self._stop.is_set():
                    break
                if self._wake_r in readable:
                    try:
                        os.read(self._wake_r, 4096)
                    except OSError:
                        pass
                if self._unplug_request:
                    self._unplug_request = False
                    self._do_unplug()
                    continue
                if self._reset_request:
                    self._reset_request = False
                    self._reset()
                if self._interlock_request is not None:
                    self._interlock_change(self._interlock_request)
                    self._interlock_request = None
                for fd in readable:
                    if fd == self._wake_r or self._unplugged:
                        continue
                    data = self._rx_fault(self._transport.on_readable(fd))
                    for pkt in self._decoder.feed(data):
                        self._handle(pkt)
                now = time.monotonic()
                if (self._state == p.STATE_SCANNING and self._end_at is not None
                        and now >= self._end_at):
                    self._end_scan()
                elif (self._state == p.STATE_SCANNING and self._end_at is None
                        and now >= self._next_trigger):
                    if now - self._next_trigger > self._period:
                        self.stats['late_triggers'] += 1
                    self._trigger()
                self._check_watchdog(time.monotonic())


def main(argv: list[str] | None = None) -> int:
    """Run the emulator as a process; print its port on the first stdout line."""
    parser = argparse.ArgumentParser(
        prog='python -m galvo_driver.serial_link.emulator',
        description='Galvo DAC board firmware emulator (pty or TCP).')
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--pty', action='store_true', help='serve a pty (default)')
    group.add_argument('--tcp', action='store_true', help='serve socket://127.0.0.1:PORT')
    parser.add_argument('--tcp-port', type=int, default=0, help='TCP port (0: any free)')
    parser.add_argument('--watchdog', type=float, default=0.15, help='watchdog time [s]')
    parser.add_argument('--log', default=None,
                        help='append every applied output to this file as JSON lines')
    parser.add_argument('--firmware-id', default='galvoscan-emu')
    args = parser.parse_args(argv)

    def _terminate(signum, frame):
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, _terminate)
    emu = FirmwareEmulator('tcp' if args.tcp else 'pty', watchdog=args.watchdog,
                           log_path=args.log, tcp_port=args.tcp_port,
                           firmware_id=args.firmware_id)
    try:
        emu.start()
        print(emu.port, flush=True)
        while True:
            time.sleep(1.0)
    except (KeyboardInterrupt, SystemExit):
        pass
    finally:
        emu.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
