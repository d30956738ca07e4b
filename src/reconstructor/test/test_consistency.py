"""Two-view consistency: a point on the laser plane is kept, a reflection off it dropped."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstructor.consistency import agreeing, two_view_sweep, view_baseline
from reconstructor.model import laser_plane_v0, nominal_example_rig, predict_pixels, triangulate

VIEWS = ((-0.3, 0.0), (0.3, 0.0))
U2 = 0.0


def _seen(model, p_v0, u1):
    """Where a view triangulates a lit point: its pixel, triangulated on the laser plane."""
    uv, ok = predict_pixels(model, p_v0[None], *u1)
    assert ok.all()
    res = triangulate(model, uv, u1[0], u1[1], U2)
    assert res.valid.all()
    return res.p_v0[0]


def test_filter_keeps_a_true_point_and_drops_a_reflection():
    model = nominal_example_rig()
    plane = laser_plane_v0(model, U2)
    n = plane[:3] / np.linalg.norm(plane[:3])
    # a point of the stripe, between the two views' axes, 650 mm out
    ray = np.array([0.0, 0.0, 1.0])
    t = -plane[3] / (plane[:3] @ ray)
    true = ray * t
    # light reflected onto the part 10 mm off the plane, seen at the same place
    ghost_lit = true + 0.010 * n
    a = np.array([_seen(model, true, VIEWS[0]), _seen(model, ghost_lit, VIEWS[0])])
    b = np.array([_seen(model, true, VIEWS[1]), _seen(model, ghost_lit, VIEWS[1])])
    assert np.linalg.norm(a[0] - b[0]) < 1e-9          # the true point: one place
    gap = np.linalg.norm(a[1] - b[1])
    # the stated parallax: delta * b / (z * sin(alpha))
    base = view_baseline(model, *VIEWS)
    sin_alpha = abs(n @ ray)
    assert gap == pytest.approx(0.010 * base / (t * sin_alpha), rel=0.5)
    keep_a, keep_b = agreeing(a, b, tolerance=0.5 * gap)
    assert keep_a.tolist() == [True, False] and keep_b.tolist() == [True, False]


def test_two_view_sweep_and_bad_input():
    v = np.zeros((3, 4))
    v[:, 3] = [0.1, 0.2, 0.3]
    s = two_view_sweep(v, (0.3, -0.1))
    assert s.shape == (6, 4)
    assert np.array_equal(s[0::2], v) and np.allclose(s[1::2, :2], [0.3, -0.1])
    assert np.array_equal(s[1::2, 3], v[:, 3])
    with pytest.raises(ValueError, match='tolerance'):
        agreeing(np.zeros((1, 3)), np.zeros((1, 3)), math.nan)
    with pytest.raises(ValueError):
        agreeing(np.zeros((2, 2)), np.zeros((1, 3)), 1e-3)
    ka, kb = agreeing(np.zeros((0, 3)), np.zeros((2, 3)), 1e-3)
    assert ka.shape == (0,) and not kb.any()


def test_expected_rows_put_the_stripe_on_the_nominal_face():
    """A face's expected rows, triangulated back with the same model, lie on the face."""
    from reconstructor.planning import expected_rows

    model = nominal_example_rig()
    c = np.array([0.0, 0.0, 0.66])
    R = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)],
                  [0.0, math.sin(0.3), math.cos(0.3)]])
    e1, e2 = R[:, 0], R[:, 1]
    volts = np.array([0.1, -0.05, 0.0, 0.02])
    rows = expected_rows(model, [(c, e1, e2, (0.02, 0.5))], volts, 720)
    cols = np.flatnonzero(np.isfinite(rows))
    assert 100 < len(cols) < 720  # the face is 40 mm wide: part of the 60 mm view
    res = triangulate(model, np.column_stack((cols, rows[cols])), *volts[[0, 1, 3]])
    n = np.cross(e1, e2)
    assert np.max(np.abs((res.p_v0[res.valid] - c) @ n)) < 2e-6
    with pytest.raises(ValueError, match='voltages'):
        expected_rows(model, [], np.array([0.0, math.nan, 0.0, 0.0]), 720)
