"""Decode a sensor_msgs/Image-like object into a 2-D numpy view, or say why not.

No rclpy here: any object with ``height``, ``width``, ``encoding``, ``is_bigendian``,
``step`` and ``data`` works. The data are read with ``np.frombuffer`` (no copy for
unpadded little-endian images); row padding (``step`` > width * bytes per pixel) is
respected.
"""

from __future__ import annotations

import numpy as np

#: Supported encodings and their element type.
ENCODINGS = {'mono8': np.uint8, '8UC1': np.uint8, 'mono16': np.uint16, '16UC1': np.uint16}

#: Why an image was skipped (the node counts each cause).
CAUSES = ('unsupported_encoding', 'zero_size', 'step_too_small', 'data_length', 'too_small')


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
