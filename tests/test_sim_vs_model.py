"""The one meeting point of the physical simulator and the reconstruction model.

With the ideal rig (every imperfection zero) the simulator's ray-traced geometry must be
exactly what the model of docs/design.md section 2 says: the virtual camera poses and the laser
planes agree to 1e-9, and the model, fed the simulator's true parameters and its true stripe
pixels, reconstructs the simulator's true stripe points to within 1 um.
"""

import numpy as np
import pytest

from galvoscan.simulated_rig import truth_model
from galvoscan_sim import Simulator, load_rig, load_scene, patterns
from reconstructor.model import (
    laser_plane_v0,
    triangulate,
    v0_T_v,
)

RIG = load_rig('ideal')
PARAMS = RIG.true_model_parameters()
MODEL = truth_model(RIG)
# DAC-exact voltages (multiples of 20 V / 2**16), so commanded == applied
G1_VOLTS = [(0.0, 0.0), (1.25, -2.5), (-7.5, 3.75), (9.375, 9.375), (-10.0, -5.0),
            (0.3125, -0.15625)]
G2_VOLTS = [0.0, 0.625, -1.25, 4.0625, -8.75, 10.0 - 2 * RIG.dac.lsb]


def test_params_are_exact_for_the_ideal_rig():
    assert PARAMS.exact
    for u in np.array(G1_VOLTS).ravel().tolist() + G2_VOLTS:
        assert RIG.dac.quantize(u) == u


@pytest.mark.parametrize('u1', G1_VOLTS)
def test_virtual_camera_pose_equals_the_models(u1):
    th = RIG.mirror_angles(np.array([u1[0], u1[1], 0.0, 0.0]))
    sim_V0_T_V = RIG.V0_T_V(th[0], th[1])
    model_V0_T_V = v0_T_v(MODEL, u1[0], u1[1])
    assert np.max(np.abs(sim_V0_T_V - model_V0_T_V)) < 1e-9


@pytest.mark.parametrize('u2', G2_VOLTS)
def test_laser_plane_equals_the_models(u2):
    th = RIG.mirror_angles(np.array([0.0, 0.0, 0.0, u2]))
    sheet = RIG.laser_sheet_G(th[2], th[3]).transformed(np.linalg.inv(RIG.G_T_V0))
    sim_plane = sheet.plane / np.linalg.norm(sheet.plane[:3])
    model_plane = laser_plane_v0(MODEL, u2)
    model_plane = model_plane / np.linalg.norm(model_plane[:3])
    sign = np.sign(sim_plane[:3] @ model_plane[:3])
    assert np.max(np.abs(sim_plane - sign * model_plane)) < 1e-9


def test_model_reconstructs_true_stripe_points_to_1um():
    sim = Simulator(RIG, load_scene('stair_block'), seed=0)
    u2_0 = patterns.aim_laser(RIG, 0.0, 0.0, 0.66)
    frames = [
        [0.0, 0.0, 0.0, float(RIG.dac.quantize(u2_0))],
        [0.15625, -0.3125, 0.0, float(RIG.dac.quantize(u2_0 - 0.3125))],
        [-0.46875, 0.3125, 0.0, float(RIG.dac.quantize(u2_0 + 0.3125))],
    ]
    for volts in frames:
        frame = sim.render(volts)
        tr = frame.truth
        assert np.array_equal(tr.voltages_applied, tr.voltages_commanded)
        s = tr.stripe
        assert len(s) > 500
        res = triangulate(MODEL, np.stack([s.u, s.v], 1), *tr.voltages_applied[[0, 1, 3]])
        assert res.valid.all()
        err = np.linalg.norm(res.p_v0 - s.points_V0, axis=1)
        assert err.max() < 1e-6, f'max error {err.max():.3g} m at {volts}'
