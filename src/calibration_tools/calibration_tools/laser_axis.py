"""Laser rotation axis (docs/design.md §3 step 4, paper Eq. 17) and the G2 angle per volt.

The laser planes ``pi_i`` measured at G2 tilt voltages ``U_i`` all contain the G2 tilt axis
(when the fan contains the mirror axis), so:

- direction: ``n`` minimises ``sum_i (n . n_i)^2``, i.e. it is the eigenvector of
  ``sum_i n_i n_i^T`` with the smallest eigenvalue;
- point: ``P`` minimises ``sum_i (n_i . P + e_i)^2``, pinned along the axis by
  ``n . (P - anchor) = 0`` (by default the point of the axis closest to the V0 origin);
  optionally with a common signed offset ``rho`` (``n_i . P + e_i = rho``) for a fan plane
  that misses the mirror axis: every plane is then tangent to a cylinder of radius |rho|;
- angle per volt: the plane's rotation about ``n`` is ``alpha_i = 2 (theta4(U_i) -
  theta4(0))``; a polynomial in U fitted to the measured ``alpha_i`` (relative to the plane
  nearest U = 0, with a free constant) gives ``k2`` and, with enough data, higher terms.

Every plane's residual to the common axis is reported: the angle between the axis and the
plane and the distance of ``P`` from the plane.

Laser mounting error (docs/design.md §5, the laser fan not containing G2's axis): a fan that is
rolled about its beam or offset from the mirror axis is still turned rigidly about the axis by
the mirror, but its planes no longer contain the axis: their normals lie on a cone about n
(``n . n_i = cos`` of a constant angle) and they are tangent to a cylinder about it.
``method='cone'`` fits that general case: n is the eigenvector with the smallest eigenvalue of
the covariance of the normals about their mean (``sum (n_i - mean)(n_i - mean)^T``), and P
comes with the common offset rho. It needs a wider sweep than the paper's method (the cone's
opening is told apart from a tilt of n only by the curvature of the arc the normals trace).
No rclpy.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from calibration_tools.laser_plane import (
    VOLTAGE_TOL,
    board_stripe_points,
    plane_covariance,
    plane_from_stripes,
)
from calibration_tools.sphere_fit import finite_rows
from calibration_tools.stages import StageResult, covariance_from_jacobian

log = logging.getLogger('galvoscan.calibration.laser_axis')


@dataclass(frozen=True)
class AxisFit:
    """Result of :func:`fit_axis`.

    Attributes
    ----------
    direction : ndarray, shape (3,)
        Unit axis direction n (sign: see ``fit_axis(reference_dir=...)``).
    point : ndarray, shape (3,), metres
        Axis point P (pinned along the axis by the anchor).
    offset : float, metres
        Common signed plane-to-axis offset rho (0 unless ``fit_offset``).
    cone_angle : float, radians
        Mean angle between the planes and the axis, ``asin(mean(n . n_i))`` (the fan's roll
        for ``method='cone'``; about 0 for the paper's method).
    eigenvalues : ndarray, shape (3,)
        Of ``sum w_i n_i n_i^T`` (centred for the cone), ascending.
    plane_angle_rad : ndarray, shape (m,)
        Angle between the axis and each plane, ``asin |n . n_i|`` (paper), or its deviation
        from the cone angle (cone).
    plane_distance_m : ndarray, shape (m,)
        ``n_i . P + e_i - rho`` for each plane (signed).
    rotation_rad : ndarray, shape (m,)
        Rotation of each plane about n relative to the plane nearest U = 0 (or the first).
    k : float or None
        G2 tilt gain, rad/V (mechanical; the plane turns by twice the mirror angle);
        None without voltages.
    poly : tuple of float
        Higher-order coefficients of the mirror angle, rad/V^2, rad/V^3, ...
    angle_fit_rms_rad : float or None
        RMS residual of the plane rotation fit (plane angle, not mirror angle).
    """

    direction: np.ndarray
    point: np.ndarray
    offset: float
    cone_angle: float
    eigenvalues: np.ndarray
    plane_angle_rad: np.ndarray
    plane_distance_m: np.ndarray
    rotation_rad: np.ndarray
    k: float | None
    poly: tuple
    angle_fit_rms_rad: float | None


def _unit_planes(planes) -> np.ndarray:
    pl = finite_rows(planes, 'planes', 2, width=4, rows='planes', n='m')
    norms = np.linalg.norm(pl[:, :3], axis=1)
    if np.any(norms < 1e-12):
        raise ValueError('planes must have non-zero normals')
    pl = pl / norms[:, None]
    # One orientation for all: the normals turn by less than 90 degrees from the first.
    flip = pl[:, :3] @ pl[0, :3] < 0.0
    pl[flip] *= -1.0
    return pl


def plane_rotation_angles(planes, direction, reference: int = 0) -> np.ndarray:
    """Signed rotation of each plane's normal about ``direction`` from a reference plane.

    Parameters
    ----------
    planes : array_like, shape (m, 4)
    direction : array_like, shape (3,)
        Rotation axis direction (right-hand rule).
    reference : int
        Index of the plane at angle 0.

    Returns
    -------
    ndarray, shape (m,), radians in (-pi, pi]
    """
    pl = _unit_planes(planes)
    n = np.asarray(direction, dtype=np.float64)
    if n.shape != (3,) or not np.linalg.norm(n) > 0:
        raise ValueError(f'direction must be a non-zero vector of shape (3,), got {n}')
    n = n / np.linalg.norm(n)
    normals = pl[:, :3] - np.outer(pl[:, :3] @ n, n)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    ref = normals[reference]
    return np.arctan2(np.cross(ref, normals) @ n, normals @ ref)


METHODS = ('paper', 'cone')


def fit_axis(planes, voltages=None, *, weights=None, anchor=(0.0, 0.0, 0.0),
             reference_dir=None, fit_offset: bool = False, poly_degree: int = 1,
             method: str = 'paper') -> AxisFit:
    """Fit the common rotation axis of laser planes, and the angle per volt.

    Parameters
    ----------
    planes : array_like, shape (m, 4)
        Laser planes (a, b, c, e) in one frame (V0), e in metres; m >= 2 (>= 3 with
        ``fit_offset``).
    voltages : array_like, shape (m,), volts, optional
        G2 tilt voltage of each plane; enables the angle-per-volt fit.
    weights : array_like, shape (m,), optional
        Relative weight of each plane (inverse variance of its normal), used in
        ``sum w_i n_i n_i^T``, in the point's least squares and in the angle fit. Default: 1.
    anchor : array_like, shape (3,), metres
        P is the axis point closest to it (default: the V0 origin).
    reference_dir : array_like, shape (3,), optional
        The direction's sign is chosen to have a positive dot product with it (e.g. the
        nominal axis). Default: the largest-magnitude component is positive. The sign of
        ``k`` follows (right-hand rotation about n for increasing angle).
    fit_offset : bool
        Also fit a common plane-to-axis offset rho (fan plane not containing the axis).
    poly_degree : int
        Degree of the mirror angle polynomial in U (1 = linear gain only). Fitted only when
        there are at least ``poly_degree + 2`` distinct voltages; otherwise the degree is
        lowered (and a warning logged).
    method : {'paper', 'cone'}
        ``'paper'``: n minimises ``sum (n . n_i)^2`` (planes contain the axis). ``'cone'``:
        n minimises ``sum (n . n_i - c)^2`` over n and c (a fan rolled about its beam), i.e.
        the eigenvector of the centred normals' covariance; needs >= 3 planes.

    Returns
    -------
    AxisFit

    Raises
    ------
    ValueError
        Bad shapes, or planes that are all parallel (no axis).
    """
    pl = _unit_planes(planes)
    m = pl.shape[0]
    a = np.asarray(anchor, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f'anchor must be a finite vector of shape (3,), got {anchor!r}')
    if not isinstance(poly_degree, int) or poly_degree < 1:
        raise ValueError(f'poly_degree must be an integer >= 1, got {poly_degree!r}')
    N = pl[:, :3]
    e = pl[:, 3]
    w = _plane_weights(weights, m)
    sw = np.sqrt(w)
    if method not in METHODS:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    n, evals, evecs = _axis_direction(N, w, method, reference_dir)
    P, rho = _axis_point(N, e, evecs[:, 1:], a, sw, fit_offset)
    dist = N @ P + e - rho
    cone, angle = _plane_angles(N, n, w, method)
    u, ref = _tilt_voltages(voltages, m)
    rot = plane_rotation_angles(pl, n, ref)
    k, poly, fit_rms = (None, (), None) if u is None else _angle_per_volt(u, rot, sw, poly_degree)
    return AxisFit(direction=n, point=P, offset=rho, cone_angle=cone, eigenvalues=evals,
                   plane_angle_rad=angle,
                   plane_distance_m=dist, rotation_rad=rot, k=k, poly=poly,
                   angle_fit_rms_rad=fit_rms)


def _plane_weights(weights, m: int) -> np.ndarray:
    """Relative plane weights scaled to a maximum of 1 (all 1 by default)."""
    w = np.ones(m)
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (m,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.max() > 0:
            raise ValueError(f'weights must be finite, >= 0, not all 0, shape ({m},)')
        w = w / w.max()
    return w


def _axis_direction(N, w, method: str, reference_dir):
    """Axis direction n (signed), and the eigenvalues and eigenvectors it came from."""
    m = N.shape[0]
    evals, evecs = np.linalg.eigh((N * w[:, None]).T @ N)
    if evals[1] < 1e-14 * max(evals[2], 1e-300):
        raise ValueError('the planes are all parallel: their normals do not span a plane, so '
                         'they define no axis (sweep the laser over a wider range)')
    if method == 'cone':
        if m < 3:
            raise ValueError("method='cone' needs at least 3 planes")
        Nc = N - (w @ N) / w.sum()
        evals, evecs = np.linalg.eigh((Nc * w[:, None]).T @ Nc)
        if evals[1] < 1e-14 * max(evals[2], 1e-300):
            raise ValueError('the plane normals trace no arc: the cone axis is undetermined '
                             '(sweep the laser over a wider range)')
    n = evecs[:, 0]
    if reference_dir is not None:
        r = np.asarray(reference_dir, dtype=np.float64)
        if r.shape != (3,):
            raise ValueError(f'reference_dir must have shape (3,), got {r.shape}')
        if n @ r < 0.0:
            n = -n
    elif n[np.argmax(np.abs(n))] < 0.0:
        n = -n
    return n, evals, evecs


def _axis_point(N, e, B, a, sw, fit_offset: bool):
    """The axis point P [m] nearest the anchor a, and the plane offset rho [m] (or 0).

    P = a + B y, with B (3, 2) spanning the plane perpendicular to the axis; y (and rho) in
    weighted least squares over the planes (normals N (m, 3), offsets e (m,)).
    """
    m = N.shape[0]
    A = N @ B
    rhs = -(e + N @ a)
    if fit_offset:
        if m < 3:
            raise ValueError('fit_offset needs at least 3 planes')
        A = np.column_stack([A, -np.ones(m)])
    sol, *_ = np.linalg.lstsq(A * sw[:, None], rhs * sw, rcond=None)
    P = a + B @ sol[:2]
    rho = float(sol[2]) if fit_offset else 0.0
    return P, rho


def _plane_angles(N, n, w, method: str):
    """The cone angle [rad], and each plane's angle to the axis (or to the cone) [rad]."""
    cosines = N @ n
    cone = float(np.arcsin(np.clip((w @ cosines) / w.sum(), -1.0, 1.0)))
    if method == 'cone':
        angle = np.abs(np.arcsin(np.clip(cosines, -1.0, 1.0)) - cone)
    else:
        angle = np.arcsin(np.clip(np.abs(cosines), 0.0, 1.0))
    return cone, angle


