"""Laser rotation axis and G2 angle per volt on the simulated ideal rig, judged by the
simulator's true axis."""

import math

import numpy as np
import pytest

from calibration_tools.board_layout import CircleGrid
from calibration_tools.laser_axis import run_laser_axis
from calibration_tools.stages import apply_result
from galvoscan.simulated_rig import board_poses_on_laser
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file as cf
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel

BOARD = CircleGrid(cols=11, rows=8, pitch=0.0045, diameter=0.0025)
# The laser swept over +-4 V (+-16 deg of laser plane); at every 1 V a board at two near and
# two far depths, each lit at U2 +- 0.05 V: 18 planes, each from 4 board poses.
CENTRES = [-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0]
DEPTHS = [0.59, 0.6, 0.7, 0.71]
OFFSETS = (-0.05, 0.05)


def operator_model(truth):
    """Intrinsics and dynamic camera from Calibration I; laser values off by what a design
    drawing leaves (they only place the boards where the stripe should fall)."""
    return RigModel(
        intrinsics=CameraIntrinsics(truth.fx, truth.fy, truth.cx, truth.cy,
                                    tuple(truth.distortion), 720, 540),
        g1_pan=MirrorParams(truth.theta0_pan, truth.k_pan),
        g1_tilt=MirrorParams(truth.theta0_tilt, truth.k_tilt),
        l=truth.l, d=truth.d,
        laser_plane_v0=truth.pi0 + [0.0, 0.002, -0.002, 0.0005],
        laser_axis_dir=truth.n + [0.0, 0.002, -0.001],
        laser_axis_point=truth.P + [0.002, -0.002, 0.002],
        g2_tilt=MirrorParams(math.pi / 4, truth.k2 * 0.998),
    )


@pytest.fixture(scope='module')
def ideal():
    rig = load_rig('ideal')
    truth = rig.true_model_parameters()
    model = operator_model(truth)
    sim = Simulator(rig, load_scene('checkerboard'), seed=0)
    views, _ = board_poses_on_laser(sim, model, CENTRES, DEPTHS, BOARD, offsets=OFFSETS,
                                    seed=0)
    return truth, model, views


def _distance_to_line(q, p, n):
    w = q - p
    return float(np.linalg.norm(w - (w @ n) * n))


def test_laser_axis_meets_the_ideal_rig_acceptance(ideal):
    truth, model, views = ideal
    cal = cf.Calibration(model=model)
    res = run_laser_axis(views, cal, board=BOARD)
    n = np.array(res.updates['laser_axis_dir'])
    P = np.array(res.updates['laser_axis_point'])
    k = res.updates['g2_tilt']['k']
    # The sign of n follows the operator's nominal axis, and k's sign follows n.
    assert n @ truth.n > 0 and k > 0
    dir_err = math.degrees(math.atan2(np.linalg.norm(np.cross(n, truth.n)), n @ truth.n))
    dist = _distance_to_line(truth.P, P, n)
    along = max(_distance_to_line(truth.P + s * truth.n, P, n)
                for s in np.linspace(-0.55, 0.55, 23))
    print(f'\nlaser axis (ideal rig, {res.residuals["planes_used"]:.0f} planes): direction '
          f'error {dir_err:.5f} deg, distance {dist * 1e3:.4f} mm at P '
          f'({along * 1e3:.4f} mm max over +-550 mm), k error {(k / truth.k2 - 1):+.2e}')
    assert dir_err < 0.01
    assert dist < 5e-5
    assert abs(k / truth.k2 - 1) < 1e-3
    assert res.updates['g2_tilt']['poly'] == []
    assert res.residuals['planes_used'] == 2 * len(CENTRES)
    assert res.residuals['axis_angle_max_rad'] < math.radians(0.01)
    assert res.residuals['axis_distance_max_m'] < 5e-5
    new = apply_result(cal, res)
    assert new.model.g2_tilt.k == k and new.model.g2_tilt.theta0 == model.g2_tilt.theta0
    np.testing.assert_allclose(new.model.laser_axis_point, P)
    np.testing.assert_allclose(new.model.laser_plane_v0, model.laser_plane_v0)


def test_one_pose_per_voltage_gives_no_plane(ideal):
    truth, model, views = ideal
    # Only the near boards of the first centre: every voltage has a single pose.
    first = [v for v in views if v.pose_index == 0]
    with pytest.raises(ValueError, match='usable laser plane.*1 board pose'):
        run_laser_axis(first, cf.Calibration(model=model), board=BOARD)


def test_the_axis_covariance_is_joint_across_direction_point_and_response(ideal):
    # Direction, point and G2's response come from the same planes: the stage's covariance
    # record carries their correlations (each plane's own covariance carried through the
    # fit), not three independent blocks. On the reference rig, 8 seeds: the block-wise
    # covariance predicted 3.3x the point error the seeds' own scatter of the parameters
    # gives; with the correlations, 0.95x.
    truth, model, views = ideal
    res = run_laser_axis(views, cf.Calibration(model=model), board=BOARD)
    rec = res.covariance
    names = rec['names']
    C = np.array(rec['matrix'])
    sd = np.sqrt(np.diag(C))
    corr = C / np.outer(np.where(sd > 0, sd, 1.0), np.where(sd > 0, sd, 1.0))
    block = [n.split('[')[0].rsplit('.', 1)[0] for n in names]
    across = np.array([[a != b for b in block] for a in block])
    print('\nlargest correlation across blocks:', np.abs(corr[across]).max())
    assert np.abs(corr[across]).max() > 0.3
    # Its sigmas are the fit's residual-based standard errors (which see every error the
    # planes show, the model's lack of fit too); the planes give the correlations.
    se = res.standard_errors
    for key in ('laser_axis_dir', 'laser_axis_point'):
        for j, s in enumerate(se[key]):
            assert sd[names.index(f'{key}[{j}]')] == pytest.approx(s, rel=1e-9, abs=1e-15)
    assert sd[names.index('g2_tilt.k')] == pytest.approx(se['g2_tilt']['k'], rel=1e-9)
    assert res.residuals['axis_lack_of_fit'] > 0
