"""Multi-view consistency: keep the points two views of the same stripe agree on (no rclpy).

A stripe (one laser plane, one G2 tilt) is imaged from two G1 positions. A point of the
true stripe lies on the laser plane, so both views triangulate it to the same place. Light
the part reflects onto itself lies off the plane: each view's ray to it meets the plane
somewhere else, and the two triangulations differ by about

    delta * b / (z * sin(alpha))

(``delta`` the lit point's distance from the plane, ``b`` the distance between the two
virtual camera centres, ``z`` the range, ``alpha`` the angle between ray and plane). On the
reference rig two G1 views half a field of view apart have b = 4-5 mm at z = 650 mm
(``python -m reconstructor.consistency`` prints it for a model), so a reflection is told
apart only where it lies well off the plane: delta > ~4 mm for a 0.1 mm tolerance. The
cost is one extra frame per stripe (twice the frames of a plain sweep).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from reconstructor.geometry.checks import as_points


def two_view_sweep(voltages, u1_second) -> np.ndarray:
    """A sweep with every stripe seen twice: after each row of ``voltages`` (n, 4) [V], the
    same G2 voltages with G1 at ``u1_second`` (pan, tilt) [V]. Returns (2n, 4) [V]."""
    v = as_points(voltages, 'voltages', 4)
    second = v.copy()
    second[:, 0], second[:, 1] = float(u1_second[0]), float(u1_second[1])
    out = np.empty((2 * len(v), 4))
    out[0::2], out[1::2] = v, second
    return out


def agreeing(points_a, points_b, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Which points of two views of one stripe have a partner in the other view.

    Parameters
    ----------
    points_a : ndarray, shape (n, 3), metres
        One view's triangulated stripe (V0).
    points_b : ndarray, shape (m, 3), metres
        The other view's triangulation of the same stripe (same laser plane).
    tolerance : float
        Largest distance between partners [m], > 0: a little above the points' noise
        and the stripe's sampling (one pixel's footprint).

    Returns
    -------
    keep_a : ndarray, shape (n,), bool
    keep_b : ndarray, shape (m,), bool
    """
    a = as_points(points_a, 'points_a', 3)
    b = as_points(points_b, 'points_b', 3)
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f'tolerance: expected > 0 m, got {tolerance}')
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool), np.zeros(len(b), bool)
    da, _ = cKDTree(b).query(a, distance_upper_bound=tolerance)
    db, _ = cKDTree(a).query(b, distance_upper_bound=tolerance)
    return np.isfinite(da), np.isfinite(db)


def view_baseline(model, u1_a, u1_b) -> float:
    """Distance between the virtual camera centres of two G1 positions [m]."""
    from reconstructor.model import v0_T_v

    ta = v0_T_v(model, float(u1_a[0]), float(u1_a[1]))[:3, 3]
    tb = v0_T_v(model, float(u1_b[0]), float(u1_b[1]))[:3, 3]
    return float(np.linalg.norm(ta - tb))


if __name__ == '__main__':
    from reconstructor.model import nominal_example_rig

    m = nominal_example_rig()
    for du in (0.35, 0.7):
        print(f'G1 pan +-{du} V: virtual camera baseline '
              f'{view_baseline(m, (-du, 0.0), (du, 0.0)) * 1e3:.2f} mm')
