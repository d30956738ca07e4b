"""Steger's sub-pixel line-centre method, evaluated only in a window around each column's peak.

No rclpy here. For each column (stripe mostly horizontal; the caller transposes otherwise):

1. The candidate row ``p`` from :mod:`.candidates` (largest 3x3 box sum of the column).
2. Region of interest: rows ``p - R .. p + R`` of this column, ``R = roi_half_height``. The
   column profile smoothed by the Gaussian ``g_sigma`` is climbed from ``p`` to its maximum,
   the pixel ``r0``; the smaller of its values at the two ROI ends is the background
   (:mod:`.profile`). A column whose smoothed peak is below ``min_strength`` has no stripe.
3. At ``r0`` the Hessian ``H = [[r_uu, r_uv], [r_uv, r_vv]]`` and the gradient ``(r_u, r_v)``
   are computed from separable Gaussian-derivative kernels (scale sigma) on the
   ``(2K+1) x (2K+1)`` pixels around it (K = ceil(3 sigma)). The stripe normal ``n`` is the
   eigenvector of the most negative eigenvalue ``lambda``; the sub-pixel offset along it is
   ``t = -(grad . n) / lambda``. The point ``(c + t n_u, r0 + t n_v)`` is accepted if
   ``|t n_u| <= 0.5`` and ``|t n_v| <= 0.5`` (Steger's condition: the line point lies in this
   pixel); otherwise the neighbouring pixel the offset points to is tried once, and if the
   two estimates straddle the pixel boundary the nearer one is kept.
4. ``strength`` = smoothed value at the sub-pixel point minus background;
   ``width = 2.3548 sqrt(S^2 - sigma^2)`` with ``S^2 = -strength / lambda`` (for a Gaussian
   profile of std s, smoothing gives std S = sqrt(s^2 + sigma^2) and curvature -peak/S^2).
5. The secondary candidate of the column (if any) is smoothed the same way; if its strength
   reaches ``min_strength`` it is rejected and counted.

The 2-D kernels are used only where the stripe is present in every column of the footprint
``c-K .. c+K`` with peak rows that differ by at most ``|dc| + 2``; elsewhere (left/right
image borders, line ends at occlusions, jumps at depth steps) the column profile alone is
used (normal fixed to the column: the one-dimensional case of the same formulae), which is
unbiased there. Rows closer than K + 1 to the top/bottom border give no centre. Work per
column is O(R K + K^2): the full image is never filtered.

Known limit: within about K columns of a sharp corner of the stripe (e.g. a box edge) the
2-D estimate can be off by a few tenths of a pixel.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .candidates import column_peaks
from .config import FWHM_PER_SIGMA
from .profile import is_secondary, roi_profile_peak, roi_rows
from .selection import select_peaks


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _line_point(h0, h1, h2, j0, K, g0, d1, d2):
    """Steger at one pixel from horizontally filtered rows h* (row j0 is the pixel).

    Returns (t*n_u, t*n_v, lambda, smoothed value at the point); lambda >= 0 means no ridge.
    """
    rr = g0[0] * h0[j0]
    rv = np.float32(0.0)
    rvv = d2[0] * h0[j0]
    ru = g0[0] * h1[j0]
    ruv = np.float32(0.0)
    ruu = g0[0] * h2[j0]
    for k in range(1, K + 1):
        s0 = h0[j0 + k] + h0[j0 - k]
        a0 = h0[j0 + k] - h0[j0 - k]
        rr += g0[k] * s0
        rv += d1[k] * a0
        rvv += d2[k] * s0
        ru += g0[k] * (h1[j0 + k] + h1[j0 - k])
        ruv += d1[k] * (h1[j0 + k] - h1[j0 - k])
        ruu += g0[k] * (h2[j0 + k] + h2[j0 - k])
    half = 0.5 * (ruu - rvv)
    root = math.sqrt(half * half + ruv * ruv)
    lam = 0.5 * (ruu + rvv) - root
    if lam >= 0.0:
        return np.float32(0.0), np.float32(0.0), lam, rr
    # Eigenvector of lam: (ruv, lam - ruu) or (lam - rvv, ruv); take the better conditioned.
    ax = ruv
    ay = lam - ruu
    bx = lam - rvv
    by = ruv
    if ax * ax + ay * ay >= bx * bx + by * by:
        nx = ax
        ny = ay
    else:
        nx = bx
        ny = by
    norm = math.sqrt(nx * nx + ny * ny)
    if norm == 0.0:                     # isotropic: normal along the column
        nx = np.float32(0.0)
        ny = 1.0
    else:
        nx /= norm
        ny /= norm
    g = ru * nx + rv * ny
    t = -g / lam
    return t * nx, t * ny, lam, rr + 0.5 * t * g


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _line_point_1d(img, r, c, K, g0, d1, d2):
    """Column-only Steger at pixel (r, c): normal = column direction."""
    rr = g0[0] * img[r, c]
    rv = np.float32(0.0)
    rvv = d2[0] * img[r, c]
    for k in range(1, K + 1):
        p = np.float32(img[r + k, c])
        m = np.float32(img[r - k, c])
        rr += g0[k] * (p + m)
        rv += d1[k] * (p - m)
        rvv += d2[k] * (p + m)
    if rvv >= 0.0:
        return np.float32(0.0), np.float32(0.0), rvv, rr
    t = -rv / rvv
    return np.float32(0.0), t, rvv, rr + np.float32(0.5) * t * rv


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _filter_row(img, r, c, K, g0, d1, d2):
    """Row r around column c correlated with g0, d1 and d2 (columns c-K..c+K must exist)."""
    x0 = np.float32(img[r, c])
    s0 = g0[0] * x0
    s1 = np.float32(0.0)
    s2 = d2[0] * x0
    for k in range(1, K + 1):
        p = np.float32(img[r, c + k])
        m = np.float32(img[r, c - k])
        s0 += g0[k] * (p + m)
        s1 += d1[k] * (p - m)
        s2 += d2[k] * (p + m)
    return s0, s1, s2


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _filter_rows(img, r0, c, K, g0, d1, d2, h0, h1, h2):
    """Rows r0-K .. r0+K around column c filtered by :func:`_filter_row` into slots 1..2K+1.

    Slot j of ``h0``/``h1``/``h2`` (length 2K+3) holds row ``r0 - K - 1 + j``; slots 0 and
    2K+2 are left for a step to a neighbouring row (:func:`_neighbour_line_point`).
    """
    for j in range(1, 2 * K + 2):
        h0[j], h1[j], h2[j] = _filter_row(img, r0 - K - 1 + j, c, K, g0, d1, d2)


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _neighbour_line_point(img, r0, r1, c, full, K, g0, d1, d2, h0, h1, h2):
    """Steger at pixel (r1, c), r1 = r0 +- 1, after :func:`_filter_rows` at r0 if ``full``.

    ``full``: the 2-D estimate, filtering the one row it needs beyond those of r0; else the
    column-only one. Returns (t*n_u, t*n_v, lambda, smoothed value) as :func:`_line_point`.
    """
    if full:
        if r1 > r0:
            h0[2 * K + 2], h1[2 * K + 2], h2[2 * K + 2] = _filter_row(
                img, r0 + K + 1, c, K, g0, d1, d2)
        else:
            h0[0], h1[0], h2[0] = _filter_row(img, r0 - K - 1, c, K, g0, d1, d2)
        return _line_point(h0, h1, h2, r1 - r0 + K + 1, K, g0, d1, d2)
    return _line_point_1d(img, r1, c, K, g0, d1, d2)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _neighbour_point(img, r0, c, full, du, dv, lam, val, K, g0, d1, d2, h0, h1, h2):
    """Steger's point of column c when the estimate (du, dv, lam, val) at its peak row r0
    lies outside pixel (r0, c): tries once the neighbouring row the offset points to.

    The rare path, so not inlined: inlined, it slows the loop of :func:`steger_columns`.

    Returns
    -------
    found : bool
        False if neither pixel holds the line point.
    du, dv : float
        Offset of the point from pixel (r, c) [px].
    lam : float
        Most negative Hessian eigenvalue there [DN/px^2].
    val : float
        Smoothed value at the point [DN].
    r : int
        Row of the pixel the point was found in.
    """
    if abs(dv) <= 0.5:
        return False, du, dv, lam, val, r0
    r1 = r0 + 1 if dv > 0 else r0 - 1
    if r1 < K + 1 or r1 > img.shape[0] - 2 - K:
        return False, du, dv, lam, val, r0
    du1, dv1, lam1, val1 = _neighbour_line_point(img, r0, r1, c, full, K, g0, d1, d2,
                                                 h0, h1, h2)
    if lam1 >= 0.0:
        return False, du, dv, lam, val, r0
    if abs(du1) <= 0.5 and abs(dv1) <= 0.5:
        return True, du1, dv1, lam1, val1, r1
    if dv1 * dv > 0.0 or abs(dv1) > 1.0 or abs(du1) > 1.0:
        return False, du, dv, lam, val, r0
    if abs(dv1) > abs(dv):
        # The point lies between the two pixels, whose sampled estimates straddle the
        # boundary: keep the nearer one.
        return not abs(du) > 1.0, du, dv, lam, val, r0
    return True, du1, dv1, lam1, val1, r1


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _profile_peaks(img, cand, R, K, g0, min_strength, r0s, bgs, present):
    """Pass 1: peak row, background and presence of the stripe in every column's profile.

    Fills ``r0s`` (int32), ``bgs`` (float32) and ``present`` (bool), each of shape (W,) and
    zero on entry; columns whose ROI is empty keep the zeros.
    """
    H, W = img.shape
    for c in range(W):
        if cand[c] < 0:
            continue
        a, b = roi_rows(cand[c], R, K, H)
        if b < a:
            continue
        r0, peak, bg = roi_profile_peak(img, c, cand[c], a, b, K, g0)
        r0s[c] = r0
        bgs[c] = bg
        present[c] = peak - bg >= min_strength


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _continuous_footprint(present, r0s, c, K):
    """True if the stripe is present in columns c-K..c+K (all inside the image) with peak
    rows that differ from column c's by at most ``|dc| + 2``: the 2-D kernels apply."""
    if not K <= c < present.shape[0] - K:
        return False
    r0 = r0s[c]
    for k in range(-K, K + 1):
        if not present[c + k] or abs(r0s[c + k] - r0) > abs(k) + 2:
            return False
    return True


