"""The calibration's covariance carried to reconstructed points (reconstructor.uncertainty).

Model-level problems with known answers: the stage-by-stage joining of covariances equals the
joint least-squares covariance of a linear chain, the linear propagation to points matches
the scatter of points re-triangulated with parameters drawn from the covariance, and bad
covariance records are refused with what is wrong named.
"""

import dataclasses
import math

import numpy as np
import pytest

from reconstructor.calibration_file import Calibration
from reconstructor.model import (
    CameraIntrinsics,
    nominal_example_rig,
    project_points,
    triangulate_batch,
)
from reconstructor.uncertainty import (
    ParameterCovariance,
    _without_rigid_motion,
    covariance_record,
    intrinsics_warp,
    parameter_covariance,
    parameter_value,
    point_uncertainty_map,
    stripe_samples,
    with_parameters,
)


def _calibration(stages):
    return Calibration(model=nominal_example_rig(), source='calibrated', stages=stages)


def test_stage_by_stage_covariance_equals_the_joint_fit_of_a_linear_chain():
    # stage 1 measures a (= l) directly; stage 2 measures b + c a (b = d) holding a fixed
    rng = np.random.default_rng(3)
    n1, n2, s1, s2, c = 20, 30, 0.2, 0.1, 1.7
    A = np.vstack([np.column_stack([np.ones(n1), np.zeros(n1)]) / s1,
                   np.column_stack([c * np.ones(n2), np.ones(n2)]) / s2])
    joint = np.linalg.inv(A.T @ A)
    var_a, var_b_given_a = s1**2 / n1, s2**2 / n2
    stages = {
        'one': {'created': '2026-01-01T00:00:00', 'updated': ['l'],
                'covariance': covariance_record(['l'], [[var_a]])},
        'two': {'created': '2026-01-01T00:00:01', 'updated': ['d'],
                'covariance': covariance_record(['d'], [[var_b_given_a]], ['l'], [[-c]])},
    }
    pc = parameter_covariance(_calibration(stages))
    assert pc.names == ['l', 'd'] and pc.stage_of == {'l': 'one', 'd': 'two'}
    np.testing.assert_allclose(pc.matrix, joint, rtol=1e-12)
    # order comes from the stamps, not from the file's order
    pc2 = parameter_covariance(_calibration(dict(reversed(list(stages.items())))))
    np.testing.assert_allclose(pc2.matrix, joint, rtol=1e-12)
    del rng


def test_a_later_estimate_replaces_an_earlier_one_and_held_priors_enter():
    stages = {
        'one': {'created': '1', 'updated': ['l', 'd'],
                'covariance': covariance_record(['l', 'd'], np.diag([1e-8, 4e-8]))},
        'two': {'created': '2', 'updated': ['d'],
                'covariance': covariance_record(
                    ['d'], [[1e-10]], ['l', 'physical.g1_axes_angle'], [[0.5, 2.0]],
                    priors={'physical.g1_axes_angle': 1e-3})},
        'three': {'created': '3', 'updated': ['l']},  # no covariance: noted
    }
    pc = parameter_covariance(_calibration(stages))
    assert pc.names == ['l', 'physical.g1_axes_angle', 'd']
    assert pc.stage_of['physical.g1_axes_angle'] == 'two (held)'
    var_d = 1e-10 + 0.25 * 1e-8 + 4.0 * 1e-6
    assert math.isclose(pc.matrix[2, 2], var_d, rel_tol=1e-12)
    assert math.isclose(pc.matrix[2, 0], 0.5 * 1e-8, rel_tol=1e-12)
    assert any('three' in note for note in pc.notes)