def _tilt_voltages(voltages, m: int):
    """Checked G2 voltages (m,) or None, and the index of the plane nearest U = 0 (else 0)."""
    ref = 0
    u = None
    if voltages is not None:
        u = np.asarray(voltages, dtype=np.float64)
        if u.shape != (m,) or not np.all(np.isfinite(u)):
            raise ValueError(f'voltages must be finite with shape ({m},), got {u.shape}')
        ref = int(np.argmin(np.abs(u)))
    return u, ref


#: Planes the physical model's laser-axis stage needs before it fits a cone with an offset
#: rather than planes through one line (two parameters more; twice their count).
CONE_MIN_PLANES = 6


def _angle_per_volt(u, rot, sw, poly_degree: int):
    """k, poly and the fit's RMS [rad] of alpha = c + 2 (k U + p0 U^2 + ...), as supported."""
    m = u.shape[0]
    k, poly, fit_rms = None, (), None
    distinct = np.unique(np.round(u / VOLTAGE_TOL)).shape[0]
    degree = min(poly_degree, distinct - 2)
    if degree < poly_degree:
        log.warning('angle per volt: %d distinct voltages support degree %d, not %d',
                    distinct, max(degree, 0), poly_degree)
    if degree >= 1:
        V = np.column_stack([np.ones(m)] + [u ** (p + 1) for p in range(degree)])
        coef, *_ = np.linalg.lstsq(V * sw[:, None], rot * sw, rcond=None)
        fit_rms = float(np.sqrt(np.mean((V @ coef - rot) ** 2)))
        k = float(coef[1] / 2.0)
        poly = tuple(float(c / 2.0) for c in coef[2:])
    return k, poly, fit_rms


