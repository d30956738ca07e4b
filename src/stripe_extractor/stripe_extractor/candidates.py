"""Per-column candidate peaks and secondary peaks: one streaming pass over the image.

No rclpy here. The only step that touches every pixel: for each column, the row of the
largest 3x3 box sum (the candidate peak, around which the extractors open their region of
interest) and the row of the largest 3x3 box sum that lies more than ``excl`` rows away from
it and is a local maximum (a secondary-peak candidate: a reflection, a speck, ...).

The pass runs row by row (memory order) with the column loop innermost; box sums are taken
at every second row (their 3-row windows still cover the image).
Box maxima of blocks of ``BLOCK_ROWS`` rows are kept on the way; the secondary search then
reads those block maxima and rescans only the (at most two) blocks cut by the exclusion zone.
"""

from __future__ import annotations

import numba
import numpy as np

#: Rows per block of the block-maximum table.
BLOCK_ROWS = 8


@numba.njit(cache=True, nogil=True, inline='always')
def _row_sum3(img, r, out):
    """out[c] = img[r, c-1] + img[r, c] + img[r, c+1] (columns clamped at the borders).

    The sums wrap to ``out``'s type: callers choose one wide enough (int16 holds 9 * 255).
    """
    W = img.shape[1]
    for c in range(1, W - 1):
        out[c] = img[r, c - 1] + img[r, c] + img[r, c + 1]
    out[0] = 2 * img[r, 0] + img[r, 1]
    out[W - 1] = 2 * img[r, W - 1] + img[r, W - 2]


@numba.njit(cache=True, nogil=True)
def box3(img, r, c):
    """3x3 box sum at (r, c), 1 <= r <= H-2; columns clamped at the borders."""
    W = img.shape[1]
    s = np.int32(0)
    for dc in (-1, 0, 1):
        cc = min(max(c + dc, 0), W - 1)
        s += np.int32(img[r - 1, cc]) + np.int32(img[r, cc]) + np.int32(img[r + 1, cc])
    return s


