"""Where the laser sits is read from the rig, never assumed: the stair block's step crosses
the stripe with its riser lit and seen on every side, and a part's nominal shape gives the
extractor's prior along a stripe of either direction."""

from functools import cache

import numpy as np
import pytest

from galvoscan import eval_scenes
from galvoscan.simulated_rig import nominal_rig, truth_model
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.rig_family import draw_rig, working_point
from reconstructor.planning import aim_camera, aim_laser, expected_rows, stripe_layout

SIDES = ('below', 'above', 'left', 'right')


@cache
def _design(side):
    """Family rig 3 at 450 mm with the laser on ``side``, its imperfections removed (the
    design values are then its exact model): (rig, model)."""
    rig = nominal_rig(draw_rig(3, 0.45, build={'sensor': 'IMX287', 'bit_depth': 8,
                                               'laser': side}))
    return rig, truth_model(rig)


def _frame(sim, model, aim_W):
    """The true stripe of the frame centred on ``aim_W`` with the sheet through it."""
    aim = (sim.V0_T_W @ np.append(aim_W, 1.0))[:3]
    u1 = aim_camera(model, aim)
    volts = np.array([*u1, 0.0, aim_laser(model, *u1, distance=float(np.linalg.norm(aim)))])
    rig = sim.rig
    geo = sim.geometry(rig.mirror_angles(rig.applied_voltages(rig.dac.quantize(volts[None])[0])))
    return volts, sim.stripe_truth(geo)


def _stair_profile(side, layout):
    """Points of the true stripe through the riser's middle on Plane-1, the riser and
    Plane-2 of the stair block at the working point, placed for ``layout``."""
    rig, model = _design(side)
    text, info = eval_scenes.stair(working_point(rig), layout=layout)
    sim = Simulator(rig, load_scene_text(text, 'stair'), seed=0)
    _, truth = _frame(sim, model, info['aim_W'])
    p = (np.linalg.inv(info['W_T_O']) @ np.column_stack(
        [truth.points_W, np.ones(len(truth))]).T).T[:, :3]
    sz, step = info['size'][2], info['step_height']
    plane1 = np.sum((p[:, 0] < -3e-3) & (np.abs(p[:, 2] + sz) < 1e-4))
    riser = np.sum((np.abs(p[:, 0]) < 1e-4) & (p[:, 2] < -sz - 2e-3)
                   & (p[:, 2] > -sz - step + 2e-3))
    plane2 = np.sum((p[:, 0] > 3e-3) & (np.abs(p[:, 2] + sz + step) < 1e-4))
    return int(plane1), int(riser), int(plane2)


@pytest.mark.parametrize('side', SIDES)
def test_the_stair_block_turns_its_step_across_the_stripe_of_any_side(side):
    rig, model = _design(side)
    layout = stripe_layout(model)
    assert layout.orientation == rig.stripe_layout().orientation
    assert layout.side == rig.stripe_layout().side
    plane1, riser, plane2 = _stair_profile(side, layout)
    assert plane1 >= 40 and plane2 >= 40, (plane1, riser, plane2)
    assert riser >= 10, (plane1, riser, plane2)  # lit by the laser and seen by the camera


def test_a_stair_set_up_for_a_laser_below_misses_the_riser_of_a_laser_beside():
    """The check above can fail: a laser beside with the block of a laser below."""
    plane1, riser, plane2 = _stair_profile('left', None)
    assert riser == 0 or min(plane1, plane2) == 0


@pytest.mark.parametrize('side', ('below', 'left'))
def test_the_expected_stripe_follows_the_stripe_direction(side):
    """A tilted plate's nominal face gives the true stripe per column (per row for a laser
    beside the camera) to a small fraction of a pixel."""
    rig, model = _design(side)
    layout = stripe_layout(model)
    centre = np.asarray(working_point(rig), dtype=np.float64)
    text = ('format_version: 1\nname: plate\nobjects:\n  - type: flat_plate\n    name: plate\n'
            f'    pose: {{translation: [{centre[0]:.9g}, {centre[1]:.9g}, {centre[2]:.9g}], '
            'rotation_vector: [0.2, -0.3, 0.1]}\n    size: [0.3, 0.3]\n    thickness: 0.01\n'
            '    albedo: 0.5\n')
    sim = Simulator(rig, load_scene_text(text, 'plate'), seed=0)
    W_T_O = sim.scene.objects[0].W_T_O
    V0_T_O = sim.V0_T_W @ W_T_O
    face = (V0_T_O[:3, 3], V0_T_O[:3, 0], V0_T_O[:3, 1], (0.15, 0.15))
    volts, truth = _frame(sim, model, centre)
    expected = expected_rows(model, [face], volts)
    size = (rig.camera.width, rig.camera.height)[layout.along]
    assert expected.shape == (size,)
    across = (truth.u, truth.v)[layout.image_axis]
    assert len(truth) > 0.5 * size
    assert np.all(np.isfinite(expected[truth.column]))
    assert np.max(np.abs(expected[truth.column] - across)) < 0.05


@pytest.mark.parametrize('side', ('left', 'above'))
def test_the_v_groove_turns_its_axis_across_the_stripe(side):
    """The stripe climbs both faces of the groove: its points reach far from the bottom."""
    rig, model = _design(side)
    reach = {}
    for name, layout in (('turned', stripe_layout(model)), ('unturned', None)):
        text, info = eval_scenes.v_groove(working_point(rig), material=None, layout=layout)
        sim = Simulator(rig, load_scene_text(text, 'groove'), seed=0)
        _, truth = _frame(sim, model, info['axis_W'])
        reach[name] = []
        for f, (n, _) in zip(('left_face', 'right_face'), info['faces'], strict=True):
            p = truth.points_W[truth.object_index == sim.scene.object_index(f)]
            # distance from the bottom line, towards the scanner along the face
            reach[name].append(float(np.max(-(p - info['axis_W']) @ np.cross(
                n, np.cross([0.0, 0.0, 1.0], n)), initial=0.0)) * 1e3)
    assert min(reach['turned']) >= 10.0, reach  # [mm] up each 40 mm face
    if side == 'left':  # a groove set up for a laser below: the stripe along its bottom
        assert max(reach['unturned']) < 2.0, reach
