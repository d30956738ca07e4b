"""The ``serial`` driver backend: a galvo DAC board over pyserial.

:class:`SerialBackend` opens the port with ``serial.serial_for_url`` (a device path such as
``/dev/ttyACM0``, a pty slave path, or ``socket://host:port``), so it talks to hardware and
to :class:`~galvo_driver.serial_link.emulator.FirmwareEmulator` the same way. The protocol is
described in :mod:`galvo_driver.serial_link.protocol`.

Threads: a reader thread decodes everything the board sends (ACK/NAK, trigger events,
STATUS, BOOT, FAULT); a heartbeat thread sends HEARTBEAT every ``heartbeat_period`` and
watches that the board answers; commands are sent stop-and-wait from the caller's thread.

Frames
------
One :class:`~galvoscan_common.frame.Frame` per trigger EVENT, with

* ``voltages`` decoded from the DAC codes *in the CRC-checked event* (what the board output),
  never from the commanded list; if they differ from the commanded row the frame's status is
  STATUS_FAULT and an ERROR is logged;
* ``seq`` = (frames of previous scans) + the event's trigger index, so a lost event leaves a
  gap in ``seq``; every gap is counted in ``stats['lost_events']``;
* ``stamp`` = the board's trigger time mapped to ``time.time()`` (offset from the
  lowest-round-trip GET_STATUS exchange before each scan, the board crystal's drift from
  the arrivals of the STATUS answering every heartbeat and of the EVENTs:
  :mod:`galvo_driver.serial_link.clock`) plus ``exposure / 2``.

Faults
------
A board reset during a scan (BOOT, or a new boot id in any EVENT/STATUS), a board watchdog
trip, a lost link (unplug, I/O error, board silent for ``link_timeout``) or a failed
upload stops the scan: no frame is produced from then on, an ERROR is logged through
:mod:`logging`, :attr:`SerialBackend.status` becomes STATUS_FAULT and the board is
commanded safe (a reset or unplugged board is safe already: boot state / watchdog).
:meth:`arm` re-establishes the session and clears the fault; after a lost link use
``close()`` then ``open()``.

No rclpy here.
"""

from __future__ import annotations

import logging
import math
import select
import threading
import time
from dataclasses import dataclass

import numpy as np
import serial

from galvo_driver.backend import BackendError, GalvoBackend
from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link.clock import BoardClock
from galvoscan_common.frame import STATUS_FAULT, STATUS_SETTLED, Frame, check_voltages

log = logging.getLogger(__name__)


class _NoAnswerError(BackendError):
    """A command went unanswered through all its retries."""


class _Aborted:
    def __init__(self, reason: str):
        self.reason = reason


class _Slot:
    __slots__ = ('event', 'response')

    def __init__(self):
        self.event = threading.Event()
        self.response = None


@dataclass
class _Scan:
    scan_id: int
    n: int
    codes: np.ndarray  # (n, 4) uint16, as commanded
    seq_base: int
    start_sent: bool = False
    start_seq: int | None = None
    started: bool = False  # ACK of SCAN_START seen
    next_index: int = 0
    active: bool = True
    period_us: int = 0
    # the host saw every EVENT before the board's STATUS DONE: the board is still scanning
    # until half a period after the last edge (laser off), and refuses a new scan until then
    board_busy: bool = False


