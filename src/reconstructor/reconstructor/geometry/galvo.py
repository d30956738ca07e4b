"""Galvanometer mirrors: voltage-to-angle, and the dynamic-camera transform (docs/design.md §2).

``G_T_V(theta_pan, theta_tilt) = Tilt(theta_tilt) @ Pan(theta_pan) @ M0`` is the pose of the
virtual camera {V} in the Galvanometer-1 base frame {G} (the paper's ^V T_G, Eq. 2). It is
always built from its three factors: the paper's printed closed-form product has a wrong entry
(row 2, column 3 must be sin2θ1·cos2θ2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .checks import as_float_array, finite_scalar, finite_vector


@dataclass(frozen=True)
class MirrorParams:
    """Voltage-to-angle response of one galvanometer mirror.

    ``theta(U) = theta0 + k U + poly[0] U^2 + poly[1] U^3 + ...``

    Parameters
    ----------
    theta0 : float
        Mirror angle at 0 V, radians (pi/4 nominal for the G1 mirrors).
    k : float
        Linear gain, rad/V (mechanical mirror rotation, not optical deflection).
    poly : tuple of float
        Higher-order coefficients, rad/V^2, rad/V^3, ... (empty for a linear galvo).
    """

    theta0: float
    k: float
    poly: tuple[float, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "theta0", finite_scalar(self.theta0, "theta0"))
        object.__setattr__(self, "k", finite_scalar(self.k, "k"))
        poly = tuple(self.poly) if not isinstance(self.poly, tuple) else self.poly
        poly = finite_vector(poly, "poly", len(poly)) if poly else ()
        object.__setattr__(self, "poly", tuple(float(c) for c in poly))

    def angle(self, u):
        """Mirror angle for voltage ``u``.

        Parameters
        ----------
        u : float or array_like, any shape, volts

        Returns
        -------
        float or ndarray, same shape as ``u``, radians
        """
        if not isinstance(u, (float, np.ndarray)):
            u = float(u) if np.ndim(u) == 0 else np.asarray(u, dtype=np.float64)
        acc = 0.0
        for c in reversed(self.poly):
            acc = (acc + c) * u
        return self.theta0 + (acc + self.k) * u

    def slope(self, u):
        """Derivative d theta / d U at voltage ``u`` (rad/V), same shape as ``u``."""
        u = u if isinstance(u, (float, np.ndarray)) else np.asarray(u, dtype=np.float64)
        acc = 0.0
        for i in range(len(self.poly) - 1, -1, -1):
            acc = acc * u + (i + 2) * self.poly[i]
        return self.k + acc * u

    def voltage(self, theta, *, tol: float = 1e-15, max_iter: int = 50):
        """Voltage giving mirror angle ``theta`` (Newton from the linear inverse).

        Parameters
        ----------
        theta : float or array_like, any shape, radians

        Returns
        -------
        ndarray or float, same shape as ``theta``, volts
            NaN where Newton did not converge (no monotonic inverse there).
        """
        if self.k == 0.0:
            raise ValueError("k must be non-zero to invert the mirror response")
        th = np.asarray(theta, dtype=np.float64)
        u = (th - self.theta0) / self.k
        if self.poly:
            with np.errstate(all="ignore"):
                for _ in range(max_iter):
                    du = (self.angle(u) - th) / self.slope(u)
                    u = u - du
                    if np.all(np.abs(du) <= tol * np.maximum(1.0, np.abs(u))):
                        break
                u = np.where(np.abs(self.angle(u) - th) <= 1e-12, u, np.nan)
        return float(u) if np.ndim(theta) == 0 else u

    def to_dict(self) -> dict:
        """Plain-float dict ``{'theta0', 'k', 'poly'}`` (SI: rad, rad/V, rad/V^n)."""
        return {"theta0": self.theta0, "k": self.k, "poly": list(self.poly)}


def _angles(theta, name: str) -> np.ndarray:
    return as_float_array(theta, name)


def pan_factor(theta_pan) -> np.ndarray:
    """Pan mirror reflection of Eq. 2 (det -1).

    Parameters
    ----------
    theta_pan : float or array_like, shape (...), radians
        Pan mirror angle θ1.

    Returns
    -------
    ndarray, shape (..., 4, 4)
    """
    t = 2.0 * _angles(theta_pan, "theta_pan")
    c, s = np.cos(t), np.sin(t)
    out = np.zeros(t.shape + (4, 4))
    out[..., 0, 0] = -c
    out[..., 0, 1] = s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    return out


def tilt_factor(theta_tilt, d: float) -> np.ndarray:
    """Tilt mirror reflection of Eq. 2 (det -1); the tilt axis passes through (0, d, 0) in G.

    Parameters
    ----------
    theta_tilt : float or array_like, shape (...), radians
        Tilt mirror angle θ2.
    d : float, metres
        Offset of the tilt axis from the pan axis along G's y.

    Returns
    -------
    ndarray, shape (..., 4, 4)
    """
    d = finite_scalar(d, "d")
    t = 2.0 * _angles(theta_tilt, "theta_tilt")
    c, s = np.cos(t), np.sin(t)
    out = np.zeros(t.shape + (4, 4))
    out[..., 0, 0] = 1.0
    out[..., 1, 1] = c
    out[..., 1, 2] = s
    out[..., 1, 3] = d * (1.0 - c)
    out[..., 2, 1] = s
    out[..., 2, 2] = -c
    out[..., 2, 3] = -d * s
    out[..., 3, 3] = 1.0
    return out


def m0_factor(l: float) -> np.ndarray:
    """Fixed camera-to-G factor M0 of Eq. 2 (a proper rotation with translation (-l, 0, 0)).

    Parameters
    ----------
    l : float, metres
        Distance from the camera centre to the pan axis.

    Returns
    -------
    ndarray, shape (4, 4)
    """
    l = finite_scalar(l, "l")
    return np.array(
        [[0.0, 0.0, 1.0, -l], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )


def g_T_v(theta_pan, theta_tilt, l: float, d: float) -> np.ndarray:
    """Pose of the virtual camera {V} in {G}: ``Tilt(θ2) @ Pan(θ1) @ M0`` (docs/design.md §2).

    Parameters
    ----------
    theta_pan, theta_tilt : float or array_like, broadcastable shapes (...), radians
        G1 pan (θ1) and tilt (θ2) mirror angles.
    l, d : float, metres
        Dynamic-camera lengths.

    Returns
    -------
    ndarray, shape (..., 4, 4)
        ``G_T_V``: maps V coordinates to G coordinates.
    """
    tp, tt = broadcast_angles(theta_pan, theta_tilt)
    tilt = tilt_factor(tt, d)
    pan = pan_factor(tp)
    return tilt @ pan @ m0_factor(l)


def broadcast_angles(theta_pan, theta_tilt) -> tuple[np.ndarray, np.ndarray]:
    """Pan and tilt angles as float arrays broadcast to one shape (ValueError if they do not
    broadcast)."""
    tp = _angles(theta_pan, "theta_pan")
    tt = _angles(theta_tilt, "theta_tilt")
    try:
        shape = np.broadcast_shapes(tp.shape, tt.shape)
    except ValueError:
        raise ValueError(
            f"theta_pan shape {tp.shape} and theta_tilt shape {tt.shape} do not broadcast"
        ) from None
    return np.broadcast_to(tp, shape), np.broadcast_to(tt, shape)


def g_T_v_scalar(theta_pan: float, theta_tilt: float, l: float, d: float) -> np.ndarray:
    """``g_T_v`` for two float angles, written out from the factors (fast single-frame path)."""
    c1, s1 = math.cos(2.0 * theta_pan), math.sin(2.0 * theta_pan)
    c2, s2 = math.cos(2.0 * theta_tilt), math.sin(2.0 * theta_tilt)
    # Tilt @ Pan @ M0 multiplied out column by column; entry [1, 2] is s1 * c2.
    return np.array(
        [
            [s1, 0.0, -c1, l * c1],
            [c1 * c2, s2, s1 * c2, -l * s1 * c2 + d * (1.0 - c2)],
            [c1 * s2, -c2, s1 * s2, -l * s1 * s2 - d * s2],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def rigid_inverse(A_T_B) -> np.ndarray:
    """Inverse of rigid transforms.

    Parameters
    ----------
    A_T_B : array_like, shape (..., 4, 4)
        Rigid transforms (rotation block orthonormal).

    Returns
    -------
    ndarray, shape (..., 4, 4)
        ``B_T_A``.
    """
    T = as_float_array(A_T_B, "A_T_B")
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"A_T_B must have shape (..., 4, 4), got {T.shape}")
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros(T.shape)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out
