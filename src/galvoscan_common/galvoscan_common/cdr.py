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

Messages: std_msgs/Header, galvoscan_msgs/GalvoState and StripeCenters (read and write),
sensor_msgs/PointCloud2 (write) and sensor_msgs/Image (read: :func:`parse_image_cdr` and
:func:`image_to_array`; write: :func:`serialize_image`). The pixels are never copied on
reading and copied once on writing.

Readers accept both byte orders and return arrays as read-only views of the buffer (no copy);
writers produce little endian. Anything that is not a well-formed message of the expected
type raises :class:`CdrError`, and only that; the Image reader raises
:class:`BadImageError` instead, which names the cause (the extractor node counts them).
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


_STRUCTS: dict[str, struct.Struct] = {}


def _struct(fmt: str) -> struct.Struct:
    """``struct.Struct(fmt)``, cached (``fmt`` starts with the byte order)."""
    s = _STRUCTS.get(fmt)
    if s is None:
        s = _STRUCTS[fmt] = struct.Struct(fmt)
    return s


class Reader:
    """Sequential reader of one CDR message; alignment counts from the end of the header.

    :meth:`unpack` reads a run of fields that share one alignment and need no padding
    between them (e.g. ``'Qdddd'`` after an 8-byte boundary) in one call.
    """

    __slots__ = ('buf', 'pos', 'end', 'order')

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

    def _take(self, n: int, align: int, what: str) -> int:
        start = self.pos + (-(self.pos - 4) % align)
        if n < 0 or start + n > self.end:
            raise CdrError(f'{what}: needs {n} bytes at offset {start}, message has {self.end}')
        self.pos = start + n
        return start

    def unpack(self, fmt: str, align: int, what: str) -> tuple:
        """The fields of ``fmt`` (struct codes, no byte order), the first aligned to ``align``."""
        s = _struct(self.order + fmt)
        return s.unpack_from(self.buf, self._take(s.size, align, what))

    def u8(self, what: str) -> int:
        return self.buf[self._take(1, 1, what)]

    def u32(self, what: str) -> int:
        return self.unpack('I', 4, what)[0]

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

    def __init__(self):
        self.buf = bytearray(CDR_LE + b'\x00\x00')

    def pack(self, fmt: str, align: int, *values) -> None:
        """Write the fields of ``fmt`` (struct codes, no byte order), aligned to ``align``."""
        pad = -(len(self.buf) - 4) % align
        if pad:
            self.buf += bytes(pad)
        self.buf += _struct('<' + fmt).pack(*values)

    def string(self, s: str) -> None:
        raw = s.encode('utf-8')
        self.pack('I', 4, len(raw) + 1)
        self.buf += raw
        self.buf.append(0)

    def f32_array(self, values: np.ndarray) -> None:
        values = np.asarray(values)
        self.pack('I', 4, values.shape[0])
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
    sec, nanosec = r.unpack('iI', 4, f'{what}.stamp')
    if nanosec >= 1_000_000_000:
        raise CdrError(f'{what}.stamp.nanosec {nanosec} >= 1e9')
    return Header(sec, nanosec, r.string(f'{what}.frame_id'))


def write_header(w: Writer, h: Header) -> None:
    w.pack('iI', 4, h.sec, h.nanosec)
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
    seq, *volts = r.unpack('Qdddd', 8, f'{what}.seq and voltages')
    laser_on, status = r.unpack('BB', 1, f'{what}.laser_on and status')
    if laser_on > 1:
        raise CdrError(f'{what}.laser_on: bool byte {laser_on}')
    return GalvoState(header, seq, *volts, bool(laser_on), status)


def _write_galvo_state(w: Writer, g: GalvoState) -> None:
    write_header(w, g.header)
    w.pack('QddddBB', 8, g.seq, g.g1_pan_voltage, g.g1_tilt_voltage, g.g2_pan_voltage,
           g.g2_tilt_voltage, 1 if g.laser_on else 0, g.status)


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
    saturated_fraction: float = 0.0
    peak_level: float = 0.0


