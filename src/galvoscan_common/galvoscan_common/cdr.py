"""Plain CDR (XCDR1, as ROS 2 puts it on the wire) for the messages of the frame path.

No rclpy here. A raw subscription hands its callback the serialised bytes, and a publisher
takes bytes; reading and writing those bytes directly skips rclpy's conversion of every
field between Python objects and C structures, which costs more than the DDS hop itself
for a message of 720 stripe centres (``benchmarks/pipeline.py``).

Layout: a 4-byte encapsulation header (``00 01`` little endian, ``00 00`` big endian, then
two option bytes), then the fields in declaration order, each primitive aligned to its own
size (at most 8) counted from the end of the encapsulation header. Strings are a uint32
length that counts the terminating NUL, then the bytes and the NUL; sequences are a uint32
count, then the elements.

Readers accept both byte orders and return arrays as read-only views of the buffer (no copy);
writers produce little endian. Anything that is not a well-formed message of the expected
type raises :class:`CdrError`, and only that.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

#: Encapsulation identifiers of plain CDR: big and little endian.
CDR_BE, CDR_LE = b'\x00\x00', b'\x00\x01'
#: Longest string accepted in a message [bytes, without the NUL].
MAX_STRING_BYTES = 4096


class CdrError(ValueError):
    """The bytes are not a well-formed CDR message of the expected type."""


_FORMATS = {'u8': 'B', 'u32': 'I', 'i32': 'i', 'u64': 'Q', 'f32': 'f', 'f64': 'd'}
_STRUCTS = {order: {k: struct.Struct(order + f) for k, f in _FORMATS.items()}
            for order in '<>'}


class Reader:
    """Sequential reader of one CDR message; alignment counts from the end of the header."""

    __slots__ = ('buf', 'pos', 'end', 'order', '_s')

    def __init__(self, data):
        try:
            buf = memoryview(data).cast('B')
        except TypeError as exc:
            raise CdrError(f'not a bytes-like object: {type(data).__name__}') from exc
        if len(buf) < 4 or bytes(buf[:2]) not in (CDR_BE, CDR_LE):
            raise CdrError('no plain-CDR encapsulation header (first bytes '
                           f'{bytes(buf[:4]).hex() or "none"})')
        self.buf, self.pos, self.end = buf, 4, len(buf)
        self.order = '<' if bytes(buf[:2]) == CDR_LE else '>'
        self._s = _STRUCTS[self.order]

    def _take(self, n: int, align: int, what: str) -> int:
        start = self.pos + (-(self.pos - 4) % align)
        if n < 0 or start + n > self.end:
            raise CdrError(f'{what}: needs {n} bytes at offset {start}, message has {self.end}')
        self.pos = start + n
        return start

    def _prim(self, kind: str, size: int, what: str):
        s = self._s[kind]
        return s.unpack_from(self.buf, self._take(size, size, what))[0]

    def u8(self, what: str) -> int:
        return self.buf[self._take(1, 1, what)]

    def boolean(self, what: str) -> bool:
        v = self.u8(what)
        if v > 1:
            raise CdrError(f'{what}: bool byte {v}')
        return bool(v)

    def u32(self, what: str) -> int:
        return self._prim('u32', 4, what)

    def i32(self, what: str) -> int:
        return self._prim('i32', 4, what)

    def u64(self, what: str) -> int:
        return self._prim('u64', 8, what)

    def f32(self, what: str) -> float:
        return self._prim('f32', 4, what)

    def f64(self, what: str) -> float:
        return self._prim('f64', 8, what)

    def string(self, what: str) -> str:
        n = self.u32(what)
        if n == 0 or n > MAX_STRING_BYTES + 1:
            raise CdrError(f'{what}: string length {n} (1..{MAX_STRING_BYTES + 1} with the NUL)')
        start = self._take(n, 1, what)
        raw = bytes(self.buf[start:start + n])
        if raw[-1] != 0:
            raise CdrError(f'{what}: string not NUL-terminated')
        try:
            return raw[:-1].decode('utf-8')
        except UnicodeDecodeError as exc:
            raise CdrError(f'{what}: not UTF-8 ({exc})') from None

    def octets(self, what: str) -> memoryview:
        n = self.u32(what)
        start = self._take(n, 1, what)
        return self.buf[start:start + n]

    def f32_array(self, what: str) -> np.ndarray:
        n = self.u32(what)
        start = self._take(4 * n, 4, what)
        return np.frombuffer(self.buf, np.dtype(self.order + 'f4'), count=n, offset=start)

    def done(self, what: str) -> None:
        """Raise if more than the alignment padding of the last field is left over."""
        if self.end - self.pos > 3:
            raise CdrError(f'{what}: {self.end - self.pos} bytes after the last field')


class Writer:
    """Little-endian CDR writer; :meth:`bytes` returns the message."""

    __slots__ = ('buf',)
    _s = _STRUCTS['<']

    def __init__(self):
        self.buf = bytearray(CDR_LE + b'\x00\x00')

    def _align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += bytes(pad)

    def _prim(self, kind: str, size: int, value) -> None:
        self._align(size)
        self.buf += self._s[kind].pack(value)

    def u8(self, v: int) -> None:
        self.buf.append(v)

    def u32(self, v: int) -> None:
        self._prim('u32', 4, v)

    def i32(self, v: int) -> None:
        self._prim('i32', 4, v)

    def u64(self, v: int) -> None:
        self._prim('u64', 8, v)

    def f32(self, v: float) -> None:
        self._prim('f32', 4, v)

    def f64(self, v: float) -> None:
        self._prim('f64', 8, v)

    def string(self, s: str) -> None:
        raw = s.encode('utf-8')
        self.u32(len(raw) + 1)
        self.buf += raw
        self.buf.append(0)

    def octets(self, data) -> None:
        data = memoryview(data).cast('B')
        self.u32(len(data))
        self.buf += data

    def f32_array(self, values: np.ndarray) -> None:
        values = np.asarray(values)
        self.u32(values.shape[0])
        self.buf += values.astype('<f4', copy=False).tobytes()

    def bytes(self) -> bytes:
        return bytes(self.buf)


# ---- messages ---------------------------------------------------------------------------
@dataclass(slots=True)
class Header:
    """std_msgs/Header: stamp [s, ns] and frame_id."""

    sec: int = 0
    nanosec: int = 0
    frame_id: str = ''

    @property
    def stamp_ns(self) -> int:
        """The stamp [ns]."""
        return self.sec * 1_000_000_000 + self.nanosec


def read_header(r: Reader, what: str = 'header') -> Header:
    sec = r.i32(f'{what}.stamp.sec')
    nanosec = r.u32(f'{what}.stamp.nanosec')
    if nanosec >= 1_000_000_000:
        raise CdrError(f'{what}.stamp.nanosec {nanosec} >= 1e9')
    return Header(sec, nanosec, r.string(f'{what}.frame_id'))


def write_header(w: Writer, h: Header) -> None:
    w.i32(h.sec)
    w.u32(h.nanosec)
    w.string(h.frame_id)


@dataclass(slots=True)
class GalvoState:
    """galvoscan_msgs/GalvoState; voltages [V]."""

    header: Header
    seq: int
    g1_pan_voltage: float
    g1_tilt_voltage: float
    g2_pan_voltage: float
    g2_tilt_voltage: float
    laser_on: bool
    status: int


def _read_galvo_state(r: Reader, what: str) -> GalvoState:
    header = read_header(r, f'{what}.header')
    return GalvoState(header, r.u64(f'{what}.seq'), r.f64(f'{what}.g1_pan_voltage'),
                      r.f64(f'{what}.g1_tilt_voltage'), r.f64(f'{what}.g2_pan_voltage'),
                      r.f64(f'{what}.g2_tilt_voltage'), r.boolean(f'{what}.laser_on'),
                      r.u8(f'{what}.status'))


def _write_galvo_state(w: Writer, g: GalvoState) -> None:
    write_header(w, g.header)
    w.u64(g.seq)
    for v in (g.g1_pan_voltage, g.g1_tilt_voltage, g.g2_pan_voltage, g.g2_tilt_voltage):
        w.f64(v)
    w.u8(1 if g.laser_on else 0)
    w.u8(g.status)


def parse_galvo_state(data) -> GalvoState:
    """A serialised galvoscan_msgs/GalvoState; raises :class:`CdrError`."""
    r = Reader(data)
    out = _read_galvo_state(r, 'GalvoState')
    r.done('GalvoState')
    return out


def serialize_galvo_state(g: GalvoState) -> bytes:
    w = Writer()
    _write_galvo_state(w, g)
    return w.bytes()


@dataclass(slots=True)
class StripeCenters:
    """galvoscan_msgs/StripeCenters; arrays are float32 of one length n [px, px, px, DN]."""

    header: Header
    galvo: GalvoState
    image_width: int
    image_height: int
    u: np.ndarray
    v: np.ndarray
    width: np.ndarray
    strength: np.ndarray
    method: str
    sigma: float
    min_strength: float
    roi_half_height: int
    orientation: int
    rejected_secondary: int


def parse_stripe_centers(data) -> StripeCenters:
    """A serialised galvoscan_msgs/StripeCenters (arrays are views); raises :class:`CdrError`.

    The four arrays are not checked for equal length here (the message type allows any).
    """
    r = Reader(data)
    header = read_header(r)
    galvo = _read_galvo_state(r, 'galvo')
    out = StripeCenters(header, galvo, r.u32('image_width'), r.u32('image_height'),
                        r.f32_array('u'), r.f32_array('v'), r.f32_array('width'),
                        r.f32_array('strength'), r.string('method'), r.f32('sigma'),
                        r.f32('min_strength'), r.u32('roi_half_height'), r.u8('orientation'),
                        r.u32('rejected_secondary'))
    r.done('StripeCenters')
    return out


def serialize_stripe_centers(m: StripeCenters) -> bytes:
    w = Writer()
    write_header(w, m.header)
    _write_galvo_state(w, m.galvo)
    w.u32(m.image_width)
    w.u32(m.image_height)
    for a in (m.u, m.v, m.width, m.strength):
        w.f32_array(a)
    w.string(m.method)
    w.f32(m.sigma)
    w.f32(m.min_strength)
    w.u32(m.roi_half_height)
    w.u8(m.orientation)
    w.u32(m.rejected_secondary)
    return w.bytes()


#: sensor_msgs/PointField datatype of each numpy field type.
POINT_FIELD_TYPES = {np.dtype('<i1'): 1, np.dtype('<u1'): 2, np.dtype('<i2'): 3,
                     np.dtype('<u2'): 4, np.dtype('<i4'): 5, np.dtype('<u4'): 6,
                     np.dtype('<f4'): 7, np.dtype('<f8'): 8}


def serialize_point_cloud(points: np.ndarray, header: Header, is_dense: bool = True) -> bytes:
    """An unorganised sensor_msgs/PointCloud2 (height 1) holding a structured array.

    Every field of ``points.dtype`` becomes a PointField (count 1) at its offset; fields must be
    little-endian scalars of a PointField type.
    """
    dt = points.dtype
    if dt.names is None:
        raise ValueError('points must be a structured array')
    w = Writer()
    write_header(w, header)
    w.u32(1)
    w.u32(points.shape[0])
    w.u32(len(dt.names))
    for name in dt.names:
        ftype, offset = dt.fields[name][:2]
        if ftype not in POINT_FIELD_TYPES:
            raise ValueError(f'field {name}: {ftype} is not a little-endian PointField type')
        w.string(name)
        w.u32(offset)
        w.u8(POINT_FIELD_TYPES[ftype])
        w.u32(1)
    w.u8(0)                                 # is_bigendian
    w.u32(dt.itemsize)
    w.u32(dt.itemsize * points.shape[0])
    w.octets(np.ascontiguousarray(points).view(np.uint8).reshape(-1))
    w.u8(1 if is_dense else 0)
    return w.bytes()