def _wls_cov(J, r, w):
    """``s2 inv(J.T W J)`` of a weighted linear least-squares fit, or None (m <= p)."""
    m, p = J.shape
    if m <= p:
        return None
    cov, _ = covariance_from_jacobian(J * np.sqrt(w)[:, None], r * np.sqrt(w))
    return cov if np.isfinite(cov).all() else None


def axis_standard_errors(fit: AxisFit, planes, voltages=None, *, weights=None,
                         anchor=(0.0, 0.0, 0.0), method: str = 'paper') -> dict:
    """1-sigma standard errors of an axis fit from the Jacobians of its three least squares.

    - direction: residuals ``n . n_i`` (``- c`` for the cone), n turned about two unit
      vectors perpendicular to it;
    - point: residuals ``n_i . P + e_i - rho`` with P moved perpendicular to n, plus its
      slide along n when n turns (P stays the axis point nearest the anchor);
    - angle per volt: the polynomial fit of the plane rotations (k and poly are half the
      plane's coefficients: a mirror doubles the angle).

    Each is ``s2 inv(J.T W J)`` with the fit's plane weights; a part with no redundancy (as
    many planes as parameters) is left out.

    Parameters
    ----------
    fit : AxisFit
        The solution of :func:`fit_axis` with the same planes, voltages, weights and method.
    planes : array_like, shape (m, 4)
    voltages : array_like, shape (m,), volts, optional
    weights : array_like, shape (m,), optional
    anchor : array_like, shape (3,), metres
    method : {'paper', 'cone'}

    Returns
    -------
    dict
        Keyed as the stage's updates: ``laser_axis_dir`` (3, unit 1), ``laser_axis_point``
        (3, metres), ``g2_tilt: {'k': rad/V, 'poly': [rad/V^2, ...]}``, as available.
    """
    out = {}
    for key, (_, cov) in axis_covariance_blocks(fit, planes, voltages, weights=weights,
                                                anchor=anchor, method=method).items():
        sd = [float(v) for v in np.sqrt(np.clip(np.diag(cov), 0.0, None))]
        if key == 'g2_tilt':
            out['g2_tilt'] = {'k': sd[0], 'poly': sd[1:]}
        else:
            out[key] = sd
    return out