def parse_stripe_centers(data) -> StripeCenters:
    """A serialised galvoscan_msgs/StripeCenters (arrays are views); raises :class:`CdrError`.

    The four arrays are not checked for equal length here (the message type allows any).
    """
    r = Reader(data)
    header = read_header(r)
    galvo = _read_galvo_state(r, 'galvo')
    size = r.unpack('II', 4, 'image_width and image_height')
    arrays = (r.f32_array('u'), r.f32_array('v'), r.f32_array('width'),
              r.f32_array('strength'))
    method = r.string('method')
    params = r.unpack('ffIB', 4, 'sigma, min_strength, roi_half_height and orientation')
    rejected = r.u32('rejected_secondary')
    levels = r.unpack('ff', 4, 'saturated_fraction and peak_level')
    out = StripeCenters(header, galvo, *size, *arrays, method, *params, rejected, *levels)
    r.done('StripeCenters')
    return out


def serialize_stripe_centers(m: StripeCenters) -> bytes:
    w = Writer()
    write_header(w, m.header)
    _write_galvo_state(w, m.galvo)
    w.pack('II', 4, m.image_width, m.image_height)
    for a in (m.u, m.v, m.width, m.strength):
        w.f32_array(a)
    w.string(m.method)
    w.pack('ffIB', 4, m.sigma, m.min_strength, m.roi_half_height, m.orientation)
    w.pack('Iff', 4, m.rejected_secondary, m.saturated_fraction, m.peak_level)
    return w.bytes()


#: sensor_msgs/PointField datatype of each numpy field type.
POINT_FIELD_TYPES = {np.dtype('<i1'): 1, np.dtype('<u1'): 2, np.dtype('<i2'): 3,
                     np.dtype('<u2'): 4, np.dtype('<i4'): 5, np.dtype('<u4'): 6,
                     np.dtype('<f4'): 7, np.dtype('<f8'): 8}


_FIELD_BLOCKS: dict[np.dtype, bytes] = {}


def _fields_block(dt: np.dtype) -> bytes:
    """The ``fields`` sequence of a PointCloud2 for ``dt``, written from a 4-byte boundary."""
    block = _FIELD_BLOCKS.get(dt)
    if block is None:
        if dt.names is None:
            raise ValueError('points must be a structured array')
        w = Writer()
        w.pack('I', 4, len(dt.names))
        for name in dt.names:
            ftype, offset = dt.fields[name][:2]
            if ftype not in POINT_FIELD_TYPES:
                raise ValueError(f'field {name}: {ftype} is not a little-endian PointField type')
            w.string(name)
            w.pack('I', 4, offset)
            w.pack('B', 1, POINT_FIELD_TYPES[ftype])
            w.pack('I', 4, 1)
        block = _FIELD_BLOCKS[dt] = w.bytes()[4:]
    return block


def serialize_point_cloud(points, header: Header, is_dense: bool = True) -> bytes:
    """An unorganised sensor_msgs/PointCloud2 (height 1) holding a structured array.

    ``points`` is one structured array, or a sequence of them with one dtype (the parts of
    an accumulated scan, written one after the other without being concatenated first).
    Every field of the dtype becomes a PointField (count 1) at its offset; fields must be
    little-endian scalars of a PointField type. Written in one join, the points copied
    once (a frame's cloud is published at up to 1 kHz, a scan's can hold millions).
    """
    parts = [points] if isinstance(points, np.ndarray) else list(points)
    if not parts:
        raise ValueError('points: an empty sequence has no dtype; pass an empty array')
    dt = parts[0].dtype
    if any(p.dtype != dt or p.ndim != 1 for p in parts):
        raise ValueError('points: every part must be 1-D with the same dtype')
    fields = _fields_block(dt)
    frame_id = header.frame_id.encode('utf-8')
    head = _struct('<4siII').pack(CDR_LE + b'\x00\x00', header.sec, header.nanosec,
                                  len(frame_id) + 1)
    pad = -(len(head) + len(frame_id) + 1 - 4) % 4
    n, step = sum(p.shape[0] for p in parts), dt.itemsize
    # after the fields (from a 4-byte boundary): is_bigendian, padding, three uint32
    tail_pad = -(len(fields) + 1) % 4
    return b''.join((head, frame_id, bytes(1 + pad), _struct('<II').pack(1, n), fields,
                     bytes(1 + tail_pad), _struct('<III').pack(step, step * n, step * n),
                     *(np.ascontiguousarray(p) for p in parts),
                     b'\x01' if is_dense else b'\x00'))


