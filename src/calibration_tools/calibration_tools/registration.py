"""Rigid registration of point clouds for the joint correction, and the paper's errors.

- :func:`register_icp`: open3d point-to-point ICP with an explicit convergence check (a
  further run from the result must not move it) and an overlap check (fitness).
- :func:`register_sphere_centres`: closed form, no correspondences: the translation that
  moves one fitted sphere centre onto another. A sphere has no orientation, so this gives
  the translation only (rotation = identity).
- :func:`registration_errors`: the paper's Error1 (nearest neighbours before registration),
  Error2 (matched pairs after) and Error3 (the same pairs, before), per point.

All transforms map source coordinates onto the target: ``p_target = T @ p_source``. No rclpy.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from calibration_tools.sphere_fit import finite_rows

log = logging.getLogger('galvoscan.calibration.registration')


def _cloud(points, name: str, min_n: int = 3) -> np.ndarray:
    """Checked point cloud, shape (n, 3), metres (:func:`sphere_fit.finite_rows`)."""
    return finite_rows(points, name, min_n)


def _transform(T, name='init') -> np.ndarray:
    T = np.eye(4) if T is None else np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f'{name} must be a finite (4, 4) transform, got shape {T.shape}')
    return T


def apply_transform(T, points) -> np.ndarray:
    """``T @ p`` for points, shape (n, 3) -> (n, 3)."""
    T = _transform(T, 'T')
    p = np.asarray(points, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def transform_change(A, B, points) -> float:
    """Largest displacement between ``A @ p`` and ``B @ p`` over points, metres."""
    return float(np.abs(apply_transform(A, points) - apply_transform(B, points)).max())


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`register_icp`.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
        Source-to-target rigid transform.
    fitness : float
        Fraction of source points with a target point within ``max_distance``.
    inlier_rmse : float, metres
        RMS distance of those pairs.
    correspondences : ndarray of int, shape (k, 2)
        (source index, target index) pairs within ``max_distance`` at the result.
    converged : bool
        False when a further ICP run from the result still moved the source by more than
        ``tolerance``.
    message : str
        Why it is not converged, or why the overlap is too small ('' when accepted).
    """

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    correspondences: np.ndarray
    converged: bool
    message: str = ''
    min_fitness: float = 0.0

    @property
    def accepted(self) -> bool:
        """Converged, with at least ``min_fitness`` of the source matched."""
        return self.converged and self.fitness >= self.min_fitness