def axis_covariance_blocks(fit: AxisFit, planes, voltages=None, *, weights=None,
                           anchor=(0.0, 0.0, 0.0), method: str = 'paper') -> dict:
    """The covariances behind :func:`axis_standard_errors` (same arguments), one block per
    least squares: ``{key: (parameter names, matrix)}`` for ``laser_axis_dir``,
    ``laser_axis_point`` and ``g2_tilt`` (k and poly), as available. The blocks are taken as
    independent (three separate fits)."""
    pl = _unit_planes(planes)
    N, e = pl[:, :3], pl[:, 3]
    w = _plane_weights(weights, pl.shape[0])
    n = fit.direction
    t = np.linalg.svd(n[None, :])[2][1:].T  # (3, 2): unit vectors perpendicular to n
    out: dict = {}
    Jd = N @ t
    rd = N @ n
    if method == 'cone':
        Jd = np.column_stack([Jd, -np.ones(len(N))])
        rd = rd - math.sin(fit.cone_angle)
    cov = _wls_cov(Jd, rd, w)
    cov_n = None
    if cov is not None:
        cov_n = t @ cov[:2, :2] @ t.T
        out['laser_axis_dir'] = ([f'laser_axis_dir[{j}]' for j in range(3)], cov_n)
    Jp = N @ t
    if fit.offset != 0.0:
        Jp = np.column_stack([Jp, -np.ones(len(N))])
    cov = _wls_cov(Jp, N @ fit.point + e - fit.offset, w)
    if cov is not None and cov_n is not None:
        # P slides along n when n turns (it stays the axis point nearest the anchor).
        lever = fit.point - np.asarray(anchor, dtype=np.float64)
        cov_p = t @ cov[:2, :2] @ t.T + np.outer(n, n) * float(lever @ cov_n @ lever)
        out['laser_axis_point'] = ([f'laser_axis_point[{j}]' for j in range(3)], cov_p)
    if fit.k is not None and voltages is not None:
        u = np.asarray(voltages, dtype=np.float64)
        V = np.column_stack([np.ones(len(u))] + [u ** (p + 1) for p in range(1 + len(fit.poly))])
        coef = np.linalg.lstsq(V * np.sqrt(w)[:, None], fit.rotation_rad * np.sqrt(w),
                               rcond=None)[0]
        cov = _wls_cov(V, V @ coef - fit.rotation_rad, w)
        if cov is not None:
            names = ['g2_tilt.k'] + [f'g2_tilt.poly[{j}]' for j in range(len(cov) - 2)]
            out['g2_tilt'] = (names, cov[1:, 1:] / 4.0)
    return out


def axis_covariance(blocks: dict, updated) -> dict:
    """The stage's covariance record from :func:`axis_covariance_blocks` (block diagonal),
    over the parameters it ``updated`` (flat keys)."""
    from reconstructor.uncertainty import covariance_record

    names, mats = [], []
    for key, (n, cov) in blocks.items():
        if key in updated:
            names += n
            mats.append(np.asarray(cov, dtype=np.float64))
    if not names:
        return {}
    M = np.zeros((len(names), len(names)))
    i = 0
    for m in mats:
        M[i:i + len(m), i:i + len(m)] = m
        i += len(m)
    return covariance_record(names, M)


