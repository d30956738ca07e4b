"""Dynamic-camera model (docs/design.md §2, paper Eq. 2): factors, G_T_V, V0_T_V, mirror response.

The independent reference builds G_T_V from the physical set-up, not from the model's
matrices: the camera at (-l, 0, 0) in G looking along +x_G, the pan mirror (a plane containing
G's z axis) and the tilt mirror (a plane containing the line through (0, d, 0) parallel to x),
each a Householder reflection ``x -> x - 2 n (n.x - n.p)`` of its plane. At 45 deg the pan
mirror sends +x to +y and the tilt mirror sends +y to +z, which fixes the normals
``n_pan = (cos t1, -sin t1, 0)`` and ``n_tilt = (0, sin t2, -cos t2)`` (the sense of positive
rotation is the paper's convention).
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reconstructor.geometry.galvo import g_T_v_scalar
from reconstructor.model import (
    MirrorParams,
    g_T_v,
    m0_factor,
    nominal_example_rig,
    pan_factor,
    rigid_inverse,
    tilt_factor,
    v0_T_v,
)

angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
lengths = st.floats(min_value=0.0, max_value=0.3, allow_nan=False)
volts = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False)


def householder(normal, point):
    """4x4 reflection in the plane with unit normal ``normal`` through ``point``."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    H = np.eye(4)
    H[:3, :3] -= 2.0 * np.outer(n, n)
    H[:3, 3] = 2.0 * (n @ np.asarray(point, dtype=float)) * n
    return H


def camera_pose_in_g(l):
    """G_T_C of the real camera: centre (-l, 0, 0), z_C = +x_G, x_C = +y_G, y_C = +z_G."""
    T = np.eye(4)
    T[:3, 0] = [0.0, 1.0, 0.0]  # x_C in G
    T[:3, 1] = [0.0, 0.0, 1.0]  # y_C in G
    T[:3, 2] = [1.0, 0.0, 0.0]  # z_C (optical axis) in G
    T[:3, 3] = [-l, 0.0, 0.0]
    return T


def reference_g_T_v(t1, t2, l, d):
    pan = householder([math.cos(t1), -math.sin(t1), 0.0], [0.0, 0.0, 0.0])
    tilt = householder([0.0, math.sin(t2), -math.cos(t2)], [0.0, d, 0.0])
    return tilt @ pan @ camera_pose_in_g(l)


@settings(max_examples=200, deadline=None)
@given(angles, angles, lengths, lengths)
def test_eq2_product_matches_householder_reference(t1, t2, l, d):
    np.testing.assert_allclose(g_T_v(t1, t2, l, d), reference_g_T_v(t1, t2, l, d), atol=1e-12)
    np.testing.assert_allclose(g_T_v_scalar(t1, t2, l, d), g_T_v(t1, t2, l, d), atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(angles, angles, lengths, lengths)
def test_eq2_entry_row2_col3_is_sin2t1_cos2t2(t1, t2, l, d):
    T = g_T_v(t1, t2, l, d)
    expected = math.sin(2 * t1) * math.cos(2 * t2)
    assert T[1, 2] == pytest.approx(expected, abs=1e-12)
    assert reference_g_T_v(t1, t2, l, d)[1, 2] == pytest.approx(expected, abs=1e-12)


def test_eq2_printed_entry_is_wrong():
    # The paper prints sin2t1*sin2t2 at (row 2, col 3); at generic angles that is not the value.
    t1, t2 = 0.61, 0.83
    T = g_T_v(t1, t2, 0.08, 0.02)
    printed = math.sin(2 * t1) * math.sin(2 * t2)
    assert abs(T[1, 2] - printed) > 0.1
    assert abs(reference_g_T_v(t1, t2, 0.08, 0.02)[1, 2] - printed) > 0.1


@settings(max_examples=100, deadline=None)
@given(angles, angles, lengths, lengths)
def test_factor_determinants(t1, t2, l, d):
    assert np.linalg.det(pan_factor(t1)) == pytest.approx(-1.0, abs=1e-12)
    assert np.linalg.det(tilt_factor(t2, d)) == pytest.approx(-1.0, abs=1e-12)
    assert np.linalg.det(m0_factor(l)) == pytest.approx(1.0, abs=1e-12)
    T = g_T_v(t1, t2, l, d)
    assert np.linalg.det(T) == pytest.approx(1.0, abs=1e-12)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def line_plane(origin, direction, normal, point):
    s = normal @ (point - origin) / (normal @ direction)
    return origin + s * direction


def reflect_dir(direction, normal):
    return direction - 2.0 * (direction @ normal) * normal


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.6, 0.95),
    st.floats(0.6, 0.95),
    st.floats(0.04, 0.12),
    st.floats(0.01, 0.04),
    st.floats(-0.03, 0.03),
    st.floats(-0.03, 0.03),
)
def test_virtual_ray_matches_ray_traced_through_both_mirrors(t1, t2, l, d, x, y):
    """A pixel ray of V, mapped by G_T_V, is the ray the camera sees after both reflections."""
    G_T_C = camera_pose_in_g(l)
    ray_c = np.array([x, y, 1.0])
    # Trace the physical ray: camera -> pan mirror -> tilt mirror -> scene.
    n_pan = np.array([math.cos(t1), -math.sin(t1), 0.0])
    n_tilt = np.array([0.0, math.sin(t2), -math.cos(t2)])
    o = G_T_C[:3, 3]
    dvec = G_T_C[:3, :3] @ ray_c
    hit1 = line_plane(o, dvec, n_pan, np.zeros(3))
    d1 = reflect_dir(dvec, n_pan)
    hit2 = line_plane(hit1, d1, n_tilt, np.array([0.0, d, 0.0]))
    d2 = reflect_dir(d1, n_tilt)
    # The same pixel's ray in V, expressed in G by the model.
    T = g_T_v(t1, t2, l, d)
    o_v = T[:3, 3]
    d_v = T[:3, :3] @ ray_c
    # Same direction, and the outgoing physical segment lies on the virtual ray's line.
    np.testing.assert_allclose(d2 / np.linalg.norm(d2), d_v / np.linalg.norm(d_v), atol=1e-12)
    off = np.cross(hit2 - o_v, d_v / np.linalg.norm(d_v))
    np.testing.assert_allclose(off, 0.0, atol=1e-12)


