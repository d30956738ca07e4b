"""Joint-correction table: exact at the nodes, rotations interpolated on SO(3), clamped outside,
holes handled, file round trip and validation, and its use by the model's triangulation."""

import dataclasses
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from reconstructor.correction import CorrectionTable, matrix_to_rotvec, rotvec_to_matrix
from reconstructor.model import nominal_example_rig, project_points, triangulate, v0_T_v


def _random_table(seed, n_pan=3, n_tilt=4, rot=0.02, trans=0.004, valid=None):
    rng = np.random.default_rng(seed)
    pan = np.sort(rng.uniform(-5, 5, n_pan)) if n_pan > 1 else np.array([0.3])
    tilt = np.sort(rng.uniform(-5, 5, n_tilt)) if n_tilt > 1 else np.array([-0.2])
    rv = rng.normal(0, rot, (n_pan, n_tilt, 3))
    tr = rng.normal(0, trans, (n_pan, n_tilt, 3))
    return CorrectionTable.from_rotvecs(pan, tilt, rv, tr, valid), rv, tr


def _is_rigid(T, tol=1e-12):
    R = T[..., :3, :3]
    eye = np.broadcast_to(np.eye(3), R.shape)
    return (np.abs(np.swapaxes(R, -1, -2) @ R - eye).max() < tol
            and np.all(np.abs(np.linalg.det(R) - 1) < tol)
            and np.allclose(T[..., 3, :], [0, 0, 0, 1]))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_nodes_are_reproduced_exactly(seed):
    table, rv, tr = _random_table(seed)
    P, Tl = np.meshgrid(table.u1_pan, table.u1_tilt, indexing='ij')
    T = table.V0c_T_V0(P, Tl)
    assert T.shape == P.shape + (4, 4)
    np.testing.assert_allclose(T[..., :3, :3], Rotation.from_rotvec(rv.reshape(-1, 3))
                               .as_matrix().reshape(rv.shape[:2] + (3, 3)), atol=1e-13)
    np.testing.assert_allclose(T[..., :3, 3], tr, atol=1e-15)


def test_two_nodes_follow_the_geodesic_like_slerp():
    rng = np.random.default_rng(3)
    rv = rng.normal(0, 0.15, (2, 1, 3))
    table = CorrectionTable.from_rotvecs([-1.0, 2.0], [0.5], rv, np.zeros((2, 1, 3)))
    u = np.linspace(-1.0, 2.0, 31)
    slerp = Slerp([-1.0, 2.0], Rotation.from_rotvec(rv[:, 0]))
    T = table.V0c_T_V0(u, 0.5)
    # The mean of two rotations is their geodesic midpoint, so tangent-space interpolation
    # about it is the geodesic itself: it must equal spherical linear interpolation.
    np.testing.assert_allclose(T[:, :3, :3], slerp(u).as_matrix(), atol=1e-12)


def test_rotations_are_not_interpolated_element_wise():
    # +-0.45 rad about z: half way the rotation must be the identity, a proper rotation;
    # element-wise averaging would give diag(cos 0.45, cos 0.45, 1), not a rotation.
    rv = np.array([[[0, 0, -0.45]], [[0, 0, 0.45]]])
    table = CorrectionTable.from_rotvecs([0.0, 1.0], [0.0], rv, np.zeros((2, 1, 3)))
    T = table.V0c_T_V0(0.5, 0.0)
    np.testing.assert_allclose(T, np.eye(4), atol=1e-14)
    T = table.V0c_T_V0(0.25, 0.0)
    assert _is_rigid(T)
    np.testing.assert_allclose(matrix_to_rotvec(T[:3, :3]), [0, 0, -0.225], atol=1e-14)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(-8, 8), st.floats(-8, 8))
def test_interpolation_is_rigid_and_bilinear_in_translation(seed, up, ut):
    table, rv, tr = _random_table(seed)
    T = table.V0c_T_V0(up, ut)
    assert _is_rigid(T)
    # Independent bilinear interpolation of the translation, with clamping.
    p = np.clip(up, table.u1_pan[0], table.u1_pan[-1])
    t = np.clip(ut, table.u1_tilt[0], table.u1_tilt[-1])
    from scipy.interpolate import RegularGridInterpolator

    ref = RegularGridInterpolator((table.u1_pan, table.u1_tilt), tr)([[p, t]])[0]
    np.testing.assert_allclose(T[:3, 3], ref, atol=1e-15)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(-6, 6), st.floats(-6, 6))
