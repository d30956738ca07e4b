"""Joint correction on the simulated rig: the corrected reconstruction is judged against the
simulator's true stripe points, at the calibration voltages and between them."""

import dataclasses
import math

import numpy as np
import pytest

from calibration_tools.joint_correction import run_joint_correction
from calibration_tools.stages import apply_result
from galvoscan.sim_scores import stripe_point_errors
from galvoscan.simulated_rig import sphere_g1_grid
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file as cf
from reconstructor.correction import CorrectionTable
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel

RADIUS = 0.01
PANS = np.linspace(-0.3, 0.3, 5)
TILTS = np.linspace(-0.2, 0.2, 5)


def model_from(truth, pan_gain=1.0, tilt_gain=1.0, dl=0.0):
    """A model with the simulator's values, optionally with a poor dynamic-camera calibration."""
    return RigModel(
        intrinsics=CameraIntrinsics(truth.fx, truth.fy, truth.cx, truth.cy,
                                    tuple(truth.distortion), 720, 540),
        g1_pan=MirrorParams(truth.theta0_pan, truth.k_pan * pan_gain),
        g1_tilt=MirrorParams(truth.theta0_tilt, truth.k_tilt * tilt_gain),
        l=truth.l + dl, d=truth.d, laser_plane_v0=truth.pi0, laser_axis_dir=truth.n,
        laser_axis_point=truth.P, g2_tilt=MirrorParams(math.pi / 4, truth.k2))


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope='module')
def ideal():
    rig = load_rig('ideal')
    truth = rig.true_model_parameters()
    # The dynamic camera calibrated poorly: G1 gains 3 % and 2 % off, l 1 mm off.
    model = model_from(truth, 1.03, 0.98, 0.001)
    sim = Simulator(rig, load_scene('sphere'), seed=0)
    views, truths, centre, aim = sphere_g1_grid(sim, model, 0.0, RADIUS, PANS, TILTS)
    mid_p, mid_t = (PANS[:-1] + PANS[1:]) / 2, (TILTS[:-1] + TILTS[1:]) / 2
    held, held_truths, _, _ = sphere_g1_grid(sim, model, 0.0, RADIUS, mid_p, mid_t)
    return truth, model, views, truths, held, held_truths, aim


def test_correction_brings_the_views_onto_the_truth(ideal):
    truth, model, views, truths, held, held_truths, aim = ideal
    cal = cf.Calibration(model=model)
    res = run_joint_correction(views, cal, sphere_radius=RADIUS, reference_voltages=aim)
    assert res.residuals['nodes_registered'] == len(views) - 1 and not res.rejected
    table = CorrectionTable.from_dict(res.extra['joint_correction'])
    corrected = dataclasses.replace(model, correction=table)
    before = rms(stripe_point_errors(model, views, truths))
    after = rms(stripe_point_errors(corrected, views, truths))
    h_before = rms(stripe_point_errors(model, held, held_truths))
    h_after = rms(stripe_point_errors(corrected, held, held_truths))
    r = res.residuals
    print(f'\njoint correction (ideal rig, poor dynamic camera): true RMS error '
          f'{before * 1e3:.4f} -> {after * 1e3:.4f} mm at the nodes, {h_before * 1e3:.4f} -> '
          f'{h_after * 1e3:.4f} mm between them; Error1 {r["error1_rms_m"] * 1e3:.4f}, '
          f'Error3 {r["error3_rms_m"] * 1e3:.4f}, Error2 {r["error2_rms_m"] * 1e3:.4f} mm')
    assert before > 0.2e-3 and h_before > 0.2e-3
    assert after < before / 10 and h_after < h_before / 10
    assert r['error2_rms_m'] < r['error1_rms_m'] / 5
    assert r['error3_rms_m'] >= r['error1_rms_m']
    # The table goes through the calibration file and comes back the same.
    new = apply_result(cal, res)
    assert new.joint_correction == res.extra['joint_correction']
    assert new.model.to_dict() == model.to_dict()