def register_icp(source, target, *, init=None, max_distance: float = 2e-4,
                 max_iterations: int = 200, min_fitness: float = 0.5,
                 tolerance: float = 1e-7, check_iterations: int = 20,
                 target_tangents=None) -> IcpResult:
    """Point-to-point ICP (open3d) from an initial transform, with a convergence check;
    optionally refined point-to-line for stripe curves.

    Parameters
    ----------
    source, target : array_like, shapes (n, 3) and (m, 3), metres
    init : array_like, shape (4, 4), optional
        Initial source-to-target transform (identity by default).
    max_distance : float, metres
        Correspondences farther apart are ignored.
    max_iterations : int
    min_fitness : float
        Smallest accepted fraction of source points with a correspondence.
    tolerance : float, metres
        Convergence: a further run of ``check_iterations`` iterations from the result must
        move no source point by more than this (with ``target_tangents``: the last
        point-to-line step must move none by more than this).
    check_iterations : int
    target_tangents : array_like, shape (m, 3), optional
        Unit tangents of the target curve. When given, the point-to-point result is refined
        by :func:`refine_point_to_line` (point-to-point ICP converges very slowly along a
        curve's weak directions), and convergence is that refinement's.

    Returns
    -------
    IcpResult
    """
    import open3d as o3d

    src = _cloud(source, 'source')
    tgt = _cloud(target, 'target')
    T0 = _transform(init)
    if not max_distance > 0:
        raise ValueError(f'max_distance must be > 0 m, got {max_distance!r}')
    reg = o3d.pipelines.registration
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    est = reg.TransformationEstimationPointToPoint()

    def run(T, iters):
        crit = reg.ICPConvergenceCriteria(relative_fitness=1e-12, relative_rmse=1e-12,
                                          max_iteration=int(iters))
        return reg.registration_icp(ps, pt, max_distance, T, est, crit)

    res = run(T0, max_iterations)
    T = np.asarray(res.transformation, dtype=np.float64).copy()
    message = ''
    if target_tangents is None:
        check = run(T, check_iterations)
        moved = transform_change(T, np.asarray(check.transformation), src)
        converged = moved <= tolerance
        if not converged:
            message = (f'ICP did not converge: a further {check_iterations} iterations moved '
                       f'the cloud by {moved * 1e6:.3f} um (> {tolerance * 1e6:.3f} um)')
    else:
        cf = refine_point_to_line(src, tgt, target_tangents, init=T, max_distance=max_distance,
                                  max_iterations=max_iterations, tolerance=tolerance)
        T = cf.transform
        converged = cf.converged
        res = reg.evaluate_registration(ps, pt, max_distance, T)
        if not converged:
            message = (f'ICP did not converge: the point-to-line refinement still moved the '
                       f'cloud by more than {tolerance * 1e6:.3f} um after {cf.iterations} '
                       f'iterations ({cf.n_pairs} pairs)')
    if not message and res.fitness < min_fitness:
        message = (f'ICP overlap too small: fitness {res.fitness:.3f} < {min_fitness:.3f} '
                   f'(source points within {max_distance * 1e3:.3f} mm of the target)')
    corr = np.asarray(res.correspondence_set, dtype=np.int64).reshape(-1, 2)
    return IcpResult(transform=T, fitness=float(res.fitness),
                     inlier_rmse=float(res.inlier_rmse), correspondences=corr,
                     converged=converged, message=message, min_fitness=float(min_fitness))


def register_sphere_centres(source_centre, target_centre) -> np.ndarray:
    """Translation moving a source sphere centre onto the target's (closed form).

    Parameters
    ----------
    source_centre, target_centre : array_like, shape (3,), metres

    Returns
    -------
    ndarray, shape (4, 4)
        Pure translation (a sphere fixes no rotation).
    """
    a = np.asarray(source_centre, dtype=np.float64)
    b = np.asarray(target_centre, dtype=np.float64)
    for name, v in (('source_centre', a), ('target_centre', b)):
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f'{name} must be a finite vector of shape (3,)')
    T = np.eye(4)
    T[:3, 3] = b - a
    return T


def _joined(p, f, max_step):
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    same = f[1:] == f[:-1]
    if max_step is None:
        max_step = 3.0 * float(np.median(step[same])) if same.any() else 0.0
    return same & (step <= max_step) & (step > 0.0)


