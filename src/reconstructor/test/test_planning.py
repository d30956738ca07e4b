"""Aiming G1 with the model: the one aim solver (reconstructor.planning.aim_g1)."""

import dataclasses

import numpy as np
import pytest

from reconstructor import planning
from reconstructor.model import (
    MirrorParams,
    nominal_example_rig,
    predict_pixels,
    rigid_inverse,
    v0_T_v,
)


def _models():
    """A design-value rig, a distorted lens at another standoff, and glued-askew mirrors."""
    yield nominal_example_rig()
    yield nominal_example_rig(dist=(-0.3, 0.9, 1e-4, -2e-4, 0.0), standoff=0.45)
    base = nominal_example_rig(standoff=0.9)
    yield dataclasses.replace(
        base, l=base.l * 1.2, d=base.d * 0.8,
        g1_pan=MirrorParams(0.80, 0.0360, (2e-5, -1e-6)),
        g1_tilt=MirrorParams(0.77, -0.0330, (1e-5,)))


def _targets(seed, n=60):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.7, 0.7, n),
                            rng.uniform(0.35, 1.1, n)])


@pytest.mark.parametrize('index', range(3))
def test_aimed_targets_sit_on_the_optical_axis_and_at_the_principal_point(index):
    model = list(_models())[index]
    P = _targets(index)
    U = planning.aim_g1(model, P)
    reached = np.isfinite(U[:, 0])
    assert 10 < reached.sum() < len(P)  # some targets are out of the +-10 V reach
    pp = np.array([model.intrinsics.cx, model.intrinsics.cy])
    for p, u in zip(P[reached], U[reached], strict=True):
        assert np.abs(u).max() <= 10.0
        q = rigid_inverse(v0_T_v(model, u[0], u[1])) @ np.append(p, 1.0)
        assert q[2] > 0 and np.hypot(q[0], q[1]) / q[2] < 1.5e-6
        uv, ok = predict_pixels(model, p[None], u[0], u[1])
        assert ok[0] and np.abs(uv[0] - pp).max() < 0.02
    # the same answers one point at a time, from another start, and through aim_camera
    for p, u in list(zip(P[reached], U[reached], strict=True))[:5]:
        np.testing.assert_allclose(planning.aim_g1(model, p), u, atol=1e-9)
        np.testing.assert_allclose(planning.aim_g1(model, p, start=(0.5, -0.5)), u, atol=1e-9)
        np.testing.assert_allclose(planning.aim_camera(model, p), u, atol=1e-9)


def test_unreachable_targets_are_nan_and_aim_camera_refuses_them():
    model = nominal_example_rig()
    far_off = np.array([[3.0, 0.0, 0.5], [0.0, -2.0, 0.3], [0.0, 0.0, -1.0]])
    assert np.all(np.isnan(planning.aim_g1(model, far_off)))
    with pytest.raises(ValueError, match='cannot be centred'):
        planning.aim_camera(model, far_off[0])
    # a smaller voltage range reaches less
    p = np.array([0.3, 0.2, 0.65])
    assert np.all(np.isfinite(planning.aim_g1(model, p)))
    assert np.all(np.isnan(planning.aim_g1(model, p, max_abs_u=1.0)))


def test_bad_input_is_refused_by_name_or_gives_nan():
    model = nominal_example_rig()
    with pytest.raises(ValueError, match='points_v0'):
        planning.aim_g1(model, np.zeros((4, 2)))
    with pytest.raises(ValueError, match='max_abs_u'):
        planning.aim_g1(model, [0.0, 0.0, 0.65], max_abs_u=float('nan'))
    with pytest.raises(ValueError, match='target_v0'):
        planning.aim_camera(model, [0.0, np.nan, 0.65])
    U = planning.aim_g1(model, [[0.0, np.nan, 0.65], [0.0, 0.0, 0.65]])
    assert np.all(np.isnan(U[0])) and np.all(np.isfinite(U[1]))


def test_where_newton_fails_the_bounded_search_still_aims(monkeypatch):
    model = nominal_example_rig()
    p = np.array([0.2, -0.15, 0.7])
    expected = planning.aim_g1(model, p)
    monkeypatch.setattr(planning, '_newton_aim', lambda model, point, u: np.array([9.0, 9.0]))
    np.testing.assert_allclose(planning.aim_g1(model, p), expected, atol=1e-7)


def test_the_aim_includes_the_joint_correction():
    """With a correction table, the aimed target lands on the principal point as
    ``predict_pixels`` (and triangulation) see the view: correction included."""
    from scipy.spatial.transform import Rotation

    from reconstructor.correction import CorrectionTable

    pans, tilts = np.linspace(-10, 10, 5), np.linspace(-10, 10, 5)
    T = np.tile(np.eye(4), (5, 5, 1, 1))
    rng = np.random.default_rng(3)
    for a in range(5):
        for b in range(5):
            T[a, b, :3, :3] = Rotation.from_rotvec(rng.normal(0, 2e-3, 3)).as_matrix()
            T[a, b, :3, 3] = rng.normal(0, 5e-4, 3)
    model = dataclasses.replace(nominal_example_rig(), correction=CorrectionTable(pans, tilts, T))
    plain = dataclasses.replace(model, correction=None)
    pp = np.array([model.intrinsics.cx, model.intrinsics.cy])
    for p in _targets(7, 12):
        u = planning.aim_g1(model, p)
        if not np.all(np.isfinite(u)):
            continue
        uv, ok = predict_pixels(model, p[None], u[0], u[1])
        assert ok[0] and np.abs(uv[0] - pp).max() < 0.02
        assert np.abs(u - planning.aim_g1(plain, p)).max() > 1e-4  # the correction matters
