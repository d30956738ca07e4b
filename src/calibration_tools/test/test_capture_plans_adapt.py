"""Capture plans that adapt to the rig: steps out of reach are replaced or dropped and
reported, every stage gets a plan at the ends of the working-distance range, and drawn
rigs of the family calibrate end to end with reduced quick plans."""

import dataclasses

import numpy as np
import pytest
import yaml

from calibration_tools import capture_plans as cp
from calibration_tools import registry, stage_runner
from calibration_tools.stages import STAGES, apply_result
from galvoscan.simulated_rig import execute_in_process, nominal_calibration
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig import RIG_DIR, rig_from_dict
from galvoscan_sim.rig_family import draw_rig, reset_for_distance, working_distance
from reconstructor.model import MirrorParams, PhysicalGeometry, laser_plane_v0

NOMINAL = nominal_calibration('reference')


def _weak_g1(model, gain):
    """The model with both G1 gains scaled: its reach shrinks by ``gain``."""
    return cp.current_model(dataclasses.replace(
        model, g1_pan=MirrorParams(model.g1_pan.theta0, model.g1_pan.k * gain),
        g1_tilt=MirrorParams(model.g1_tilt.theta0, model.g1_tilt.k * gain)))


def test_a_board_out_of_reach_is_replaced_and_reported_instead_of_failing():
    model = _weak_g1(NOMINAL.model, 0.6)
    # The old fixed rows (+-4 V) need G1 near the end of its range under this model.
    from reconstructor.planning import aim_g1

    t = cp.choose_targets(model)
    worst = 0.0
    for u in (-4.0, 4.0):
        pi = laser_plane_v0(model, u)
        p = np.array([0.0, -(pi[2] * t.depth + pi[3]) / pi[1], t.depth])
        g1 = aim_g1(model, p, max_abs_u=cp.MAX_ABS_VOLTAGE)
        worst = max(worst, np.inf if not np.all(np.isfinite(g1)) else np.abs(g1).max())
    assert worst > 0.85 * cp.MAX_ABS_VOLTAGE
    plan = cp.laser_axis_steps(model, quick=False)
    assert any('narrowed' in line for line in plan.report)
    rows = {round(u, 2) for u in cp._boards(plan).values()}
    assert len(rows) >= 5 and max(abs(u) for u in rows) < 4.0
    # the physical model's rows: searched within reach, beyond +-4 V where reachable
    phys = dataclasses.replace(model, physical=PhysicalGeometry())
    plan = cp.laser_axis_steps(phys, quick=False)
    assert any('G2 rows over' in line for line in plan.report)
    rows = {round(u, 2) for u in cp._boards(plan).values()}
    assert len(rows) >= 5 and all(cp._axis_reach(phys, t, u) for u in rows)
    nominal = dataclasses.replace(NOMINAL.model, physical=PhysicalGeometry())
    full = {round(u, 2) for u in cp._boards(cp.laser_axis_steps(nominal, False)).values()}
    assert min(full) < -4.0 and len(full) >= 7
    for s in plan:
        assert np.abs(s.voltages[:, :2]).max() <= cp.MAX_ABS_VOLTAGE

    # One board of a row planned far outside G1 reach: the row is placed without it (or
    # with a replacement), and the report says which board and why.
    report = []
    steps = cp.laser_row_steps(NOMINAL.model, [0.0], boards=((-0.5833, 0), (40.0, 1)),
                               report=report)
    assert len(yaml.safe_load(steps[0].scene_yaml)['objects']) == 1
    assert len(report) == 1 and 'board 1' in report[0] and 'reach' in report[0]

    # A circle-board placement whose large circles are out of reach moves in.
    weak = _weak_g1(NOMINAL.model, 0.3)
    dyn = cp.dynamic_camera_steps(weak, [5] * 5)
    assert any('moved in' in line for line in dyn.report) or len(dyn) < 5
    poses = cp.circle_board_poses(weak)
    for s in dyn:
        obj = yaml.safe_load(s.scene_yaml)['objects'][0]
        np.testing.assert_allclose(obj['pose']['translation'], poses[s.pose_index][:3, 3],
                                   atol=1e-9)


