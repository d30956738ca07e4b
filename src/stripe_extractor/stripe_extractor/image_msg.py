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

from dataclasses import dataclass

import numpy as np

from galvoscan_common.cdr import CdrError, Reader, read_header

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
    try:
        r = Reader(data)
        header = read_header(r)
        fields = (r.u32('height'), r.u32('width'), r.string('encoding'),
                  r.u8('is_bigendian'), r.u32('step'), r.octets('data'))
    except CdrError as exc:
        raise BadImageError('malformed_cdr', str(exc)) from None
    return RawImage(header.sec, header.nanosec, header.frame_id, *fields)
