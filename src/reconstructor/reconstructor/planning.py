"""Scan planning with the calibrated model (no rclpy).

Where to point the mirrors, computed from the model a user has (the calibration), never
from the rig's hidden truth:

- :func:`aim_g1` (the one aim solver) and :func:`aim_camera`: G1 voltages whose view centre
  looks at a V0 point;
- :func:`aim_laser`: the G2 tilt voltage whose laser plane crosses the view's optical axis
  at a given distance;
- :func:`view_sweep`: a G2 sweep that moves the stripe across one G1 view;
- :func:`expected_rows`: where a part of known nominal shape and pose puts the stripe in a
  frame's image (the extractor's prior for picking the stripe among reflections);
- :func:`stripe_layout`: which way the stripe runs in the image and which G1 axis moves
  the view across it, from the model's laser plane
  (:func:`galvoscan_common.stripe_layout.stripe_layout`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq, least_squares

from galvoscan_common.frame import VOLTAGE_LIMIT
from galvoscan_common.stripe_layout import StripeLayout
from galvoscan_common.stripe_layout import stripe_layout as _layout
from reconstructor.model import (
    RigModel,
    laser_plane_v0,
    predict_pixels,
    rigid_inverse,
    v0_T_v,
)

#: An aim is reached when the target is this close to the optical axis (tangent of the angle:
#: about 0.01 px at the telephoto focal length).
AIM_TOLERANCE = 1e-6


def stripe_layout(model: RigModel) -> StripeLayout:
    """The stripe's direction in the image, the V0 axis it moves along with U2 and the G1
    axis that moves the view across it, from the model's laser plane at U2 = 0 seen at
    U1 = 0 (design values or a calibration: where the laser sits is read from them)."""
    intr = model.intrinsics
    return _layout(laser_plane_v0(model, 0.0), intr.fx, intr.fy,
                   plane_moved=laser_plane_v0(model, 0.1))


def _off_axis(model: RigModel, u, point) -> np.ndarray:
    """Where ``point`` (V0) lies off the optical axis of the view at G1 ``u``: (x/z, y/z).

    The view's pose includes the model's joint correction, as triangulation and
    ``predict_pixels`` apply it.
    """
    T = v0_T_v(model, u[0], u[1])
    if model.correction is not None:
        T = np.asarray(model.correction.V0c_T_V0(u[0], u[1]), dtype=np.float64) @ T
    q = rigid_inverse(T) @ np.append(point, 1.0)
    return q[:2] / q[2] if q[2] > 0 else np.array([1e3, 1e3])


def _newton_aim(model: RigModel, point, u) -> np.ndarray:
    """Newton on the off-axis offset (numerical Jacobian, steps clipped to 2 V)."""
    u = np.array(u, dtype=np.float64)
    for _ in range(30):
        f = _off_axis(model, u, point)
        J = np.column_stack([(_off_axis(model, u + h, point) - f) / 1e-4
                             for h in (np.array([1e-4, 0.0]), np.array([0.0, 1e-4]))])
        try:
            step = np.linalg.solve(J, -f)
        except np.linalg.LinAlgError:
            break
        u = u + np.clip(step, -2.0, 2.0)
        if not np.all(np.isfinite(u)) or np.abs(step).max() < 1e-12:
            break
    return u


def _bounded_aim(model: RigModel, point, u0, max_abs_u: float) -> np.ndarray:
    """Bounded least squares from the four sign combinations of ``u0`` (Newton's fallback)."""
    best = None
    for sign in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        sol = least_squares(lambda u: _off_axis(model, u, point),
                            np.clip(u0 * sign, -max_abs_u, max_abs_u),
                            bounds=(-max_abs_u, max_abs_u), x_scale=1.0, xtol=1e-15,
                            ftol=1e-15, gtol=1e-15)
        if best is None or sol.cost < best.cost:
            best = sol
        if np.abs(best.fun).max() < AIM_TOLERANCE:
            break
    return best.x


def aim_g1(model: RigModel, points_v0, *, start=None,
           max_abs_u: float = VOLTAGE_LIMIT) -> np.ndarray:
    """G1 voltages that put V0 points on the view's optical axis (at the principal point).

    The one aim solver of the project (capture plans, calibration, evaluation). Newton on
    the target's offset from the optical axis, from ``start`` or from the small-angle guess
    (the view turns by twice the mirror angle); where Newton does not converge, bounded
    least squares from the guess's four sign combinations. A target Newton puts on the
    axis beyond ``max_abs_u`` is out of reach.

    Parameters
    ----------
    model : RigModel
        The user's model (nominal or calibrated), never the rig's truth.
    points_v0 : array_like, shape (n, 3) or (3,), metres
        Targets in V0.
    start : array_like, shape (2,), volts, optional
        Newton's starting voltages (default: the small-angle guess).
    max_abs_u : float, volts
        Voltage range; a target out of reach gets NaN.

    Returns
    -------
    ndarray, shape (n, 2) (or (2,) for one point), volts
        (U1_pan, U1_tilt); NaN where no voltage within range puts the target on the axis
        to :data:`AIM_TOLERANCE`.
    """
    P = np.asarray(points_v0, dtype=np.float64)
    single = P.shape == (3,)
    P = P.reshape(1, 3) if single else P
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'points_v0 must have shape (n, 3), got {np.shape(points_v0)}')
    if not (np.isfinite(max_abs_u) and max_abs_u > 0):
        raise ValueError(f'max_abs_u must be > 0 V, got {max_abs_u}')
    out = np.full((len(P), 2), np.nan)
    k = np.array([model.g1_pan.k, model.g1_tilt.k])
    for i, p in enumerate(P):
        if not np.all(np.isfinite(p)):
            continue
        guess = np.nan_to_num(np.array([np.arctan2(p[0], p[2]), -np.arctan2(p[1], p[2])])
                              / (2 * k))
        guess = np.clip(guess, -max_abs_u, max_abs_u)
        u = _newton_aim(model, p, guess if start is None else start)
        if not (np.all(np.isfinite(u)) and np.abs(_off_axis(model, u, p)).max() < AIM_TOLERANCE):
            u = _bounded_aim(model, p, guess, max_abs_u)  # Newton did not converge
        if np.abs(u).max() <= max_abs_u and np.abs(_off_axis(model, u, p)).max() < AIM_TOLERANCE:
            out[i] = u
    return out[0] if single else out


