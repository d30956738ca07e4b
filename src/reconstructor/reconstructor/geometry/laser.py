"""Dynamic laser (docs/design.md §2, paper Eqs. 6-7) and plane transforms.

The G2 tilt mirror rotates about an axis lying in its surface, so the reflected laser plane is
the U2 = 0 plane ``pi0`` rotated rigidly about the axis (unit n through P, in V0) by
``alpha = 2 (θ4(U2) - θ4(0))``::

    normal = R(n, alpha) @ n0                      (Rodrigues)
    e      = e0 + n0·P - normal·P

When P lies on pi0 (``n0·P + e0 = 0``, which the axis calibration makes true up to its
residual) this is exactly docs/design.md's ``e = -normal·P``; when it does not, the rigid rotation
keeps pi0 at U2 = 0 and still models a fan plane that misses the mirror axis exactly.
"""

from __future__ import annotations

import math

import numpy as np

from .checks import as_float_array
from .rig import RigModel, v0_T_v


def transform_plane(A_T_B, pi_A) -> np.ndarray:
    """Express a plane given in frame A in frame B: ``pi_B = A_T_B.T @ pi_A``.

    Parameters
    ----------
    A_T_B : array_like, shape (..., 4, 4)
        Transform mapping B coordinates to A coordinates.
    pi_A : array_like, shape (..., 4)
        Plane (a, b, c, e) in A, metres for e; shapes broadcast over the leading axes.

    Returns
    -------
    ndarray, shape (broadcast ..., 4)
        Plane in B. Not renormalised (a rigid transform keeps a unit normal unit).
    """
    T = as_float_array(A_T_B, "A_T_B")
    pi = as_float_array(pi_A, "pi_A")
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"A_T_B must have shape (..., 4, 4), got {T.shape}")
    if pi.ndim < 1 or pi.shape[-1] != 4:
        raise ValueError(f"pi_A must have shape (..., 4), got {pi.shape}")
    try:
        np.broadcast_shapes(T.shape[:-2], pi.shape[:-1])
    except ValueError:
        raise ValueError(
            f"A_T_B shape {T.shape} and pi_A shape {pi.shape} do not broadcast"
        ) from None
    return (np.swapaxes(T, -1, -2) @ pi[..., None])[..., 0]


def laser_plane_v0(model: RigModel, u2_tilt) -> np.ndarray:
    """Laser plane in V0 for G2 tilt voltages.

    Parameters
    ----------
    model : RigModel
    u2_tilt : float or array_like, shape (...), volts

    Returns
    -------
    ndarray, shape (..., 4)
        Planes (a, b, c, e) with unit normals, e in metres.
    """
    u = as_float_array(u2_tilt, "u2_tilt")
    pre = model._pre
    if pre.g2 is not None:
        return pre.g2.plane(model.g2_tilt.angle(u) - model.g2_tilt.theta0)
    alpha = 2.0 * (model.g2_tilt.angle(u) - model.g2_tilt.theta0)
    c = np.cos(alpha)[..., None]
    s = np.sin(alpha)[..., None]
    out = np.empty(u.shape + (4,))
    out[..., :3] = c * pre.n0 + s * pre.m + (1.0 - c) * pre.q
    out[..., 3] = (pre.e0 + pre.n0P) - (c * pre.n0P + s * pre.mP + (1.0 - c) * pre.qP)[..., 0]
    return out


def laser_plane_v0_scalar(model: RigModel, u2_tilt: float) -> tuple[float, float, float, float]:
    """``laser_plane_v0`` for one float voltage, as a tuple (fast single-frame path)."""
    pre = model._pre
    if pre.g2 is not None:
        return pre.g2.plane_scalar(model.g2_tilt.angle(float(u2_tilt)) - model.g2_tilt.theta0)
    alpha = 2.0 * (model.g2_tilt.angle(u2_tilt) - model.g2_tilt.theta0)
    c, s = math.cos(alpha), math.sin(alpha)
    w = 1.0 - c
    n0, m, q = pre.n0_t, pre.m_t, pre.q_t
    return (
        c * n0[0] + s * m[0] + w * q[0],
        c * n0[1] + s * m[1] + w * q[1],
        c * n0[2] + s * m[2] + w * q[2],
        (pre.e0 + pre.n0P) - (c * pre.n0P + s * pre.mP + w * pre.qP),
    )


def laser_plane_v(model: RigModel, u1_pan, u1_tilt, u2_tilt) -> np.ndarray:
    """Laser plane in the current virtual camera frame V: ``V0_T_V.T @ pi_V0``.

    Parameters
    ----------
    model : RigModel
    u1_pan, u1_tilt, u2_tilt : float or array_like, broadcastable shapes (...), volts

    Returns
    -------
    ndarray, shape (..., 4)
        Planes (a, b, c, e) in V (unit normals, e in metres).
    """
    return transform_plane(v0_T_v(model, u1_pan, u1_tilt), laser_plane_v0(model, u2_tilt))
