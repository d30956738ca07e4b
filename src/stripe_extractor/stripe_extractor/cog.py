"""Centre-of-gravity stripe centres: the simple baseline, sharing Steger's ROI and candidates.

No rclpy here. Per column: candidate row and region of interest as in :mod:`.steger`; the
Gaussian-smoothed column profile gives the integer peak ``r0``, the background ``bg`` (the
smaller of its two ROI-end values) and the strength (its maximum minus ``bg``). The centre is
the intensity-weighted mean row of the raw pixels ``r0 - h .. r0 + h`` with weights
``max(I - bg, 0)``, ``h = max(2, ceil(line_width_px))``; the width is 2.3548 times the
weighted standard deviation. ``u`` is the integer column.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .candidates import column_peaks
from .extractor import FWHM_PER_SIGMA, ExtractorConfig, stacked_kernels
from .steger import is_secondary, roi_profile_peak


@numba.njit(cache=True, nogil=True)
def cog_columns(img, R, kern, h, min_strength, out):
    """Centre of gravity of every column; arguments as :func:`.steger.steger_columns`, plus
    the half window ``h`` [px]. Returns (n, rejected_secondary)."""
    H, W = img.shape
    g0 = kern[0]
    K = kern.shape[1] - 1
    cand = np.empty(W, np.int32)
    sec = np.empty(W, np.int32)
    column_peaks(img, R, cand, sec)
    n = 0
    nsec = 0
    for c in range(W):
        p = cand[c]
        a = max(p - R, K + 1)
        b = min(p + R, H - 2 - K)
        if b < a:
            continue
        r0, peak, bg = roi_profile_peak(img, c, p, a, b, K, g0)
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


def extract_columns(img: np.ndarray, config: ExtractorConfig):
    """Centre-of-gravity centres of a C-contiguous uint8/uint16 image, one per column at most.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8 or uint16, DN
    config : ExtractorConfig

    Returns
    -------
    u, v, width, strength : ndarray, shape (n,), float32
    rejected_secondary : int
    """
    h = max(2, int(math.ceil(config.line_width_px)))
    out = np.empty((4, img.shape[1]), np.float32)
    n, nsec = cog_columns(img, config.roi_half_height, stacked_kernels(config.sigma), h,
                          config.min_strength, out)
    return out[0, :n], out[1, :n], out[2, :n], out[3, :n], nsec