def test_circle_board_side_placements_stay_in_reach_wherever_a_person_puts_them():
    """A narrow head (a drawn rig's +-12.5 deg GVS011-class head, 10 mm-pitch board) reaches
    only the inner part of a side placement: the plan moves it in until its large circles
    stay within G1 reach anywhere in the region asked for, so that the scanner accepts
    every placement a person makes there; the reference rig keeps its full offsets."""
    from calibration_tools import operator_flow as of
    from galvoscan.operator import Person, draw_placement

    rig = draw_rig(4)
    assert 10.0 * rig['g1']['pan']['gain'] < np.radians(13.0)  # +-12.5 deg at 10 V
    model = cp.current_model(nominal_calibration(rig))
    plan = cp.dynamic_camera_steps(model, [5] * 5)
    assert len(plan) == 5 and any('moved in' in line for line in plan.report)
    rng, person = np.random.default_rng(0), Person(mistake_rate=0.0)
    for p in of.placements('dynamic_camera', plan):
        assert cp._anchors_wherever_placed(model, p.target, p.V0_T_target) >= 2
        instr = of.instruction_fields(p, 'place', '')
        refused = [of.check_pose(model, p, draw_placement(instr, rng, person).T,
                                 plan.targets) for _ in range(12)]
        assert refused == [None] * 12, (p.index, refused)
    full = cp.dynamic_camera_steps(NOMINAL.model, [5] * 5)
    assert not full.report
    scale = cp.choose_targets(NOMINAL.model).depth / cp.WORKING_DISTANCE
    for s in full:
        off = np.array(cp.CIRCLE_BOARD_OFFSETS[s.pose_index]) * scale
        got = yaml.safe_load(s.scene_yaml)['objects'][0]['pose']['translation']
        np.testing.assert_allclose(got[:2], off, atol=1e-9)


def test_a_stage_fails_only_when_the_rest_cannot_constrain_it_and_says_what():
    with pytest.raises(cp.PlanError, match=r'intrinsics: .*fx, fy, cx, cy.*3 checkerboard'):
        cp.intrinsics_steps(NOMINAL.model, 3)


def test_targets_come_from_the_kit_and_suit_the_view():
    ref = cp.choose_targets(NOMINAL.model)
    # the reference rig keeps the kit it was built around
    assert ref.checkerboard == cp.INTRINSICS_BOARD and ref.laser_board == cp.LASER_BOARD
    assert ref.circle_board == cp.CIRCLE_BOARD and ref.sphere_radius == cp.SPHERE_RADIUS
    for seed in (1, 3, 7):
        cal = nominal_calibration(draw_rig(seed))
        t = cp.choose_targets(cal.model)
        assert t.checkerboard.square in cp.CHECKERBOARD_SQUARES
        assert t.laser_board.pitch in cp.CIRCLE_GRID_PITCHES
        assert t.circle_board.pitch in cp.CIRCLE_BOARD_PITCHES
        assert t.sphere_radius in cp.SPHERE_RADII
        assert 12 * t.checkerboard.square <= t.view[0]
        assert min(t.view) / t.circle_board.pitch >= cp.CIRCLE_BOARD_PITCHES_PER_VIEW
        # the solver gets what the plan placed
        opts = registry.stage_options('laser_plane', cal)
        assert opts['board'] == t.laser_board
        # margins scale with the working depth, as the boards and their stripes do
        k = t.depth / cp.WORKING_DISTANCE
        assert opts['edge_margin'] == pytest.approx(cp.LASER_EDGE_MARGIN * k)
        assert opts['min_spread'] == pytest.approx(cp.LASER_MIN_SPREAD * k)
        assert registry.stage_options('joint_correction', cal)['sphere_radius'] == \
            t.sphere_radius