@pytest.mark.parametrize('kwargs, what', [
    (dict(names=['l'], matrix=[[float('nan')]]), 'finite'),
    (dict(names=['l', 'd'], matrix=[[1.0, 0.5], [0.0, 1.0]]), 'symmetric'),
    (dict(names=['l', 'd'], matrix=[[1.0]]), '2 x 2'),
    (dict(names=['l'], matrix=[[-1.0]]), 'diagonal'),
    (dict(names=['l bad'], matrix=[[1.0]]), 'parameter name'),
    (dict(names=['l'], matrix=[[1.0]], inputs=['d'], sensitivity=[[1.0, 2.0]]), 'sensitivity'),
    (dict(names=['l'], matrix=[[1.0]], inputs=['l'], sensitivity=[[1.0]]), 'own input'),
    (dict(names=['l'], matrix=[[1.0]], inputs=['d'], sensitivity=[[1.0]],
          priors={'fx': 1.0}), 'priors'),
])
def test_bad_covariance_records_are_refused(kwargs, what):
    with pytest.raises(ValueError, match=what):
        covariance_record(**kwargs)


def test_a_malformed_stored_covariance_names_its_stage():
    stages = {'dynamic_camera': {'created': '1', 'covariance': {'names': ['l'],
                                                                'matrix': 'oops'}}}
    with pytest.raises(ValueError, match='stages.dynamic_camera.covariance'):
        parameter_covariance(_calibration(stages))


def test_named_parameters_read_and_move():
    m = nominal_example_rig()
    assert parameter_value(m, 'intrinsics.cx') == m.intrinsics.cx
    assert parameter_value(m, 'laser_plane_v0[3]') == pytest.approx(m.laser_plane_v0[3])
    moved = with_parameters(m, {'intrinsics.dist[1]': 0.5, 'g1_pan.poly[1]': 1e-6})
    assert moved.intrinsics.dist[1] == m.intrinsics.dist[1] + 0.5
    assert moved.g1_pan.poly[1] == 1e-6
    for bad in ('intrinsics.nope', 'intrinsics', 'laser_plane_v0[7]', 'l[0]', '3x'):
        with pytest.raises(ValueError):
            with_parameters(m, {bad: 1.0})


def test_the_intrinsics_warp_keeps_the_pixels_of_points_near_the_axis():
    before = CameraIntrinsics(7800.0, 7800.0, 360.0, 270.0, (0, 0, 0, 0, 0), 720, 540)
    after = dataclasses.replace(before, fx=7806.0, fy=7805.0, cx=362.5, cy=268.0)
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-0.02, 0.02, 50), rng.uniform(-0.015, 0.015, 50),
                         rng.uniform(0.6, 0.7, 50)])
    W = intrinsics_warp(before, after)
    q = p @ W[:3, :3].T + W[:3, 3]
    moved = np.abs(project_points(after, q) - project_points(before, p)).max()
    unwarped = np.abs(project_points(after, p) - project_points(before, p)).max()
    assert moved < 0.02 * unwarped, (moved, unwarped)
    # and the depth moves with the focal length (a board of known size seen by PnP)
    assert np.median(q[:, 2] / p[:, 2]) == pytest.approx(1 + 5.5 / 7800.0, rel=1e-5)


def test_rigid_motions_are_removed_and_shape_changes_kept():
    rng = np.random.default_rng(1)
    p = rng.normal(0, 0.1, (40, 3)) + [0, 0, 0.65]
    w, t = np.array([1e-3, -2e-3, 5e-4]), np.array([1e-4, 0, -3e-4])
    rigid = np.cross(w, p) + t
    scale = 1e-3 * p                               # a change of scale is a change of shape
    J = np.stack([rigid, scale], axis=2)
    out = _without_rigid_motion(J, p)
    assert np.abs(out[:, :, 0]).max() < 1e-12
    assert np.linalg.norm(out[:, :, 1]) > 0.5 * np.linalg.norm(scale - scale.mean(axis=0))


def _grid_points(model, n=3, span=6.0, depth=0.65):
    uv, fi, volts = [], [], []
    for ut in np.linspace(-span, span, n):
        for up in np.linspace(-span, span, n):
            s = stripe_samples(model, float(up), float(ut), depth)
            assert s is not None
            uv.append(s[0])
            fi.append(np.full(len(s[0]), len(volts)))
            volts.append([up, ut, 0.0, s[2]])
    return np.concatenate(uv), np.concatenate(fi), np.array(volts)


