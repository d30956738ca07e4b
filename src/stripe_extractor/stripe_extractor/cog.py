"""Centre-of-gravity stripe centres: the simple baseline, sharing Steger's ROI and candidates.

No rclpy here. Per column: candidate row and region of interest as in :mod:`.steger`; the
Gaussian-smoothed column profile (:func:`.profile.roi_profile_peak`) gives the integer peak
``r0``, the background ``bg`` (the smaller of its two ROI-end values) and the strength (its
maximum minus ``bg``). The centre is the intensity-weighted mean row of the raw pixels
``r0 - h .. r0 + h`` with weights ``max(I - bg, 0)``, ``h = max(2, ceil(line_width_px))``;
the width is 2.3548 times the weighted standard deviation. ``u`` is the integer column.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .candidates import column_peaks
from .config import FWHM_PER_SIGMA
from .profile import is_secondary, roi_profile_peak, roi_rows
from .selection import select_peaks


def cog_half_window(line_width_px: float) -> int:
    """Half window ``h = max(2, ceil(line_width_px))`` of the weighted mean [px]."""
    return max(2, int(math.ceil(line_width_px)))


@numba.njit(cache=True, nogil=True)
def cog_columns(img, R, kern, h, min_strength, out, mode, expected, ratio, counts):
    """Centre of gravity of every column; arguments as :func:`.steger.steger_columns`, but
    the half window ``h`` [px] (:func:`cog_half_window`) in place of ``sigma``.

    Returns (n, rejected_secondary).
    """
    H, W = img.shape
    g0 = kern[0]
    K = kern.shape[1] - 1
    cand = np.empty(W, np.int32)
    sec = np.empty(W, np.int32)
    column_peaks(img, R, cand, sec)
    select_peaks(img, R, K, g0, min_strength, cand, sec, mode, expected, ratio, counts)
    n = 0
    nsec = 0
    for c in range(W):
        if cand[c] < 0:
            continue
        a, b = roi_rows(cand[c], R, K, H)
        if b < a:
            continue
        r0, peak, bg = roi_profile_peak(img, c, cand[c], a, b, K, g0)
        strength = peak - bg
        if strength < min_strength:
            continue
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for r in range(max(r0 - h, 0), min(r0 + h, H - 1) + 1):
            wgt = np.float64(img[r, c]) - bg
            if wgt > 0.0:
                d = r - r0
                s0 += wgt
                s1 += wgt * d
                s2 += wgt * d * d
        if s0 <= 0.0:
            continue
        mean = s1 / s0
        var = max(s2 / s0 - mean * mean, 0.0)
        out[0, n] = c
        out[1, n] = r0 + mean
        out[2, n] = FWHM_PER_SIGMA * math.sqrt(var)
        out[3, n] = strength
        n += 1
        if is_secondary(img, sec[c], c, K, g0, bg, min_strength):
            nsec += 1
    return n, nsec