@pytest.mark.parametrize('layout', [(7, 5), (11, 8), (5, 3)])
def test_the_laser_plane_crosses_a_grid_between_its_circle_rows(layout):
    # A board centred on the plane with an odd number of rows put the stripe along the
    # middle row's circle edges (13 and 17 usable points on a drawn rig at 100 mm).
    from scipy.spatial.transform import Rotation

    model = NOMINAL.model
    t = cp.choose_targets(model)
    pitch = t.laser_board.pitch
    board = dataclasses.replace(t.laser_board, cols=layout[0], rows=layout[1])
    t = dataclasses.replace(t, laser_board=board)
    rows = (-2.0, 0.0, 2.0)
    steps = cp.laser_row_steps(model, rows, targets=t)
    objects = yaml.safe_load(steps[0].scene_yaml)['objects']
    assert len(objects) == len(rows) * len(cp.LASER_ROW)
    centres = (np.arange(layout[1]) - 0.5 * (layout[1] - 1)) * pitch
    for k, obj in enumerate(objects):
        pi = laser_plane_v0(model, rows[k // len(cp.LASER_ROW)])
        c = np.array(obj['pose']['translation'])
        R = Rotation.from_rotvec(obj['pose']['rotation_vector']).as_matrix()
        # where the plane crosses the board's y axis, in board coordinates
        y = -(pi[:3] @ c + pi[3]) / (pi[:3] @ R[:, 1])
        assert np.min(np.abs(centres - y)) == pytest.approx(0.5 * pitch, abs=1e-3 * pitch)
        assert abs(y) <= 0.5 * pitch + 1e-9


@pytest.mark.parametrize('distance', [0.1, 1.0])
def test_the_reference_rig_re_set_for_the_ends_of_the_range_gets_every_stages_plan(distance):
    # The paper's Fig. 13 range: 100 mm (a ~16 x 12 mm view) and 1000 mm (~105 x 79 mm).
    data = reset_for_distance(read_yaml_file(RIG_DIR / 'reference.yaml'), distance)
    cal = nominal_calibration(data)
    t = cp.choose_targets(cal.model)
    # the crossing is at the rig's working distance (stand-off from the G1 exit mirror)
    assert t.depth - float(cal.model.l + cal.model.d) == pytest.approx(distance, abs=0.01)
    # the kit items suit the view: the whole target inside it, a grid OpenCV can find
    assert 12 * t.checkerboard.square <= t.view[0] and 9 * t.checkerboard.square <= t.view[1]
    grid = t.laser_board
    assert (grid.cols, grid.rows) in cp.CIRCLE_GRID_LAYOUTS and min(grid.cols, grid.rows) >= 3
    assert (grid.cols + 1) * grid.pitch <= t.view[0]
    assert 2 * t.sphere_radius <= cp.SPHERE_FILL * t.view[0]
    for quick in (True, False):
        for stage in STAGES:
            plan = registry.plan(stage, cal, quick=quick)
            assert cp.total_frames(plan) > 0, (distance, quick, stage)
            for s in plan:
                assert np.abs(s.voltages[:, :2]).max() <= cp.MAX_ABS_VOLTAGE
    # a full plan keeps more of the stage than a quick one
    assert len(cp._boards(registry.plan('laser_axis', cal))) > \
        len(cp._boards(registry.plan('laser_axis', cal, quick=True)))


#: Drawn rigs at a short, a mid and a long working distance.
FAMILY_SEEDS = (7, 0, 8)


def _reduced(stage, steps):
    """A quick plan thinned for a fast test: every other checkerboard view (4, all around)
    and the circle board's first 12 views (its 3 large-circle anchors first)."""
    if stage == 'intrinsics' and len(steps) >= 8:
        return steps[::2]
    if stage == 'dynamic_camera':
        return [dataclasses.replace(s, voltages=s.voltages[:12]) for s in steps[:1]]
    return steps


def test_drawn_rigs_at_short_mid_and_long_distances_calibrate_with_reduced_plans():
    distances = []
    empty = load_scene_text('format_version: 1\nname: empty\nobjects:\n  - type: plane\n'
                            '    name: floor\n    pose: {translation: [0.0, 0.0, 5.0]}\n'
                            '    albedo: 0.1\n')
    for seed in FAMILY_SEEDS:
        data = draw_rig(seed)
        distances.append(working_distance(data))
        sim = Simulator(rig_from_dict(data, f'drawn rig {seed}'), empty, seed=seed)
        cal = nominal_calibration(data)
        for stage in STAGES:
            steps = _reduced(stage, registry.plan(stage, cal, quick=True))
            views, _ = execute_in_process(sim, steps)
            result = stage_runner.compute(stage, views, cal)
            flat = stage_runner.flatten(result.updates)
            # a stage estimates model parameters, or (joint correction) its table
            assert flat or set(result.extra) - {'coverage'}, (seed, stage)
            assert all(np.isfinite(v) for v in flat.values()), (seed, stage)
            assert all(np.isfinite(v) for v in result.residuals.values()), (seed, stage)
            cov = result.extra['coverage']
            assert cov['used'] > 0 and cov['views'] == len(views)
            cal = apply_result(cal, result)
    assert min(distances) < 0.3 and max(distances) > 0.8