def line_distance(p1, d1, p2, d2) -> float:
    """Shortest distance between two lines (points p, directions d), metres."""
    p1, d1, p2, d2 = (np.asarray(x, dtype=np.float64) for x in (p1, d1, p2, d2))
    c = np.cross(d1, d2)
    nc = np.linalg.norm(c)
    w = p2 - p1
    if nc < 1e-12 * np.linalg.norm(d1) * np.linalg.norm(d2):
        d = d1 / np.linalg.norm(d1)
        return float(np.linalg.norm(w - (w @ d) * d))
    return float(abs(w @ c) / nc)


# ----------------------------------------------------------------------------- stage
def run_laser_axis(views, calibration, *, board, extractor_config=None, k_sigma: float = 4.0,
                   max_pnp_rms_px: float = 0.5, min_stripe_points: int = 20,
                   min_poses: int = 2, min_spread: float = 1e-3,
                   fit_offset: bool | None = None, poly_degree: int | None = None,
                   anchor=(0.0, 0.0, 0.0), method: str | None = None,
                   edge_margin: float = 0.6e-3, bundle: bool | None = None) -> StageResult:
    """Calibrate the G2 tilt axis (n, P) and the G2 tilt angle per volt.

    Parameters
    ----------
    views : list of CaptureView
        Per board pose (``pose_index``): laser-off views of the board and laser-on views at
        several G2 tilt voltages, at the same G1 voltages as a laser-off view of that pose.
        G1 may be anywhere (planes are mapped to V0 with the current model), but G1 = 0
        avoids the dynamic-camera model's error. Each G2 voltage needs the stripe on at
        least ``min_poses`` board poses to give a plane.
    calibration : reconstructor.calibration_file.Calibration
        Current calibration: intrinsics, dynamic camera; the current axis direction fixes
        the sign of n (and so of k).
    board : board_layout.Checkerboard or board_layout.CircleGrid
    extractor_config : stripe_extractor.extractor.ExtractorConfig, optional
    poly_degree : int, optional
        As :func:`fit_axis`. Default: 2 with the physical model (G2's response curves: gain
        and square; the cube too made the shape error worse on 3 of 7 rigs, up to 0.59 mm,
        where the square alone improved all 7), 1 with the paper's (its linear θ4 = k2 U, as
        published).
    fit_offset, method : optional
        As :func:`fit_axis`. Default with the physical model: ``'cone'`` with the offset (the
        planes a real G2 sweeps do not contain its axis: the fan is not square to the
        mirror axis, the mirror surface is off the axis; on a drawn rig the paper's planes
        through one line missed the true planes by up to 73 um, the cone by 9 um), from
        :data:`CONE_MIN_PLANES` planes on; with the paper's, or fewer planes: ``'paper'``,
        no offset, as published (needs only 2 planes).
    anchor
        See :func:`fit_axis` (``method='cone', fit_offset=True`` for a laser whose fan does
        not contain the mirror axis). Planes are weighted by the squared spread of their points
        across the stripe (a plane from nearby board poses has a poorly known tilt).
    k_sigma, max_pnp_rms_px, min_stripe_points, min_poses, min_spread, edge_margin
        See :func:`laser_plane.board_stripe_points` and :func:`laser_plane.plane_from_stripes`.
    bundle : bool, optional
        End with the laser's bundle adjustment (:mod:`calibration_tools.laser_bundle`): the
        U2 = 0 plane, the axis and G2's response fitted to every stripe point at once,
        started from the staged fit. Default: with the physical model's cone fit. When the
        views cannot determine the laser the staged fit stands (logged, and
        ``bundle_failed`` in the residuals).

    Returns
    -------
    StageResult
        ``updates``: ``laser_axis_dir``, ``laser_axis_point`` and, when the voltages span
        enough, ``g2_tilt: {'k': ..., 'poly': [...]}``. Residuals: ``axis_angle_rms_rad``,
        ``axis_angle_max_rad``, ``axis_distance_rms_m``, ``axis_distance_max_m``,
        ``axis_offset_m``, ``axis_cone_angle_rad``, ``plane_rms_max_m``, ``angle_fit_rms_rad``,
        ``planes_used``. ``standard_errors``: see :func:`axis_standard_errors`. With the
        bundle, ``updates`` also hold ``laser_plane_v0``, the standard errors and covariance
        are the bundle's, and the residuals add ``bundle_point_rms_m``,
        ``bundle_start_rms_m``, ``bundle_views``, ``bundle_points``,
        ``bundle_poly_degree`` and ``frame_noise_u2_tilt_V`` (G2's per-frame noise,
        :func:`calibration_tools.laser_bundle._g2_frame_noise`). Without it,
        ``axis_lack_of_fit`` (the planes' reduced chi-square about the axis model,
        :func:`lack_of_fit`) where every plane has 3 views.

    Raises
    ------
    ValueError
        Fewer than 2 (3 with ``fit_offset``) usable planes; the reasons are in the message.
    """
    model = calibration.model
    physical = model.kind == 'physical'
    if poly_degree is None:
        poly_degree = 2 if physical else 1
    coll = board_stripe_points(views, model, board, extractor_config=extractor_config,
                               max_pnp_rms_px=max_pnp_rms_px,
                               min_stripe_points=min_stripe_points, edge_margin=edge_margin)
    rejected = list(coll.rejected)
    groups: dict[int, list] = {}
    for s in coll.stripes:
        groups.setdefault(int(round(s.u2_tilt / VOLTAGE_TOL)), []).append(s)
    planes, volts, rms, weights, used = [], [], [], [], []
    orient = model.laser_plane_v0[:3]
    for key in sorted(groups):
        stripes = groups[key]
        u2 = float(np.mean([s.u2_tilt for s in stripes]))
        try:
            fit = plane_from_stripes(stripes, k_sigma=k_sigma, orient=orient,
                                     min_poses=min_poses, min_spread=min_spread)
        except ValueError as exc:
            msg = f'U2_tilt = {u2:.4f} V: {exc}'
            log.warning('rejected: %s', msg)
            rejected.append(msg)
            continue
        planes.append(fit.plane)
        used.append((stripes, fit.inliers))
        volts.append(u2)
        rms.append(fit.rms)
        # A plane's tilt across the stripe is known to about (pose error) / (spread of its
        # points across the stripe): weight by the spread squared.
        weights.append(fit.singular_values[1] ** 2)
    # the cone and its offset from as many planes as CONE_MIN_PLANES (a quick plan's three
    # determine them exactly and leave their noise in; the line then fits better)
    cone = physical and len(planes) >= CONE_MIN_PLANES
    method = ('cone' if cone else 'paper') if method is None else method
    fit_offset = cone if fit_offset is None else fit_offset
    need = 3 if fit_offset else 2
    if len(planes) < need:
        raise ValueError(f'laser_axis: {len(planes)} usable laser plane(s), at least {need} '
                         f'needed; rejected: {rejected}')
    fit = fit_axis(np.array(planes), np.array(volts), weights=np.array(weights), anchor=anchor,
                   reference_dir=model.laser_axis_dir, fit_offset=fit_offset,
                   poly_degree=poly_degree, method=method)
    updates = {'laser_axis_dir': [float(v) for v in fit.direction],
               'laser_axis_point': [float(v) for v in fit.point]}
    if fit.k is not None:
        updates['g2_tilt'] = {'k': fit.k, 'poly': list(fit.poly)}
    residuals = {
        'axis_angle_rms_rad': float(np.sqrt(np.mean(fit.plane_angle_rad ** 2))),
        'axis_angle_max_rad': float(fit.plane_angle_rad.max()),
        'axis_distance_rms_m': float(np.sqrt(np.mean(fit.plane_distance_m ** 2))),
        'axis_distance_max_m': float(np.abs(fit.plane_distance_m).max()),
        'axis_offset_m': fit.offset,
        'axis_cone_angle_rad': fit.cone_angle,
        'plane_rms_max_m': float(max(rms)),
        'planes_used': float(len(planes)),
    }
    if fit.angle_fit_rms_rad is not None:
        residuals['angle_fit_rms_rad'] = fit.angle_fit_rms_rad
    if not math.isfinite(sum(residuals.values())):
        raise ValueError(f'laser_axis: non-finite residuals {residuals}')
    if bundle is None:
        bundle = physical and method == 'cone'
    if bundle:
        try:
            return _bundle_result(calibration, model, updates, residuals, used, coll,
                                  rejected)
        except ValueError as exc:
            log.warning('laser_axis: the laser bundle failed (%s); the staged fit stands', exc)
            residuals['bundle_failed'] = 1.0
    errors = {k: v for k, v in axis_standard_errors(
        fit, np.array(planes), np.array(volts), weights=np.array(weights), anchor=anchor,
        method=method).items() if k in updates}
    blocks = axis_covariance_blocks(fit, np.array(planes), np.array(volts),
                                    weights=np.array(weights), anchor=anchor, method=method)
    record = axis_covariance(blocks, updates)
    if record:
        from reconstructor.uncertainty import camera_inputs, covariance_record

        def axis_of(pl):
            f = fit_axis(np.array(pl), np.array(volts), weights=np.array(weights),
                         anchor=anchor, reference_dir=fit.direction, fit_offset=fit_offset,
                         poly_degree=poly_degree, method=method)
            return _axis_vector(f, record['names'])

        # Jointly, from every plane's own covariance: direction, point and response come
        # from the same planes. By blocks (axis_covariance_blocks) when a plane has fewer
        # than 3 views to give its covariance.
        try:
            covs = []
            for (stripes, inl), pl in zip(used, planes, strict=True):
                pts, views_of = _plane_points(stripes, inl)
                covs.append(plane_covariance(pts, pl, views_of))
        except ValueError as exc:
            log.info('laser_axis covariance by blocks: %s', exc)
        else:
            # direction and point 2 + 2, cone angle and offset, response intercept, k, poly
            fitted = 4 + (method == 'cone') + bool(fit_offset) + 2 + len(fit.poly)
            birge = lack_of_fit(fit, planes, volts, covs, fitted)
            if math.isfinite(birge):
                residuals['axis_lack_of_fit'] = birge
            record = covariance_record(record['names'], with_marginals(
                propagated_covariance(axis_of, planes, covs), np.diag(record['matrix'])))
        record = _with_camera_sensitivity(record, model, used, camera_inputs(calibration),
                                          axis_of, orient)
    return StageResult(stage='laser_axis', updates=updates, residuals=residuals,
                       samples_used=len(coll.stripes), samples_rejected=len(rejected),
                       rejected=rejected, standard_errors=errors, covariance=record)