def test_scalar_fast_path_matches_array_path(seed, up, ut):
    valid = np.random.default_rng(seed).random((3, 4)) > 0.3
    valid[0, 0] = True
    table, _, _ = _random_table(seed, valid=valid)
    np.testing.assert_allclose(table.V0c_T_V0(float(up), float(ut)),
                               table.V0c_T_V0(np.array([up]), np.array([ut]))[0], atol=1e-15)


def test_continuous_across_cell_edges():
    table, _, _ = _random_table(7, n_pan=4, n_tilt=4, rot=0.05)
    edge = table.u1_pan[1]
    t = np.linspace(table.u1_tilt[0], table.u1_tilt[-1], 17)
    a = table.V0c_T_V0(edge - 1e-9, t)
    b = table.V0c_T_V0(edge + 1e-9, t)
    assert np.abs(a - b).max() < 1e-9


def test_outside_the_grid_is_clamped_to_the_edge():
    table, _, _ = _random_table(11)
    lo_p, hi_p = table.u1_pan[[0, -1]]
    lo_t, hi_t = table.u1_tilt[[0, -1]]
    np.testing.assert_array_equal(table.V0c_T_V0(lo_p - 3.0, hi_t + 7.0),
                                  table.V0c_T_V0(lo_p, hi_t))
    np.testing.assert_array_equal(table.V0c_T_V0(0.5 * (lo_p + hi_p), lo_t - 1.0),
                                  table.V0c_T_V0(0.5 * (lo_p + hi_p), lo_t))


def test_single_voltage_axis_is_constant_along_it():
    table, rv, tr = _random_table(5, n_pan=1, n_tilt=3)
    T1 = table.V0c_T_V0(-4.0, table.u1_tilt[1])
    T2 = table.V0c_T_V0(9.0, table.u1_tilt[1])
    np.testing.assert_array_equal(T1, T2)
    np.testing.assert_allclose(T1[:3, 3], tr[0, 1], atol=1e-15)


def test_invalid_nodes_renormalise_or_fall_back_to_the_nearest_valid_node():
    tr = np.zeros((3, 3, 3))
    tr[..., 0] = np.arange(9).reshape(3, 3) * 1e-3
    valid = np.ones((3, 3), dtype=bool)
    valid[1, 1] = False
    table = CorrectionTable.from_rotvecs([0, 1, 2], [0, 1, 2], np.zeros((3, 3, 3)), tr, valid)
    # Cell [0,1]x[0,1] at its centre: corners (0,0) 0, (1,0) 3, (0,1) 1 valid; (1,1) invalid.
    T = table.V0c_T_V0(0.5, 0.5)
    assert math.isclose(T[0, 3], (0 + 3 + 1) / 3 * 1e-3, rel_tol=1e-12)
    # At the invalid node itself the weight is all on it: fall back to the nearest valid node.
    only = np.zeros((3, 3), dtype=bool)
    only[2, 0] = True
    table = CorrectionTable.from_rotvecs([0, 1, 2], [0, 1, 2], np.zeros((3, 3, 3)), tr, only)
    np.testing.assert_allclose(table.V0c_T_V0(0.2, 1.9)[:3, 3], tr[2, 0])
    with pytest.raises(ValueError, match='holds no correction'):
        table.node_transform(0, 0)


def test_non_finite_voltages_give_nan():
    table, _, _ = _random_table(2)
    T = table.V0c_T_V0(np.array([0.0, np.nan]), np.array([np.inf, 0.0]))
    assert np.isnan(T).all()
    assert np.isnan(table.V0c_T_V0(float('nan'), 0.0)).all()


