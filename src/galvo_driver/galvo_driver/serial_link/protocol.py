"""Wire protocol between the host and the galvo DAC board (protocol version 1).

The protocol is specified in ``docs/board-protocol.md``; this module and the board
firmware (``firmware/src``) both implement that document byte for byte. Pure Python, no
rclpy: used by the host backend (:mod:`galvo_driver.serial_link.backend`) and by the
firmware emulator (:mod:`galvo_driver.serial_link.emulator`).

In short:

* wire frame ``COBS(packet) 0x00``; packet = type u8, seq u16, payload (0..240 bytes),
  CRC-32 (zlib) of the rest; all integers little-endian; frames over 256 bytes are dropped;
* host commands (types 0x01..0x0A: HELLO, HEARTBEAT, SET_VOLTS, LASER, SCAN_BEGIN,
  SCAN_DATA, SCAN_START, SCAN_STOP, SAFE, GET_STATUS) are numbered 1..65535 and answered
  stop-and-wait with ACK or NAK under their seq; the board repeats its stored answer to a
  retransmission instead of executing it twice;
* board messages (0x80..0x85: ACK, NAK, EVENT, BOOT, STATUS, FAULT) carry the board's own
  seq; one EVENT per trigger with the codes in the DAC outputs at the edge;
* the board goes safe (0 V, laser off) when no host packet arrives for 150 ms (HEARTBEAT
  every 50 ms), and when its interlock opens;
* DAC code ``U = (code - 32768) * 10 V / 32767``, code 0 reserved.
"""

from __future__ import annotations

import binascii
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from galvoscan_common.frame import VOLTAGE_LIMIT

PROTOCOL_VERSION = 1

#: DAC resolution and channel count of the board.
DAC_BITS = 16
N_CHANNELS = 4
#: Code of 0 V, and the lowest / highest valid codes (-10 V / +10 V).
CODE_ZERO = 32768
CODE_MIN = 1
CODE_MAX = 65535
#: One DAC step [V].
VOLTS_PER_CODE = VOLTAGE_LIMIT / (CODE_MAX - CODE_ZERO)

HEADER_SIZE = 3
CRC_SIZE = 4
MAX_PAYLOAD = 240
MAX_PACKET = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
#: Longest COBS frame (without its delimiter) a receiver accepts [bytes].
MAX_ENCODED_FRAME = 256
#: Scan rows per SCAN_DATA packet.
ROWS_PER_CHUNK = 29

# Message types.
HELLO = 0x01
HEARTBEAT = 0x02
SET_VOLTS = 0x03
LASER = 0x04
SCAN_BEGIN = 0x05
SCAN_DATA = 0x06
SCAN_START = 0x07
SCAN_STOP = 0x08
SAFE = 0x09
GET_STATUS = 0x0A
ACK = 0x80
NAK = 0x81
EVENT = 0x82
BOOT = 0x83
STATUS = 0x84
FAULT = 0x85

# NAK reasons.
NAK_BAD_MESSAGE = 1
NAK_NO_SESSION = 2
NAK_VERSION = 3
NAK_BUSY = 4
NAK_BAD_ARGUMENT = 5
NAK_TABLE_MISMATCH = 6
NAK_INTERLOCK = 7
NAK_REASONS = {
    NAK_BAD_MESSAGE: 'bad message',
    NAK_NO_SESSION: 'no session (HELLO first)',
    NAK_VERSION: 'protocol version mismatch',
    NAK_BUSY: 'busy scanning',
    NAK_BAD_ARGUMENT: 'bad argument',
    NAK_TABLE_MISMATCH: 'scan table incomplete or CRC mismatch',
    NAK_INTERLOCK: 'interlock open',
}

# Board states (BoardStatus.state).
STATE_IDLE = 0
STATE_LOADED = 1
STATE_SCANNING = 2
STATE_DONE = 3
STATE_NAMES = {STATE_IDLE: 'idle', STATE_LOADED: 'loaded', STATE_SCANNING: 'scanning',
               STATE_DONE: 'done'}
FLAG_WATCHDOG = 0x01
FLAG_INTERLOCK = 0x02