def test_exact_model_needs_no_correction(ideal):
    truth, _, views, truths, *_ = ideal
    exact = model_from(truth)
    res = run_joint_correction(views, cf.Calibration(model=exact), sphere_radius=RADIUS,
                               reference_voltages=views[len(views) // 2].voltages[:2])
    table = CorrectionTable.from_dict(res.extra['joint_correction'])
    pts = np.array([[x, y, 0.66] for x in (-0.02, 0.0, 0.02) for y in (-0.015, 0.0, 0.015)])
    for up in PANS:
        for ut in TILTS:
            C = table.V0c_T_V0(float(up), float(ut))
            assert np.abs(pts @ C[:3, :3].T + C[:3, 3] - pts).max() < 1e-5


def test_occluded_and_off_sphere_views_are_skipped_with_reasons(ideal, caplog):
    truth, model, *_ = ideal
    sim = Simulator(load_rig('ideal'), load_scene('sphere'), seed=1)
    # A box in front of the right half of the arc in one view; one view aimed off the sphere.
    views, truths, centre, aim = sphere_g1_grid(
        sim, model, 0.0, RADIUS, [-0.2, 0.0, 0.2, 0.9], [0.0, 0.1],
        occluder=((0.007, 0.0, -0.04), (0.012, 0.03, 0.004)), occluded_nodes=[(2, 1)])
    res = run_joint_correction(views, cf.Calibration(model=model), sphere_radius=RADIUS,
                               reference_voltages=views[2].voltages[:2])
    nodes = {(round(n['u1_pan'] - aim[0], 1), round(n['u1_tilt'] - aim[1], 1)): n
             for n in res.extra['nodes']}
    assert nodes[(0.2, 0.1)]['status'] == 'skipped'
    assert 'occluded' in nodes[(0.2, 0.1)]['reason'] or 'in front' in nodes[(0.2, 0.1)]['reason']
    for t in (0.0, 0.1):
        assert nodes[(0.9, t)]['status'] == 'skipped' and 'sphere' in nodes[(0.9, t)]['reason']
    assert res.residuals['nodes_skipped'] == 3
    table = CorrectionTable.from_dict(res.extra['joint_correction'])
    assert table.valid.sum() == 5 and not table.valid[2, 1] and not table.valid[3].any()
    for n in nodes.values():
        if n['status'] == 'skipped':
            assert n['reason'] in caplog.text


def test_physical_model_measures_the_table_but_does_not_install_it(ideal):
    """With the physical mirror model the stage still measures Error1/Error2, but keeps no
    table (and drops one a calibration had); the paper's model installs it."""
    from reconstructor.model import PhysicalGeometry

    truth, model, views, *_ = ideal
    aim = views[len(views) // 2].voltages[:2]
    physical = dataclasses.replace(model, physical=PhysicalGeometry())
    res = run_joint_correction(views, cf.Calibration(model=physical), sphere_radius=RADIUS,
                               reference_voltages=aim)
    assert 'joint_correction' not in res.extra
    assert 'not installed' in res.extra['joint_correction_not_installed']
    assert res.residuals['error2_rms_m'] < res.residuals['error1_rms_m']
    stale = run_joint_correction(views, cf.Calibration(model=model), sphere_radius=RADIUS,
                                 reference_voltages=aim).extra['joint_correction']
    new = apply_result(cf.Calibration(model=physical, joint_correction=stale), res)
    assert new.joint_correction is None and new.model.correction is None
    assert 'not installed' in new.stages['joint_correction']['not_installed']


def test_physical_model_reports_an_unmeasurable_correction_without_failing(ideal):
    """Only a table that would be installed makes the stage fail: with the physical model a
    capture where no node registers is reported, and the chain goes on."""
    from reconstructor.model import PhysicalGeometry

    truth, model, views, *_ = ideal
    few = [views[0]]  # one node: nothing to register against
    physical = dataclasses.replace(model, physical=PhysicalGeometry())
    with pytest.raises(ValueError):
        run_joint_correction(few, cf.Calibration(model=model), sphere_radius=RADIUS,
                             reference_voltages=(9.0, 9.0))
    res = run_joint_correction(few, cf.Calibration(model=physical), sphere_radius=RADIUS,
                               reference_voltages=(9.0, 9.0))
    assert 'not measured either' in res.extra['joint_correction_not_installed']
    assert res.rejected and 'joint_correction' not in res.extra
    new = apply_result(cf.Calibration(model=physical), res)
    assert new.joint_correction is None