def _bundle_result(calibration, model, updates, residuals, used, coll, rejected):
    """The stage's result from the laser bundle (:mod:`calibration_tools.laser_bundle`),
    started from the staged fit's ``updates``, over every plane's inlier stripe points."""
    from reconstructor.model import RigModel
    from reconstructor.uncertainty import camera_inputs, frame_noise

    from .laser_bundle import bundle_covariance_record, fit_laser_bundle

    data = model.to_dict()
    data.update({k: v for k, v in updates.items() if k != 'g2_tilt'})
    if 'g2_tilt' in updates:
        data['g2_tilt'] = {**data['g2_tilt'], **updates['g2_tilt']}
    start = RigModel.from_dict(data, correction=model.correction)
    stripes = []
    for plane_stripes, inliers in used:
        keep = np.split(inliers, np.cumsum([len(s.points_v0) for s in plane_stripes])[:-1])
        stripes += [(s.points_v0[k], s.u2_tilt, *s.u1)
                    for s, k in zip(plane_stripes, keep, strict=True) if k.any()]
    b = fit_laser_bundle(start, stripes, g1_frame_noise_v=frame_noise(calibration))
    out = dict(residuals)
    out.update({'bundle_point_rms_m': b.rms_m, 'bundle_start_rms_m': b.rms_start_m,
                'bundle_views': float(b.views), 'bundle_points': float(b.points),
                'bundle_poly_degree': float(b.poly_degree)})
    if np.isfinite(b.frame_noise_u2_V):
        out['frame_noise_u2_tilt_V'] = b.frame_noise_u2_V
    record = bundle_covariance_record(b, model, camera_inputs(calibration))
    return StageResult(stage='laser_axis', updates=b.updates, residuals=out,
                       samples_used=len(coll.stripes), samples_rejected=len(rejected),
                       rejected=rejected, standard_errors=b.standard_errors(),
                       covariance=record)


