"""Exposure that suits the part: frame levels, auto exposure from a pre-scan, HDR merge.

No rclpy here. A dark part (black anodised) returns a few percent of the light and its
stripe sinks below ``min_strength``; a shiny one saturates it (a flat-topped profile whose
centre Steger still finds, but whose width and strength lie). The driver measures the
stripe's level on a few pre-scan frames and scales the exposure (:func:`auto_exposure`);
HDR takes two exposures at each position and keeps, per column, the longer one's centre
unless its peak is clipped (:func:`merge_hdr`).
"""

from __future__ import annotations

import numpy as np

from .config import white_level
from .extractor import StripeResult

#: The stripe peak that auto exposure aims at, as a share of full scale: headroom for
#: speckle (contrast ~0.1-0.3) above the mean peak, and well above min_strength.
TARGET_PEAK = 0.7
#: Percentile of the columns' peaks that auto exposure sets to the target: the median
#: column, so that a glint or a reflection's bright glow in a few columns does not keep
#: the rest of the stripe dark.
PEAK_PERCENTILE = 50.0
#: A pre-scan frame counts as clipped when more than this share of its columns are: a
#: glint (the specular corner of a shiny part) may clip a few columns and still leave the
#: rest of the stripe well exposed.
CLIPPED_SHARE = 0.1
#: Share of the frame period an exposure may take (the rest: the sensor's transfer and
#: the trigger's jitter).
MAX_EXPOSURE_SHARE = 0.9


def exposure_limits(frame_rate: float, shortest: float,
                    longest: float = float('inf')) -> tuple[float, float]:
    """(shortest, longest) exposure [s] a camera allows at ``frame_rate`` [Hz].

    ``shortest`` and ``longest`` are the camera's own bounds [s] (its GenICam ExposureTime
    minimum and maximum); the longest is further held to :data:`MAX_EXPOSURE_SHARE` of the
    frame period, and never below the shortest.
    """
    if not (frame_rate > 0 and 0 < shortest <= longest):
        raise ValueError(f'exposure_limits: frame rate {frame_rate} Hz, bounds '
                         f'[{shortest}, {longest}] s')
    return float(shortest), float(max(shortest, min(longest, MAX_EXPOSURE_SHARE / frame_rate)))


def on_increment(exposure: float, shortest: float, increment: float) -> float:
    """``exposure`` [s] moved down onto the camera's grid ``shortest + k * increment``
    (``increment`` 0: no grid), never below ``shortest``."""
    if increment <= 0 or exposure <= shortest:
        return float(max(exposure, shortest))
    k = np.floor((exposure - shortest) / increment + 1e-9)
    return float(shortest + k * increment)


def frame_levels(image: np.ndarray, white: int | None = None,
                 vertical: bool = False) -> tuple[float, float]:
    """(saturated fraction, peak level) of one frame.

    The saturated fraction is the share of columns whose brightest pixel is at the white
    level; the peak level the :data:`PEAK_PERCENTILE` percentile of the columns' brightest
    pixels over the white level [1] (a horizontal stripe: one peak per column; a stripe
    across the whole image). Rows instead of columns if ``vertical``.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16
    white : int, optional
        The image's top code [DN]; default :func:`.config.white_level` of the image (state
        it when the camera's bit depth is known: a 12-bit frame in uint16 then clips at 4095).
    vertical : bool
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or img.size == 0:
        raise ValueError('image: expected a non-empty 2-D uint8 or uint16 array')
    top = white_level(img) if white is None else int(white)
    if top < 1:
        raise ValueError(f'white: expected a top code >= 1 DN, got {white}')
    peaks = img.max(axis=1 if vertical else 0)
    return (float(np.mean(peaks >= top)),
            float(np.percentile(peaks, PEAK_PERCENTILE)) / top)


def auto_exposure(images, exposure: float, limits: tuple[float, float],
                  target: float = TARGET_PEAK, background: float = 0.0,
                  white: int | None = None) -> float:
    """The exposure [s] that puts the pre-scan frames' stripe peak at ``target``.

    The signal is proportional to the exposure (the sensor is linear below full well);
    a frame with more than :data:`CLIPPED_SHARE` of its columns clipped gives only a lower
    bound on its level, so the exposure falls by at least half (the driver repeats the
    pre-scan once when it was clipped).

    Parameters
    ----------
    images : sequence of ndarray (H, W), uint8/uint16
        Pre-scan frames taken at ``exposure``.
    exposure : float
        [s], > 0.
    limits : (float, float)
        Shortest and longest exposure the camera allows within the frame period [s].
    target : float
        Peak level aimed at, share of full scale, in (0, 1).
    background : float
        Dark level (black level plus room light) as a share of full scale, subtracted.
    white : int, optional
        The frames' top code [DN] (:func:`frame_levels`).

    Returns
    -------
    float
        [s], within ``limits``.
    """
    lo, hi = (float(x) for x in limits)
    if not (exposure > 0 and 0 < lo <= hi and 0 < target < 1 and 0 <= background < target):
        raise ValueError(f'auto_exposure: exposure {exposure}, limits {limits}, target '
                         f'{target}, background {background}')
    levels = [frame_levels(im, white) for im in images]
    if not levels:
        raise ValueError('auto_exposure: no pre-scan frames')
    sat = max(s for s, _ in levels)
    peak = max(p for _, p in levels)
    if sat > CLIPPED_SHARE:
        new = exposure * min(0.5, target / max(peak, 1e-6))
    elif peak - background <= 1e-3:
        new = hi
    else:
        new = exposure * (target - background) / (peak - background)
    return float(min(max(new, lo), hi))


def merge_hdr(long: StripeResult, short: StripeResult, long_image: np.ndarray) -> tuple:
    """One stripe from two exposures of the same position.

    Per column (row, if vertical) the long exposure's centre is kept unless the long image
    is clipped within its stripe (a pixel at full scale within the half width plus one
    pixel); the short exposure's centre is used there, and where the long one has none.

    Returns
    -------
    (u, v, width, strength, from_short)
        Arrays (n,) float32 sorted along the stripe, and the count taken from the short
        exposure.
    """
    img = np.asarray(long_image)
    vertical = long.config.orientation == 'vertical'
    if vertical:
        img = img.T
    top = long.white_level
    along_l, across_l = (long.v, long.u) if vertical else (long.u, long.v)
    along_s = short.v if vertical else short.u
    keys_l = np.rint(along_l).astype(np.int64)
    keys_s = np.rint(along_s).astype(np.int64)
    clipped = np.zeros(len(keys_l), bool)
    H = img.shape[0]
    for i, (c, r, w) in enumerate(zip(keys_l, across_l, long.width, strict=True)):
        h = int(np.ceil(0.5 * w)) + 1
        r0 = int(np.rint(r))
        col = img[max(r0 - h, 0):min(r0 + h + 1, H), min(max(c, 0), img.shape[1] - 1)]
        clipped[i] = col.size > 0 and col.max() >= top
    keep_l = ~clipped
    take_s = ~np.isin(keys_s, keys_l[keep_l])
    fields = []
    for name in ('u', 'v', 'width', 'strength'):
        fields.append(np.concatenate((getattr(long, name)[keep_l],
                                      getattr(short, name)[take_s])).astype(np.float32))
    along = fields[1] if vertical else fields[0]
    order = np.argsort(along, kind='stable')
    return (*(f[order] for f in fields), int(np.sum(take_s)))
