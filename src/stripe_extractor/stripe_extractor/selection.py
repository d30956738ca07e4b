"""Peak selection: which of a column's two peaks is the stripe (numba, no rclpy).

A shiny part throws the stripe onto itself: a column then holds the stripe and its
reflection. :func:`.candidates.column_peaks` finds the strongest peak of each column and
the strongest other local maximum (the secondary). Where the secondary is a peak of its
own (:func:`.profile.is_secondary`), the mode decides which one the extractors centre:

``strongest``   the strongest (the extractors' behaviour without selection);
``nearest``     the local maximum of the smoothed profile nearest the expected row of the
                column (``expected`` (W,) [px]; :data:`NO_EXPECTATION`, from NaN by
                :func:`kernel_expected`: no expectation, the strongest), within
                ``R`` rows of it and ``min_strength`` above the background: a prior from
                where the part should be (its nominal pose, projected) or from the previous
                frame. Unlike the others it also separates a reflection that merges into
                the stripe's flank (closer than ``R``, where there is no second candidate);
``widest``      the wider one (a reflection off a glossy face is blurred by its lobe and
                is wider; a mirror-sharp one is not, see docs/materials.md);
``unambiguous`` the strongest, unless the secondary reaches ``ratio`` times its strength:
                then no centre in that column.

Each decision is counted in ``counts`` (int64, shape (5,)): columns with two peaks, the
strongest kept, the other taken, the column dropped as ambiguous, and (``nearest`` with
``max_offset_px``, applied by :func:`.extractor.extract` to the centres) dropped as too far
from the expectation. ``nearest`` counts each column with an expectation as kept or taken.
"""

from __future__ import annotations

import numba
import numpy as np

from .config import PEAK_MODES
from .profile import is_secondary, roi_profile_peak, smooth_column

MODE_CODES = {m: i for i, m in enumerate(PEAK_MODES)}
#: "No expectation" in the kernels' ``expected`` (:func:`kernel_expected`), and the value
#: above which one is taken as a row.
NO_EXPECTATION = -1.0e9
NO_EXPECTATION_ABOVE = -1.0e8
#: ``counts`` entries.
#: Diagnostic names of the ``counts`` entries.
COUNT_NAMES = ('two_peaks', 'kept_strongest', 'took_other', 'dropped_ambiguous',
               'dropped_far')


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _peak_and_width(img, r, c, K, g0, bg, H):
    """Smoothed height above ``bg`` of column c at its local maximum near row r, that
    row, and its full width at half height [px] (walked on the smoothed profile)."""
    lo_lim, hi_lim = K + 1, H - 2 - K
    r, best, _ = roi_profile_peak(img, c, r, lo_lim, hi_lim, K, g0)
    height = best - bg
    half = bg + 0.5 * height
    a = r
    while a > lo_lim and smooth_column(img, a - 1, c, K, g0) > half:
        a -= 1
    b = r
    while b < hi_lim and smooth_column(img, b + 1, c, K, g0) > half:
        b += 1
    return height, r, b - a + 1


@numba.njit(cache=True, nogil=True, fastmath=True, inline='always')
def _nearest_local_max(img, c, e, R, K, g0, min_strength, H):
    """Row of the strict local maximum of column c's smoothed profile nearest row e,
    within R rows of it and at least min_strength above the smaller of the values at the
    window's ends; -1 if none."""
    lo = max(int(e) - R, K + 1)
    hi = min(int(e) + R + 1, H - 2 - K)
    if hi - lo < 2:
        return -1
    bg = min(smooth_column(img, lo, c, K, g0), smooth_column(img, hi, c, K, g0))
    best = -1
    dist = 1e30
    prev = smooth_column(img, lo, c, K, g0)
    cur = smooth_column(img, lo + 1, c, K, g0)
    for r in range(lo + 1, hi):
        nxt = smooth_column(img, r + 1, c, K, g0)
        if cur > prev and cur >= nxt and cur - bg >= min_strength and abs(r - e) < dist:
            dist = abs(r - e)
            best = r
        prev = cur
        cur = nxt
    return best


@numba.njit(cache=True, nogil=True, fastmath=True)
def select_peaks(img, R, K, g0, min_strength, cand, sec, mode, expected, ratio, counts):
    """Apply the selection ``mode`` (index into PEAK_MODES) to every column in place:
    ``cand`` becomes the chosen peak's row (-1: none), ``sec`` the other's (or -1)."""
    H, W = img.shape
    if mode == 0:
        return
    for c in range(W):
        q = sec[c]
        p = cand[c]
        if mode == 1 and p >= 0:
            e = expected[c]
            if e > NO_EXPECTATION_ABOVE:
                r = _nearest_local_max(img, c, e, R, K, g0, min_strength, H)
                if q >= 0:
                    a = max(p - R, K + 1)
                    b = min(p + R, H - 2 - K)
                    if b >= a:
                        bg = min(smooth_column(img, a, c, K, g0),
                                 smooth_column(img, b, c, K, g0))
                        if is_secondary(img, q, c, K, g0, bg, min_strength):
                            counts[0] += 1
                if r >= 0 and abs(r - p) > 2:
                    cand[c] = r
                    sec[c] = p
                    counts[2] += 1
                else:
                    counts[1] += 1
                continue
        if q < 0 or p < 0:
            continue
        a = max(p - R, K + 1)
        b = min(p + R, H - 2 - K)
        if b < a:
            continue
        bg = min(smooth_column(img, a, c, K, g0), smooth_column(img, b, c, K, g0))
        if not is_secondary(img, q, c, K, g0, bg, min_strength):
            continue
        counts[0] += 1
        hp, rp, wp = _peak_and_width(img, p, c, K, g0, bg, H)
        hq, rq, wq = _peak_and_width(img, q, c, K, g0, bg, H)
        take_other = False
        if mode == 1:
            take_other = False  # no expectation in this column: the strongest
        elif mode == 2:
            take_other = wq > wp
        else:
            if hq >= ratio * hp:
                cand[c] = -1
                sec[c] = -1
                counts[3] += 1
                continue
        if take_other:
            cand[c] = rq
            sec[c] = rp
            counts[2] += 1
        else:
            counts[1] += 1


def no_expectation(width: int) -> np.ndarray:
    """An ``expected`` array without expectations (all NaN), shape (width,)."""
    return np.full(int(width), np.nan, np.float32)


def kernel_expected(expected) -> np.ndarray:
    """``expected`` (NaN: none) as :func:`select_peaks` takes it: float32, NaN (and any
    other value that is not finite) replaced by :data:`NO_EXPECTATION`. The kernels are
    compiled with fastmath, which assumes no NaN: a NaN test there may be folded away, and
    a NaN row then read as a garbage integer."""
    e = np.asarray(expected, dtype=np.float32)
    return np.ascontiguousarray(np.where(np.isfinite(e), e, np.float32(NO_EXPECTATION)))
