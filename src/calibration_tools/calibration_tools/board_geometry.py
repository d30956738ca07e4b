"""Projection of board circles through the dynamic camera, and pixel rays onto the board.

The image of a circle is an ellipse whose centre is not the image of the circle's centre
(perspective bias, up to ~0.3 px for 10 mm circles seen obliquely at 650 mm). The detector
measures ellipse centres, so the fit predicts ellipse centres: with the board-to-image
homography ``H = [r1 r2 t]`` of ``V_T_W`` and the dual conic of a circle of radius r centred
at ``c = (cx, cy, 1)``, ``C* = c c^T - r^2 diag(1, 1, 0)``, the centre of the image conic is
the pole of the line at infinity::

    x ~ H C* H^T e3 = p Z - r^2 (R[2, 0] r1 + R[2, 1] r2),

with ``p = R c + t`` the circle centre in V and ``Z = p_z``. Lens distortion is then applied
to that (undistorted, normalised) centre.

Distortion bends the ellipse itself, and the detector fits an ellipse to the bent outline:
its centre is not the distorted ellipse centre. On the reference rig (k1 = -0.6, 5 mm
circles about 60 px across) the difference runs radially inwards from 0.005 px near the
image centre to 0.022 px at its edge: what the simulator's true centres showed as the
detector's "bias", and what made the dynamic camera's l 4 sigma off on a rig without galvo
scatter. :func:`contour_offsets` gives that difference.
"""

from __future__ import annotations

import numpy as np

from reconstructor.model import (
    CameraIntrinsics,
    RigModel,
    distort_normalised,
    rigid_inverse,
    undistort_points,
    v0_T_v,
)


def _check_transforms(T, name: str, m: int | None = None) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        return T
    if T.ndim != 3 or T.shape[1:] != (4, 4) or (m is not None and T.shape[0] != m):
        want = "(4, 4)" if m is None else f"(4, 4) or ({m}, 4, 4)"
        raise ValueError(f"{name} must have shape {want}, got {T.shape}")
    return T


