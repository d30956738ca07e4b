"""The whole calibration chain in-process on the reference rig with the quick plans
(``galvoscan calibrate all --sim --quick``), judged by the simulator's physics.

On a rig with imperfections no single model parameter is "true" (the simulator's
model-equivalent l, d and fx are its design values, i.e. exactly the nominal ones), so the
chain is judged by what the parameters do: where the model triangulates the true stripe
pixels of a wall scanned over +-8 V of G1, where it puts points seen through the dynamic
camera, and the lens distortion it found.
"""

import math

import numpy as np
import pytest

from calibration_tools.stages import STAGES
from galvoscan import offline, sim_scores
from galvoscan.simulated_rig import NOMINAL_NOTE, nominal_calibration, nominal_rig, truth_model
from galvoscan_sim import load_rig
from reconstructor import calibration_file


@pytest.fixture(scope='module')
def chain(tmp_path_factory):
    path = tmp_path_factory.mktemp('chain') / 'calibration.yaml'
    rc = offline.main(['all', '--sim', '--quick', '--rig', 'reference', '--calibration',
                       str(path)])
    return rc, path, load_rig('reference')


def test_every_stage_runs_in_order_from_the_design_values(chain):
    rc, path, _ = chain
    assert rc == 0
    cal = calibration_file.load(path)
    assert cal.source == 'calibrated'
    assert list(cal.stages) == ['nominal', *STAGES]
    assert cal.stages['nominal']['note'] == NOMINAL_NOTE
    for stage in STAGES:
        meta = cal.stages[stage]
        assert meta['samples_used'] > 0, stage
        assert len(meta['bags']) == 1 and len(meta['bags'][0]['sha256']) == 64
    # the default chain fits the physical model: the joint correction is measured (its
    # residuals below) and deliberately not installed
    assert cal.model.kind == 'physical'
    assert cal.joint_correction is None and cal.model.correction is None
    assert 'not installed' in cal.stages['joint_correction']['not_installed']
    r = cal.stages['joint_correction']['residuals']
    assert r['error2_rms_m'] < r['error1_rms_m']


def test_calibrated_model_beats_the_design_values(chain):
    _, path, rig = chain
    cal = calibration_file.load(path)
    nominal = nominal_calibration('reference').model
    got, before = cal.model, nominal
    rec, rec0 = (sim_scores.reconstruction_errors(m, rig) for m in (got, before))
    print(f'\nquick chain, wall scanned over +-8 V: RMS error {rec0["absolute_rms_m"] * 1e3:.3f} '
          f'-> {rec["absolute_rms_m"] * 1e3:.3f} mm, shape {rec0["aligned_rms_m"] * 1e3:.3f} -> '
          f'{rec["aligned_rms_m"] * 1e3:.3f} mm')
    assert rec['points'] > 10000
    assert rec['absolute_rms_m'] < 0.5 * rec0['absolute_rms_m']
    assert rec['aligned_rms_m'] < 0.3 * rec0['aligned_rms_m']
    # Dynamic camera (l, d, gains): points seen at 650 mm over the paper's 36 G1 positions.
    assert sim_scores.pointing_error_m(got, rig) < sim_scores.pointing_error_m(before, rig)
    # Lens: the design has no distortion; the rig's k1 = -0.6 is found.
    true = rig.camera
    assert before.intrinsics.dist[0] == 0.0
    assert -0.9 < got.intrinsics.dist[0] < -0.3
    # The design's fx, l and d are the rig's model-equivalent values: calibration keeps
    # them close (Zhang's method at a 5 deg field of view is good to ~0.1 % in fx).
    assert abs(got.intrinsics.fx / true.fx - 1) < 3e-3
    assert abs(got.l - rig.l) < 2e-3 and abs(got.d - rig.d) < 2e-3
    # The laser sweep: every plane over +-4 V is within 2 mm of the true one.
    assert sim_scores.laser_sweep_error_m(got, rig) < 2e-3


def test_nominal_is_the_design_without_imperfections(tmp_path):
    ideal, ref = load_rig('ideal'), load_rig('reference')
    nominal = nominal_calibration('reference')
    # The ideal rig is the reference rig's design with every imperfection zero.
    want = truth_model(ideal).to_dict()
    got = nominal.model.to_dict()
    for key in ('l', 'd', 'g1_pan', 'g1_tilt', 'g2_tilt', 'intrinsics'):
        assert got[key] == want[key], key
    np.testing.assert_allclose(got['laser_plane_v0'], want['laser_plane_v0'], atol=1e-12)
    np.testing.assert_allclose(got['laser_axis_dir'], want['laser_axis_dir'], atol=1e-12)
    np.testing.assert_allclose(got['laser_axis_point'], want['laser_axis_point'], atol=1e-12)
    # ... and not the reference rig's physics.
    true = truth_model(ref)
    assert true.intrinsics.dist[0] == -0.6 and got['intrinsics']['dist'] == [0.0] * 5
    assert abs(true.g1_pan.theta0 - math.pi / 4) > 1e-4 and got['g1_pan']['theta0'] == \
        math.pi / 4
    # Every way of naming the rig gives the same; the file round-trips.
    from galvoscan_sim.rig import RIG_DIR

    for name in (RIG_DIR / 'reference.yaml', ref):
        assert nominal_calibration(name).model.to_dict() == got
    assert nominal_rig(ref).geometric_imperfection is False
    calibration_file.save(nominal, tmp_path / 'nominal.yaml')
    again = calibration_file.load(tmp_path / 'nominal.yaml')
    assert again.source == 'calibrated' and again.stages['nominal']['note'] == NOMINAL_NOTE
    for bad in ('no_such_rig', 3.0):
        with pytest.raises(ValueError):
            nominal_calibration(bad)
