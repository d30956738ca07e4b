"""Triangulation of stripe pixels against the dynamic laser plane (docs/design.md §2, Eq. 8), and
prediction of pixels from V0 points.

For an undistorted normalised ray ``r = (x, y, 1)`` in V and the laser plane
``pi_V = (a, b, c, e)`` in V: ``Z = -e / (a x + b y + c)``, ``p_V = Z r``,
``p_V0 = V0_T_V @ p_V`` (then the joint correction, if the model has one).

A point is invalid when its pixel or any voltage of its frame is non-finite, when its
undistortion does not converge, when its ray meets the plane at less than ``min_angle``
(nearly parallel), or when the intersection is not in front of the camera (``Z <= 0``).
Invalid points keep their row, are set to 0 in ``p_v`` and ``p_v0`` (never NaN) and are False
in ``valid``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .camera import CameraIntrinsics, project_points, undistort_normalised
from .checks import as_float_array, as_points, as_scalar
from .galvo import rigid_inverse
from .laser import laser_plane_v0, laser_plane_v0_scalar, transform_plane
from .rig import RigModel, v0_T_v, v0_T_v_scalar

#: Default smallest angle between a pixel ray and the laser plane, radians.
DEFAULT_MIN_RAY_PLANE_ANGLE = 1e-3


@dataclass(eq=False, slots=True)
class TriangulationResult:
    """Triangulated points; one row per input pixel.

    Attributes
    ----------
    p_v : ndarray, shape (n, 3), metres
        Points in their frame's virtual camera V (0 where invalid).
    p_v0 : ndarray, shape (n, 3), metres
        Points in V0, after the joint correction if the model has one (0 where invalid).
    valid : ndarray of bool, shape (n,)
    n_nonfinite : int
        Points with a non-finite pixel or a non-finite voltage in their frame.
    n_unconverged : int
        Points whose undistortion did not converge (no preimage under the lens distortion).
    n_parallel : int
        Points whose ray is within ``min_angle`` of parallel to the laser plane.
    n_behind : int
        Points whose intersection is not in front of the camera (Z <= 0).

    ``p_v`` and ``p_v0`` may be transposed views of (3, n) arrays (not C-contiguous).
    """

    p_v: np.ndarray
    p_v0: np.ndarray
    valid: np.ndarray
    n_nonfinite: int = 0
    n_unconverged: int = 0
    n_parallel: int = 0
    n_behind: int = 0

    @property
    def n_invalid(self) -> int:
        """Total number of invalid points."""
        return self.n_nonfinite + self.n_unconverged + self.n_parallel + self.n_behind


def _check_min_angle(min_angle) -> float:
    a = as_scalar(min_angle, "min_angle")
    if not 0.0 <= a < math.pi / 2:
        raise ValueError(f"min_angle must be in [0, pi/2), got {a}")
    return a


def _rays(intr: CameraIntrinsics, uv: np.ndarray):
    """Undistorted rays of pixels ``uv`` (n, 2): see :func:`undistort_normalised`."""
    plan = intr._plan
    xd = np.subtract(uv.T, plan.c, order="C")
    xd *= plan.finv
    return undistort_normalised(intr, xd)


def _angle_ok(x: np.ndarray, denom: np.ndarray, sin_min: float) -> np.ndarray:
    """Per-ray test ``|cos(normal, ray)| >= sin(min_angle)`` for a unit normal."""
    r2 = x[0] * x[0] + x[1] * x[1]
    return denom * denom >= (sin_min * sin_min) * (1.0 + r2)


def _bookkeeping(p_v, p_v0, ok, front, finite, converged):
    """Zero invalid rows and count the reasons; arrays are (3, n)."""
    n = ok.shape[0]
    good_in = np.ones(n, dtype=bool) if finite is None else finite.copy()
    conv = np.ones(n, dtype=bool) if converged is None else converged
    unconv = good_in & ~conv
    reach = good_in & conv
    parallel = reach & ~ok
    behind = reach & ok & ~front
    valid = reach & ok & front
    p_v[:, ~valid] = 0.0
    p_v0[:, ~valid] = 0.0
    return TriangulationResult(
        p_v=p_v.T,
        p_v0=p_v0.T,
        valid=valid,
        n_nonfinite=int(n - np.count_nonzero(good_in)),
        n_unconverged=int(np.count_nonzero(unconv)),
        n_parallel=int(np.count_nonzero(parallel)),
        n_behind=int(np.count_nonzero(behind)),
    )


@numba.njit(cache=True, nogil=True)
def _hot_path(uv, cx, cy, fxi, fyi, s_max, distorted, use_guess, n_fast, k1, k2, k3, p1, p2,
              b1, b2, b3, plane, threshold, T, p_v, p_v0):  # pragma: no cover - numba
    """The common frame in one compiled pass: every pixel in the hot-path disk and every ray
    clearly in front of the camera and not near-parallel to the plane.

    Same formulas, in the same order, as :func:`undistort_normalised`'s disk branch and the
    numpy hot path of :func:`triangulate`. Fills ``p_v`` and ``p_v0`` (shape (3, n)) and
    returns True, or returns False as soon as a point needs the general path (the outputs
    are then meaningless).
    """
    n = uv.shape[0]
    neg_e = -plane[3]
    if neg_e == 0.0:
        return False
    lo = np.inf
    hi = -np.inf
    for i in range(n):
        xd = (uv[i, 0] - cx) * fxi
        yd = (uv[i, 1] - cy) * fyi
        sq = xd * xd + yd * yd
        if not sq <= s_max:                     # also False for NaN
            return False
        x = xd
        y = yd
        if distorted:
            if use_guess:
                f = 1.0 + sq * (b1 + sq * (b2 + sq * b3))
                dot = 2.0 * p2 * xd + 2.0 * p1 * yd
                x = xd * f - (dot * xd + sq * p2)
                y = yd * f - (dot * yd + sq * p1)
            for _ in range(n_fast):
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                dot = 2.0 * p2 * x + 2.0 * p1 * y
                x, y = (xd - (dot * x + r2 * p2)) / radial, (yd - (dot * y + r2 * p1)) / radial
        denom = plane[0] * x + plane[1] * y + plane[2]
        lo = min(lo, denom)
        hi = max(hi, denom)
        p_v[0, i] = x
        p_v[1, i] = y
        p_v[2, i] = denom
    if not ((neg_e > 0.0 and lo > threshold) or (neg_e < 0.0 and hi < -threshold)):
        return False
    for i in range(n):
        Z = neg_e / p_v[2, i]
        px = p_v[0, i] * Z
        py = p_v[1, i] * Z
        p_v[0, i] = px
        p_v[1, i] = py
        p_v[2, i] = Z
        for r in range(3):
            p_v0[r, i] = T[r, 0] * px + T[r, 1] * py + T[r, 2] * Z + T[r, 3]
    return True


def _try_hot_path(intr: CameraIntrinsics, uv, plane_v, sin_min, T):
    """``(p_v, p_v0)`` of shape (3, n) from :func:`_hot_path`, or None."""
    plan = intr._plan
    n = uv.shape[0]
    if n == 0 or plan.s_max < 0.0:
        return None
    p_v = np.empty((3, n))
    p_v0 = np.empty((3, n))
    ok = _hot_path(np.ascontiguousarray(uv), *plan.kernel_args,
                   np.ascontiguousarray(plane_v, dtype=np.float64),
                   sin_min * plan.ray_norm_max, np.ascontiguousarray(T, dtype=np.float64),
                   p_v, p_v0)
    return (p_v, p_v0) if ok else None


def _all_invalid(n: int) -> TriangulationResult:
    return TriangulationResult(
        p_v=np.zeros((n, 3)), p_v0=np.zeros((n, 3)), valid=np.zeros(n, dtype=bool), n_nonfinite=n
    )


def triangulate(
    model: RigModel,
    uv,
    u1_pan,
    u1_tilt,
    u2_tilt,
    *,
    min_angle: float = DEFAULT_MIN_RAY_PLANE_ANGLE,
) -> TriangulationResult:
    """Triangulate the stripe pixels of one frame.

    Parameters
    ----------
    model : RigModel
    uv : array_like, shape (n, 2), pixels
        Distorted stripe-centre pixel coordinates (undistorted here).
    u1_pan, u1_tilt, u2_tilt : float, volts
        G1 pan, G1 tilt and G2 tilt voltages of the frame (non-finite -> all points invalid).
    min_angle : float, radians
        Rays meeting the laser plane at a smaller angle are invalid.

    Returns
    -------
    TriangulationResult
    """
    uv = as_points(uv, "uv", 2)
    u1p = as_scalar(u1_pan, "u1_pan")
    u1t = as_scalar(u1_tilt, "u1_tilt")
    u2t = as_scalar(u2_tilt, "u2_tilt")
    sin_min = math.sin(_check_min_angle(min_angle))
    n = uv.shape[0]
    if not (math.isfinite(u1p) and math.isfinite(u1t) and math.isfinite(u2t)):
        return _all_invalid(n)
    T = v0_T_v_scalar(model, u1p, u1t)
    plane_v = T.T @ np.array(laser_plane_v0_scalar(model, u2t))
    if model.correction is not None:
        T = np.asarray(model.correction.V0c_T_V0(u1p, u1t), dtype=np.float64) @ T
    hot = _try_hot_path(model.intrinsics, uv, plane_v, sin_min, T)
    if hot is not None:
        return TriangulationResult(p_v=hot[0].T, p_v0=hot[1].T, valid=np.ones(n, dtype=bool))
    x, finite, converged, in_disk = _rays(model.intrinsics, uv)
    neg_e = -float(plane_v[3])
    if in_disk and neg_e != 0.0:
        # Hot path: one reduction proves, for every ray at once, |denom| > sin(min_angle)
        # * max |ray| (not nearly parallel) and sign(denom) = sign(-e), i.e. Z > 0.
        denom = plane_v[:2] @ x
        denom += plane_v[2]
        threshold = sin_min * model.intrinsics._plan.ray_norm_max
        if neg_e > 0.0:
            fast = denom.min() > threshold
        else:
            fast = denom.max() < -threshold
        if fast:
            Z = neg_e / denom
            p_v, p_v0 = _points(x, Z, T)
            return TriangulationResult(p_v=p_v.T, p_v0=p_v0.T, valid=np.ones(n, dtype=bool))
    with np.errstate(all="ignore"):
        denom = plane_v[:2] @ x
        denom += plane_v[2]
        ok = _angle_ok(x, denom, sin_min)
        Z = np.divide(neg_e, denom, out=np.zeros_like(denom), where=ok)
        p_v, p_v0 = _points(x, Z, T)
    return _bookkeeping(p_v, p_v0, ok, Z > 0.0, finite, converged)


def _points(x: np.ndarray, Z: np.ndarray, T: np.ndarray):
    """Points in V and in V0 (via ``T``, shape (4, 4)), both shape (3, n)."""
    p_v = np.empty((3, Z.shape[0]))
    np.multiply(x, Z, out=p_v[:2])
    p_v[2] = Z
    p_v0 = T[:3, :3] @ p_v
    p_v0 += T[:3, 3:]
    return p_v, p_v0


def triangulate_batch(
    model: RigModel,
    uv,
    frame_index,
    voltages,
    *,
    min_angle: float = DEFAULT_MIN_RAY_PLANE_ANGLE,
) -> TriangulationResult:
    """Triangulate the stripe pixels of several frames at once.

    Parameters
    ----------
    model : RigModel
    uv : array_like, shape (n, 2), pixels
        Distorted stripe-centre pixel coordinates of all frames.
    frame_index : array_like of int, shape (n,)
        Row of ``voltages`` that each pixel belongs to, in [0, m).
    voltages : array_like, shape (m, 4), volts
        Per frame ``(U1_pan, U1_tilt, U2_pan, U2_tilt)``. U2_pan does not enter the model
        (the paper's model has no G2 pan term) but a non-finite value still invalidates the
        frame, like any other non-finite voltage.
    min_angle : float, radians
        Rays meeting the laser plane at a smaller angle are invalid.

    Returns
    -------
    TriangulationResult
    """
    uv = as_points(uv, "uv", 2)
    volts = as_points(voltages, "voltages", 4)
    fi = frame_index if isinstance(frame_index, np.ndarray) else np.asarray(frame_index)
    n, m = uv.shape[0], volts.shape[0]
    if fi.shape != (n,):
        raise ValueError(f"frame_index must have shape ({n},) like uv, got {fi.shape}")
    if n and not np.issubdtype(fi.dtype, np.integer):
        raise ValueError(f"frame_index must be integers, got dtype {fi.dtype}")
    if n and (fi.min() < 0 or fi.max() >= m):
        raise ValueError(f"frame_index must be in [0, {m}), got [{fi.min()}, {fi.max()}]")
    sin_min = math.sin(_check_min_angle(min_angle))
    frame_ok = np.isfinite(volts).all(axis=1)
    v = np.where(frame_ok[:, None], volts, 0.0)
    T = v0_T_v(model, v[:, 0], v[:, 1])
    plane_v = transform_plane(T, laser_plane_v0(model, v[:, 3]))
    if model.correction is not None:
        C = np.asarray(model.correction.V0c_T_V0(v[:, 0], v[:, 1]), dtype=np.float64)
        T = C @ T
    x, finite, converged, _ = _rays(model.intrinsics, uv)
    if not frame_ok.all():
        point_ok = frame_ok[fi]
        finite = point_ok if finite is None else finite & point_ok
    with np.errstate(all="ignore"):
        pl = plane_v[fi].T  # (4, n)
        denom = pl[0] * x[0] + pl[1] * x[1] + pl[2]
        ok = _angle_ok(x, denom, sin_min)
        Z = np.divide(-pl[3], denom, out=np.zeros_like(denom), where=ok)
        front = Z > 0.0
        p_v = np.empty((3, n))
        np.multiply(x, Z, out=p_v[:2])
        p_v[2] = Z
        Tp = T[fi]
        p_v0 = (Tp[:, :3, :3] @ p_v.T[:, :, None])[:, :, 0].T + Tp[:, :3, 3].T
        return _bookkeeping(p_v, p_v0, ok, front, finite, converged)


def predict_pixels(model: RigModel, p_v0, u1_pan, u1_tilt) -> tuple[np.ndarray, np.ndarray]:
    """Project V0 points into the image for given G1 voltages, with distortion.

    Parameters
    ----------
    model : RigModel
    p_v0 : array_like, shape (n, 3), metres
        Points in V0 (the corrected V0 if the model has a joint correction, i.e. the frame
        that :func:`triangulate` outputs).
    u1_pan, u1_tilt : float or array_like of shape (n,), volts
        G1 voltages, one pair for all points or one pair per point.

    Returns
    -------
    uv : ndarray, shape (n, 2), pixels
        Distorted pixel coordinates; NaN where ``in_front`` is False.
    in_front : ndarray of bool, shape (n,)
        True where the point is finite and in front of the virtual camera (Z > 0). Image
        bounds are not checked.
    """
    p = as_points(p_v0, "p_v0", 3)
    n = p.shape[0]
    up = as_float_array(u1_pan, "u1_pan")
    ut = as_float_array(u1_tilt, "u1_tilt")
    for name, arr in (("u1_pan", up), ("u1_tilt", ut)):
        if arr.shape not in ((), (n,)):
            raise ValueError(f"{name} must be a scalar or have shape ({n},), got {arr.shape}")
    T = v0_T_v(model, up, ut)
    if model.correction is not None:
        C = np.asarray(model.correction.V0c_T_V0(up, ut), dtype=np.float64)
        T = C @ T
        V_T_V0 = np.linalg.inv(T)
    else:
        V_T_V0 = rigid_inverse(T)
    with np.errstate(all="ignore"):
        if V_T_V0.ndim == 2:
            p_v = p @ V_T_V0[:3, :3].T + V_T_V0[:3, 3]
        else:
            p_v = (V_T_V0[:, :3, :3] @ p[:, :, None])[:, :, 0] + V_T_V0[:, :3, 3]
    uv = project_points(model.intrinsics, p_v)
    in_front = np.isfinite(uv).all(axis=1)
    return uv, in_front