# ---- sensor_msgs/Image --------------------------------------------------------------------
#: sensor_msgs/Image encoding written for each image dtype (:func:`serialize_image`).
IMAGE_ENCODINGS = {np.dtype(np.uint8): 'mono8', np.dtype(np.uint16): 'mono16'}
#: Encodings :func:`image_to_array` reads, and their element type.
IMAGE_DTYPES = {'mono8': np.uint8, '8UC1': np.uint8, 'mono16': np.uint16, '16UC1': np.uint16}
#: Why an image cannot be read (:attr:`BadImageError.cause`; the extractor node counts each).
BAD_IMAGE_CAUSES = ('unsupported_encoding', 'zero_size', 'step_too_small', 'data_length',
                    'too_small', 'malformed_cdr')


#: numpy type code (no byte order) of each sensor_msgs/PointField datatype.
_POINT_FIELD_CODES = {code: dt.str[1:] for dt, code in POINT_FIELD_TYPES.items()}


def parse_point_cloud(data) -> tuple[Header, np.ndarray]:
    """A serialised sensor_msgs/PointCloud2 as its header and a structured array of points.

    Each PointField becomes a field of the array's dtype at its offset (a sub-array when its
    ``count`` > 1), in the cloud's byte order; the array is a read-only view of ``data``
    (a copy when rows are padded), of shape (height * width,).

    Raises
    ------
    CdrError
        Not a well-formed PointCloud2, or fields / sizes that do not describe its data.
    """
    r = Reader(data)
    header = read_header(r)
    height, width = r.unpack('II', 4, 'height and width')
    fields = []
    for i in range(r.u32('fields')):
        name = r.string(f'fields[{i}].name')
        offset = r.u32(f'fields[{i}].offset')
        code = _POINT_FIELD_CODES.get(r.u8(f'fields[{i}].datatype'))
        count = r.u32(f'fields[{i}].count')
        if code is None or count == 0:
            raise CdrError(f'fields[{i}] ({name}): bad datatype or count {count}')
        fields.append((name, code, offset, count))
    big = r.u8('is_bigendian')
    point_step, row_step = r.unpack('II', 4, 'point_step and row_step')
    raw = r.octets('data')
    r.u8('is_dense')
    r.done('PointCloud2')
    order = '>' if big else '<'
    try:
        dtype = np.dtype({'names': [f[0] for f in fields],
                          'formats': [(order + f[1], (f[3],)) if f[3] > 1 else order + f[1]
                                      for f in fields],
                          'offsets': [f[2] for f in fields], 'itemsize': point_step})
    except (ValueError, TypeError) as exc:
        raise CdrError(f'PointCloud2 fields do not fit point_step {point_step}: {exc}') \
            from None
    if row_step < width * point_step or len(raw) != row_step * height:
        raise CdrError(f'PointCloud2: {len(raw)} data bytes for {height} rows of '
                           f'row_step {row_step}, width {width} x point_step {point_step}')
    if row_step == width * point_step:
        return header, np.frombuffer(raw, dtype, count=width * height)
    rows = np.frombuffer(raw, np.uint8).reshape(height, row_step)[:, :width * point_step]
    return header, np.ascontiguousarray(rows).view(dtype).reshape(-1)


class BadImageError(ValueError):
    """The message cannot be read as an image; ``cause`` is one of :data:`BAD_IMAGE_CAUSES`."""

    def __init__(self, cause: str, detail: str):
        assert cause in BAD_IMAGE_CAUSES
        self.cause = cause
        super().__init__(f'{cause}: {detail}')


@dataclass(frozen=True)
class RawImage:
    """The fields of a sensor_msgs/Image read from CDR; ``data`` is a view of the buffer."""

    stamp_sec: int
    stamp_nanosec: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview

    @property
    def stamp_ns(self) -> int:
        """Header stamp [ns]."""
        return self.stamp_sec * 1_000_000_000 + self.stamp_nanosec