@numba.njit(cache=True, nogil=True)
def _box_maxima(img, best, cand, bmax, barg, hprev, hmid, hnext):
    """Largest 3x3 box sum at the odd rows of every column, and of every block of rows.

    ``best``/``cand``: the column's largest sum and its row; ``bmax``/``barg``: the same per
    block of ``BLOCK_ROWS`` rows (entry -1: no odd row in the block). Every array has one
    integer type, wide enough for 9 pixels and for the row numbers; with int16 for uint8
    images the loops run on twice as many SIMD lanes as with int32. The updates are written
    as selects, not branches, so that they vectorise too.
    """
    H, W = img.shape
    B = BLOCK_ROWS
    best[:] = -1
    bmax[:] = -1
    barg[:] = 0
    _row_sum3(img, 0, hprev)
    for r in range(1, H - 1, 2):
        _row_sum3(img, r, hmid)
        _row_sum3(img, r + 1, hnext)
        bm = bmax[r // B]
        ba = barg[r // B]
        row = cand.dtype.type(r)
        for c in range(W):
            s = best.dtype.type(hprev[c] + hmid[c] + hnext[c])
            hprev[c] = hnext[c]
            b = best[c]
            cand[c] = row if s > b else cand[c]
            best[c] = s if s > b else b
            m = bm[c]
            ba[c] = row if s > m else ba[c]
            bm[c] = s if s > m else m


@numba.njit(cache=True, nogil=True)
def _secondaries(img, excl, cand, sec, bmax, barg):
    """The secondary candidate of every column from the block maxima (see column_peaks)."""
    H, W = img.shape
    B = BLOCK_ROWS
    nb = bmax.shape[0]
    # Secondary: largest box sum (odd rows) outside [cand - excl, cand + excl].
    sv = np.full(W, -1, np.int32)
    for c in range(W):
        sec[c] = -1
    for k in range(nb):
        r0 = k * B
        r1 = min(r0 + B, H) - 1
        for c in range(W):
            if r1 < cand[c] - excl or r0 > cand[c] + excl:
                if bmax[k, c] > sv[c]:
                    sv[c] = bmax[k, c]
                    sec[c] = barg[k, c]
    for c in range(W):
        lo = cand[c] - excl
        hi = cand[c] + excl
        for k in (lo // B, hi // B):
            if k < 0 or k >= nb or bmax[k, c] <= sv[c]:
                continue
            if barg[k, c] < lo or barg[k, c] > hi:
                sv[c] = bmax[k, c]
                sec[c] = barg[k, c]
                continue
            for r in range(k * B + 1, min(k * B + B, H - 1), 2):
                if r < lo or r > hi:
                    s = box3(img, r, c)
                    if s > sv[c]:
                        sv[c] = s
                        sec[c] = r
        # Climb to the local maximum; reaching the zone means the main peak's flank.
        r = sec[c]
        if r < 0:
            continue
        v = sv[c]
        for step in (1, -1):
            while 1 <= r + step <= H - 2:
                nv = box3(img, r + step, c)
                if nv <= v:
                    break
                v = nv
                r += step
        if lo <= r <= hi:
            # the largest sum outside the zone is the main peak's flank (a wide peak, e.g.
            # a reflection blurred by a glossy lobe): look for a peak of its own beyond it
            sec[c] = _local_maximum_outside(img, c, lo, hi)
        else:
            sec[c] = r


@numba.njit(cache=True, nogil=True)
def _local_maximum_outside(img, c, lo, hi):
    """Row of the largest 3x3 box sum of column c that is a strict local maximum (both
    neighbouring rows lower) outside rows lo..hi and not next to them; -1 if none."""
    H = img.shape[0]
    best = np.int32(-1)
    row = -1
    prev = box3(img, 1, c)
    cur = box3(img, 2, c) if H > 3 else prev
    for r in range(2, H - 2):
        nxt = box3(img, r + 1, c)
        if (r < lo - 1 or r > hi + 1) and cur > prev and cur > nxt and cur > best:
            best = cur
            row = r
        prev = cur
        cur = nxt
    return row


@numba.njit(cache=True, nogil=True)
def column_peaks(img, excl, cand, sec):
    """Candidate and secondary-candidate row of every column.

    The 3x3 box sums are evaluated at the odd rows 1, 3, 5, ... only: their windows still
    cover every row, and the extractors refine the peak row on the smoothed profile.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8 or uint16, C-contiguous; H, W >= 3
    excl : int
        Half size of the zone around the candidate in which no secondary is sought [px].
    cand : ndarray, shape (W,), int32 (output)
        Odd row of the largest 3x3 box sum, in 1..H-2.
    sec : ndarray, shape (W,), int32 (output)
        Row of a local maximum of the column's box sums outside ``[cand - excl, cand + excl]``
        (the largest one found at the odd rows, climbed to its local maximum), or -1 if there
        is none or if it is only the main peak's flank rising into the zone.
    """
    if img.itemsize == 1 and img.shape[0] <= 32767:
        _column_peaks_as(img, excl, cand, sec, np.empty(0, np.int16))  # 9 * 255 and rows fit
    else:
        _column_peaks_as(img, excl, cand, sec, np.empty(0, np.int32))


@numba.njit(cache=True, nogil=True)
def _column_peaks_as(img, excl, cand, sec, like):
    """:func:`column_peaks` with the box sums and rows kept in ``like``'s integer type."""
    H, W = img.shape
    nb = (H + BLOCK_ROWS - 1) // BLOCK_ROWS
    t = like.dtype
    rows = np.empty(W, t)
    bmax = np.empty((nb, W), t)
    barg = np.empty((nb, W), t)
    _box_maxima(img, np.empty(W, t), rows, bmax, barg, np.empty(W, t), np.empty(W, t),
                np.empty(W, t))
    cand[:] = rows
    _secondaries(img, excl, cand, sec, bmax, barg)


def find_candidates(img: np.ndarray, excl: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidate and secondary rows per column (see :func:`column_peaks`).

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8 or uint16, DN
    excl : int
        Secondary exclusion half size [px], >= 1.

    Returns
    -------
    cand, sec : ndarray, shape (W,), int32
    """
    if not isinstance(img, np.ndarray) or img.ndim != 2 or img.shape[0] < 3 or \
            img.shape[1] < 3:
        raise ValueError('img must be a 2-D array of at least 3x3 px')
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f'img dtype must be uint8 or uint16, got {img.dtype}')
    if int(excl) < 1:
        raise ValueError(f'excl must be >= 1, got {excl}')
    img = np.ascontiguousarray(img)
    W = img.shape[1]
    cand = np.empty(W, np.int32)
    sec = np.empty(W, np.int32)
    column_peaks(img, int(excl), cand, sec)
    return cand, sec
