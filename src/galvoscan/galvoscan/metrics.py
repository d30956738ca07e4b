"""Accuracy figures of reconstructed clouds against the scene's ground truth (no rclpy).

The protocols follow the paper's experiments section:

- stair block: fit Plane-2 (the upper face) by least squares, take the mean distance of up
  to 500 random Plane-1 (lower face) points to it; the error is that thickness minus the
  true step height. Faces are told apart with the scene's known object pose (as a person
  marks regions in a viewer); every distance is computed from reconstructed points only.
- flat plate: a RANSAC plane, then point-to-plane distances.
- sphere: a least-squares sphere; radius error and fit RMS.

All inputs and outputs in metres unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _points(points, name='points') -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f'{name}: expected shape (n, 3) in metres, got {p.shape}')
    return p[np.all(np.isfinite(p), axis=1)]


def to_frame(A_T_B, points_B) -> np.ndarray:
    """Map (n, 3) points from frame B to frame A."""
    T = np.asarray(A_T_B, dtype=np.float64)
    return _points(points_B) @ T[:3, :3].T + T[:3, 3]


def fit_plane(points) -> tuple[np.ndarray, float]:
    """Least-squares plane (a, b, c, e), unit normal, and the RMS distance [m]."""
    p = _points(points)
    if p.shape[0] < 3:
        raise ValueError(f'points: need at least 3 to fit a plane, got {p.shape[0]}')
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    plane = np.append(n, -n @ c)
    return plane, float(np.sqrt(np.mean((p @ n + plane[3]) ** 2)))


def ransac_plane(points, threshold=0.5e-3, iterations=2000, seed=0):
    """RANSAC plane (unit normal) refined by least squares on its inliers.

    Returns
    -------
    plane : ndarray, shape (4,)
    inliers : ndarray of bool, shape (n,)
    """
    p = _points(points)
    if p.shape[0] < 3:
        raise ValueError(f'points: need at least 3 to fit a plane, got {p.shape[0]}')
    rng = np.random.default_rng(seed)
    best, best_count = None, -1
    for _ in range(iterations):
        a, b, c = p[rng.choice(p.shape[0], 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int(np.count_nonzero(np.abs((p - a) @ n) < threshold))
        if count > best_count:
            best, best_count = np.append(n, -n @ a), count
    inliers = np.abs(p @ best[:3] + best[3]) < threshold
    plane, _ = fit_plane(p[inliers])
    return plane, np.abs(p @ plane[:3] + plane[3]) < threshold


def fit_sphere(points) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere: centre (3,), radius and RMS radial residual [m]."""
    from scipy.optimize import least_squares

    p = _points(points)
    if p.shape[0] < 4:
        raise ValueError(f'points: need at least 4 to fit a sphere, got {p.shape[0]}')
    A = np.column_stack([2 * p, np.ones(p.shape[0])])
    sol, *_ = np.linalg.lstsq(A, (p ** 2).sum(axis=1), rcond=None)
    c0 = sol[:3]
    r0 = np.sqrt(max(sol[3] + c0 @ c0, 0.0))

    def res(x):
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    fit = least_squares(res, np.append(c0, r0), method='lm')
    return fit.x[:3], float(fit.x[3]), float(np.sqrt(np.mean(fit.fun ** 2)))


@dataclass
class StairResult:
    thickness: float       # measured Plane-1 to Plane-2 distance [m]
    error: float           # thickness - true step height [m]
    n_plane1: int
    n_plane2: int
    plane2_rms: float      # RMS of the Plane-2 fit [m]


def stair_step(points_O, size, step_height, margin=3e-3, samples=500, seed=0) -> StairResult:
    """The paper's stair-block thickness from points given in the block's own frame O.

    The block (galvoscan_sim scene type ``stair_block``) rests on z = 0 with its lower top
    face (Plane-1, x < 0) at z = -size[2] and its upper top face (Plane-2, x >= 0) at
    z = -size[2] - step_height. Points within ``margin`` of an edge, or more than 5 mm from
    either face, are not used.

    Parameters
    ----------
    points_O : array_like, shape (n, 3), metres
        Reconstructed points mapped into the block frame with the known block pose.
    """
    p = _points(points_O, 'points_O')
    sx, sy, sz = size
    inside = (np.abs(p[:, 1]) < sy / 2 - margin) & (np.abs(p[:, 0]) < sx / 2 - margin)
    z1, z2 = -sz, -sz - step_height
    plane1 = p[inside & (p[:, 0] < -margin) & (np.abs(p[:, 2] - z1) < 5e-3)]
    plane2 = p[inside & (p[:, 0] > margin) & (np.abs(p[:, 2] - z2) < 5e-3)]
    if plane1.shape[0] < 20 or plane2.shape[0] < 20:
        raise ValueError(f'stair: too few points on the faces ({plane1.shape[0]} on Plane-1, '
                         f'{plane2.shape[0]} on Plane-2)')
    pl2, rms2 = fit_plane(plane2)
    rng = np.random.default_rng(seed)
    pick = plane1[rng.choice(plane1.shape[0], min(samples, plane1.shape[0]), replace=False)]
    thickness = float(np.mean(np.abs(pick @ pl2[:3] + pl2[3])))
    return StairResult(thickness, thickness - step_height, plane1.shape[0], plane2.shape[0],
                       rms2)


def rmse(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float('nan')