# Fault codes.
FAULT_WATCHDOG = 1
FAULT_OVERRUN = 2
FAULT_INTERLOCK = 3
FAULT_NAMES = {FAULT_WATCHDOG: 'watchdog (heartbeats stopped)',
               FAULT_OVERRUN: 'trigger overrun', FAULT_INTERLOCK: 'interlock opened'}

# Event status (same numbers as galvoscan_common.frame.STATUS_*).
EVENT_SETTLED = 0
EVENT_MOVING = 1
EVENT_FAULT = 2


class ProtocolError(Exception):
    """A frame or packet that does not follow the protocol.

    Attributes
    ----------
    seq : int or None
        Sequence number of the packet when its CRC was good (so the sender is known to have
        sent a malformed packet), else None.
    msg_type : int or None
        Its type byte under the same condition.
    """

    def __init__(self, message: str, seq: int | None = None, msg_type: int | None = None):
        super().__init__(message)
        self.seq = seq
        self.msg_type = msg_type


# ---------------------------------------------------------------------------------------
# COBS and CRC
# ---------------------------------------------------------------------------------------

def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``; the result contains no zero byte (delimiter not appended)."""
    out = bytearray()
    parts = bytes(data).split(b'\x00')
    last = len(parts) - 1
    for i, part in enumerate(parts):
        n = len(part)
        pos = 0
        while n - pos >= 254:
            out.append(0xFF)
            out += part[pos:pos + 254]
            pos += 254
        if pos < n or i < last or pos == 0:
            # A shorter block, or the empty block before an implied zero.
            out.append(n - pos + 1)
            out += part[pos:]
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Invert :func:`cobs_encode`.

    Raises
    ------
    ProtocolError
        A zero byte inside the frame, or a block running past its end.
    """
    out = bytearray()
    n = len(data)
    i = 0
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError('COBS: zero byte inside a frame')
        end = i + code
        if end > n:
            raise ProtocolError('COBS: block runs past the end of the frame (truncated)')
        out += data[i + 1:end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (IEEE 802.3, zlib) of ``data``; check value of b'123456789' is
    0xCBF43926."""
    return binascii.crc32(data) & 0xFFFFFFFF


def table_crc(codes: np.ndarray) -> int:
    """CRC-32 of a scan table as it is sent: rows of 4 little-endian u16 codes.

    Parameters
    ----------
    codes : ndarray, shape (n, 4), integer DAC codes
    """
    arr = np.asarray(codes)
    if arr.ndim != 2 or arr.shape[1] != N_CHANNELS:
        raise ValueError(f'codes: expected shape (n, 4), got {arr.shape}')
    return crc32(arr.astype('<u2').tobytes())


# ---------------------------------------------------------------------------------------
# Voltages <-> DAC codes
# ---------------------------------------------------------------------------------------

def volts_to_codes(voltages) -> np.ndarray:
    """Quantise voltages to DAC codes, rounding half up: ``32768 + floor(U / LSB + 1/2)``.

    Parameters
    ----------
    voltages : array_like, any shape, volts
        Each value in [-10, +10] V.

    Returns
    -------
    ndarray, same shape, uint16 codes in [1, 65535]

    Raises
    ------
    ValueError
        A NaN / infinite value or one outside +-10 V (nothing is converted).
    """
    arr = np.asarray(voltages, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError('voltages: contains NaN or infinite values')
    if arr.size and float(np.max(np.abs(arr))) > VOLTAGE_LIMIT:
        raise ValueError(f'voltages: |U| = {float(np.max(np.abs(arr))):.6g} V exceeds '
                         f'the DAC range of +-{VOLTAGE_LIMIT} V')
    steps = np.floor(arr / VOLTS_PER_CODE + 0.5)
    codes = np.clip(steps + CODE_ZERO, CODE_MIN, CODE_MAX)
    return codes.astype(np.uint16)


def codes_to_volts(codes) -> np.ndarray:
    """Voltages of DAC codes: ``(code - 32768) * 10 V / 32767``.

    Parameters
    ----------
    codes : array_like, any shape, integers in [1, 65535]

    Returns
    -------
    ndarray, same shape, float64, volts

    Raises
    ------
    ValueError
        A code outside [1, 65535] or not an integer.
    """
    arr = np.asarray(codes)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f'codes: expected integers, got dtype {arr.dtype}')
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < CODE_MIN or arr.max() > CODE_MAX):
        raise ValueError(f'codes: must be in [{CODE_MIN}, {CODE_MAX}]')
    return (arr - CODE_ZERO) * VOLTS_PER_CODE


def _check_codes(codes, seq, msg_type) -> tuple[int, ...]:
    for c in codes:
        if c < CODE_MIN:
            raise ProtocolError('DAC code 0 is reserved', seq, msg_type)
    return tuple(codes)


def _check_bool(value: int, what: str, seq, msg_type) -> bool:
    if value > 1:
        raise ProtocolError(f'{what}: expected 0 or 1, got {value}', seq, msg_type)
    return bool(value)


# ---------------------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------------------

_CODES4 = struct.Struct('<4H')


@dataclass(frozen=True, slots=True)
class BoardInfo:
    """Identity of the board: the ACK data of HELLO and the payload of BOOT."""

    version: int
    firmware_id: str
    dac_bits: int
    channels: int
    boot_id: int
    uptime_us: int
    max_scan_rows: int
    min_period_us: int

    _S = struct.Struct('<H16sBBIQII')

    def pack(self) -> bytes:
        fid = self.firmware_id.encode('ascii')[:16]
        return self._S.pack(self.version, fid, self.dac_bits, self.channels, self.boot_id,
                            self.uptime_us, self.max_scan_rows, self.min_period_us)

    @classmethod
    def unpack(cls, data: bytes, seq=None, msg_type=None) -> BoardInfo:
        if len(data) != cls._S.size:
            raise ProtocolError(f'BoardInfo: expected {cls._S.size} bytes, got {len(data)}',
                                seq, msg_type)
        v, fid, bits, ch, boot, up, rows, per = cls._S.unpack(data)
        try:
            name = fid.rstrip(b'\x00').decode('ascii')
        except UnicodeDecodeError:
            raise ProtocolError('BoardInfo: firmware id is not ASCII', seq, msg_type) from None
        return cls(v, name, bits, ch, boot, up, rows, per)


@dataclass(frozen=True, slots=True)
class BoardStatus:
    """State of the board: payload of STATUS and the ACK data of GET_STATUS."""

    boot_id: int
    uptime_us: int
    state: int
    flags: int
    laser_on: bool
    codes: tuple[int, int, int, int]
    scan_id: int
    triggers: int
    rx_errors: int

    _S = struct.Struct('<IQBBB4HHII')

    def pack(self) -> bytes:
        return self._S.pack(self.boot_id, self.uptime_us, self.state, self.flags,
                            int(self.laser_on), *self.codes, self.scan_id, self.triggers,
                            self.rx_errors)

    @classmethod
    def unpack(cls, data: bytes, seq=None, msg_type=None) -> BoardStatus:
        if len(data) != cls._S.size:
            raise ProtocolError(f'BoardStatus: expected {cls._S.size} bytes, got {len(data)}',
                                seq, msg_type)
        f = cls._S.unpack(data)
        if f[2] not in STATE_NAMES:
            raise ProtocolError(f'BoardStatus: unknown state {f[2]}', seq, msg_type)
        laser = _check_bool(f[4], 'laser', seq, msg_type)
        codes = _check_codes(f[5:9], seq, msg_type)
        return cls(f[0], f[1], f[2], f[3], laser, codes, f[9], f[10], f[11])


class Message:
    """Base of all message classes; ``TYPE`` is the type byte."""

    __slots__ = ()
    TYPE = -1

    def payload(self) -> bytes:
        return b''

    @classmethod
    def from_payload(cls, payload: bytes, seq: int):
        if payload:
            raise ProtocolError(f'{cls.__name__}: expected an empty payload, '
                                f'got {len(payload)} bytes', seq, cls.TYPE)
        return cls()


def _expect_len(cls, payload: bytes, size: int, seq: int) -> None:
    if len(payload) != size:
        raise ProtocolError(f'{cls.__name__}: expected {size} payload bytes, '
                            f'got {len(payload)}', seq, cls.TYPE)


@dataclass(frozen=True, slots=True)
class Hello(Message):
    version: int = PROTOCOL_VERSION
    TYPE = HELLO
    _S = struct.Struct('<H')

    def payload(self) -> bytes:
        return self._S.pack(self.version)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        return cls(*cls._S.unpack(payload))


@dataclass(frozen=True, slots=True)
class Heartbeat(Message):
    TYPE = HEARTBEAT


@dataclass(frozen=True, slots=True)
class SetVolts(Message):
    codes: tuple[int, int, int, int]
    TYPE = SET_VOLTS

    def payload(self) -> bytes:
        return _CODES4.pack(*self.codes)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, 8, seq)
        return cls(_check_codes(_CODES4.unpack(payload), seq, cls.TYPE))


@dataclass(frozen=True, slots=True)
class Laser(Message):
    on: bool
    TYPE = LASER

    def payload(self) -> bytes:
        return bytes((int(self.on),))

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, 1, seq)
        return cls(_check_bool(payload[0], 'laser', seq, cls.TYPE))


@dataclass(frozen=True, slots=True)
class ScanBegin(Message):
    scan_id: int
    n_rows: int
    TYPE = SCAN_BEGIN
    _S = struct.Struct('<HI')

    def payload(self) -> bytes:
        return self._S.pack(self.scan_id, self.n_rows)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        scan_id, n = cls._S.unpack(payload)
        if n == 0:
            raise ProtocolError('ScanBegin: n_rows must be >= 1', seq, cls.TYPE)
        return cls(scan_id, n)


@dataclass(frozen=True, slots=True)
class ScanData(Message):
    """``rows``: tuple of 4-tuples of codes, 1..ROWS_PER_CHUNK of them."""

    scan_id: int
    offset: int
    rows: tuple[tuple[int, int, int, int], ...]
    TYPE = SCAN_DATA
    _S = struct.Struct('<HIB')

    def payload(self) -> bytes:
        flat = [c for row in self.rows for c in row]
        return self._S.pack(self.scan_id, self.offset, len(self.rows)) + struct.pack(
            f'<{len(flat)}H', *flat)

    @classmethod
    def from_payload(cls, payload, seq):
        if len(payload) < cls._S.size:
            raise ProtocolError('ScanData: payload too short', seq, cls.TYPE)
        scan_id, offset, count = cls._S.unpack_from(payload)
        if not 1 <= count <= ROWS_PER_CHUNK:
            raise ProtocolError(f'ScanData: count {count} not in 1..{ROWS_PER_CHUNK}',
                                seq, cls.TYPE)
        _expect_len(cls, payload, cls._S.size + 8 * count, seq)
        flat = _check_codes(struct.unpack_from(f'<{4 * count}H', payload, cls._S.size),
                            seq, cls.TYPE)
        rows = tuple(flat[4 * i:4 * i + 4] for i in range(count))
        return cls(scan_id, offset, rows)


@dataclass(frozen=True, slots=True)
class ScanStart(Message):
    scan_id: int
    n_rows: int
    period_us: int
    laser_on: bool
    table_crc: int
    TYPE = SCAN_START
    _S = struct.Struct('<HIIBI')

    def payload(self) -> bytes:
        return self._S.pack(self.scan_id, self.n_rows, self.period_us, int(self.laser_on),
                            self.table_crc)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        scan_id, n, period, laser, crc = cls._S.unpack(payload)
        if period == 0 or n == 0:
            raise ProtocolError('ScanStart: period_us and n_rows must be >= 1', seq, cls.TYPE)
        return cls(scan_id, n, period, _check_bool(laser, 'laser', seq, cls.TYPE), crc)


@dataclass(frozen=True, slots=True)
class ScanStop(Message):
    TYPE = SCAN_STOP


@dataclass(frozen=True, slots=True)
class Safe(Message):
    TYPE = SAFE


@dataclass(frozen=True, slots=True)
class GetStatus(Message):
    TYPE = GET_STATUS


@dataclass(frozen=True, slots=True)
class Ack(Message):
    acked_seq: int
    data: bytes = b''
    TYPE = ACK

    def payload(self) -> bytes:
        return struct.pack('<H', self.acked_seq) + self.data

    @classmethod
    def from_payload(cls, payload, seq):
        if len(payload) < 2:
            raise ProtocolError('Ack: payload too short', seq, cls.TYPE)
        return cls(struct.unpack_from('<H', payload)[0], bytes(payload[2:]))


@dataclass(frozen=True, slots=True)
class Nak(Message):
    acked_seq: int
    reason: int
    TYPE = NAK
    _S = struct.Struct('<HB')

    def payload(self) -> bytes:
        return self._S.pack(self.acked_seq, self.reason)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        return cls(*cls._S.unpack(payload))


@dataclass(frozen=True, slots=True)
class Event(Message):
    """One trigger: what the board output and when."""

    boot_id: int
    scan_id: int
    index: int
    timestamp_us: int
    codes: tuple[int, int, int, int]
    laser_on: bool
    status: int
    TYPE = EVENT
    _S = struct.Struct('<IHIQ4HBB')

    def payload(self) -> bytes:
        return self._S.pack(self.boot_id, self.scan_id, self.index, self.timestamp_us,
                            *self.codes, int(self.laser_on), self.status)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        f = cls._S.unpack(payload)
        if f[9] > EVENT_FAULT:
            raise ProtocolError(f'Event: unknown status {f[9]}', seq, cls.TYPE)
        return cls(f[0], f[1], f[2], f[3], _check_codes(f[4:8], seq, cls.TYPE),
                   _check_bool(f[8], 'laser', seq, cls.TYPE), f[9])


@dataclass(frozen=True, slots=True)
class Boot(Message):
    info: BoardInfo
    TYPE = BOOT

    def payload(self) -> bytes:
        return self.info.pack()

    @classmethod
    def from_payload(cls, payload, seq):
        return cls(BoardInfo.unpack(payload, seq, cls.TYPE))


@dataclass(frozen=True, slots=True)
class Status(Message):
    status: BoardStatus
    TYPE = STATUS

    def payload(self) -> bytes:
        return self.status.pack()

    @classmethod
    def from_payload(cls, payload, seq):
        return cls(BoardStatus.unpack(payload, seq, cls.TYPE))


@dataclass(frozen=True, slots=True)
class Fault(Message):
    code: int
    timestamp_us: int
    detail: int = 0
    TYPE = FAULT
    _S = struct.Struct('<BQI')

    def payload(self) -> bytes:
        return self._S.pack(self.code, self.timestamp_us, self.detail)

    @classmethod
    def from_payload(cls, payload, seq):
        _expect_len(cls, payload, cls._S.size, seq)
        return cls(*cls._S.unpack(payload))


MESSAGE_TYPES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Hello, Heartbeat, SetVolts, Laser, ScanBegin, ScanData,
                              ScanStart, ScanStop, Safe, GetStatus, Ack, Nak, Event, Boot,
                              Status, Fault)
}


@dataclass(frozen=True, slots=True)
class Packet:
    """A decoded packet: its sequence number and its message."""

    seq: int
    msg: Message


_HEADER = struct.Struct('<BH')
_CRC = struct.Struct('<I')


def encode_packet(seq: int, msg: Message) -> bytes:
    """Packet bytes (header, payload, CRC) before COBS."""
    if not 0 <= seq <= 0xFFFF:
        raise ValueError(f'seq: must be in 0..65535, got {seq}')
    payload = msg.payload()
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f'msg: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}')
    body = _HEADER.pack(msg.TYPE, seq) + payload
    return body + _CRC.pack(binascii.crc32(body) & 0xFFFFFFFF)


def encode_frame(seq: int, msg: Message) -> bytes:
    """The wire frame of one message: COBS(packet) followed by the 0x00 delimiter."""
    return cobs_encode(encode_packet(seq, msg)) + b'\x00'


def decode_packet(packet: bytes) -> Packet:
    """Check the CRC of raw packet bytes (after COBS decoding) and parse them.

    Raises
    ------
    ProtocolError
        Too short, bad CRC (``seq`` is None), or a well-protected packet whose type or
        payload is invalid (``seq`` and ``msg_type`` set).
    """
    n = len(packet)
    if n < HEADER_SIZE + CRC_SIZE:
        raise ProtocolError(f'packet of {n} bytes is shorter than header + CRC')
    if n > MAX_PACKET:
        raise ProtocolError(f'packet of {n} bytes exceeds {MAX_PACKET}')
    body = packet[:-CRC_SIZE]
    if binascii.crc32(body) & 0xFFFFFFFF != _CRC.unpack_from(packet, n - CRC_SIZE)[0]:
        raise ProtocolError('CRC mismatch')
    msg_type, seq = _HEADER.unpack_from(body)
    cls = MESSAGE_TYPES.get(msg_type)
    if cls is None:
        raise ProtocolError(f'unknown message type 0x{msg_type:02x}', seq, msg_type)
    return Packet(seq, cls.from_payload(body[HEADER_SIZE:], seq))


def decode_frame(frame: bytes) -> Packet:
    """Decode one wire frame given without its 0x00 delimiter.

    Raises
    ------
    ProtocolError
        Anything wrong with it; never any other exception.
    """
    if len(frame) > MAX_ENCODED_FRAME:
        raise ProtocolError(f'frame of {len(frame)} bytes exceeds {MAX_ENCODED_FRAME}')
    return decode_packet(cobs_decode(frame))


class FrameDecoder:
    """Streaming decoder: feed byte chunks of any size, get the packets they complete.

    Bad frames are counted (``errors``, by kind), the last few kept in ``recent_errors``
    and passed to ``on_error``; decoding resumes at the next ``0x00``. The buffer never
    holds more than :data:`MAX_ENCODED_FRAME` bytes between calls: a longer run without a
    delimiter is dropped together with the rest of its frame.

    Parameters
    ----------
    on_error : callable(ProtocolError), optional
        Called for every bad frame (e.g. by the board, to NAK a malformed command).
    """

    def __init__(self, on_error: Callable[[ProtocolError], None] | None = None):
        self._buf = bytearray()
        self._skipping = False
        self.on_error = on_error
        self.frames_ok = 0
        self.errors = {'cobs': 0, 'crc': 0, 'message': 0, 'oversize': 0}
        self.recent_errors: deque[ProtocolError] = deque(maxlen=32)

    @property
    def error_count(self) -> int:
        return sum(self.errors.values())

    @property
    def buffered(self) -> int:
        """Bytes waiting for their delimiter."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget any partial frame (e.g. after a reconnect)."""
        self._buf.clear()
        self._skipping = False

    def _error(self, kind: str, err: ProtocolError) -> None:
        self.errors[kind] += 1
        self.recent_errors.append(err)
        if self.on_error is not None:
            self.on_error(err)

    def feed(self, data: bytes) -> list[Packet]:
        """Add received bytes; return the packets completed by them, in order.

        Never raises for any content of ``data``.
        """
        out: list[Packet] = []
        buf = self._buf
        buf += data
        start = 0
        while True:
            end = buf.find(0, start)
            if end < 0:
                break
            frame = bytes(buf[start:end])
            start = end + 1
            if self._skipping:
                self._skipping = False
                continue
            if not frame:
                continue
            if len(frame) > MAX_ENCODED_FRAME:
                self._error('oversize', ProtocolError(
                    f'frame of {len(frame)} bytes exceeds {MAX_ENCODED_FRAME}'))
                continue
            try:
                packet = cobs_decode(frame)
            except ProtocolError as err:
                self._error('cobs', err)
                continue
            try:
                out.append(decode_packet(packet))
            except ProtocolError as err:
                self._error('crc' if err.seq is None else 'message', err)
                continue
            self.frames_ok += 1
        if start:
            del buf[:start]
        if len(buf) > MAX_ENCODED_FRAME:
            buf.clear()
            if not self._skipping:
                self._skipping = True
                self._error('oversize', ProtocolError(
                    f'no delimiter within {MAX_ENCODED_FRAME} bytes; skipping to the next'))
        return out