def densify_polylines(points, frame_ids, *, factor: int = 10, max_step=None):
    """Insert points along each frame's stripe polyline (for curve-to-curve matching).

    A stripe is sampled once per image column, about 0.08 mm apart at 650 mm: a nearest
    neighbour in another view's sampling of the same curve is off by up to half that along
    the curve. Linear interpolation between consecutive points of the same frame makes the
    nearest-neighbour distance measure the misalignment instead of the sampling.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres
        Stripe points, each frame's points consecutive and in stripe order.
    frame_ids : array_like of int, shape (n,)
        Frame of each point.
    factor : int
        Points per original segment after densification (>= 1).
    max_step : float, metres, optional
        Consecutive points farther apart are not joined (a gap in the stripe); default three
        times the median step.

    Returns
    -------
    dense : ndarray, shape (m, 3), metres
        The original points plus the inserted ones.
    tangents : ndarray, shape (m, 3)
        Unit direction of the polyline at each point (the segment's direction; for an
        original point the mean of its two segments). Points joined to nothing get the
        direction of their frame's principal axis.
    """
    p = _cloud(points, 'points', 1)
    f = np.asarray(frame_ids)
    if f.shape != (p.shape[0],):
        raise ValueError(f'frame_ids must have shape ({p.shape[0]},), got {f.shape}')
    if not isinstance(factor, int) or factor < 1:
        raise ValueError(f'factor must be an integer >= 1, got {factor!r}')
    n = p.shape[0]
    tang = np.zeros((n, 3))
    if n >= 2:
        join = _joined(p, f, max_step)
        seg = np.diff(p, axis=0)
        seg_u = seg / np.maximum(np.linalg.norm(seg, axis=1), 1e-300)[:, None]
        tang[:-1][join] += seg_u[join]
        tang[1:][join] += seg_u[join]
    else:
        join = np.zeros(0, dtype=bool)
    norms = np.linalg.norm(tang, axis=1)
    lonely = norms < 1e-12
    if lonely.any():
        for fid in np.unique(f[lonely]):
            q = p[f == fid]
            d = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)[2][0] if len(q) > 1 \
                else np.array([1.0, 0.0, 0.0])
            tang[lonely & (f == fid)] = d
        norms = np.linalg.norm(tang, axis=1)
    tang /= norms[:, None]
    if n < 2 or factor == 1 or not join.any():
        return p.copy(), tang
    a, b = p[:-1][join], p[1:][join]
    t = (np.arange(1, factor) / factor)[None, :, None]
    inserted = (a[:, None, :] * (1.0 - t) + b[:, None, :] * t).reshape(-1, 3)
    ins_tang = np.repeat(seg_u[join], factor - 1, axis=0)
    return np.vstack([p, inserted]), np.vstack([tang, ins_tang])


def _skew(v):
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


@dataclass(frozen=True)
class CurveFit:
    """Result of :func:`refine_point_to_line`.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
    converged : bool
        The last Gauss-Newton step moved no source point by more than the tolerance.
    iterations : int
    rms : float, metres
        RMS point-to-line distance of the pairs.
    n_pairs : int
    sigma_twist : ndarray, shape (6,)
        Standard errors of the (rotation [rad], translation [m]) increments about the source
        centroid, from the residual RMS and the Gauss-Newton normal matrix: how well the data
        fix each degree of freedom.
    """

    transform: np.ndarray
    converged: bool
    iterations: int
    rms: float
    n_pairs: int
    sigma_twist: np.ndarray


