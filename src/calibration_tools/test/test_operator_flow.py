"""The scanner finds targets an operator placed imprecisely (in process, on the simulator).

Each target is placed in the simulator where a person might put it, never where the plan
asked; the search (:func:`calibration_tools.operator_flow.search`) sees it only through
laser-off frames the simulator renders at the G1 voltages it asks for.
"""

import math

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration_tools import capture_plans as cp
from calibration_tools import operator_flow as of
from calibration_tools import stage_runner
from calibration_tools.registry import plan
from calibration_tools.stages import CaptureStep
from galvoscan.operator import scene_text
from galvoscan.simulated_rig import execute_in_process, nominal_calibration, truth_model
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene_text
from galvoscan_sim.simulator import Simulator
from reconstructor.planning import aim_g1


@pytest.fixture(scope='module')
def bench():
    rig = load_rig('reference')
    cal = nominal_calibration('reference')
    model = cp.current_model(cal)
    sim = Simulator(rig, load_scene_text(scene_text('sphere', {'radius': 0.01}, np.eye(4)),
                                         'start'), seed=5)
    return rig, cal, model, cp.choose_targets(model), sim


def _place(sim, p, T):
    """Put the placement's target at ``T`` (V0 is the scene frame here)."""
    spec = yaml.safe_load(of.instruction_fields(p, 'place', '')['target_spec'])
    sim.set_scene(load_scene_text(scene_text(p.kind, spec, T), 'operator'))


def _looker(sim):
    def look(volts):
        return execute_in_process(sim, [CaptureStep(0, None, volts, False)])[0]
    return look


def _off(p, offset, tilt):
    """The placement asked for, moved by ``offset`` [m] and turned ``tilt`` rad about x."""
    T = p.V0_T_target.copy()
    T[:3, :3] = Rotation.from_rotvec([tilt, 0.0, 0.0]).as_matrix() @ T[:3, :3]
    T[:3, 3] += offset
    return T


def test_boards_80_mm_off_and_10_deg_wrong_still_calibrate(bench):
    """Every intrinsics board 80 mm from where it was asked and turned 10 deg: the search
    finds each one, measures its pose from its own corners, the views are aimed at it, and
    the intrinsics computed from them are the rig's."""
    rig, cal, model, targets, sim = bench
    places = of.placements('intrinsics', plan('intrinsics', cal, quick=True))[:5]
    views = []
    for k, p in enumerate(places):
        a = 2 * math.pi * k / len(places)
        T = _off(p, [0.08 * math.cos(a), 0.08 * math.sin(a), 0.0], math.radians(10.0))
        _place(sim, p, T)
        loc, move = of.search(model, p, targets, _looker(sim))
        assert move is None, move.words
        # the pose is the board's own, to a fraction of a millimetre
        assert np.linalg.norm(loc.V0_T_target[:3, 3] - T[:3, 3]) < 2e-3
        views += execute_in_process(sim, of.views_for(model, p, loc.V0_T_target, targets))[0]
    result = stage_runner.compute('intrinsics', views, cal)
    assert result.samples_used == len(places)
    true = truth_model(rig).intrinsics
    assert abs(result.updates['intrinsics']['fx'] - true.fx) / true.fx < 2e-3


def test_circle_grid_off_the_laser_line_is_told_which_way(bench):
    """A laser board found 30 mm below the laser line is told to move up (-y)."""
    _, cal, model, targets, sim = bench
    p = of.placements('laser_plane', plan('laser_plane', cal, quick=True))[1]
    T = _off(p, [0.02, 0.03, 0.0], 0.0)
    _place(sim, p, T)
    loc, move = of.search(model, p, targets, _looker(sim))
    assert loc is not None and move is not None and move.reason == 'off_laser_line'
    assert move.move[1] < -0.02 and 'up (-y)' in move.words