def aim_camera(model: RigModel, target_v0) -> tuple[float, float]:
    """G1 (pan, tilt) voltages that put ``target_v0`` at the principal point (:func:`aim_g1`).

    Parameters
    ----------
    target_v0 : array_like, shape (3,), metres

    Raises
    ------
    ValueError
        The target is not finite or cannot be reached within +-10 V.
    """
    target = np.asarray(target_v0, dtype=np.float64)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise ValueError(f'target_v0: expected 3 finite coordinates in metres, got {target_v0}')
    u = aim_g1(model, target)
    if not np.all(np.isfinite(u)):
        raise ValueError(f'target_v0 {target.tolist()} cannot be centred within '
                         f'+-{VOLTAGE_LIMIT} V')
    return float(u[0]), float(u[1])


def laser_through(model: RigModel, point_v0, max_abs_u: float = VOLTAGE_LIMIT) -> float:
    """G2 tilt voltage whose laser plane passes through a V0 point.

    The one such solver of the project (plans, sweeps, evaluation, scores): the root of the
    point's signed distance from the sheet over +-``max_abs_u`` [V].

    Raises
    ------
    ValueError
        No voltage within +-``max_abs_u`` puts the sheet through the point.
    """
    point = np.asarray(point_v0, dtype=np.float64).ravel()[:3]
    if point.size != 3 or not np.all(np.isfinite(point)):
        raise ValueError(f'point_v0: expected 3 finite coordinates [m], got {point_v0!r}')
    if not (math.isfinite(max_abs_u) and max_abs_u > 0):
        raise ValueError(f'max_abs_u: expected a positive voltage, got {max_abs_u!r}')

    def f(u):
        plane = laser_plane_v0(model, u)
        return float(plane[:3] @ point + plane[3])

    lo, hi = -float(max_abs_u), float(max_abs_u)
    if f(lo) * f(hi) > 0:
        raise ValueError(f'the laser cannot reach {np.round(point, 6).tolist()} within '
                         f'+-{max_abs_u:g} V of G2 tilt')
    return float(brentq(f, lo, hi, xtol=1e-12))