def test_the_predicted_map_matches_the_scatter_of_drawn_calibrations():
    model = nominal_example_rig()
    names = ['l', 'd', 'g1_pan.theta0', 'intrinsics.fx', 'intrinsics.cx',
             'laser_plane_v0[0]', 'laser_plane_v0[3]', 'laser_axis_point[2]']
    sd = np.array([2e-4, 1e-4, 2e-4, 2.0, 3.0, 5e-5, 4e-5, 1e-4])
    rng = np.random.default_rng(7)
    L = rng.normal(size=(len(names), len(names))) * 0.3 + np.eye(len(names))
    corr = L @ L.T
    corr /= np.sqrt(np.outer(np.diag(corr), np.diag(corr)))
    C = corr * np.outer(sd, sd)
    pc = ParameterCovariance(names, C, {n: 'stage' for n in names})
    umap = point_uncertainty_map(model, pc, depth=0.65, span=6.0, n=3)
    assert umap.points > 50 and np.isfinite(umap.sigma_m).all()
    # Monte Carlo: the same pixels triangulated with parameters drawn from C
    uv, fi, volts = _grid_points(model)
    p0 = triangulate_batch(model, uv, fi, volts).p_v0
    draws = rng.multivariate_normal(np.zeros(len(names)), C, size=300)
    err = []
    for x in draws:
        p = triangulate_batch(with_parameters(model, dict(zip(names, x, strict=True))), uv, fi,
                              volts).p_v0
        d = (p - p0)[:, :, None]
        err.append(_without_rigid_motion(d, p0)[:, :, 0])
    mc = math.sqrt(np.mean(np.sum(np.array(err) ** 2, axis=2)))
    assert umap.rms_m == pytest.approx(mc, rel=0.12), (umap.rms_m, mc)
    # four times the variance: twice the predicted error
    twice = point_uncertainty_map(model, dataclasses.replace(pc, matrix=4 * C), depth=0.65,
                                  span=6.0, n=3)
    assert twice.rms_m == pytest.approx(2 * umap.rms_m, rel=1e-3)
    shares = np.nansum([v for v in umap.by_stage.values()], axis=0)
    np.testing.assert_allclose(shares, 1.0, atol=1e-9)


def test_the_frame_noise_in_the_map_matches_the_scatter_of_scattered_frames():
    """Galvos that scatter from frame to frame (each view at its own voltages, off by the
    noise): the map's frame part against the same pixels triangulated at drawn voltages, and
    the noise read back from the stages' records."""
    from reconstructor.calibration_file import Calibration
    from reconstructor.uncertainty import frame_noise

    model = nominal_example_rig()
    pc = ParameterCovariance(['l'], np.array([[1e-8]]), {'l': 'stage'})
    noise = {'u1_pan': 2.3e-4, 'u1_tilt': 1.5e-4, 'u2_tilt': 3.0e-4}
    umap = point_uncertainty_map(model, pc, depth=0.65, span=6.0, n=3, frame_noise_v=noise)
    quiet = point_uncertainty_map(model, pc, depth=0.65, span=6.0, n=3)
    assert quiet.frame_rms_m == 0.0 and umap.rms_m == pytest.approx(quiet.rms_m)
    assert umap.total_rms_m == pytest.approx(math.hypot(umap.rms_m, umap.frame_rms_m))
    uv, fi, volts = _grid_points(model)
    p0 = triangulate_batch(model, uv, fi, volts).p_v0
    rng = np.random.default_rng(11)
    sd = np.array([noise['u1_pan'], noise['u1_tilt'], 0.0, noise['u2_tilt']])
    sq = []
    for _ in range(400):
        moved = volts + rng.normal(size=volts.shape) * sd  # every view its own draw
        sq.append(np.sum((triangulate_batch(model, uv, fi, moved).p_v0 - p0) ** 2, axis=1))
    per_view = [math.sqrt(np.mean(np.array(sq)[:, fi == k])) for k in range(len(volts))]
    mc = math.sqrt(np.mean(np.square(per_view)))
    assert umap.frame_rms_m == pytest.approx(mc, rel=0.1), (umap.frame_rms_m, mc)
    assert 1e-6 < umap.frame_rms_m < 1e-3
    with pytest.raises(ValueError, match='frame_noise_v'):
        point_uncertainty_map(model, pc, n=3, frame_noise_v={'u2_pan': 1e-4})
    cal = Calibration(model=model, stages={
        'dynamic_camera': {'residuals': {'frame_noise_u1_pan_V': 2.3e-4,
                                         'frame_noise_u1_tilt_V': float('nan')}},
        'laser_axis': {'residuals': {'frame_noise_u2_tilt_V': 3.0e-4}}})
    assert frame_noise(cal) == {'u1_pan': 2.3e-4, 'u2_tilt': 3.0e-4}  # NaN: not measured