def test_a_laser_axis_board_in_from_its_rows_end_is_told_to_move_out(bench):
    """The laser axis asks for boards at the two ends of each row along the stripe: one
    found 45 mm in from its end (towards the row's middle) is told to move out by as much,
    along the line; one 45 mm beyond its end, or between the ends, is taken as it is."""
    _, cal, model, targets, sim = bench
    places = of.placements('laser_axis', plan('laser_axis', cal))
    ends = [p for p in places if p.row_end is not None]
    between = [p for p in places if p.row_end is None]
    assert ends and between
    p = ends[0]
    _, inward, slack = p.row_end
    assert abs(np.linalg.norm(inward) - 1.0) < 1e-9 and abs(inward[0]) > 0.9  # along x
    assert 0.02 < slack < 0.045
    for shift, told in ((0.045, True), (-0.045, False)):
        _place(sim, p, _off(p, shift * inward, 0.0))
        loc, move = of.search(model, p, targets, _looker(sim))
        assert loc is not None
        if told:
            assert move is not None and move.reason == 'off_row_end', move
            assert move.move @ inward == pytest.approx(-0.045, abs=3e-3)
            assert abs(move.move[1]) < 3e-3 and 'mm in from the end' in move.words
        else:
            assert move is None, move.words
    q = between[0]
    _place(sim, q, _off(q, [0.045, 0.0, 0.0], 0.0))
    loc, move = of.search(model, q, targets, _looker(sim))
    assert loc is not None and move is None, move.words


def test_target_out_of_reach_gets_the_direction_to_move_it(bench):
    """A board put beyond G1's reach (its edge still seen from the outermost views) is
    reported out of reach, with the way back: towards -x."""
    _, cal, model, targets, sim = bench
    p = of.placements('intrinsics', plan('intrinsics', cal, quick=True))[0]
    depth = float(p.centre[2])
    xs = np.linspace(0.0, 1.2, 241)
    u = aim_g1(model, np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, depth)]),
               max_abs_u=20.0)
    edge = xs[np.argmax(np.abs(u[:, 0]) > of.MAX_ABS_VOLTAGE)]  # last reachable x
    asked = _off(p, [edge - 0.05 - p.centre[0], -p.centre[1], 0.0], 0.0)
    p.V0_T_target = asked  # the instruction asked for a board near the edge of reach
    _place(sim, p, _off(p, [0.05, 0.0, 0.0], 0.0))  # it was put 50 mm beyond
    loc, move = of.search(model, p, targets, _looker(sim))
    assert move is not None and move.reason == 'out_of_reach', move
    assert move.move[0] < -0.02 and 'left (-x)' in move.words


def test_motion_gate_catches_a_moved_board_and_passes_a_still_one(bench):
    _, cal, model, targets, sim = bench
    p = of.placements('laser_plane', plan('laser_plane', cal, quick=True))[0]
    T = _off(p, [-0.03, 0.004, 0.01], 0.05)
    _place(sim, p, T)
    seen = []

    def look(volts):
        got = _looker(sim)(volts)
        seen.extend(got)
        return got
    loc, move = of.search(model, p, targets, look)
    assert move is None, move.words
    # the features come with the stamp of the image they were detected in (the progress
    # topic's view_stamp), the view at the gate's voltages
    src = [v for v in seen if v.stamp == loc.stamp
           and np.allclose(v.voltages[:2], loc.check_voltages[:2])]
    assert len(src) == 1
    assert of.feature_shift_px(loc.features, of.features(p, src[0].image)) < 1e-9
    check = of.check_step(p, loc.check_voltages)
    still = execute_in_process(sim, [check])[0][0]
    assert of.feature_shift_px(loc.features, of.features(p, still.image)) < of.MOVED_PX
    _place(sim, p, _off(p, [-0.03 + 0.001, 0.004, 0.01], 0.05))  # nudged by 1 mm
    moved = execute_in_process(sim, [check])[0][0]
    assert of.feature_shift_px(loc.features, of.features(p, moved.image)) > 5 * of.MOVED_PX


def test_view_gates_reject_motion_blur_and_reprojection_outliers(bench):
    """A still view passes both gates; the same view with the board moving 0.5 mm during
    the exposure (the frames of the motion averaged: what the sensor integrates) is
    rejected as motion blur; a pattern whose corners do not fit one flat board (six moved
    by 5 px) is a reprojection outlier."""
    _, cal, model, targets, sim = bench
    p = of.placements('intrinsics', plan('intrinsics', cal, quick=True))[1]
    T = p.V0_T_target.copy()
    _place(sim, p, T)
    step = of.views_for(model, p, T, targets)[0]
    off = CaptureStep(0, None, step.voltages[:1], False)
    still = execute_in_process(sim, [off])[0][0].image
    pts, why, rms = of.gate_view(model, p, still,
                                 of.edge_spread_px(still, of.features(p, still)))
    assert why == '' and pts is not None and rms < 0.3
    frames = []
    for dx in np.linspace(-0.00025, 0.00025, 9):
        _place(sim, p, _off(p, [dx, 0.0, 0.0], 0.0))
        frames.append(execute_in_process(sim, [off])[0][0].image.astype(np.float64))
    blurred = np.mean(frames, axis=0).round().astype(still.dtype)
    spread = of.edge_spread_px(still, pts)
    _, why, _ = of.gate_view(model, p, blurred, spread)
    assert why == 'motion_blur', (of.edge_spread_px(blurred, pts), spread)
    bad = pts.copy()
    bad[[0, 7, 20, 40, 60, 80]] += 5.0
    assert of.reprojection_rms_px(model, p, pts) < 0.3
    assert of.reprojection_rms_px(model, p, bad) > of.REPROJECTION_MAX_PX