def refine_point_to_line(source, target, target_tangents, *, init=None,
                         max_distance: float = 2e-4, max_iterations: int = 50,
                         tolerance: float = 1e-9) -> CurveFit:
    """Rigid alignment of a stripe cloud to a stripe curve (Gauss-Newton, point-to-line).

    Each source point is paired with its nearest target point (within ``max_distance``); the
    residual is its offset from the target's local line (the component perpendicular to the
    tangent). Unlike point-to-point ICP, sliding along the curve costs nothing, so the
    iteration converges in a few steps and only the geometry, not the sampling, fixes the
    transform.

    Parameters
    ----------
    source : array_like, shape (n, 3), metres
    target : array_like, shape (m, 3), metres
    target_tangents : array_like, shape (m, 3)
        Unit tangents of the target curve (see :func:`densify_polylines`).
    init : array_like, shape (4, 4), optional
    max_distance : float, metres
    max_iterations : int
    tolerance : float, metres

    Returns
    -------
    CurveFit
    """
    from scipy.spatial import cKDTree

    from reconstructor.correction import rotvec_to_matrix

    src = _cloud(source, 'source')
    tgt = _cloud(target, 'target')
    tan = np.asarray(target_tangents, dtype=np.float64)
    if tan.shape != tgt.shape:
        raise ValueError(f'target_tangents must have shape {tgt.shape}, got {tan.shape}')
    T = _transform(init).copy()
    tree = cKDTree(tgt)
    c = src.mean(axis=0)
    converged = False
    iterations = 0
    rms, npair, H, res_sq = float('nan'), 0, np.eye(6), 0.0
    while iterations < int(max_iterations):
        iterations += 1
        moved = apply_transform(T, src)
        d, j = tree.query(moved)
        ok = d <= max_distance
        npair = int(ok.sum())
        if npair < 6:
            break
        q, t = tgt[j[ok]], tan[j[ok]]
        x = moved[ok] - c
        P = np.eye(3)[None] - t[:, :, None] * t[:, None, :]
        r = (P @ (moved[ok] - q)[:, :, None])[:, :, 0]
        J = P @ np.concatenate([-_skew(x), np.broadcast_to(np.eye(3), x.shape + (3,))],
                               axis=2)
        H = np.einsum('nki,nkj->ij', J, J)
        g = np.einsum('nki,nk->i', J, r)
        res_sq = float(np.sum(r * r))
        rms = float(np.sqrt(res_sq / npair))
        try:
            delta = -np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = rotvec_to_matrix(delta[:3])
        step[:3, 3] = c + delta[3:] - step[:3, :3] @ c  # rotation about the centroid
        newT = step @ T
        change = transform_change(newT, T, src)
        T = newT
        if change <= tolerance:
            converged = True
            break
    dof = max(2 * npair - 6, 1)
    try:
        cov = np.linalg.inv(H) * (res_sq / dof)
        sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sigma = np.full(6, np.inf)
    return CurveFit(transform=T, converged=converged, iterations=iterations, rms=rms,
                    n_pairs=npair, sigma_twist=sigma)


def nearest_neighbours(source, target):
    """Nearest target point of every source point.

    Returns
    -------
    distances : ndarray, shape (n,), metres
    index : ndarray of int, shape (n,)
    """
    from scipy.spatial import cKDTree

    src = _cloud(source, 'source', 1)
    tgt = _cloud(target, 'target', 1)
    d, i = cKDTree(tgt).query(src)
    return d, i


@dataclass(frozen=True)
class RegistrationErrors:
    """Per-point errors of one view against the reference view, metres (paper Eq. 18).

    Attributes
    ----------
    error1 : ndarray, shape (k,)
        Before registration: distance of each matched source point to its nearest target
        point (nearest-neighbour search).
    error2 : ndarray, shape (k,)
        After registration: distance of each pair (source point moved by the transform, its
        nearest target point within ``max_distance``).
    error3 : ndarray, shape (k,)
        Before registration, over the same pairs as error2 (unmoved source point).
    """

    error1: np.ndarray
    error2: np.ndarray
    error3: np.ndarray

    @staticmethod
    def rms(values) -> float:
        v = np.asarray(values, dtype=np.float64)
        return float(np.sqrt(np.mean(v * v))) if v.size else float('nan')


def registration_errors(source, target, transform, *, max_distance: float = 2e-4):
    """The paper's Error1, Error2 and Error3 of a registered view.

    The pairs are the source points that, moved by ``transform``, have a target point within
    ``max_distance`` (the overlap of the two views); all three errors use only these source
    points, so they compare like with like.

    Parameters
    ----------
    source, target : array_like, shapes (n, 3) and (m, 3), metres
    transform : array_like, shape (4, 4)
        Source-to-target registration.
    max_distance : float, metres

    Returns
    -------
    RegistrationErrors
    """
    src = _cloud(source, 'source', 1)
    tgt = _cloud(target, 'target', 1)
    T = _transform(transform, 'transform')
    moved = apply_transform(T, src)
    d_after, idx = nearest_neighbours(moved, tgt)
    pair = d_after <= max_distance
    d_before_pairs = np.linalg.norm(src[pair] - tgt[idx[pair]], axis=1)
    d_nn_before, _ = nearest_neighbours(src[pair], tgt) if pair.any() else (np.zeros(0), None)
    return RegistrationErrors(error1=d_nn_before, error2=d_after[pair], error3=d_before_pairs)
