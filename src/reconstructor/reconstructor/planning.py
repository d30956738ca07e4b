"""Scan planning with the calibrated model (no rclpy).

Where to point the mirrors, computed from the model a user has (the calibration), never
from the rig's hidden truth:

- :func:`aim_camera`: G1 voltages whose view centre looks at a V0 point;
- :func:`aim_laser`: the G2 tilt voltage whose laser plane crosses the view's optical axis
  at a given distance;
- :func:`view_sweep`: a G2 sweep that moves the stripe across one G1 view.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq, least_squares

from galvoscan_common.frame import VOLTAGE_LIMIT
from reconstructor.model import RigModel, laser_plane_v0, predict_pixels, v0_T_v


def aim_camera(model: RigModel, target_v0) -> tuple[float, float]:
    """G1 (pan, tilt) voltages that put ``target_v0`` at the principal point.

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
    intr = model.intrinsics
    pp = np.array([intr.cx, intr.cy])

    def residual(u):
        uv, ok = predict_pixels(model, target[None, :], u[0], u[1])
        return (uv[0] - pp) if ok[0] else np.array([1e6, 1e6])

    # small-angle start: the view turns by twice the mirror angle
    k = (model.g1_pan.k, model.g1_tilt.k)
    u0 = np.array([np.arctan2(target[0], target[2]) / (2 * k[0]),
                   -np.arctan2(target[1], target[2]) / (2 * k[1])])
    u0 = np.clip(np.nan_to_num(u0), -VOLTAGE_LIMIT, VOLTAGE_LIMIT)
    best = None
    for sign in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        sol = least_squares(residual, u0 * sign, bounds=(-VOLTAGE_LIMIT, VOLTAGE_LIMIT),
                            x_scale=1.0, xtol=1e-12, ftol=1e-12)
        if best is None or sol.cost < best.cost:
            best = sol
        if best.cost < 1e-6:
            break
    if best.cost > 1e-2:
        raise ValueError(f'target_v0 {target.tolist()} cannot be centred within '
                         f'+-{VOLTAGE_LIMIT} V (residual {np.sqrt(2 * best.cost):.3g} px)')
    return float(best.x[0]), float(best.x[1])


def aim_laser(model: RigModel, u1_pan: float, u1_tilt: float, distance: float = 0.65) -> float:
    """G2 tilt voltage whose laser plane meets the view's optical axis at ``distance`` [m]."""
    if not distance > 0:
        raise ValueError(f'distance: expected > 0 m, got {distance}')
    T = v0_T_v(model, u1_pan, u1_tilt)
    point = T[:3, 3] + distance * T[:3, 2]

    def f(u):
        plane = laser_plane_v0(model, u)
        return float(plane[:3] @ point + plane[3])

    lo, hi = -VOLTAGE_LIMIT, VOLTAGE_LIMIT
    if f(lo) * f(hi) > 0:
        raise ValueError(f'no G2 tilt voltage within +-{VOLTAGE_LIMIT} V puts the laser at '
                         f'{distance} m on the optical axis for U1 = ({u1_pan}, {u1_tilt})')
    return float(brentq(f, lo, hi, xtol=1e-12))


def view_sweep(model: RigModel, u1_pan: float, u1_tilt: float, distance: float,
               frames: int, fraction: float = 0.8) -> np.ndarray:
    """Voltages (frames, 4) sweeping the stripe over ``fraction`` of one view's height.

    G1 is held at (u1_pan, u1_tilt); G2 tilt runs between the voltages that put the laser
    on the rays through the top and bottom of the central ``fraction`` of the image at
    ``distance`` [m].
    """
    if frames < 1:
        raise ValueError(f'frames: expected >= 1, got {frames}')
    intr = model.intrinsics
    T = v0_T_v(model, u1_pan, u1_tilt)
    ends = []
    for v in (intr.cy - fraction * intr.height / 2, intr.cy + fraction * intr.height / 2):
        ray = np.array([0.0, (v - intr.cy) / intr.fy, 1.0])
        point = T[:3, 3] + T[:3, :3] @ (ray * distance)

        def f(u, point=point):
            plane = laser_plane_v0(model, u)
            return float(plane[:3] @ point + plane[3])

        if f(-VOLTAGE_LIMIT) * f(VOLTAGE_LIMIT) > 0:
            raise ValueError(f'the laser cannot reach this view at {distance:g} m within '
                             f'+-{VOLTAGE_LIMIT} V of G2 tilt (U1 = ({u1_pan:.3g}, '
                             f'{u1_tilt:.3g}) V)')
        ends.append(brentq(f, -VOLTAGE_LIMIT, VOLTAGE_LIMIT, xtol=1e-12))
    u2 = np.linspace(ends[0], ends[1], frames) if frames > 1 else np.array([np.mean(ends)])
    out = np.zeros((frames, 4))
    out[:, 0], out[:, 1], out[:, 3] = u1_pan, u1_tilt, u2
    return out