def aim_laser(model: RigModel, u1_pan: float, u1_tilt: float, distance: float = 0.65) -> float:
    """G2 tilt voltage whose laser plane meets the view's optical axis at ``distance`` [m]."""
    if not distance > 0:
        raise ValueError(f'distance: expected > 0 m, got {distance}')
    T = v0_T_v(model, u1_pan, u1_tilt)
    try:
        return laser_through(model, T[:3, 3] + distance * T[:3, 2])
    except ValueError:
        raise ValueError(f'no G2 tilt voltage within +-{VOLTAGE_LIMIT} V puts the laser at '
                         f'{distance} m on the optical axis for U1 = ({u1_pan}, {u1_tilt})'
                         ) from None


def view_sweep(model: RigModel, u1_pan: float, u1_tilt: float, distance: float,
               frames: int, fraction: float = 0.8) -> np.ndarray:
    """Voltages (frames, 4) sweeping the stripe over ``fraction`` of one view across it.

    G1 is held at (u1_pan, u1_tilt); G2 tilt runs between the voltages that put the laser
    on the rays through the two ends of the central ``fraction`` of the image across the
    stripe (its top and bottom for a stripe along the rows, left and right along the
    columns: :func:`stripe_layout`) at ``distance`` [m].
    """
    if frames < 1:
        raise ValueError(f'frames: expected >= 1, got {frames}')
    T = v0_T_v(model, u1_pan, u1_tilt)
    ends = []
    for ray in view_edge_rays(model, fraction):
        try:
            ends.append(laser_through(model, T[:3, 3] + T[:3, :3] @ (ray * distance)))
        except ValueError:
            raise ValueError(f'the laser cannot reach this view at {distance:g} m within '
                             f'+-{VOLTAGE_LIMIT} V of G2 tilt (U1 = ({u1_pan:.3g}, '
                             f'{u1_tilt:.3g}) V)') from None
    u2 = np.linspace(ends[0], ends[1], frames) if frames > 1 else np.array([np.mean(ends)])
    out = np.zeros((frames, 4))
    out[:, 0], out[:, 1], out[:, 3] = u1_pan, u1_tilt, u2
    return out


def view_edge_rays(model: RigModel, fraction: float) -> list[np.ndarray]:
    """The two rays (in the view's frame, z = 1) through the ends of the central
    ``fraction`` of the image across the stripe, through the principal point along it
    (:func:`stripe_layout`: the top and bottom rows for a stripe along the rows, the left
    and right columns for one along the columns)."""
    intr = model.intrinsics
    k = stripe_layout(model).across
    size, c, f = ((intr.height, intr.cy, intr.fy) if k == 1 else (intr.width, intr.cx, intr.fx))
    rays = []
    for px in (c - fraction * size / 2, c + fraction * size / 2):
        ray = np.array([0.0, 0.0, 1.0])
        ray[k] = (px - c) / f
        rays.append(ray)
    return rays