def test_the_circle_boards_views_are_not_judged_by_edge_blur(bench):
    """The large circle board's raster views see parts of it at other depths than its
    check view (focus spreads their edges): its views are kept on their circles, whatever
    the check view's edge spread."""
    _, cal, model, targets, sim = bench
    p = of.placements('dynamic_camera', plan('dynamic_camera', cal, quick=True))[0]
    _place(sim, p, p.V0_T_target)
    step = of.views_for(model, p, p.V0_T_target, targets)[0]
    views = execute_in_process(sim, [CaptureStep(0, None, step.voltages[:6], False)])[0]
    seen = [v for v in views if of.features(p, v.image) is not None]
    assert seen
    pts, why, _ = of.gate_view(model, p, seen[0].image, 1e-3)
    assert why == '' and pts is not None and len(pts) >= 4
    assert 'circle_board' not in of.BLUR_GATED


def test_a_circle_board_reaching_past_g1s_range_is_found_and_taken(bench):
    """The large circle board with its centre beyond G1's reach but two large circles in
    it (where its plan puts it on a rig of short reach) is searched on its part nearer the
    axis, found, and its views are planned."""
    from calibration_tools.dynamic_camera import anchor_voltages

    _, cal, model, targets, sim = bench
    p = of.placements('dynamic_camera', plan('dynamic_camera', cal, quick=True))[0]
    T = p.V0_T_target.copy()
    for x in np.arange(0.3, 0.9, 0.01):  # the first x whose centre is out of reach
        T[0, 3] = x
        if np.abs(aim_g1(model, T[:3, 3], max_abs_u=20.0)).max() > of.MAX_ABS_VOLTAGE:
            break
    assert len(anchor_voltages(model, p.target, T, max_abs_u=of.MAX_ABS_VOLTAGE)) >= 2
    p.V0_T_target = T
    _place(sim, p, T)
    loc, move = of.search(model, p, targets, _looker(sim))
    assert move is None, move.words
    assert np.linalg.norm(loc.V0_T_target[:3, 3] - T[:3, 3]) < 5e-3
    assert len(of.views_for(model, p, loc.V0_T_target, targets)[0].voltages) >= 3


def test_placements_of_the_plans_and_their_instructions(bench):
    """Every stage's plan becomes placements whose instructions name a kit target, a region
    around the plan's pose and a tilt; the laser stages' boards go on the laser line."""
    _, cal, model, _, _ = bench
    for stage, kind, n in (('intrinsics', 'checkerboard', 8),
                           ('dynamic_camera', 'circle_board', 1),
                           ('laser_plane', 'circle_grid', 4),
                           ('laser_axis', 'circle_grid', 6),
                           ('joint_correction', 'sphere', 1)):
        steps = plan(stage, cal, quick=True)
        places = of.placements(stage, steps)
        assert [p.kind for p in places] == [kind] * n
        assert sum(len(v) for p in places for v, _, _ in p.views) == cp.total_frames(steps)
        for p in places:
            f = of.instruction_fields(p, 'place', of.describe(p))
            assert of.target_from_spec(f['target'], yaml.safe_load(f['target_spec'])) \
                is not None
            assert np.allclose(f['centre'], p.V0_T_target[:3, 3])
            assert f['on_laser_line'] == (stage != 'intrinsics' and
                                          stage != 'dynamic_camera')
            assert 0.0 <= f['tilt'] < math.pi / 2 and f['tilt_tolerance'] > 0