def test_map_arguments_are_checked():
    model = nominal_example_rig()
    pc = ParameterCovariance(['l'], np.array([[1e-8]]), {'l': 's'})
    for kw in (dict(depth=-1.0), dict(depth=float('nan')), dict(span=30.0), dict(n=0),
               dict(n=1000)):
        with pytest.raises(ValueError):
            point_uncertainty_map(model, pc, **kw)


def test_one_calibrations_error_scatters_about_the_prediction_by_its_modes():
    from scipy.stats import norm

    from reconstructor.uncertainty import error_modes, prediction_check

    # one mode: the RMS error is |z| times the prediction
    A = np.diag([1.0, 0.0, 0.0])
    modes, p = error_modes(A, np.diag([4e-8, 1e-8, 1e-8]))
    assert modes == pytest.approx(1.0)
    assert p == pytest.approx(2 * (norm.cdf(2) - norm.cdf(0.5)), abs=0.01)
    # many equal modes: the error is close to its prediction every time
    modes, p = error_modes(np.eye(40), np.eye(40) * 1e-8)
    assert modes == pytest.approx(40.0) and p > 0.999
    # correlated parameters whose errors cancel in A: one mode left
    C = np.array([[1.0, 0.999], [0.999, 1.0]]) * 1e-8
    modes, _ = error_modes(np.eye(2), C)
    assert 1.0 <= modes < 1.01
    assert all(np.isnan(error_modes(np.zeros((2, 2)), C)))  # no error at all: no figure

    check = prediction_check([1.0, 1.0, 1.0, 3.0], [1.0, 0.4, 2.0, 1.0], [0.6, 0.6, 0.6, 0.6])
    assert check['within'] == 2
    assert check['within_expected'] == pytest.approx(2.4)
    assert check['within_expected_sd'] == pytest.approx(np.sqrt(4 * 0.24))
    assert check['pooled_ratio'] == pytest.approx(np.sqrt(3.0 / 1.54))


def test_the_prediction_summary_checks_the_point_error_and_the_calibrations_part():
    from reconstructor.uncertainty import prediction_summary

    rows = [{'predicted_uncertainty_mm': 0.08, 'measured_shape_error_mm': 0.06,
             'uncertainty_within_2x_probability': 0.99,
             'predicted_calibration_uncertainty_mm': 0.05, 'measured_systematic_error_mm': 0.02,
             'uncertainty_calibration_within_2x_probability': 0.9},
            {'predicted_uncertainty_mm': 0.08, 'measured_shape_error_mm': 0.08,
             'uncertainty_within_2x_probability': 0.99,
             'predicted_calibration_uncertainty_mm': 0.05, 'measured_systematic_error_mm': 0.05,
             'uncertainty_calibration_within_2x_probability': 0.9},
            {'predicted_uncertainty_mm': float('nan'), 'measured_shape_error_mm': 0.08}]
    got, lines = prediction_summary(rows)
    assert got['measured'] == 2 and got['within_2x'] == 2
    assert got['within_2x_expected'] == pytest.approx(1.98)
    pooled = math.sqrt(0.08 ** 2 / ((0.06 ** 2 + 0.08 ** 2) / 2))
    assert got['pooled_ratio'] == pytest.approx(pooled)
    assert got['calibration_measured'] == 2 and got['calibration_within_2x'] == 1  # 2.5x off
    assert got['calibration_ratio_max'] == pytest.approx(2.5)
    assert len(lines) == 2 and "calibration's part" in lines[1]
