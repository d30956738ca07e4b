"""The Gaussian-smoothed column profile that both extractors start from (numba, inlined).

No rclpy here. The stripe runs along the rows (the caller transposes otherwise); for each
column ``c`` the candidate row ``p`` of :mod:`.candidates` opens a region of interest
(:func:`roi_rows`: rows ``max(p - R, K + 1) .. min(p + R, H - 2 - K)``, ``R =
roi_half_height``, ``K`` the half length of the Gaussian ``g0``, so that the smoothing never
leaves the image). In it:

- :func:`roi_profile_peak` climbs the column profile smoothed by ``g0`` from ``p`` to its
  maximum, the pixel ``r0``; the smaller of its values at the two ROI ends is the
  background;
- :func:`is_secondary` says whether the column's secondary candidate is a peak of its own.

Every function is inlined into the calling kernel (``inline='always'``), so it is compiled
with that kernel's options (e.g. ``fastmath``) and costs no call.
"""

from __future__ import annotations

import numba
import numpy as np

from .candidates import box3


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def smooth_column(img, r, c, K, g0):
    """Column profile at (r, c) smoothed by the 1-D Gaussian g0 (rows r-K..r+K must exist)."""
    s = g0[0] * img[r, c]
    for k in range(1, K + 1):
        s += g0[k] * (np.float32(img[r + k, c]) + np.float32(img[r - k, c]))
    return s


@numba.njit(cache=True, nogil=True, inline='always')
def roi_rows(p, R, K, H):
    """Rows ``a .. b`` of the region of interest around candidate row p (empty if b < a).

    ``a = max(p - R, K + 1)``, ``b = min(p + R, H - 2 - K)``: at most R rows either side of
    p, and far enough from the top/bottom border (image height H) for the smoothing.
    """
    return max(p - R, K + 1), min(p + R, H - 2 - K)


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def roi_profile_peak(img, c, p, a, b, K, g0):
    """Peak of the Gaussian-smoothed profile of column c inside the ROI rows a..b.

    Climbs the smoothed profile from the candidate row p (clamped to a..b) to its local
    maximum. Returns (row of the maximum, smoothed value there, background), the background
    being the smaller of the smoothed values at the ROI ends a and b [DN].
    """
    r0 = min(max(p, a), b)
    best = smooth_column(img, r0, c, K, g0)
    step = 0
    if r0 < b:
        nxt = smooth_column(img, r0 + 1, c, K, g0)
        if nxt > best:
            best = nxt
            r0 += 1
            step = 1
    if step == 0 and r0 > a:
        prv = smooth_column(img, r0 - 1, c, K, g0)
        if prv > best:
            best = prv
            r0 -= 1
            step = -1
    if step != 0:
        while a <= r0 + step <= b:
            nxt = smooth_column(img, r0 + step, c, K, g0)
            if nxt <= best:
                break
            best = nxt
            r0 += step
    bg = min(smooth_column(img, a, c, K, g0), smooth_column(img, b, c, K, g0))
    return r0, best, bg


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def smooth_at(img, r, c, K, g0):
    """2-D Gaussian-smoothed value at pixel (r, c); indices clamped at the image borders."""
    H, W = img.shape
    s = np.float32(0.0)
    for j in range(-K, K + 1):
        rr = min(max(r + j, 0), H - 1)
        h = np.float32(0.0)
        for k in range(-K, K + 1):
            cc = min(max(c + k, 0), W - 1)
            h += g0[abs(k)] * img[rr, cc]
        s += g0[abs(j)] * h
    return s


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def is_secondary(img, q, c, K, g0, bg, min_strength):
    """True if row q (-1: none) of column c holds a peak of strength >= min_strength.

    The 3x3 box mean, which attenuates a peak less than the Gaussian, screens first so the
    (2K+1)^2 smoothing runs only for plausible peaks.
    """
    if q < 0:
        return False
    if box3(img, q, c) / 9.0 - bg < 0.5 * min_strength:
        return False
    return smooth_at(img, q, c, K, g0) - bg >= min_strength