def with_marginals(cov, variances) -> np.ndarray:
    """``cov``'s correlations with the given variances: ``D^1/2 R D^1/2``."""
    cov = np.asarray(cov, dtype=np.float64)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    R = cov / np.outer(np.where(sd > 0, sd, 1.0), np.where(sd > 0, sd, 1.0))
    s = np.sqrt(np.clip(np.asarray(variances, dtype=np.float64), 0.0, None))
    return R * np.outer(s, s)


def lack_of_fit(fit: AxisFit, planes, voltages, plane_covs, n_params: int) -> float:
    """Reduced chi-square (Birge ratio) of the planes about the fitted axis model.

    Per plane three residuals, each over its sigma from the plane's own covariance: its angle
    to the axis off the cone's (``plane_angle_rad``), its distance to the axis
    (``plane_distance_m``) and its rotation about the axis off G2's fitted response. Their
    squares summed over ``3 m - n_params`` degrees of freedom. Above 1 the planes scatter
    more than their views say: errors common to a plane's views (the G2 angle of the frame
    that lit them: one draw of the galvo's jitter for all its boards) and what the model
    leaves out (G2's mirror held ideal, the response's higher terms). The covariance
    carried from the planes is scaled by it, as a least-squares fit with an unknown noise
    level scales its own.

    Returns
    -------
    float
        NaN when there are no degrees of freedom.
    """
    n = fit.direction
    pl = _unit_planes(planes)
    m = len(pl)
    dof = 3 * m - n_params
    if dof <= 0:
        return math.nan
    u = np.asarray(voltages, dtype=np.float64)
    V = np.column_stack([np.ones(m)] + [u ** (p + 1) for p in range(1 + len(fit.poly))])
    rot_res = fit.rotation_rad - V @ np.linalg.lstsq(V, fit.rotation_rad, rcond=None)[0]
    chi2 = 0.0
    for i, C in enumerate(plane_covs):
        C = np.asarray(C, dtype=np.float64)
        ni = pl[i, :3]
        turn = np.cross(n, ni)  # how n_i moves when the plane turns about the axis
        turn /= max(np.linalg.norm(turn), 1e-300)
        grads = (np.append(n, 0.0), np.append(fit.point, 1.0), np.append(turn, 0.0))
        res = (fit.plane_angle_rad[i], fit.plane_distance_m[i], rot_res[i])
        for g, r in zip(grads, res, strict=True):
            var = float(g @ C @ g)
            if var > 0.0:
                chi2 += float(r) ** 2 / var
    return chi2 / dof