class SerialBackend(GalvoBackend):
    """Galvo DAC board on a serial port (or anything ``serial.serial_for_url`` opens).

    Parameters
    ----------
    port : str
        Device path or pyserial URL, e.g. '/dev/ttyACM0', '/dev/pts/5',
        'socket://127.0.0.1:5000'.
    baudrate : int
        Baud rate [bit/s] (ignored by ptys and sockets).
    ack_timeout : float
        Time to wait for an ACK/NAK before resending a command [s].
    retries : int
        Resends before a command fails with BackendError.
    heartbeat_period : float
        HEARTBEAT interval [s]; must be well below the board's watchdog time (150 ms).
    link_timeout : float
        The link counts as lost when the board sends nothing for this long [s].
    exposure : float
        Camera exposure time [s]; frame stamps are trigger time + exposure / 2.
    boot_wait : float
        When the board does not answer the first HELLO, wait this long for its BOOT and
        try once more [s]: an Arduino Mega resets when its port is opened (DTR) and spends
        about a second in its bootloader first. 0: fail at once.
    """

    name = 'serial'

    def __init__(self, port: str, *, baudrate: int = 921600, ack_timeout: float = 0.05,
                 retries: int = 10, heartbeat_period: float = 0.05, link_timeout: float = 1.0,
                 exposure: float = 0.0, boot_wait: float = 3.0):
        for arg, value in (('ack_timeout', ack_timeout), ('heartbeat_period', heartbeat_period),
                           ('link_timeout', link_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f'{arg}: must be a positive time in s, got {value}')
        if not (math.isfinite(exposure) and exposure >= 0):
            raise ValueError(f'exposure: must be >= 0 s, got {exposure}')
        if not (math.isfinite(boot_wait) and boot_wait >= 0):
            raise ValueError(f'boot_wait: must be >= 0 s, got {boot_wait}')
        self.boot_wait = float(boot_wait)
        self._boot_seen = threading.Event()
        if int(retries) < 0:
            raise ValueError(f'retries: must be >= 0, got {retries}')
        if not isinstance(port, str) or not port:
            raise ValueError('port: expected a device path or pyserial URL')
        self.port = port
        self.baudrate = int(baudrate)
        self.ack_timeout = float(ack_timeout)
        self.retries = int(retries)
        self.heartbeat_period = float(heartbeat_period)
        self.link_timeout = float(link_timeout)
        self.exposure = float(exposure)

        self._ser: serial.SerialBase | None = None
        self._reader_thread: threading.Thread | None = None
        self._hb_thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._tx_lock = threading.Lock()
        self._cmd_lock = threading.RLock()
        self._cond = threading.Condition()  # guards everything the reader thread touches
        self._pending: dict[int, _Slot] = {}
        self._seq = 0
        self._abort_gen = 0
        self._decoder = p.FrameDecoder()
        self._info: p.BoardInfo | None = None
        self._boot_id: int | None = None
        self._session_lost = False
        self._need_safe = False
        self._link_error: str | None = None
        self._fault: str | None = None
        self._clock = BoardClock()
        self._rx_time = 0.0  # time.time() of the last read from the board
        self._last_rx = 0.0
        self._last_board_seq: int | None = None
        self._board_status: p.BoardStatus | None = None
        self._scan: _Scan | None = None
        self._next_scan_id = 1
        self._seq_base = 0
        self._frames: list[Frame] = []
        self._counters = {'lost_events': 0, 'rejected_events': 0, 'mismatched_events': 0,
                          'retries': 0, 'board_seq_gaps': 0, 'board_resets': 0}
        self._listeners: list = []

    # ------------------------------------------------------------------ raw board messages
    def add_listener(self, callback) -> None:
        """Also hand every EVENT, BOOT and STATUS the board sends to ``callback``.

        Parameters
        ----------
        callback : callable
            ``callback(msg)`` with a :class:`~galvo_driver.serial_link.protocol.Event`,
            :class:`~galvo_driver.serial_link.protocol.Boot` or
            :class:`~galvo_driver.serial_link.protocol.Status`, exactly as decoded (CRC
            checked; duplicates, other scans and other boots included), before this backend
            handles it. Called in the reader thread: keep it short (queue the message) and
            do not call back into the backend. An exception it raises is logged and
            counted in ``stats['listener_errors']``; the backend goes on.
        """
        if not callable(callback):
            raise ValueError('callback: expected a callable(msg)')
        self._listeners.append(callback)

    def board_to_host(self, board_us: float) -> float:
        """A board clock time [us] in the host's ``time.time()`` base [s]: the offset of the
        lowest-round-trip GET_STATUS exchange before the last scan (or handshake), and the
        board crystal's drift since, from the arrivals of its STATUS and EVENT messages
        (:mod:`.clock`)."""
        with self._cond:
            return self._clock.to_host(board_us)

    @property
    def board_clock_drift_ppm(self) -> float:
        """The host clock's rate against the board's, minus one [ppm]; 0 for the first
        2 s after the handshake (:class:`.clock.BoardClock`)."""
        with self._cond:
            return self._clock.drift_ppm

    @property
    def boot_id(self) -> int | None:
        """Boot id of the board session (from HELLO), None before :meth:`open`."""
        return self._boot_id

    @property
    def scan_id(self) -> int | None:
        """Id of the last scan started (the one its EVENTs carry), None before any."""
        scan = self._scan
        return None if scan is None else scan.scan_id

    # ------------------------------------------------------------------ properties
    @property
    def running(self) -> bool:
        scan = self._scan
        return scan is not None and scan.active

    @property
    def status(self) -> int:
        """STATUS_FAULT after a fault (until :meth:`arm`), else STATUS_SETTLED."""
        return STATUS_FAULT if self._fault is not None else STATUS_SETTLED

    @property
    def fault(self) -> str | None:
        """Why the backend is in FAULT, or None."""
        return self._fault

    @property
    def board_info(self) -> p.BoardInfo | None:
        """What the board said in its HELLO answer."""
        return self._info

    @property
    def board_status(self) -> p.BoardStatus | None:
        """The last STATUS received."""
        return self._board_status

    @property
    def stats(self) -> dict:
        """Counters: lost_events, rejected_events, mismatched_events, retries,
        board_seq_gaps, board_resets and the decoder's bad-frame counts; and
        ``clock_drift_ppm`` (:attr:`board_clock_drift_ppm`)."""
        with self._cond:
            out = dict(self._counters)
            out['clock_drift_ppm'] = round(self._clock.drift_ppm, 2)
        out.update({f'rx_{k}_errors': v for k, v in self._decoder.errors.items()})
        return out

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the port, handshake (HELLO, version check) and start the heartbeat.

        Raises
        ------
        BackendError
            The port cannot be opened, the board does not answer, or it speaks another
            protocol version.
        """
        if self._ser is not None:
            raise BackendError('serial backend is already open')
        try:
            ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0,
                                        write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as err:
            raise BackendError(f'cannot open {self.port}: {err}') from err
        try:
            ser.reset_input_buffer()
            fd = ser.fileno()
        except Exception:  # noqa: BLE001 - URL handlers without fileno(): timed reads
            fd = None
            ser.timeout = 0.05
        self._ser = ser
        self._stop_evt.clear()
        self._decoder = p.FrameDecoder()
        self._link_error = None
        self._fault = None
        self._boot_id = None
        self._session_lost = False
        self._last_board_seq = None
        self._last_rx = time.monotonic()
        self._boot_seen.clear()
        self._reader_thread = threading.Thread(target=self._reader, args=(ser, fd),
                                               name='galvo-serial-reader', daemon=True)
        self._reader_thread.start()
        try:
            try:
                self._handshake()
            except _NoAnswerError:
                # opening the port may have reset the board into its bootloader
                if not self._boot_seen.wait(self.boot_wait) or self._link_error is not None:
                    raise
                log.info('the board booted after its port was opened; handshaking again')
                self._handshake()
        except BaseException:
            self._shutdown()
            raise
        self._hb_thread = threading.Thread(target=self._heartbeat, name='galvo-serial-hb',
                                           daemon=True)
        self._hb_thread.start()
        info = self._info
        log.info('serial board %r on %s: protocol %d, %d-bit DAC, %d channels, boot %08x',
                 info.firmware_id, self.port, info.version, info.dac_bits, info.channels,
                 info.boot_id)

    def arm(self) -> None:
        """Re-establish the session if the board was reset, clear a FAULT, go safe.

        Raises
        ------
        BackendError
            Not open, link lost, or the board does not answer.
        """
        self._require_link()
        if self._session_lost or self._fault is not None:
            log.info('re-establishing the board session (fault was: %s)', self._fault)
            self._handshake()
            with self._cond:
                self._fault = None
        with self._cmd_lock:  # this Safe serves a fault's deferred one too
            self._need_safe = False
            self._command(p.Safe())

    def start(self, voltages: np.ndarray, frame_rate: float, laser_on: bool = True) -> int:
        """Upload the scan (ACKed chunks, CRC-verified on the board) and start triggering.

        Parameters
        ----------
        voltages : ndarray, shape (n, 4), volts
            Rows of (U1_pan, U1_tilt, U2_pan, U2_tilt), one per trigger, each in +-10 V.
        frame_rate : float
            Trigger rate [Hz]; the board uses the period rounded to whole microseconds.
        laser_on : bool
            Laser on during the scan (the board switches it off after the last row).

        Returns
        -------
        int
            n, the number of trigger events the scan will produce.

        Raises
        ------
        ValueError
            Bad voltages or frame_rate (nothing is sent).
        BackendError
            Not open, in FAULT, already running, or the board refused or did not answer
            (the board is then commanded safe).
        """
        arr = check_voltages(voltages)
        n = len(arr)
        if n == 0:
            raise ValueError('voltages: the scan needs at least one row')
        rate = float(frame_rate)
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f'frame_rate: must be a positive rate in Hz, got {frame_rate}')
        period_us = round(1e6 / rate)
        codes = p.volts_to_codes(arr)
        self._require_link()
        if self._fault is not None:
            raise BackendError(f'backend in FAULT ({self._fault}); call arm() to clear it')
        if self.running:
            raise BackendError('a scan is already running; stop() it first')
        info = self._info
        if n > info.max_scan_rows:
            raise ValueError(f'voltages: {n} rows exceed the board limit of '
                             f'{info.max_scan_rows}')
        if not info.min_period_us <= period_us <= 0xFFFFFFFF:
            raise ValueError(f'frame_rate: {rate} Hz is outside the board range '
                             f'(period >= {info.min_period_us} us)')
        if self._session_lost:
            log.warning('board was reset while idle; re-establishing the session')
            self._handshake()
        self._serve_pending_safe()
        prev = self._scan
        if prev is not None and prev.board_busy:  # its last edge came a moment ago
            with self._cond:
                self._cond.wait_for(lambda: not prev.board_busy or self._fault is not None,
                                    timeout=prev.period_us * 1e-6 + 0.5)
        gen = self._abort_gen
        self._sync_clock(gen)
        scan_id = self._next_scan_id
        self._next_scan_id = (scan_id + 1) & 0xFFFF
        scan = _Scan(scan_id, n, codes, self._seq_base, period_us=period_us)
        with self._cond:
            self._scan = scan

        def mark_start(seq):
            with self._cond:
                scan.start_seq = seq
                scan.start_sent = True

        try:
            self._command(p.ScanBegin(scan_id, n), gen=gen)
            for off in range(0, n, p.ROWS_PER_CHUNK):
                rows = tuple(tuple(int(c) for c in row)
                             for row in codes[off:off + p.ROWS_PER_CHUNK])
                self._command(p.ScanData(scan_id, off, rows), gen=gen)
            self._command(p.ScanStart(scan_id, n, period_us, bool(laser_on),
                                      p.table_crc(codes)), gen=gen, on_seq=mark_start)
        except BackendError as err:
            with self._cond:
                if scan.active:
                    self._end_scan(scan, aborted=True)
            log.error('scan %d not started: %s; commanding safe state', scan_id, err)
            self.safe()
            raise
        log.info('scan %d started: %d rows at %.6g Hz', scan_id, n, 1e6 / period_us)
        return n

    def set_output(self, voltages, laser_on: bool = False) -> np.ndarray:
        """Hold the galvos at one set of voltages (no triggers), laser on or off.

        Parameters
        ----------
        voltages : array_like, shape (4,), volts
            (U1_pan, U1_tilt, U2_pan, U2_tilt), each in +-10 V.
        laser_on : bool

        Returns
        -------
        ndarray, shape (4,), volts
            The voltages the DAC outputs (after quantisation).

        Raises
        ------
        ValueError
            Bad shape or values (nothing is sent).
        BackendError
            Not open, in FAULT, a scan is running, or the board refused.
        """
        arr = np.asarray(voltages, dtype=np.float64)
        if arr.shape != (p.N_CHANNELS,):
            raise ValueError(f'voltages: expected shape (4,) in volts, got {arr.shape}')
        codes = p.volts_to_codes(check_voltages(arr[None, :])[0])
        self._require_link()
        if self._fault is not None:
            raise BackendError(f'backend in FAULT ({self._fault}); call arm() to clear it')
        if self.running:
            raise BackendError('a scan is running; stop() it first')
        if self._session_lost:
            self._handshake()
        self._command(p.SetVolts(tuple(int(c) for c in codes)))
        self._command(p.Laser(bool(laser_on)))
        return p.codes_to_volts(codes)

    def poll(self, timeout: float = 0.0) -> list[Frame]:
        """Frames decoded since the last call; waits up to ``timeout`` [s] for the first
        one while a scan runs."""
        with self._cond:
            if not self._frames and timeout > 0 and self.running:
                self._cond.wait_for(lambda: self._frames or not self.running, timeout)
            out, self._frames = self._frames, []
        return out

    def stop(self) -> None:
        """Abort the scan and command the safe state (0 V, laser off).

        Raises
        ------
        BackendError
            The board did not confirm the safe state (it was logged; the board's watchdog
            remains the last line of defence).
        """
        if self._ser is None:
            return
        self._abort_scan('stop() called')
        try:
            self._command(p.Safe(), gen=self._abort_gen)
        except BackendError as err:
            log.error('stop(): board did not confirm the safe state: %s', err)
            raise

    def safe(self) -> None:
        """Best effort: abort the scan, 0 V on all channels, laser off. Never raises."""
        try:
            if self._ser is None:
                return
            self._abort_scan('safe() called')
            if self._link_error is not None:
                log.error('safe(): link lost (%s); relying on the board watchdog',
                          self._link_error)
                return
            self._command(p.Safe(), gen=self._abort_gen)
        except Exception as err:  # noqa: BLE001 - must never raise
            log.error('safe(): could not confirm the safe state: %s', err)

    def close(self) -> None:
        """Command the safe state, stop the threads and close the port."""
        if self._ser is None:
            return
        self.safe()
        self._shutdown()

    # ------------------------------------------------------------------ internals
    def _shutdown(self) -> None:
        self._stop_evt.set()
        self._abort_pending('backend closed')
        for th in (self._hb_thread, self._reader_thread):
            if th is not None and th is not threading.current_thread():
                th.join(timeout=2.0)
        self._hb_thread = self._reader_thread = None
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - closing a dead port
                pass
        with self._cond:
            if self._scan is not None and self._scan.active:
                self._end_scan(self._scan, aborted=True)
            self._cond.notify_all()

    def _require_link(self) -> None:
        if self._ser is None:
            raise BackendError('serial backend is not open')
        if self._link_error is not None:
            raise BackendError(f'serial link lost ({self._link_error}); close() and open()')

    def _timed_query(self, command, answer_type, what: str, gen: int | None = None):
        """Send ``command``; its answer decoded as ``answer_type``, with the host times
        (seconds) just before sending and just after the answer arrived."""
        t0 = time.time()
        ack = self._command(command, gen=gen)
        t1 = time.time()
        try:
            return t0, t1, answer_type.unpack(ack.data)
        except p.ProtocolError as err:
            raise BackendError(f'bad {what}: {err}') from err

    def _handshake(self) -> None:
        t0, t1, info = self._timed_query(p.Hello(p.PROTOCOL_VERSION), p.BoardInfo,
                                         'HELLO answer from the board')
        if info.version != p.PROTOCOL_VERSION:
            raise BackendError(f'protocol version mismatch: board {info.firmware_id!r} speaks '
                               f'version {info.version}, this host speaks '
                               f'{p.PROTOCOL_VERSION}')
        if info.dac_bits != p.DAC_BITS or info.channels != p.N_CHANNELS:
            raise BackendError(f'unsupported board: {info.dac_bits}-bit DAC with '
                               f'{info.channels} channels (need {p.DAC_BITS} / '
                               f'{p.N_CHANNELS})')
        with self._cond:
            self._info = info
            self._boot_id = info.boot_id
            self._session_lost = False
            self._clock.reset()  # a new session: the board may have restarted its clock
            self._clock.sync((t0 + t1) / 2 - info.uptime_us * 1e-6, info.uptime_us)
        status = self._sync_clock(self._abort_gen)
        # Never reuse the board's current scan id: stale STATUS cannot match a new scan.
        self._next_scan_id = (status.scan_id + 1) & 0xFFFF

    def _sync_clock(self, gen: int) -> p.BoardStatus:
        best = None
        for _ in range(3):
            t0, t1, st = self._timed_query(p.GetStatus(), p.BoardStatus, 'GET_STATUS answer',
                                           gen=gen)
            if st.boot_id != self._boot_id:
                with self._cond:
                    self._board_reset(st.boot_id, 'GET_STATUS answered by a new boot')
                raise BackendError('the board was reset')
            if best is None or t1 - t0 < best[0]:
                best = (t1 - t0, (t0 + t1) / 2 - st.uptime_us * 1e-6, st)
        with self._cond:
            self._clock.sync(best[1], best[2].uptime_us)
        return best[2]

    def _next_seq(self) -> int:
        self._seq = self._seq % 0xFFFF + 1
        return self._seq

    def _write(self, data: bytes) -> None:
        ser = self._ser
        if ser is None:
            raise BackendError('serial backend is not open')
        try:
            with self._tx_lock:
                ser.write(data)
        except (serial.SerialException, OSError, TypeError, AttributeError) as err:
            self._on_link_lost(f'write failed: {err}')
            raise BackendError(f'serial write failed: {err}') from err

    def _command(self, msg: p.Message, *, gen: int | None = None,
                 on_seq=None) -> p.Ack:
        """Send one command stop-and-wait; return its ACK or raise BackendError."""
        name = type(msg).__name__
        with self._cmd_lock:
            if gen is not None and gen != self._abort_gen:
                raise BackendError(f'{name} cancelled: the scan was aborted')
            self._require_link()
            seq = self._next_seq()
            frame = p.encode_frame(seq, msg)
            slot = _Slot()
            self._pending[seq] = slot
            if on_seq is not None:
                on_seq(seq)
            try:
                attempts = self.retries + 1
                for attempt in range(attempts):
                    if attempt:
                        with self._cond:
                            self._counters['retries'] += 1
                        log.debug('%s seq %d: no answer, resending (%d)', name, seq, attempt)
                    self._write(frame)
                    if slot.event.wait(self.ack_timeout):
                        break
                else:
                    raise _NoAnswerError(f'{name} (seq {seq}) not acknowledged after '
                                    f'{attempts} attempts')
            finally:
                self._pending.pop(seq, None)
        resp = slot.response
        if isinstance(resp, _Aborted):
            raise BackendError(f'{name} aborted: {resp.reason}')
        if isinstance(resp, p.Nak):
            reason = p.NAK_REASONS.get(resp.reason, f'reason {resp.reason}')
            raise BackendError(f'board refused {name}: {reason}')
        return resp

    def _abort_pending(self, reason: str) -> None:
        for slot in list(self._pending.values()):
            if not slot.event.is_set():
                slot.response = _Aborted(reason)
                slot.event.set()

    def _abort_scan(self, reason: str) -> None:
        self._abort_gen += 1
        self._abort_pending(reason)
        with self._cond:
            if self._scan is not None and self._scan.active:
                log.info('scan %d aborted (%s) after %d of %d frames', self._scan.scan_id,
                         reason, self._scan.next_index, self._scan.n)
                self._end_scan(self._scan, aborted=True)

    # -- called with self._cond held ----------------------------------------------------
    def _end_scan(self, scan: _Scan, aborted: bool) -> None:
        scan.active = False
        self._seq_base = scan.seq_base + (scan.next_index if aborted else scan.n)
        self._cond.notify_all()

    def _set_fault(self, reason: str) -> None:
        if self._fault is None:
            self._fault = reason
        scan = self._scan
        if scan is not None and scan.active:
            self._end_scan(scan, aborted=True)

    def _board_reset(self, new_boot: int, why: str) -> None:
        if self._session_lost:
            return
        self._session_lost = True
        self._counters['board_resets'] += 1
        self._clock.reset()
        scan = self._scan
        if scan is not None and scan.active:
            log.error('board reset during scan %d (%s; new boot %08x) after %d of %d frames: '
                      'scan aborted, no further frames tagged; call arm() to resume',
                      scan.scan_id, why, new_boot, scan.next_index, scan.n)
            self._set_fault(f'board reset during scan {scan.scan_id}')
        else:
            log.warning('board reset while idle (%s; new boot %08x)', why, new_boot)
        self._need_safe = True
        self._abort_pending('board reset')

    # -- reader thread ------------------------------------------------------------------
    def _on_link_lost(self, reason: str) -> None:
        with self._cond:
            if self._link_error is not None or self._stop_evt.is_set():
                return
            self._link_error = reason
            scan = self._scan
            log.error('serial link to the board lost (%s)%s; the board watchdog drives it to '
                      '0 V with the laser off', reason,
                      f' during scan {scan.scan_id}' if scan is not None and scan.active else '')
            self._set_fault(f'link lost: {reason}')
            self._cond.notify_all()
        self._abort_pending(f'link lost: {reason}')

    def _reader(self, ser, fd) -> None:
        while not self._stop_evt.is_set():
            try:
                if fd is not None:
                    ready, _, _ = select.select([fd], [], [], 0.05)
                    if not ready:
                        continue
                    data = ser.read(4096)
                else:
                    data = ser.read(ser.in_waiting or 1)
            except Exception as err:  # noqa: BLE001 - any read failure means the link is gone
                if not self._stop_evt.is_set():
                    self._on_link_lost(f'read failed: {err}')
                return
            if data:
                self._rx_time = time.time()
                for pkt in self._decoder.feed(data):
                    if self._listeners and isinstance(pkt.msg, (p.Event, p.Boot, p.Status)):
                        self._notify(pkt.msg)
                    self._dispatch(pkt)

    def _notify(self, msg) -> None:
        for callback in self._listeners:
            try:
                callback(msg)
            except Exception as err:  # noqa: BLE001 - a listener never stops the reader
                with self._cond:
                    self._counters['listener_errors'] = \
                        self._counters.get('listener_errors', 0) + 1
                log.error('board message listener failed: %r', err)

    def _dispatch(self, pkt: p.Packet) -> None:
        msg = pkt.msg
        self._last_rx = time.monotonic()
        with self._cond:
            last = self._last_board_seq
            if last is not None and not isinstance(msg, p.Boot) and pkt.seq != (last + 1) & 0xFFFF:
                self._counters['board_seq_gaps'] += (pkt.seq - last - 1) & 0xFFFF
            self._last_board_seq = pkt.seq
            if isinstance(msg, (p.Ack, p.Nak)):
                scan = self._scan
                if (scan is not None and scan.start_seq == msg.acked_seq
                        and isinstance(msg, p.Ack)):
                    scan.started = True
                slot = self._pending.get(msg.acked_seq)
                if slot is not None and not slot.event.is_set():
                    slot.response = msg
                    slot.event.set()
            elif isinstance(msg, p.Event):
                self._on_event(msg)
            elif isinstance(msg, p.Status):
                self._on_status(msg.status)
            elif isinstance(msg, p.Boot):
                self._boot_seen.set()
                if self._boot_id is not None and msg.info.boot_id != self._boot_id:
                    self._board_reset(msg.info.boot_id, 'BOOT received')
            elif isinstance(msg, p.Fault):
                self._on_fault(msg)

    def _on_event(self, ev: p.Event) -> None:
        if self._boot_id is None or ev.boot_id != self._boot_id:
            if self._boot_id is not None:
                self._board_reset(ev.boot_id, 'EVENT from a new boot')
            self._counters['rejected_events'] += 1
            return
        self._clock.arrival(self._rx_time, ev.timestamp_us)
        scan = self._scan
        if (scan is None or not scan.active or not scan.start_sent
                or ev.scan_id != scan.scan_id or ev.index >= scan.n
                or ev.index < scan.next_index):
            self._counters['rejected_events'] += 1
            return
        if ev.index > scan.next_index:
            lost = ev.index - scan.next_index
            self._counters['lost_events'] += lost
            log.warning('scan %d: %d trigger event(s) lost before index %d', scan.scan_id,
                        lost, ev.index)
        status = ev.status
        commanded = scan.codes[ev.index]
        if tuple(int(c) for c in commanded) != ev.codes:
            self._counters['mismatched_events'] += 1
            status = STATUS_FAULT
            log.error('scan %d trigger %d: board output codes %s, commanded %s', scan.scan_id,
                      ev.index, ev.codes, tuple(int(c) for c in commanded))
        self._frames.append(Frame(
            seq=scan.seq_base + ev.index,
            stamp=self._clock.to_host(ev.timestamp_us) + 0.5 * self.exposure,
            voltages=p.codes_to_volts(np.array(ev.codes, dtype=np.int64)),
            laser_on=ev.laser_on, status=status, image=None))
        scan.next_index = ev.index + 1
        if scan.next_index == scan.n:
            scan.board_busy = True
            self._end_scan(scan, aborted=False)
            log.info('scan %d complete (%d frames, %d lost in total)', scan.scan_id, scan.n,
                     self._counters['lost_events'])
        self._cond.notify_all()

    def _on_status(self, st: p.BoardStatus) -> None:
        if self._boot_id is not None and st.boot_id != self._boot_id:
            self._board_reset(st.boot_id, 'STATUS from a new boot')
            return
        self._clock.arrival(self._rx_time, st.uptime_us)  # every heartbeat's answer
        self._board_status = st
        scan = self._scan
        if scan is not None and st.scan_id == scan.scan_id and st.state != p.STATE_SCANNING:
            scan.board_busy = False
            self._cond.notify_all()
        if scan is None or not scan.active or not scan.started or st.scan_id != scan.scan_id:
            return
        if st.state == p.STATE_DONE:
            missing = scan.n - scan.next_index
            if missing:
                self._counters['lost_events'] += missing
                log.warning('scan %d: the last %d trigger event(s) were lost', scan.scan_id,
                            missing)
            scan.next_index = scan.n
            self._end_scan(scan, aborted=False)
            log.info('scan %d complete (%d frames, %d lost in total)', scan.scan_id, scan.n,
                     self._counters['lost_events'])
        elif st.state != p.STATE_SCANNING:
            log.error('scan %d: the board stopped scanning on its own (state %s, flags 0x%02x) '
                      'after %d of %d frames', scan.scan_id,
                      p.STATE_NAMES.get(st.state, st.state), st.flags, scan.next_index, scan.n)
            self._set_fault(f'board stopped scan {scan.scan_id}')
            self._need_safe = True

    def _on_fault(self, msg: p.Fault) -> None:
        what = p.FAULT_NAMES.get(msg.code, f'code {msg.code}')
        scan = self._scan
        log.error('board fault: %s (detail %d)%s', what, msg.detail,
                  f' during scan {scan.scan_id}' if scan is not None and scan.active else '')
        if scan is not None and scan.active:
            self._set_fault(f'board fault: {what}')
            self._need_safe = True

    def _serve_pending_safe(self) -> None:
        """Command the safe state a fault asked for, if no one has since.

        The check and the command hold the command lock, so a Safe asked for by an old
        fault is sent before the next scan's upload or not at all, never in its middle."""
        if not self._need_safe:
            return
        with self._cmd_lock:
            if not self._need_safe:
                return
            self._need_safe = False
            self._command(p.Safe())

    # -- heartbeat thread ---------------------------------------------------------------
    def _heartbeat(self) -> None:
        frame = p.encode_frame(0, p.Heartbeat())
        while not self._stop_evt.wait(self.heartbeat_period):
            if self._link_error is not None:
                continue
            try:
                self._serve_pending_safe()
            except BackendError as err:
                log.error('could not command the safe state after a fault: %s', err)
            try:
                self._write(frame)
            except BackendError:
                continue
            silent = time.monotonic() - self._last_rx
            if silent > self.link_timeout:
                self._on_link_lost(f'no packet from the board for {silent:.2f} s')
