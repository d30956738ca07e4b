"""The stripe's full width at half maximum, measured in the image around centres found.

No rclpy, no numba here. The extractors' own ``width`` is read through their filter and
window: a stripe much wider than the filter's window is measured short there. This measure
averages the columns' profiles, aligned on their centres, and walks the mean from its top
down to half its height above the background on both sides, so it holds for any width up to
a quarter of the probe (:data:`PROBE_HALF_PX`). :func:`.extractor.extract` uses it to match
the filter to the stripe (``ExtractorConfig.adapt_line_width``).
"""

from __future__ import annotations

import math

import numpy as np

from .config import FWHM_PER_SIGMA

#: Half length of the column searched for the half-maximum crossings and the background
#: [px]: twice the widest stripe a configuration accepts (``LINE_WIDTH_RANGE_PX``, 30 px).
PROBE_HALF_PX = 60
#: Columns sampled (evenly over the centres) [1]: their mean profile is smooth under speckle
#: (contrast 0.5), at a cost far below one extraction pass.
SAMPLES = 96
#: Centres in the running median that the profiles are aligned on [1] (odd).
TRACK_CENTRES = 31
#: Gaussian sigma of the mean profile's smoothing [px]: it takes the remaining noise off the
#: half-maximum crossings; its FWHM is subtracted in quadrature.
SMOOTH_SIGMA_PX = 1.0
#: The background is this percentile of the mean profile [%]: the stripe covers under half
#: of the probe (its FWHM at most a quarter of it).
BACKGROUND_PERCENTILE = 10.0


def _kernel(sigma: float) -> np.ndarray:
    k = np.arange(-math.ceil(3 * sigma), math.ceil(3 * sigma) + 1, dtype=np.float64)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    return g / g.sum()


def _crossing(prof: np.ndarray, i0: int, half: float, step: int) -> float | None:
    """Sub-pixel index where ``prof`` first falls below ``half`` walking from ``i0`` by
    ``step`` (+1 or -1), or None if it does not within the probe."""
    i = i0
    while 0 <= i + step < prof.size:
        j = i + step
        if prof[j] < half:
            return i + step * (prof[i] - half) / (prof[i] - prof[j])
        i = j
    return None


def measure_fwhm(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[float, int]:
    """FWHM [px] of the stripe's mean profile across its run, and the columns averaged.

    :data:`SAMPLES` columns, evenly over the centres, are averaged with their profiles
    shifted so that their rows coincide (linear interpolation at the sub-pixel row). The
    row each is aligned on is the running median of :data:`TRACK_CENTRES` centres around it:
    a filter far narrower than the stripe leaves speckle in each centre, and profiles aligned
    on those would share a spike (their speckle peaks) and look narrow; the median keeps a
    step's two levels. The mean profile is walked from its top down to half its height above
    the background.

    Parameters
    ----------
    img : ndarray, shape (H, W)
        The image with the stripe along its rows (a vertical stripe's image transposed).
    u, v : ndarray, shape (n,), px
        Centres found in it: column and row.

    Returns
    -------
    fwhm_px : float
        NaN when no column's probe fits in the image or the mean profile has no two
        half-maximum crossings.
    columns : int
        Columns averaged.
    """
    n = len(u)
    H, W = img.shape
    if n == 0:
        return float('nan'), 0
    order = np.argsort(np.asarray(u), kind='stable')
    us = np.asarray(u, np.float64)[order]
    vs = np.asarray(v, np.float64)[order]
    pick = np.unique(np.linspace(0, n - 1, min(SAMPLES, n)).round().astype(np.int64))
    h = min(TRACK_CENTRES // 2, (n - 1) // 2)
    near = np.clip(pick[:, None] + np.arange(-h, h + 1), 0, n - 1)
    rows = np.median(vs[near], axis=1)
    cols = np.rint(us[pick]).astype(np.int64)
    keep = ((rows - PROBE_HALF_PX >= 0) & (rows + PROBE_HALF_PX + 1 <= H - 1)
            & (cols >= 0) & (cols < W))
    if not np.any(keep):  # every probe would leave the image: the background unknown
        return float('nan'), 0
    rows, cols = rows[keep], cols[keep]
    at = rows[:, None] + np.arange(-PROBE_HALF_PX, PROBE_HALF_PX + 1)  # (S, 2P+1) rows
    lo = np.floor(at).astype(np.int64)
    frac = at - lo
    c = cols[:, None]
    samples = (1.0 - frac) * img[lo, c] + frac * img[lo + 1, c]
    g = _kernel(SMOOTH_SIGMA_PX)
    pad = g.size // 2  # past it, 'same' has smoothed in zeros
    prof = np.convolve(samples.mean(axis=0), g, mode='same')[pad:-pad]
    i0 = PROBE_HALF_PX - pad
    top = i0 - 1 + int(np.argmax(prof[i0 - 1:i0 + 2]))
    bg = float(np.percentile(prof, BACKGROUND_PERCENTILE))
    if prof[top] <= bg:
        return float('nan'), 0
    half = bg + 0.5 * (prof[top] - bg)
    up, down = _crossing(prof, top, half, +1), _crossing(prof, top, half, -1)
    if up is None or down is None:
        return float('nan'), 0
    blur = FWHM_PER_SIGMA * SMOOTH_SIGMA_PX
    return math.sqrt(max((up - down) ** 2 - blur ** 2, 0.25)), int(rows.size)


def stripe_fwhm(image: np.ndarray, result) -> float:
    """FWHM [px] of the stripe of an :class:`.extractor.StripeResult` in its ``image``
    (either orientation), by :func:`measure_fwhm`; NaN when it cannot be measured."""
    if result.config.orientation == 'vertical':
        return measure_fwhm(np.asarray(image).T, result.v, result.u)[0]
    return measure_fwhm(np.asarray(image), result.u, result.v)[0]