def _plane_points(stripes, inliers) -> tuple:
    """A plane fit's inlier points and their view (stripe) of each: ``(points, groups)``."""
    pts = np.concatenate([s.points_v0 for s in stripes])
    grp = np.concatenate([np.full(len(s.points_v0), k) for k, s in enumerate(stripes)])
    return pts[inliers], grp[inliers]


def propagated_covariance(estimate, planes, plane_covs) -> np.ndarray:
    """Covariance of ``estimate(planes)`` (a vector) from independent planes' covariances.

    Every plane is moved by +-1 sigma along each principal direction of its covariance and
    the estimate made again: the central differences are the columns ``g`` of a square root,
    and the covariance is ``sum g g^T``. All of the estimate's outputs keep their
    correlations (the axis direction, its point and G2's response come from the same planes).

    Parameters
    ----------
    estimate : callable
        List of (4,) planes -> ndarray (p,).
    planes : sequence of array_like, shape (4,)
    plane_covs : sequence of ndarray, shape (4, 4)
        Each plane's covariance, in its (a, b, c, e).

    Returns
    -------
    ndarray, shape (p, p)
    """
    base = [np.asarray(pl, dtype=np.float64) for pl in planes]
    cols = []
    for i, C in enumerate(plane_covs):
        lam, vec = np.linalg.eigh(np.asarray(C, dtype=np.float64))
        for val, v in zip(lam, vec.T, strict=True):
            if not val > 0.0:
                continue
            step = math.sqrt(val) * v
            plus, minus = list(base), list(base)
            plus[i], minus[i] = base[i] + step, base[i] - step
            cols.append(0.5 * (np.asarray(estimate(plus)) - np.asarray(estimate(minus))))
    G = np.array(cols)
    return G.T @ G


def _axis_vector(fit: AxisFit, names) -> np.ndarray:
    """An axis fit's values in the order of its covariance record's ``names``."""
    values = {**{f'laser_axis_dir[{j}]': fit.direction[j] for j in range(3)},
              **{f'laser_axis_point[{j}]': fit.point[j] for j in range(3)},
              'g2_tilt.k': fit.k if fit.k is not None else 0.0,
              **{f'g2_tilt.poly[{j}]': c for j, c in enumerate(fit.poly)}}
    return np.array([values.get(n, 0.0) for n in names], dtype=np.float64)


def _with_camera_sensitivity(record, model, used, inputs, axis_of, orient) -> dict:
    """The axis record with its sensitivity to the camera's calibrated parameters: every
    plane's inlier stripe points as the moved camera would have measured them
    (:func:`reconstructor.uncertainty.remeasured_sensitivity`), the planes (``used``: per
    plane its stripes and inlier mask) and the axis (``axis_of(planes)``) fitted again."""
    from reconstructor.uncertainty import covariance_record, remeasured_sensitivity

    from .laser_plane import _svd_plane, inlier_groups

    if not inputs:
        return record
    groups, owner = [], []
    for k, (stripes, inliers) in enumerate(used):
        mine = inlier_groups(stripes, inliers)
        groups += mine
        owner += [k] * len(mine)

    def estimate(pts):
        planes = []
        for k in range(len(used)):
            pl, _ = _svd_plane(np.concatenate([p for p, o in zip(pts, owner, strict=True)
                                               if o == k]))
            planes.append(pl if pl[:3] @ orient > 0 else -pl)
        return axis_of(planes)

    S = remeasured_sensitivity(model, groups, inputs, estimate)
    return covariance_record(record['names'], record['matrix'], list(inputs),
                             S.reshape(len(record['names']), len(inputs)))