def expected_rows(model: RigModel, faces_v0, voltages, size: int | None = None,
                  samples: int = 400) -> np.ndarray:
    """Where the stripe should cross each image column (each row, for a stripe along the
    columns) on a part of nominal shape: the extractor's prior (``expected_v`` of
    ``stripe_extractor.extractor.extract``).

    The part is a set of rectangular faces (its CAD, placed where the operator put it).
    Each face is cut with the model's laser plane of the frame; the cut is projected into
    the frame's view; per column (row) the nearest face (smallest depth) gives the row
    (column). Which way the stripe runs is the model's (:func:`stripe_layout`): along the
    rows for a laser below or above the camera, along the columns beside it.

    Parameters
    ----------
    model : RigModel
    faces_v0 : sequence of (centre (3,), e1 (3,), e2 (3,), half (2,))
        Rectangles in V0 [m]: centre, unit in-plane axes, half sizes along them. Faces
        turned away from the view are skipped.
    voltages : array_like, shape (4,), volts
        The frame's (U1_pan, U1_tilt, U2_pan, U2_tilt).
    size : int, optional
        Image columns (rows, for a stripe along the columns) [px]; default the model's
        image width (height).
    samples : int
        Points along each face's cut.

    Returns
    -------
    ndarray, shape (size,), px
        Expected row per column (column per row); NaN where no face is cut.
    """
    U = np.asarray(voltages, dtype=np.float64)
    if U.shape != (4,) or not np.all(np.isfinite(U)):
        raise ValueError(f'voltages: expected 4 finite volts, got {U}')
    # image axis along the stripe (0: u, one value per column) and across it
    across = stripe_layout(model).image_axis
    along = 1 - across
    if size is None:
        size = model.intrinsics.width if along == 0 else model.intrinsics.height
    if not (isinstance(size, (int, np.integer)) and size >= 1):
        raise ValueError(f'size: expected a positive number of pixels, got {size}')
    plane = laser_plane_v0(model, U[3])
    T = v0_T_v(model, U[0], U[1])
    centre = T[:3, 3]
    rows = np.full(int(size), np.nan)
    depth = np.full(int(size), np.inf)
    cols = np.arange(int(size), dtype=np.float64)
    for c, e1, e2, half in faces_v0:
        c, e1, e2 = (np.asarray(x, dtype=np.float64) for x in (c, e1, e2))
        n = np.cross(e1, e2)
        if n @ (centre - c) < 0:
            n = -n  # two-sided: the side facing the view
        # the cut: c + a e1 + b e2 with plane . (that) = 0, |a| <= h1, |b| <= h2
        ga, gb = plane[:3] @ e1, plane[:3] @ e2
        g0 = plane[:3] @ c + plane[3]
        if abs(ga) < 1e-12 and abs(gb) < 1e-12:
            continue
        t = np.linspace(-1.0, 1.0, samples)
        if abs(ga) >= abs(gb):
            b = t * half[1]
            a = -(g0 + gb * b) / ga
        else:
            a = t * half[0]
            b = -(g0 + ga * a) / gb
        ok = (np.abs(a) <= half[0]) & (np.abs(b) <= half[1])
        if np.count_nonzero(ok) < 2:
            continue
        pts = c + a[ok, None] * e1 + b[ok, None] * e2
        uv, front = predict_pixels(model, pts, U[0], U[1])
        z = (pts - centre) @ T[:3, 2]
        keep = front & np.isfinite(uv).all(axis=1)
        if np.count_nonzero(keep) < 2:
            continue
        uv, z = uv[keep], z[keep]
        order = np.argsort(uv[:, along])
        uu, vv, zz = uv[order, along], uv[order, across], z[order]
        inside = (cols >= uu[0]) & (cols <= uu[-1])
        v_face = np.interp(cols[inside], uu, vv)
        z_face = np.interp(cols[inside], uu, zz)
        idx = np.flatnonzero(inside)
        nearer = z_face < depth[idx]
        rows[idx[nearer]] = v_face[nearer]
        depth[idx[nearer]] = z_face[nearer]
    return rows