def ellipse_centres_normalised(V_T_W, points_w, radii) -> np.ndarray:
    """Undistorted normalised image coordinates of the ellipse centres of board circles.

    Parameters
    ----------
    V_T_W : array_like, shape (4, 4) or (m, 4, 4)
        Board-to-camera transform(s), metres; one for all circles or one per circle.
    points_w : array_like, shape (m, 3), metres
        Circle centres in the board frame (z = 0).
    radii : array_like, shape (m,), metres
        Circle radii; zero gives the plain projection of the centre.

    Returns
    -------
    ndarray, shape (m, 2)
        ``(x, y)``; NaN where the circle is not in front of the camera.
    """
    P = np.asarray(points_w, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points_w must have shape (m, 3), got {P.shape}")
    m = P.shape[0]
    r = np.asarray(radii, dtype=np.float64)
    if r.shape != (m,):
        raise ValueError(f"radii must have shape ({m},), got {r.shape}")
    T = _check_transforms(V_T_W, "V_T_W", m)
    if T.ndim == 2:
        R = np.broadcast_to(T[:3, :3], (m, 3, 3))
        t = np.broadcast_to(T[:3, 3], (m, 3))
    else:
        R = T[:, :3, :3]
        t = T[:, :3, 3]
    p = np.einsum("mij,mj->mi", R, P) + t
    Z = p[:, 2]
    corr = R[:, :, 0] * R[:, 2, 0:1] + R[:, :, 1] * R[:, 2, 1:2]
    xh = p * Z[:, None] - (r * r)[:, None] * corr
    with np.errstate(all="ignore"):
        out = xh[:, :2] / xh[:, 2:3]
    out[~(Z > 0.0)] = np.nan
    return out


def project_circle_centres(intrinsics: CameraIntrinsics, V_T_W, points_w, radii) -> np.ndarray:
    """Pixel coordinates of the (distorted) ellipse centres of board circles.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
    V_T_W : array_like, shape (4, 4) or (m, 4, 4)
        Board-to-camera transform(s), metres.
    points_w : array_like, shape (m, 3), metres
    radii : array_like, shape (m,), metres

    Returns
    -------
    ndarray, shape (m, 2), pixels
        NaN where the circle is behind the camera.
    """
    x = ellipse_centres_normalised(V_T_W, points_w, radii)
    xd = distort_normalised(intrinsics, x.T).T
    return xd * np.array([intrinsics.fx, intrinsics.fy]) + np.array([intrinsics.cx, intrinsics.cy])


def view_T_board(model: RigModel, u1_pan, u1_tilt, V0_T_W) -> np.ndarray:
    """``V_T_W = inv(V0_T_V(U1)) @ V0_T_W`` for G1 voltages.

    Parameters
    ----------
    model : RigModel
    u1_pan, u1_tilt : float or array_like, shape (n,), volts
    V0_T_W : array_like, shape (4, 4)
        Board pose in V0, metres.

    Returns
    -------
    ndarray, shape (4, 4) or (n, 4, 4)
    """
    T = _check_transforms(V0_T_W, "V0_T_W")
    if T.ndim != 2:
        raise ValueError(f"V0_T_W must have shape (4, 4), got {T.shape}")
    return rigid_inverse(v0_T_v(model, u1_pan, u1_tilt)) @ T


def pixels_to_board(model: RigModel, uv, u1_pan: float, u1_tilt: float, V0_T_W) -> np.ndarray:
    """Intersect the pixel rays of one view with the board plane.

    Parameters
    ----------
    model : RigModel
    uv : array_like, shape (n, 2), pixels
        Distorted pixel coordinates.
    u1_pan, u1_tilt : float, volts
        G1 voltages of the view.
    V0_T_W : array_like, shape (4, 4)
        Board pose in V0, metres.

    Returns
    -------
    ndarray, shape (n, 2), metres
        Board-frame (x, y) of the intersections; NaN where a ray misses the board plane
        (parallel, behind the camera, or no undistortion).
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must have shape (n, 2), got {uv.shape}")
    W_T_V = rigid_inverse(view_T_board(model, float(u1_pan), float(u1_tilt), V0_T_W))
    xy = undistort_points(model.intrinsics, uv)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ W_T_V[:3, :3].T
    o = W_T_V[:3, 3]
    with np.errstate(all="ignore"):
        s = -o[2] / rays[:, 2]
        out = o[:2] + s[:, None] * rays[:, :2]
    out[~(s > 0.0)] = np.nan
    return out


#: Outline points per circle in :func:`contour_offsets`.
CONTOUR_POINTS = 24


def contour_offsets(intrinsics: CameraIntrinsics, V_T_W, points_w, radii,
                    n: int = CONTOUR_POINTS) -> np.ndarray:
    """Centre of an ellipse fitted to each circle's distorted outline, minus its
    :func:`project_circle_centres`, pixels.

    Per circle, ``n`` points of its outline are projected with the lens distortion and a
    conic ``x^2 + b xy + c (y^2 - x^2) + d x + e y + f = 0`` fitted to them by least
    squares (about the distorted ellipse centre, in units of the circle's radius); its
    centre is what an ellipse fit to the detected edge reports. Zero without distortion
    (the outline is then an exact ellipse); a second-order effect of the distortion over a
    circle's size, so a fit can hold it at its starting geometry.

    Returns
    -------
    ndarray, shape (m, 2)
        NaN where the circle is not in front of the camera.
    """
    P = np.asarray(points_w, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    m = P.shape[0] if P.ndim == 2 else 0
    if P.ndim != 2 or P.shape[1] != 3 or r.shape != (m,):
        raise ValueError(f"points_w (m, 3) and radii (m,) expected, got {P.shape}, {r.shape}")
    centre = project_circle_centres(intrinsics, V_T_W, P, r)
    if m == 0 or not np.any(r > 0):
        return np.zeros((m, 2))
    T = _check_transforms(V_T_W, "V_T_W", m)
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    outline = (P[:, None, :] + r[:, None, None]
               * np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)[None])  # (m, n, 3)
    R = T[:3, :3] if T.ndim == 2 else T[:, None, :3, :3]
    t = T[:3, 3] if T.ndim == 2 else T[:, None, :3, 3]
    q = (np.einsum("...ij,...j->...i", R, outline) if T.ndim == 3
         else outline @ R.T) + t
    with np.errstate(all="ignore"):
        x = (q[..., :2] / q[..., 2:3]).reshape(-1, 2)
        xd = distort_normalised(intrinsics, x.T).T.reshape(m, n, 2)
    uv = xd * [intrinsics.fx, intrinsics.fy] + [intrinsics.cx, intrinsics.cy]
    scale = np.where(r > 0, np.abs(intrinsics.fx) * r / np.maximum(q[:, 0, 2], 1e-12), 1.0)
    u = (uv - centre[:, None, :]) / scale[:, None, None]
    X, Y = u[..., 0], u[..., 1]
    A = np.stack([X * Y, Y * Y - X * X, X, Y, np.ones_like(X)], axis=-1)  # (m, n, 5)
    with np.errstate(all="ignore"):
        # pinv: an outline seen edge-on (collinear points) gives NaN, not an exception
        coef = (np.linalg.pinv(np.einsum("mki,mkj->mij", A, A))
                @ np.einsum("mki,mk->mi", A, -X * X)[..., None])[..., 0]
        b, c, d, e = coef[:, 0], coef[:, 1], coef[:, 2], coef[:, 3]
        # centre of the conic: [[2(1 - c), b], [b, 2c]] x = [-d, -e]
        det = 4.0 * (1.0 - c) * c - b * b
        x0 = (-d * 2.0 * c + e * b) / det
        y0 = (-e * 2.0 * (1.0 - c) + d * b) / det
    out = np.stack([x0, y0], axis=1) * scale[:, None]
    out[~(r > 0)] = 0.0
    out[~np.isfinite(centre).all(axis=1)] = np.nan
    return out