def parse_image_cdr(data) -> RawImage:
    """Read a serialised sensor_msgs/Image (CDR, as a raw subscription delivers it).

    Reading the bytes in place skips building the rclpy message and copying its pixels
    (389 kB at 720x540 mono8) into an ``array.array``.

    Parameters
    ----------
    data : bytes-like
        The CDR bytes including the 4-byte encapsulation header; not copied: the returned
        ``data`` field is a view into it.

    Raises
    ------
    BadImageError
        Cause ``malformed_cdr``: unknown encapsulation, truncated message, bad string.
        The image fields themselves are checked by :func:`image_to_array`.
    """
    try:
        r = Reader(data)
        header = read_header(r)
        fields = (r.u32('height'), r.u32('width'), r.string('encoding'),
                  r.u8('is_bigendian'), r.u32('step'), r.octets('data'))
    except CdrError as exc:
        raise BadImageError('malformed_cdr', str(exc)) from None
    return RawImage(header.sec, header.nanosec, header.frame_id, *fields)


def image_to_array(msg) -> np.ndarray:
    """The image as an array of shape (height, width), uint8 or uint16, a view of its data.

    ``msg`` is any object with ``height``, ``width``, ``encoding``, ``is_bigendian``, ``step``
    and ``data``: an rclpy sensor_msgs/Image, or the :class:`RawImage` of
    :func:`parse_image_cdr`. The data are read with ``np.frombuffer`` (no copy); row padding
    (``step`` > width * bytes per pixel) is skipped and ``is_bigendian`` gives the byte
    order of the returned dtype.

    Raises
    ------
    BadImageError
        Unsupported encoding, zero size, step < width * bytes per pixel, data length !=
        step * height, or smaller than 3x3 px.
    """
    dtype = IMAGE_DTYPES.get(msg.encoding)
    if dtype is None:
        raise BadImageError('unsupported_encoding',
                            f'encoding {msg.encoding!r} (supported: {", ".join(IMAGE_DTYPES)})')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise BadImageError('zero_size', f'{w}x{h} px')
    bpp = np.dtype(dtype).itemsize
    if step < w * bpp:
        raise BadImageError('step_too_small', f'step {step} < width {w} x {bpp} bytes')
    n = len(msg.data)
    if n != step * h:
        raise BadImageError('data_length', f'{n} bytes != step {step} x height {h}')
    if h < 3 or w < 3:
        raise BadImageError('too_small', f'{w}x{h} px (at least 3x3 needed)')
    raw = np.frombuffer(msg.data, np.uint8).reshape(h, step)
    if step != w * bpp:
        raw = raw[:, :w * bpp]
    big = bool(msg.is_bigendian)
    arr = raw.view(np.dtype(dtype).newbyteorder('>' if big else '<')) if bpp > 1 else raw
    return arr


def serialize_image(image: np.ndarray, header: Header) -> bytes:
    """A mono8 / mono16 sensor_msgs/Image of a 2-D uint8 / uint16 array, pixels copied once.

    ``is_bigendian`` and the pixel bytes follow the array's byte order; ``step`` is the row
    length in bytes (rows are written without padding).
    """
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise ValueError('image must be a 2-D numpy array')
    encoding = IMAGE_ENCODINGS.get(image.dtype.newbyteorder('='))
    if encoding is None:
        raise ValueError(f'image dtype must be uint8 or uint16, got {image.dtype}')
    order = image.dtype.byteorder
    big = order == '>' or (order == '=' and not np.little_endian)
    h, w = image.shape
    step = w * image.dtype.itemsize
    frame_id = header.frame_id.encode('utf-8')
    enc = encoding.encode()
    head = _struct('<4siII').pack(CDR_LE + b'\x00\x00', header.sec, header.nanosec,
                                  len(frame_id) + 1)
    pad = -(len(frame_id) + 1) % 4     # head ends on a 4-byte boundary (counted after 4)
    return b''.join((head, frame_id, bytes(1 + pad), _struct('<III').pack(h, w, len(enc) + 1),
                     # encoding and its NUL, is_bigendian, padding to step's 4-byte boundary
                     enc, b'\x00', b'\x01' if big else b'\x00', bytes(-(len(enc) + 2) % 4),
                     _struct('<II').pack(step, step * h), np.ascontiguousarray(image)))
