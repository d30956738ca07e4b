"""Dynamic laser (paper Eqs. 6-7) and plane transforms, against scipy rotations."""

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from reconstructor.model import (
    MirrorParams,
    laser_plane_v,
    laser_plane_v0,
    nominal_example_rig,
    transform_plane,
    v0_T_v,
)

volts = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False)
unit3 = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)


def plane_basis(pi):
    """Two in-plane unit directions and one point of plane pi (unit normal)."""
    n = np.asarray(pi[:3])
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    return a, b, -pi[3] * n


def rigid(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def model_with_laser(axis_dir, axis_point, plane, g2=None):
    base = nominal_example_rig()
    return dataclasses.replace(
        base,
        laser_axis_dir=axis_dir,
        laser_axis_point=axis_point,
        laser_plane_v0=plane,
        g2_tilt=g2 or base.g2_tilt,
    )


@settings(max_examples=100, deadline=None)
@given(volts)
def test_plane_equals_rodrigues_when_axis_lies_in_plane(u):
    """docs/design.md: normal = R(n, 2 theta4) n0 and e = -normal . P (P on pi0)."""
    model = nominal_example_rig()  # its U2 = 0 plane contains the axis
    n, P = model.laser_axis_dir, model.laser_axis_point
    n0 = model.laser_plane_v0[:3].copy()  # model arrays are read-only
    assert n0 @ P + model.laser_plane_v0[3] == pytest.approx(0.0, abs=1e-15)
    theta4 = model.g2_tilt.k * u  # linear galvo, theta4 measured from 0 V
    normal = Rotation.from_rotvec(2.0 * theta4 * n).apply(n0)
    np.testing.assert_allclose(
        laser_plane_v0(model, u), np.append(normal, -normal @ P), atol=1e-14
    )


@settings(max_examples=100, deadline=None)
@given(unit3, unit3, st.floats(-0.1, 0.1), volts, st.floats(-1e-3, 1e-3))
def test_plane_is_rigid_rotation_of_pi0_about_the_axis(n_raw, n0_raw, offset, u, c2):
    """With P off pi0, every point of pi0 rotated about (n, P) lies on the predicted plane."""
    n = np.array(n_raw) / np.linalg.norm(n_raw)
    n0 = np.array(n0_raw) / np.linalg.norm(n0_raw)
    P = np.array([0.01, -0.2, 0.26])
    plane0 = np.append(n0, -n0 @ P + offset)  # P lies `offset` metres off pi0
    g2 = MirrorParams(0.3, 0.035, (c2,))
    model = model_with_laser(n, P, plane0, g2)
    alpha = 2.0 * (g2.angle(u) - g2.angle(0.0))
    rot = Rotation.from_rotvec(alpha * n)
    a, b, p0 = plane_basis(plane0)
    pts = p0 + np.outer([-1, 0.3, 2.0, 0.7], a) + np.outer([0.5, -2, 1.1, 0.0], b)
    moved = rot.apply(pts - P) + P
    pi = laser_plane_v0(model, u)
    np.testing.assert_allclose(np.linalg.norm(pi[:3]), 1.0, atol=1e-14)
    np.testing.assert_allclose(moved @ pi[:3] + pi[3], 0.0, atol=1e-13)


def test_plane_at_zero_volts_is_pi0_and_batched():
    model = model_with_laser([1, 0.02, -0.0004], [0.0, -0.2, 0.25], [0.0, 0.9, -0.44, -0.3])
    np.testing.assert_allclose(laser_plane_v0(model, 0.0), model.laser_plane_v0, atol=1e-16)
    u = np.array([[-3.0, 0.0], [2.5, 9.0]])
    batch = laser_plane_v0(model, u)
    assert batch.shape == (2, 2, 4)
    for idx in np.ndindex(2, 2):
        np.testing.assert_allclose(batch[idx], laser_plane_v0(model, float(u[idx])), atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(unit3, unit3, st.floats(-1, 1), unit3, st.floats(-np.pi, np.pi))
def test_transform_plane_keeps_points_on_plane(n_raw, t_raw, e, axis_raw, angle):
    n = np.array(n_raw) / np.linalg.norm(n_raw)
    pi_A = np.append(n, e)
    axis = np.array(axis_raw) / np.linalg.norm(axis_raw)
    A_T_B = rigid(angle * axis, np.array(t_raw))
    a, b, p0 = plane_basis(pi_A)
    p_A = p0 + np.outer([0.0, 1.0, -2.0, 0.4], a) + np.outer([0.0, 0.5, 1.5, -3.0], b)
    p_B = (np.linalg.inv(A_T_B) @ np.column_stack([p_A, np.ones(4)]).T).T
    pi_B = transform_plane(A_T_B, pi_A)
    np.testing.assert_allclose(p_B @ pi_B, 0.0, atol=1e-12)
    # Batched: several transforms against one plane.
    stack = np.stack([A_T_B, np.eye(4)])
    np.testing.assert_allclose(transform_plane(stack, pi_A), [pi_B, pi_A], atol=1e-15)


@settings(max_examples=50, deadline=None)
@given(volts, volts, volts)
def test_laser_plane_in_v_contains_the_v0_points_mapped_to_v(u1p, u1t, u2):
    model = nominal_example_rig()
    pi_v0 = laser_plane_v0(model, u2)
    a, b, p0 = plane_basis(pi_v0)
    p_v0 = p0 + np.outer([0.0, 0.1, -0.3], a) + np.outer([0.0, 0.2, 0.05], b)
    V_T_V0 = np.linalg.inv(v0_T_v(model, u1p, u1t))
    p_v = (V_T_V0 @ np.column_stack([p_v0, np.ones(3)]).T).T
    pi_v = laser_plane_v(model, u1p, u1t, u2)
    np.testing.assert_allclose(p_v @ pi_v, 0.0, atol=1e-13)
    assert np.linalg.norm(pi_v[:3]) == pytest.approx(1.0, abs=1e-14)


def test_transform_plane_shape_errors():
    with pytest.raises(ValueError, match="A_T_B"):
        transform_plane(np.eye(3), [0, 0, 1, 0])
    with pytest.raises(ValueError, match="pi_A"):
        transform_plane(np.eye(4), [0, 0, 1])
    with pytest.raises(ValueError, match="A_T_B"):
        transform_plane(np.tile(np.eye(4), (3, 1, 1)), np.zeros((2, 4)))


def test_rotation_sense_is_right_handed_about_n():
    # Axis +x through the origin, pi0 = plane y = 0 (normal +y): +90 deg turns the normal to +z.
    g2 = MirrorParams(0.0, 1.0)
    model = model_with_laser([1, 0, 0], [0, 0, 0], [0, 1, 0, 0], g2)
    np.testing.assert_allclose(laser_plane_v0(model, math.pi / 4), [0, 0, 1, 0], atol=1e-15)