def test_malformed_instruction_targets_are_refused():
    with pytest.raises(ValueError, match='unknown target'):
        of.target_from_spec('teapot', {})
    with pytest.raises(ValueError, match='missing'):
        of.target_from_spec('checkerboard', {'cols': 11})


def test_sphere_the_laser_line_misses_is_told_to_move_along_the_sheet(bench):
    """The joint correction's sphere put 10 mm too near: the lit frame shows the line off
    its middle, and the instruction moves it away (+z); where asked, it passes."""
    _, cal, model, targets, sim = bench
    p = of.placements('joint_correction', plan('joint_correction', cal, quick=True))[0]

    def look_lit(volts):
        return execute_in_process(sim, [CaptureStep(0, None, volts, True)])[0]

    _place(sim, p, p.V0_T_target)
    loc, move = of.search(model, p, targets, _looker(sim), None, look_lit)
    assert move is None and np.linalg.norm(loc.V0_T_target[:2, 3] - p.centre[:2]) < 2e-3
    _place(sim, p, _off(p, [0.0, 0.0, -0.01], 0.0))
    loc, move = of.search(model, p, targets, _looker(sim), None, look_lit)
    assert move is not None and move.reason == 'off_laser_line', move
    assert move.move[2] > 0.004 and 'away (+z)' in move.words


def test_beside_the_camera_the_laser_line_is_crossed_along_x():
    """A rig with the laser beside the camera (the stripe along the image columns): the
    instructions' tight tolerance is across the line, along V0's x, and a laser board
    found 15 mm to the right of the line is told to move left (-x)."""
    from galvoscan_sim.rig import rig_from_dict
    from galvoscan_sim.rig_family import draw_rig
    from reconstructor.planning import stripe_layout

    data = draw_rig(3, 0.45, build={'sensor': 'IMX287', 'bit_depth': 8, 'laser': 'left'})
    cal = nominal_calibration(data)
    model = cp.current_model(cal)
    assert stripe_layout(model).across == 0
    sim = Simulator(rig_from_dict(data, 'beside'), load_scene_text(
        scene_text('sphere', {'radius': 0.01}, np.eye(4)), 'start'), seed=5)
    places = of.placements('laser_plane', plan('laser_plane', cal, quick=True), across=0)
    assert all(p.extents()[0] < p.extents()[1] for p in places)
    p = places[1]
    T = _off(p, [0.015, 0.005, 0.0], 0.0)
    _place(sim, p, T)
    loc, move = of.search(model, p, cp.choose_targets(model), _looker(sim))
    assert loc is not None and move is not None and move.reason == 'off_laser_line'
    assert move.move[0] < -0.01 and move.move[1] == 0.0 and 'left (-x)' in move.words


@pytest.mark.parametrize('offset', [(0.10, -0.09), (-0.16, 0.12), (0.0, 0.0), (0.05, 0.03)])
def test_a_circle_board_placed_past_half_a_sub_pattern_is_pinned_by_its_edges(bench, offset):
    """The large circles fix the circle board's labels only modulo the sub-pattern (140 mm
    on this rig): a board put 100-200 mm from where asked reads whole sub-patterns off until
    its edges are probed; then its pose is its own and its planned views all land on it. One
    put where asked, or within half a sub-pattern, is left where it was read."""
    _, cal, model, targets, sim = bench
    p = of.placements('dynamic_camera', plan('dynamic_camera', cal, quick=True))[0]
    T = _off(p, [offset[0], offset[1], 0.0], math.radians(5.0 if any(offset) else 0.0))
    _place(sim, p, T)
    loc, move = of.search(model, p, targets, _looker(sim))
    assert move is None, move.words
    assert np.linalg.norm(loc.V0_T_target[:3, 3] - T[:3, 3]) < 5e-3, loc.note
    far = max(abs(o) for o in offset) > 0.5 * p.target.sub_pattern * p.target.pitch
    assert ('moved' in loc.note) == far, loc.note
    assert 'not seen' not in loc.note, loc.note
    steps = of.views_for(model, p, loc.V0_T_target, targets)
    views = execute_in_process(sim, steps)[0]
    from calibration_tools.circle_board import detect_circles
    from calibration_tools.small_board import as_uint8_image

    seen = [len(detect_circles(as_uint8_image(np.asarray(v.image)), dark_circles=True)) >= 3
            for v in views]  # an anchor view: its large circle and two more
    assert all(seen), f'{seen.count(False)} of {len(seen)} views miss the board'
