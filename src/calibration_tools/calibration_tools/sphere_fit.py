"""Sphere fitting for the joint correction (no rclpy).

- :func:`fit_sphere_algebraic`: closed form (Kasa): ``|p|^2 = 2 c.p + (r^2 - |c|^2)`` is linear
  in ``c`` and ``r^2 - |c|^2``. Needs points that are not coplanar.
- :func:`fit_circle_3d`: plane (SVD) plus the algebraic circle in that plane.
- :func:`fit_sphere`: robust fit. RANSAC on minimal samples (3 points and the known radius: the
  circle through them and the two sphere centres on its axis; or 4 points without a radius),
  then geometric refinement of ``sum (|p - c| - r)^2`` (scipy least squares) on the inliers,
  repeated with MAD-based rejection. A laser stripe on a sphere is one planar circle arc
  (G2 fixed), so the radius must be known; of the two mirror-image centres the one that makes
  the points face the viewpoint is chosen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SphereFit:
    """A fitted sphere.

    Attributes
    ----------
    centre : ndarray, shape (3,), metres
    radius : float, metres
    rms : float, metres
        RMS of ``|p - c| - r`` over the inliers.
    inliers : ndarray of bool, shape (n,)
    """

    centre: np.ndarray
    radius: float
    rms: float
    inliers: np.ndarray

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def finite_rows(a, name: str = 'points', min_n: int = 4, *, width: int = 3,
                rows: str = 'points', n: str = 'n') -> np.ndarray:
    """An array of row vectors (points, planes), checked.

    Parameters
    ----------
    a : array_like, shape (n, width)
    name : str
        Its name in the error messages.
    min_n : int
        Fewest rows accepted.
    width : int
        Length of a row (3 for points).
    rows : str
        What a row is, in the messages ('points', 'planes').
    n : str
        Name of the row count in the shape message.

    Returns
    -------
    ndarray, shape (n, width), float64

    Raises
    ------
    ValueError
        Another shape, fewer than ``min_n`` rows, or a value that is not finite.
    """
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != width:
        raise ValueError(f'{name} must have shape ({n}, {width}), got {p.shape}')
    if p.shape[0] < min_n:
        raise ValueError(f'{name} must hold at least {min_n} {rows}, got {p.shape[0]}')
    if not np.all(np.isfinite(p)):
        raise ValueError(f'{name} must be finite')
    return p


def _kasa(q: np.ndarray):
    """Closed-form (Kasa) sphere or circle through centred points ``q``, shape (n, d).

    Solves ``|q|^2 = 2 c.q + k`` in least squares; returns ``c``, shape (d,), and the squared
    radius ``k + |c|^2``.
    """
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, np.sum(q * q, axis=1), rcond=None)
    c = sol[:-1]
    return c, sol[-1] + c @ c


def fit_sphere_algebraic(points):
    """Closed-form (Kasa) sphere through points.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres, n >= 4, not coplanar

    Returns
    -------
    centre : ndarray, shape (3,), metres
    radius : float, metres

    Raises
    ------
    ValueError
        Coplanar points (the sphere is undetermined: give its radius to :func:`fit_sphere`).
    """
    p = finite_rows(points)
    m = p.mean(axis=0)
    q = p - m  # centred for conditioning
    s = np.linalg.svd(q, compute_uv=False)
    if s[2] <= 1e-9 * s[0]:
        raise ValueError('points are coplanar: a sphere through them is undetermined')
    c, r2 = _kasa(q)
    if not r2 > 0:
        raise ValueError('algebraic sphere fit failed (negative squared radius)')
    return c + m, float(np.sqrt(r2))


def fit_circle_3d(points):
    """Circle through 3-D points: best plane (SVD), then the algebraic circle in it.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres
        n >= 3, not all collinear; more than 3 need not lie exactly on one plane or circle.

    Returns
    -------
    centre : ndarray, shape (3,), metres
    normal : ndarray, shape (3,)
        Unit normal of the circle's plane.
    radius : float, metres
    """
    p = finite_rows(points, min_n=3)
    m = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - m, full_matrices=False)
    if s[1] <= 1e-9 * s[0]:
        raise ValueError('points are collinear: no circle through them')
    e1, e2, n = vt
    uv = np.column_stack([(p - m) @ e1, (p - m) @ e2])
    c2, r2 = _kasa(uv)
    return m + c2[0] * e1 + c2[1] * e2, n, float(np.sqrt(max(r2, 0.0)))


def _centres_from_circle(c, n, rc, R):
    h2 = R * R - rc * rc
    h = np.sqrt(h2) if h2 > 0 else 0.0
    return [c + h * n, c - h * n]


def _facing_fraction(p, c, viewpoint) -> float:
    """Fraction of points whose outward normal faces the viewpoint."""
    return float(np.mean(np.sum((p - c) * (viewpoint - p), axis=1) > 0.0))


def _refine(p, c, r, fix_radius):
    from scipy.optimize import least_squares

    if fix_radius:
        fun = lambda x: np.linalg.norm(p - x, axis=1) - r  # noqa: E731
        sol = least_squares(fun, c, method='lm', xtol=1e-15, ftol=1e-15, gtol=1e-15)
        return sol.x, r
    fun = lambda x: np.linalg.norm(p - x[:3], axis=1) - x[3]  # noqa: E731
    sol = least_squares(fun, np.append(c, r), method='lm', xtol=1e-15, ftol=1e-15,
                        gtol=1e-15)
    return sol.x[:3], float(sol.x[3])


def fit_sphere(points, *, radius=None, viewpoint=(0.0, 0.0, 0.0), inlier_tol: float = 2e-4,
               k_sigma: float = 4.0, trials: int = 300, seed: int = 0,
               refine: bool = True, centre_hint=None, sample_window=None) -> SphereFit:
    """Robust sphere fit (RANSAC, then geometric refinement with outlier rejection).

    Parameters
    ----------
    points : array_like, shape (n, 3), metres
    radius : float, metres, optional
        Known radius (a calibration sphere). Required when the points are (nearly) coplanar,
        e.g. one laser stripe.
    viewpoint : array_like, shape (3,), metres
        Where the points were seen from (V0 origin). A planar arc fits two mirror-image
        centres equally well: the one that makes more points face the viewpoint is taken,
        and when both make them all face it (the arc ends at the laser's terminator, not
        the camera's), the one farther from the viewpoint, i.e. on the far side of the arc's
        plane (the visible surface of a sphere is always nearer to the viewer than its
        centre, and a stripe across the front of the sphere has its centre behind it).
    centre_hint : array_like, shape (3,), metres, optional
        Take the mirror-image centre nearest to this instead (e.g. the reference view's).
    sample_window : int, optional
        The points are in stripe order (consecutive points are neighbours on the curve):
        half of the RANSAC samples are then spread over a random run of at most this many
        consecutive points, which finds a sphere arc holding only a small share of the
        points (the rest on the background) far more often than uniform sampling.
    inlier_tol : float, metres
        RANSAC inlier distance ``| |p - c| - r |``.
    k_sigma : float
        Refinement rejects points beyond ``max(k_sigma * 1.4826 MAD, inlier_tol / 4)``.
    trials : int
        RANSAC samples.
    seed : int
    refine : bool
        Geometric refinement (else the best RANSAC hypothesis refitted in closed form).

    Returns
    -------
    SphereFit

    Raises
    ------
    ValueError
        Bad arguments, or no sphere hypothesis with at least 4 inliers.
    """
    p = finite_rows(points, min_n=3 if radius is not None else 4)
    vp, hint, R = _fit_arguments(viewpoint, centre_hint, radius, inlier_tol)
    c, r = _ransac(p, R, vp, inlier_tol, int(trials), seed, sample_window)
    c, r, inl = _refit_with_rejection(p, c, r, R, hint, vp, refine=refine, k_sigma=k_sigma,
                                      inlier_tol=inlier_tol)
    res = np.linalg.norm(p[inl] - c, axis=1) - r
    return SphereFit(centre=np.asarray(c, dtype=np.float64), radius=float(r),
                     rms=float(np.sqrt(np.mean(res * res))), inliers=inl)


def _fit_arguments(viewpoint, centre_hint, radius, inlier_tol):
    """Checked viewpoint (3,), centre hint (3,) or None, and radius [m] or None."""
    vp = np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,):
        raise ValueError(f'viewpoint must have shape (3,), got {vp.shape}')
    hint = None
    if centre_hint is not None:
        hint = np.asarray(centre_hint, dtype=np.float64)
        if hint.shape != (3,) or not np.all(np.isfinite(hint)):
            raise ValueError(f'centre_hint must be a finite vector of shape (3,), got {hint}')
    R = None
    if radius is not None:
        R = float(radius)
        if not R > 0:
            raise ValueError(f'radius must be > 0 m, got {radius!r}')
    if not inlier_tol > 0:
        raise ValueError(f'inlier_tol must be > 0 m, got {inlier_tol!r}')
    return vp, hint, R


def _hypotheses(sample, R):
    """Sphere hypotheses (centre, radius) through a minimal sample ([] if degenerate)."""
    try:
        if R is not None:
            c, nn, rc = fit_circle_3d(sample)
            if rc > R * 1.01:
                return []
            return [(cc, R) for cc in _centres_from_circle(c, nn, rc, R)]
        return [fit_sphere_algebraic(sample)]
    except (ValueError, np.linalg.LinAlgError):
        return []


def _ransac(p, R, vp, inlier_tol, trials, seed, sample_window):
    """The hypothesis with the most inliers (ties: the most facing the viewpoint)."""
    n = p.shape[0]
    rng = np.random.default_rng(seed)
    best = None  # ((count, facing), centre, radius)
    k = 3 if R is not None else 4
    window = None
    if sample_window is not None:
        window = int(min(sample_window, n - 1))
        if window < k:
            window = None
    for trial in range(trials):
        if window is not None and trial % 2:
            w = int(rng.integers(max(k, window // 4), window + 1))
            start = int(rng.integers(0, n - w))
            idx = start + np.sort(rng.choice(w + 1, size=k, replace=False))
        else:
            idx = rng.choice(n, size=k, replace=False)
        for cc, rr in _hypotheses(p[idx], R):
            inl = np.abs(np.linalg.norm(p - cc, axis=1) - rr) <= inlier_tol
            cnt = int(inl.sum())
            facing = _facing_fraction(p[inl], cc, vp) if cnt else 0.0
            key = (cnt, facing)
            if best is None or key > best[0]:
                best = (key, cc, rr)
    if best is None or best[0][0] < 4:
        raise ValueError('no sphere hypothesis with at least 4 inliers')
    return best[1], best[2]


def _mirror_centre(q, c, R, hint, vp):
    """For a known radius, the centre of the inliers' arc on the right side of its plane."""
    if R is None:
        return c
    try:
        cc, nn, rc = fit_circle_3d(q)
    except ValueError:
        return c
    cands = _centres_from_circle(cc, nn, rc, R)
    if hint is not None:
        return min(cands, key=lambda x: np.linalg.norm(x - hint))
    return max(cands, key=lambda x: (round(_facing_fraction(q, x, vp), 2),
                                     np.linalg.norm(x - vp)))


def _refit_with_rejection(p, c, r, R, hint, vp, *, refine: bool, k_sigma: float,
                          inlier_tol: float):
    """Refit the RANSAC sphere to its inliers, rejecting by MAD, until they stop changing.

    Returns the centre (3,) [m], the radius [m] and the inlier mask (n,).
    """
    inl = np.abs(np.linalg.norm(p - c, axis=1) - r) <= inlier_tol
    # When the inliers are one planar arc, re-decide between the two mirror centres.
    for _ in range(10):
        q = p[inl]
        c0 = _mirror_centre(q, c, R, hint, vp)
        if refine:
            c, r = _refine(q, c0, R if R is not None else r, R is not None)
        else:
            c = c0
        res = np.linalg.norm(p - c, axis=1) - r
        sigma = 1.4826 * np.median(np.abs(res[inl] - np.median(res[inl])))
        new = np.abs(res) <= max(k_sigma * sigma, inlier_tol / 4.0)
        if new.sum() < 4 or np.array_equal(new, inl):
            break
        inl = new
    return c, r, inl
