"""Stripe centres scored against the physical simulator's ground truth (galvoscan_sim).

The simulator ray-traces the laser sheet onto the scene and reports, per image column, the
exact sub-pixel projection of the sheet's centre plane on the surface (``truth.stripe``).
The ideal rig has no speckle and no imperfections; the reference rig has shot and read
noise, per-pixel laser speckle (contrast 0.5 before a blur, ~0.2 after), lens distortion.
"""

import numpy as np
import pytest

from stripe_extractor.extractor import ExtractorConfig, extract, warm_up

sim_rig = pytest.importorskip('galvoscan_sim.rig')
sim_scene = pytest.importorskip('galvoscan_sim.scene')
sim_simulator = pytest.importorskip('galvoscan_sim.simulator')


@pytest.fixture(scope='module', autouse=True)
def _compiled():
    warm_up()


def _truth_errors(res, stripe):
    """v - v_true(u): truth interpolated linearly between the two columns around each u,
    on the branch nearest to v; centres without truth on both sides are left out."""
    errs = []
    for u, v in zip(res.u.astype(float), res.v.astype(float), strict=True):
        c0 = int(np.floor(u))
        vals = []
        for c in (c0, c0 + 1):
            tv = stripe.v[stripe.column == c]
            if tv.size == 0:
                break
            vals.append(tv[np.argmin(np.abs(tv - v))])
        if len(vals) == 2 and abs(vals[1] - vals[0]) < 2.0:
            errs.append(v - (vals[0] + (u - c0) * (vals[1] - vals[0])))
    return np.asarray(errs)


def _run(rig, scene, voltages, method='steger'):
    sim = sim_simulator.Simulator(sim_rig.load_rig(rig), sim_scene.load_scene(scene), seed=3)
    frame = sim.render(np.asarray(voltages, float))
    stripe = frame.truth.stripe
    assert len(stripe) > 300
    res = extract(frame.image, ExtractorConfig(method=method, line_width_px=4.7,
                                               min_strength=15.0))
    err = _truth_errors(res, stripe)
    truth_cols = np.unique(stripe.column)
    coverage = np.isin(truth_cols, np.rint(res.u).astype(int)).mean()
    assert err.size >= 0.95 * truth_cols.size
    return float(np.sqrt(np.mean(err**2))), float(coverage)


@pytest.mark.parametrize('scene', ['plane', 'stair_block'])
@pytest.mark.parametrize('voltages', [(0.0, 0.0, 0.0, 0.0), (0.5, -0.3, 0.0, 0.05)])
def test_ideal_rig_meets_the_accuracy_target(scene, voltages):
    rms, coverage = _run('ideal', scene, voltages)
    assert coverage >= 0.995
    assert rms <= 0.02


def test_reference_rig_speckle_limited_and_better_than_cog():
    rms_s, cov_s = _run('reference', 'plane', (0.0, 0.0, 0.0, 0.0))
    rms_c, cov_c = _run('reference', 'plane', (0.0, 0.0, 0.0, 0.0), 'center_of_gravity')
    assert cov_s >= 0.99 and cov_c >= 0.99
    assert rms_s <= 0.25
    assert rms_s < rms_c