def test_v0_optical_axis_points_along_g_z():
    # At 45/45 deg the virtual camera looks out along +z_G.
    T = g_T_v(math.pi / 4, math.pi / 4, 0.08345, 0.02214)
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, 1.0], atol=1e-15)


@settings(max_examples=50, deadline=None)
@given(
    st.floats(0.7, 0.9),
    st.floats(0.7, 0.9),
    st.floats(0.02, 0.05),
    st.floats(-0.001, 0.001),
    lengths,
    lengths,
)
def test_v0_T_v_identity_at_zero_volts(th_p, th_t, k, c2, l, d):
    base = nominal_example_rig()
    model = _replace(
        base,
        g1_pan=MirrorParams(th_p, k, (c2, 1e-5)),
        g1_tilt=MirrorParams(th_t, -k, (-c2,)),
        l=l,
        d=d,
    )
    np.testing.assert_allclose(v0_T_v(model, 0.0, 0.0), np.eye(4), atol=1e-14)
    np.testing.assert_allclose(
        v0_T_v(model, np.zeros(3), 0.0), np.tile(np.eye(4), (3, 1, 1)), atol=1e-14
    )


@settings(max_examples=100, deadline=None)
@given(volts, volts)
def test_v0_T_v_matches_reference_composition(u1, u2):
    model = nominal_example_rig()
    t1 = model.g1_pan.angle(u1)
    t2 = model.g1_tilt.angle(u2)
    ref = np.linalg.inv(reference_g_T_v(math.pi / 4, math.pi / 4, model.l, model.d))
    ref = ref @ reference_g_T_v(t1, t2, model.l, model.d)
    np.testing.assert_allclose(v0_T_v(model, u1, u2), ref, atol=1e-12)
    assert np.linalg.det(v0_T_v(model, u1, u2)) == pytest.approx(1.0, abs=1e-12)


def test_v0_T_v_batched_shapes_and_values():
    model = nominal_example_rig()
    u1 = np.linspace(-10, 10, 6).reshape(2, 3)
    u2 = np.linspace(5, -5, 3)
    T = v0_T_v(model, u1, u2)
    assert T.shape == (2, 3, 4, 4)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(T[i, j], v0_T_v(model, u1[i, j], u2[j]), atol=1e-15)


def test_rigid_inverse():
    T = g_T_v(np.array([0.3, 0.9]), np.array([0.7, 1.2]), 0.08, 0.02)
    np.testing.assert_allclose(rigid_inverse(T) @ T, np.tile(np.eye(4), (2, 1, 1)), atol=1e-14)
    with pytest.raises(ValueError, match="A_T_B"):
        rigid_inverse(np.eye(3))


def test_g_T_v_rejects_bad_arguments():
    with pytest.raises(ValueError, match="theta_pan"):
        g_T_v(np.zeros(3), np.zeros(4), 0.08, 0.02)
    with pytest.raises(ValueError, match="theta_pan"):
        g_T_v(np.array(["a"]), 0.0, 0.08, 0.02)
    with pytest.raises(ValueError, match="^l "):
        g_T_v(0.0, 0.0, float("nan"), 0.02)
    with pytest.raises(ValueError, match="^d "):
        g_T_v(0.0, 0.0, 0.08, np.ones(2))


# ------------------------------------------------------------------------------ mirrors
@settings(max_examples=200, deadline=None)
@given(
    st.floats(-1, 1),
    st.floats(0.02, 0.1),
    st.tuples(st.floats(-1e-4, 1e-4), st.floats(-1e-5, 1e-5), st.floats(-1e-6, 1e-6)),
    st.integers(0, 3),
    volts,
)
def test_mirror_angle_polynomial_and_inverse(theta0, k, coeffs, order, u):
    poly = coeffs[:order]
    m = MirrorParams(theta0, k, poly)
    expected = np.polynomial.polynomial.polyval(u, [theta0, k, *poly])
    assert m.angle(u) == pytest.approx(expected, abs=1e-14)
    arr = np.array([u, -u, 0.5 * u])
    np.testing.assert_allclose(
        m.angle(arr), np.polynomial.polynomial.polyval(arr, [theta0, k, *poly]), atol=1e-14
    )
    # |d theta/dU - k| < 0.009 rad/V < k on +-10 V: monotonic, so the inverse is unique.
    assert m.voltage(m.angle(u)) == pytest.approx(u, abs=1e-9)


def test_mirror_params_validation():
    with pytest.raises(ValueError, match="theta0"):
        MirrorParams(float("nan"), 0.03)
    with pytest.raises(ValueError, match="^k "):
        MirrorParams(0.7, float("inf"))
    with pytest.raises(ValueError, match="poly"):
        MirrorParams(0.7, 0.03, (1.0, float("nan")))


def _replace(model, **changes):
    import dataclasses

    return dataclasses.replace(model, **changes)