@numba.njit(cache=True, nogil=True, fastmath=True)
def steger_columns(img, R, kern, sigma, min_strength, out, mode, expected, ratio, counts):
    """Steger centre of every column (see module docstring).

    ``kern`` stacks the half kernels (g0, d1, d2), shape (3, K + 1); ``out`` (shape (4, W))
    receives u, v, width, strength in its first n columns. ``mode``, ``expected``,
    ``ratio`` and ``counts`` are those of :func:`.selection.select_peaks`, which picks
    each column's peak first. Returns (n, rejected_secondary).
    """
    W = img.shape[1]
    g0 = kern[0]
    d1 = kern[1]
    d2 = kern[2]
    K = kern.shape[1] - 1
    cand = np.empty(W, np.int32)
    sec = np.empty(W, np.int32)
    column_peaks(img, R, cand, sec)
    select_peaks(img, R, K, g0, min_strength, cand, sec, mode, expected, ratio, counts)
    r0s = np.zeros(W, np.int32)
    bgs = np.zeros(W, np.float32)
    present = np.zeros(W, np.bool_)
    _profile_peaks(img, cand, R, K, g0, min_strength, r0s, bgs, present)
    # Pass 2: Steger at each column with a stripe. The 2-D kernels are used where the stripe
    # is present and continuous over the whole footprint c-K..c+K; elsewhere (line ends,
    # occlusion edges, jumps, left/right borders) the column-only case.
    n = 0
    nsec = 0
    h0 = np.empty(2 * K + 3, np.float32)
    h1 = np.empty(2 * K + 3, np.float32)
    h2 = np.empty(2 * K + 3, np.float32)
    for c in range(W):
        if not present[c]:
            continue
        r0 = r0s[c]
        bg = bgs[c]
        full = _continuous_footprint(present, r0s, c, K)
        if full:
            _filter_rows(img, r0, c, K, g0, d1, d2, h0, h1, h2)
            du, dv, lam, val = _line_point(h0, h1, h2, K + 1, K, g0, d1, d2)
        else:
            du, dv, lam, val = _line_point_1d(img, r0, c, K, g0, d1, d2)
        if lam >= 0.0:
            continue
        r = r0
        if not (abs(du) <= 0.5 and abs(dv) <= 0.5):
            found, du, dv, lam, val, r = _neighbour_point(img, r0, c, full, du, dv, lam, val,
                                                          K, g0, d1, d2, h0, h1, h2)
            if not found:
                continue
        strength = val - bg
        if strength < min_strength:
            continue
        S2 = -strength / lam
        out[0, n] = c + du
        out[1, n] = r + dv
        out[3, n] = strength
        out[2, n] = FWHM_PER_SIGMA * math.sqrt(max(S2 - sigma * sigma, 0.0))
        n += 1
        if is_secondary(img, sec[c], c, K, g0, bg, min_strength):
            nsec += 1
    return n, nsec