def test_file_round_trip_through_yaml():
    valid = np.ones((3, 4), dtype=bool)
    valid[2, 1] = False
    table, _, _ = _random_table(9, valid=valid)
    text = yaml.safe_dump(table.to_dict())
    loaded = CorrectionTable.from_dict(yaml.safe_load(text))
    u = np.random.default_rng(1).uniform(-6, 6, (50, 2))
    np.testing.assert_allclose(loaded.V0c_T_V0(u[:, 0], u[:, 1]),
                               table.V0c_T_V0(u[:, 0], u[:, 1]), atol=1e-15)
    np.testing.assert_array_equal(loaded.valid, valid)


def _good_dict():
    return _random_table(4, n_pan=2, n_tilt=2)[0].to_dict()


@pytest.mark.parametrize('mutate, message', [
    (lambda d: d.pop('translation'), r'missing key translation'),
    (lambda d: d.__setitem__('extra', 1), r'unknown key extra'),
    (lambda d: d.__setitem__('format_version', 2), r'format_version is 2'),
    (lambda d: d.__setitem__('format', 'matrix'), r'format must be'),
    (lambda d: d['translation'][1][0].__setitem__(2, float('nan')),
     r'translation\[1\]\[0\]\[2\] must be finite'),
    (lambda d: d['translation'][0][1].__setitem__(0, 4.0),
     r'translation\[0\]\[1\] .* millimetres'),
    (lambda d: d['rotation_vector'][0][0].__setitem__(1, 30.0),
     r'rotation_vector\[0\]\[0\] .* degrees'),
    (lambda d: d['rotation_vector'][1].pop(), r'rotation_vector must have shape'),
    (lambda d: d.__setitem__('u1_pan', [1.0, 0.0]), r'u1_pan must be strictly increasing'),
    (lambda d: d.__setitem__('u1_tilt', [0.0, 'a']), r'u1_tilt\[1\] must be a number'),
    (lambda d: d['valid'][0].__setitem__(1, 1), r'valid\[0\]\[1\] must be true or false'),
    (lambda d: d.__setitem__('valid', [[False, False], [False, False]]), r'at least one'),
])
def test_bad_dicts_are_refused_naming_the_key(mutate, message):
    data = _good_dict()
    mutate(data)
    with pytest.raises(ValueError, match=message):
        CorrectionTable.from_dict(data)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match='transforms must have shape'):
        CorrectionTable([0, 1], [0], np.tile(np.eye(4), (2, 2, 1, 1)))
    T = np.tile(np.eye(4), (2, 1, 1, 1))
    T[1, 0, :3, :3] = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match=r'transforms\[1\]\[0\] rotation block'):
        CorrectionTable([0, 1], [0], T)


def test_rodrigues_helpers_invert_each_other():
    rv = np.random.default_rng(0).normal(0, 0.7, (100, 3))
    rv[0] = 0.0
    rv[1] = [1e-9, 0, 0]
    np.testing.assert_allclose(matrix_to_rotvec(rotvec_to_matrix(rv)), rv, atol=1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(rv), Rotation.from_rotvec(rv).as_matrix(),
                               atol=1e-14)


def test_triangulation_applies_the_table_after_V0_T_V():
    model = nominal_example_rig()
    table, _, _ = _random_table(21, rot=0.01, trans=0.003)
    corrected = dataclasses.replace(model, correction=table)
    u1p, u1t, u2 = 0.7, -1.3, 0.2
    # Pixels of points on the laser plane seen from this G1 setting.
    from reconstructor.model import laser_plane_v

    pi = laser_plane_v(model, u1p, u1t, u2)
    xs = np.linspace(-0.02, 0.02, 7)
    p_v = np.array([[x, -(pi[0] * x + pi[2] * 0.65 + pi[3]) / pi[1], 0.65] for x in xs])
    uv = project_points(model.intrinsics, p_v)
    plain = triangulate(model, uv, u1p, u1t, u2)
    got = triangulate(corrected, uv, u1p, u1t, u2)
    assert plain.valid.all() and got.valid.all()
    T = v0_T_v(model, u1p, u1t)
    np.testing.assert_allclose(plain.p_v0, p_v @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    C = table.V0c_T_V0(u1p, u1t)
    np.testing.assert_allclose(got.p_v0, plain.p_v0 @ C[:3, :3].T + C[:3, 3], atol=1e-12)
