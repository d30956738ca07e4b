"""Laser plane at U2 = 0 on the simulated ideal rig, judged by the simulator's true plane."""

import dataclasses
import math

import numpy as np
import pytest

from calibration_tools.board_layout import CircleGrid
from calibration_tools.laser_plane import run_laser_plane
from calibration_tools.stages import CaptureView, apply_result
from galvoscan.simulated_rig import board_poses_on_laser
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file as cf
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel

BOARD = CircleGrid(cols=11, rows=8, pitch=0.0045, diameter=0.0025)
# 16 board poses: 8 near, 8 far, the laser crossing each board's centre; G1 follows them.
DEPTHS = [0.585 + 0.0025 * i for i in range(8)] + [0.6975 + 0.0025 * i for i in range(8)]


def operator_model(truth, seed=0):
    """What the operator has before this stage: intrinsics and dynamic camera from
    Calibration I (here the simulator's values) and only rough laser values."""
    rng = np.random.default_rng(seed)
    return RigModel(
        intrinsics=CameraIntrinsics(truth.fx, truth.fy, truth.cx, truth.cy,
                                    tuple(truth.distortion), 720, 540),
        g1_pan=MirrorParams(truth.theta0_pan, truth.k_pan),
        g1_tilt=MirrorParams(truth.theta0_tilt, truth.k_tilt),
        l=truth.l, d=truth.d,
        laser_plane_v0=truth.pi0 + np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.002)],
        laser_axis_dir=truth.n + rng.normal(0, 0.01, 3),
        laser_axis_point=truth.P + rng.normal(0, 0.01, 3),
        g2_tilt=MirrorParams(math.pi / 4, truth.k2 * 1.01),
    )


@pytest.fixture(scope='module')
def ideal():
    rig = load_rig('ideal')
    truth = rig.true_model_parameters()
    model = operator_model(truth)
    sim = Simulator(rig, load_scene('checkerboard'), seed=0)
    views, _ = board_poses_on_laser(sim, model, [0.0], DEPTHS, BOARD, seed=0)
    return truth, model, views


def test_laser_plane_meets_the_ideal_rig_acceptance(ideal):
    truth, model, views = ideal
    cal = cf.Calibration(model=model)
    res = run_laser_plane(views, cal, board=BOARD)
    plane = np.array(res.updates['laser_plane_v0'])
    true = truth.pi0 if truth.pi0[:3] @ plane[:3] > 0 else -truth.pi0
    normal_err = math.degrees(math.atan2(np.linalg.norm(np.cross(plane[:3], true[:3])),
                                         plane[:3] @ true[:3]))
    work = np.array([0.0, 0.0, 0.65])  # the working point on the V0 optical axis
    print(f'\nlaser plane (ideal rig, {len(DEPTHS)} poses): normal error {normal_err:.5f} deg, '
          f'offset error {(plane[3] - true[3]) * 1e3:+.5f} mm, at 650 mm '
          f'{(plane[:3] @ work + plane[3]) * 1e3:+.5f} mm, fit RMS '
          f'{res.residuals["plane_rms_m"] * 1e6:.2f} um')
    assert normal_err < 0.005
    assert abs(plane[3] - true[3]) < 1e-5
    assert abs(plane[:3] @ work + plane[3]) < 1e-5
    assert res.samples_used == len(DEPTHS) and not res.rejected
    assert 0 < res.residuals['plane_rms_m'] < 1e-5
    assert res.residuals['pnp_rms_px_max'] < 0.05
    # The stage result merges into the calibration: only the laser plane changes.
    new = apply_result(cal, res)
    np.testing.assert_allclose(new.model.laser_plane_v0, plane / np.linalg.norm(plane[:3]))
    before, after = model.to_dict(), new.model.to_dict()
    before.pop('laser_plane_v0')
    after.pop('laser_plane_v0')
    assert before == after
    assert new.stages['laser_plane']['updated'] == ['laser_plane_v0']


def test_bad_views_are_rejected_with_reasons(ideal):
    truth, model, views = ideal
    blank = np.zeros_like(views[0].image)
    extra = [
        # A laser-on frame at another G2 voltage does not belong to this stage.
        dataclasses.replace(views[1], voltages=views[1].voltages + [0, 0, 0, 0.5]),
        # A pose whose board frames show no board.
        CaptureView(blank, views[0].voltages, False, 99),
        CaptureView(blank, views[0].voltages, True, 99),
    ]
    res = run_laser_plane(views[:8] + extra, cf.Calibration(model=model), board=BOARD)
    text = '\n'.join(res.rejected)
    assert 'U2_tilt = 0.5000 V, not 0 V' in text
    assert 'pose 99' in text and 'board not found' in text
    assert res.samples_used == 4 and res.samples_rejected == 2
    # One board pose gives a line, not a plane.
    with pytest.raises(ValueError, match='at least 2 needed'):
        run_laser_plane(views[:2], cf.Calibration(model=model), board=BOARD)
    with pytest.raises(ValueError, match=r'views\[0\] must be a CaptureView'):
        run_laser_plane([views[0].image], cf.Calibration(model=model), board=BOARD)
    with pytest.raises(ValueError, match='board must be'):
        run_laser_plane(views, cf.Calibration(model=model), board='circles')
