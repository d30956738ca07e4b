"""Decode a sensor_msgs/Image into a 2-D numpy view, or say why not.

No rclpy here. :func:`image_to_array` takes any object with ``height``, ``width``,
``encoding``, ``is_bigendian``, ``step`` and ``data``: an rclpy message, or the
:class:`RawImage` that :func:`parse_image_cdr` reads straight from the serialised CDR bytes
of a raw subscription (which skips building the rclpy message and copying its 389 kB of
pixels into an ``array.array``). The data are read with ``np.frombuffer`` (no copy for
unpadded little-endian images); row padding (``step`` > width * bytes per pixel) is
respected.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

#: Supported encodings and their element type.
ENCODINGS = {'mono8': np.uint8, '8UC1': np.uint8, 'mono16': np.uint16, '16UC1': np.uint16}

#: Why an image was skipped (the node counts each cause).
CAUSES = ('unsupported_encoding', 'zero_size', 'step_too_small', 'data_length', 'too_small',
          'malformed_cdr')


class BadImageError(ValueError):
    """The message cannot be read as an image; ``cause`` is one of :data:`CAUSES`."""

    def __init__(self, cause: str, detail: str):
        assert cause in CAUSES
        self.cause = cause
        super().__init__(f'{cause}: {detail}')


def image_to_array(msg) -> np.ndarray:
    """The image as an array of shape (height, width), uint8 or uint16 (native order).

    Raises
    ------
    BadImageError
        Unsupported encoding, zero size, step < width * bytes per pixel, data length !=
        step * height, or smaller than 3x3 px.
    """
    dtype = ENCODINGS.get(msg.encoding)
    if dtype is None:
        raise BadImageError('unsupported_encoding',
                       f'encoding {msg.encoding!r} (supported: {", ".join(ENCODINGS)})')
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


#: CDR encapsulation identifiers (plain CDR, as ROS 2 writes it): big and little endian.
_CDR_BE, _CDR_LE = b'\x00\x00', b'\x00\x01'
#: (uint32, int32) unpackers for little- and big-endian CDR.
_LE = (struct.Struct('<I'), struct.Struct('<i'))
_BE = (struct.Struct('>I'), struct.Struct('>i'))
#: Longest header.frame_id / encoding string accepted [bytes].
MAX_STRING_BYTES = 4096


class _Reader:
    """Sequential CDR reader; alignment is relative to the end of the 4-byte encapsulation."""

    def __init__(self, buf: memoryview, little: bool):
        self.buf, self.pos, self.end = buf, 4, len(buf)
        self.u32, self.i32 = _LE if little else _BE

    def _take(self, n: int, what: str) -> int:
        start = self.pos
        if n < 0 or start + n > self.end:
            raise BadImageError('malformed_cdr', f'{what}: needs {n} bytes at offset {start}, '
                                                 f'message has {self.end}')
        self.pos = start + n
        return start

    def _align4(self) -> None:
        self.pos += -(self.pos - 4) % 4

    def uint32(self, what: str) -> int:
        self._align4()
        return self.u32.unpack_from(self.buf, self._take(4, what))[0]

    def int32(self, what: str) -> int:
        self._align4()
        return self.i32.unpack_from(self.buf, self._take(4, what))[0]

    def uint8(self, what: str) -> int:
        return self.buf[self._take(1, what)]

    def string(self, what: str) -> str:
        n = self.uint32(what)
        if n == 0 or n > MAX_STRING_BYTES + 1:
            raise BadImageError('malformed_cdr', f'{what}: string length {n} (1..'
                                                 f'{MAX_STRING_BYTES + 1} with the NUL)')
        start = self._take(n, what)
        raw = bytes(self.buf[start:start + n])
        if raw[-1] != 0:
            raise BadImageError('malformed_cdr', f'{what}: string not NUL-terminated')
        try:
            return raw[:-1].decode('utf-8')
        except UnicodeDecodeError as exc:
            raise BadImageError('malformed_cdr', f'{what}: not UTF-8 ({exc})') from None

    def octets(self, what: str) -> memoryview:
        n = self.uint32(what)
        start = self._take(n, what)
        return self.buf[start:start + n]


def parse_image_cdr(data) -> RawImage:
    """Read a serialised sensor_msgs/Image (CDR, as a raw subscription delivers it).

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
    buf = memoryview(data).cast('B')
    if len(buf) < 4 or bytes(buf[:2]) not in (_CDR_BE, _CDR_LE):
        raise BadImageError('malformed_cdr', 'no plain-CDR encapsulation header '
                                             f'(first bytes {bytes(buf[:4]).hex() or "none"})')
    r = _Reader(buf, little=bytes(buf[:2]) == _CDR_LE)
    sec = r.int32('header.stamp.sec')
    nanosec = r.uint32('header.stamp.nanosec')
    if nanosec >= 1_000_000_000:
        raise BadImageError('malformed_cdr', f'header.stamp.nanosec {nanosec} >= 1e9')
    frame_id = r.string('header.frame_id')
    height = r.uint32('height')
    width = r.uint32('width')
    encoding = r.string('encoding')
    is_bigendian = r.uint8('is_bigendian')
    step = r.uint32('step')
    pixels = r.octets('data')
    return RawImage(sec, nanosec, frame_id, height, width, encoding, is_bigendian, step,
                    pixels)
