"""Capture plans: made from the operator's model only, within the galvos' range, and run
in-process exactly as the driver's sim backend runs them."""

import dataclasses
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration_tools import capture_plans as cp
from calibration_tools.capture_plans import CaptureStep, total_frames
from calibration_tools.registry import plan
from calibration_tools.stages import STAGES
from galvo_driver.sim_backend import SimBackend
from galvoscan.simulated_rig import execute_in_process, nominal_calibration
from galvoscan_sim import Simulator, load_rig, load_scene
from reconstructor.calibration_file import Calibration
from reconstructor.model import (
    MirrorParams,
    PhysicalGeometry,
    laser_plane_v0,
    predict_pixels,
    project_points,
)

NOMINAL = nominal_calibration('reference')


def _objects(step):
    return yaml.safe_load(step.scene_yaml)['objects']


def _pose(obj):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(obj['pose'].get('rotation_vector', [0, 0, 0])).as_matrix()
    T[:3, 3] = obj['pose']['translation']
    return T


def _perturbed(model, dl=0.0, gain=1.0, dtheta=0.0, tilt_plane=0.0):
    R = Rotation.from_rotvec([tilt_plane, 0.0, 0.0]).as_matrix()
    pl = np.asarray(model.laser_plane_v0)
    return dataclasses.replace(
        model, l=model.l + dl,
        g1_pan=MirrorParams(model.g1_pan.theta0 + dtheta, model.g1_pan.k * gain),
        g1_tilt=MirrorParams(model.g1_tilt.theta0, model.g1_tilt.k / gain),
        laser_plane_v0=np.append(R @ pl[:3], pl[3]))


@pytest.fixture(scope='module')
def plans():
    return {(s, q): plan(s, NOMINAL, quick=q) for s in STAGES for q in (False, True)}


def test_every_plan_is_well_formed(plans):
    for (stage, _), steps in plans.items():
        assert steps and all(isinstance(s, CaptureStep) for s in steps), stage
        assert steps[0].scene_yaml is not None, stage  # a plan starts by placing its target
        for s in steps:
            assert s.voltages.ndim == 2 and s.voltages.shape[1] == 4
            assert np.abs(s.voltages).max() <= cp.MAX_ABS_VOLTAGE
            assert s.note
        if stage != 'joint_correction':  # the board views of a scene come before its lit ones
            for a, b in zip(steps, steps[1:], strict=False):
                if b.laser_on:
                    assert b.scene_yaml is None and not a.laser_on
                    assert b.pose_index == a.pose_index
        else:
            assert all(s.laser_on for s in steps)
        assert total_frames(plans[(stage, True)]) < total_frames(plans[(stage, False)])
    # What the CI end-to-end run renders (~50 ms a board frame, ~5 ms a stripe frame).
    quick = [s for (_, q), steps in plans.items() if q for s in steps]
    off = sum(s.frames for s in quick if not s.laser_on)
    on = sum(s.frames for s in quick if s.laser_on)
    assert off * 0.05 + on * 0.005 < 5.0 and len(quick) <= 20


def test_intrinsics_views_are_at_u1_zero_and_fit_the_image(plans):
    intr = NOMINAL.model.intrinsics
    for s in plans[('intrinsics', False)]:
        assert np.all(s.voltages == 0.0) and not s.laser_on and s.frames == 1
        (obj,) = _objects(s)
        T = _pose(obj)
        half = np.array(obj['size'][:2]) / 2 - obj['square_size']  # the pattern's corners
        corners = np.array([[x, y, 0.0] for x in (-half[0], half[0]) for y in (-half[1],
                                                                              half[1])])
        uv = project_points(intr, corners @ T[:3, :3].T + T[:3, 3])
        assert np.all((uv > 0) & (uv < [intr.width, intr.height]))
        tilt = np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec()[:2])
        assert 0.5 < tilt < 0.7


def test_dynamic_camera_views_are_aimed_at_the_placed_board_with_the_model(plans):
    m = NOMINAL.model
    B = cp.CIRCLE_BOARD
    big = np.flatnonzero(B.is_large(np.arange(B.n_circles)))
    steps = plans[('dynamic_camera', False)]
    assert [s.pose_index for s in steps] == list(range(5))
    for s in steps:
        T = cp.circle_board_pose(s.pose_index, m)
        np.testing.assert_allclose(_pose(_objects(s)[0]), T, atol=1e-9)
        pts = B.points(big) @ T[:3, :3].T + T[:3, 3]
        # The first views are centred on large circles (identification anchors).
        for u in s.voltages[:2]:
            uv, _ = predict_pixels(m, pts, u[0], u[1])
            d = np.linalg.norm(uv - [m.intrinsics.cx, m.intrinsics.cy], axis=1)
            assert np.nanmin(d) < 0.5
        # Every view looks at the board: the ray through the image centre hits it.
        for u in s.voltages:
            from reconstructor.model import v0_T_v

            V = v0_T_v(m, u[0], u[1])
            o, d = V[:3, 3], V[:3, 2]
            n = T[:3, 2]
            hit = o + d * ((T[:3, 3] - o) @ n) / (d @ n)
            local = (hit - T[:3, 3]) @ T[:3, :3]
            assert np.all(np.abs(local[:2]) < 0.35)


def _laser_checks(model, steps, expect_rows, expect_lit):
    m = dataclasses.replace(model, correction=None)
    rows, lit_volts = set(), set()
    for off, on in zip(steps[::2], steps[1::2], strict=True):
        objs = _objects(off)
        assert len(objs) == off.frames
        assert on.frames % off.frames == 0
        k = on.frames // off.frames
        for j, obj in enumerate(objs):
            p = np.asarray(obj['pose']['translation'])
            u1 = off.voltages[j, :2]
            lit = on.voltages[j * k:(j + 1) * k]
            np.testing.assert_array_equal(lit[:, :2], np.tile(u1, (k, 1)))
            u2 = float(np.mean(lit[:, 3]))
            rows.add(round(u2, 6))
            lit_volts |= {round(float(u), 6) for u in lit[:, 3]}
            # On the model's laser plane of its row, and centred in its view by the model.
            pi = laser_plane_v0(m, u2)
            assert abs(pi[:3] @ p + pi[3]) < 1e-9
            uv, _ = predict_pixels(m, p[None], u1[0], u1[1])
            np.testing.assert_allclose(uv[0], [m.intrinsics.cx, m.intrinsics.cy], atol=1e-3)
        # No two boards of a scene in one view: centres at least a view width apart.
        P = np.array([o['pose']['translation'] for o in objs])
        ang = P[:, :2] / P[:, 2:]
        dist = np.linalg.norm(ang[:, None] - ang[None], axis=2) + np.eye(len(P))
        assert dist.min() > 0.09
    assert rows == set(expect_rows) and lit_volts == set(expect_lit)


def test_laser_boards_lie_on_the_models_planes_and_are_aimed_at(plans):
    _laser_checks(NOMINAL.model, plans[('laser_plane', False)], [0.0], [0.0])
    _laser_checks(NOMINAL.model, plans[('laser_plane', True)], [0.0], [0.0])
    three = [-2.0, 0.0, 2.0]
    _laser_checks(NOMINAL.model, plans[('laser_axis', True)], three, three)
    full = [round(c + o, 6) for c in range(-4, 5) for o in cp.LASER_AXIS_LIT_OFFSETS]
    _laser_checks(NOMINAL.model, plans[('laser_axis', False)], range(-4, 5), full)
    # the physical model's full plan: rows evenly over the G2 voltages the scans need, as
    # far as boards on their planes are in G1 reach
    phys = dataclasses.replace(NOMINAL.model, physical=PhysicalGeometry())
    a, b, _ = cp._axis_rows(phys, cp.choose_targets(phys))
    rows = [round(u, 6) for u in a + b]
    assert len(rows) == cp.LASER_AXIS_ROW_COUNT and min(rows) < -4.0
    full = [round(c + o, 6) for c in rows for o in cp.LASER_AXIS_LIT_OFFSETS]
    _laser_checks(phys, cp.laser_axis_steps(phys, False), rows, full)


def test_joint_correction_positions_chain_from_the_reference_node(plans):
    steps = plans[('joint_correction', False)]
    nodes = [{tuple(np.round(v[:2] / 0.1).astype(int)) for v in s.voltages} for s in steps]
    assert (0, 0) in nodes[0]
    for i in range(1, len(nodes)):
        assert nodes[i] & set().union(*nodes[:i]), f'position {i} shares no G1 node'
    for s in steps:
        assert np.all(s.voltages[:, 3] == 0.0)  # G2 held still
        np.testing.assert_allclose(s.voltages[:, :2] / 0.1, np.round(s.voltages[:, :2] / 0.1),
                                   atol=1e-9)  # one global 0.1 V grid


def test_plans_follow_the_model_and_only_the_model():
    m = NOMINAL.model
    other = Calibration(model=_perturbed(m, dl=0.002, gain=1.01, dtheta=math.radians(0.1),
                                         tilt_plane=0.01))
    for stage in STAGES:
        a, b = plan(stage, NOMINAL, quick=True), plan(stage, NOMINAL, quick=True)
        assert [s.scene_yaml for s in a] == [s.scene_yaml for s in b]
        assert all(np.array_equal(x.voltages, y.voltages) for x, y in zip(a, b, strict=True))
        c = plan(stage, other, quick=True)
        if stage == 'intrinsics':  # U1 = 0 and the same lens: only the placement counts
            continue
        volts = any(not np.array_equal(x.voltages, y.voltages) for x, y in zip(a, c, strict=True))
        scenes = [s.scene_yaml for s in a] != [s.scene_yaml for s in c]
        # The G1 aim follows the model (the sphere's G1 grid is a fixed 0.1 V lattice, the
        # sphere itself goes where the model's laser plane is).
        assert volts if stage != 'joint_correction' else scenes, stage
    # The big board goes to the model's working depth (where its laser sheet crosses the
    # optical axis); the laser boards follow the plane.
    for cal in (NOMINAL, other):
        z = _pose(_objects(plan('dynamic_camera', cal)[0])[0])[2, 3]
        assert z == pytest.approx(cp.laser_crossing_depth(cp.current_model(cal)), abs=1e-9)
    assert plan('laser_plane', other)[0].scene_yaml != plan('laser_plane', NOMINAL)[0].scene_yaml
    with pytest.raises(ValueError, match='stage'):
        plan('focus', NOMINAL)
    with pytest.raises(ValueError, match='calibration'):
        plan('intrinsics', 'reference')


@settings(max_examples=8, deadline=None)
@given(st.floats(-0.003, 0.003), st.floats(0.98, 1.02), st.floats(-0.004, 0.004),
       st.floats(-0.02, 0.02))
def test_plans_stay_within_range_for_rough_models(dl, gain, dtheta, tilt):
    cal = Calibration(model=_perturbed(NOMINAL.model, dl, gain, dtheta, tilt))
    for stage in ('dynamic_camera', 'laser_axis', 'joint_correction'):
        for s in plan(stage, cal, quick=True):
            assert np.abs(s.voltages).max() <= cp.MAX_ABS_VOLTAGE


def test_capture_step_checks_and_truncation():
    s = CaptureStep(2, None, np.arange(12.0).reshape(3, 4) / 10, True, note='x')
    t = s.truncated(2)
    assert t.frames == 2 and s.frames == 3 and t.pose_index == 2 and t.laser_on
    np.testing.assert_array_equal(t.voltages, s.voltages[:2])
    assert CaptureStep(0, None, [0.0, 0.0, 0.0, 1.0], False).voltages.shape == (1, 4)
    for bad in (np.zeros((2, 3)), np.zeros((0, 4)), [[0, 0, 0, 11.0]], [[np.nan, 0, 0, 0]]):
        with pytest.raises(ValueError, match='voltages'):
            CaptureStep(0, None, bad, False)
    with pytest.raises(ValueError, match='pose_index'):
        CaptureStep(-1, None, np.zeros((1, 4)), False)
    with pytest.raises(ValueError, match='frame_rate'):
        CaptureStep(0, None, np.zeros((1, 4)), False, frame_rate=0.0)
    with pytest.raises(ValueError, match='n must'):
        s.truncated(0)


def test_in_process_execution_is_what_the_sim_backend_produces():
    steps = plan('laser_plane', NOMINAL, quick=True)
    rig = load_rig('reference')
    views, truths = execute_in_process(Simulator(rig, load_scene('plane'), seed=3), steps)
    backend = SimBackend(rig='reference', scene='plane', seed=3, max_frames_per_poll=100)
    backend.open()
    frames = []
    for s in steps:
        if s.scene_yaml:
            backend.set_scene(text=s.scene_yaml)
        backend.start(s.voltages, 1e4, laser_on=s.laser_on)
        while backend.running:
            frames += backend.poll()
    assert len(frames) == len(views) == total_frames(steps)
    for v, f, t in zip(views, frames, truths, strict=True):
        np.testing.assert_array_equal(v.image, f.image)
        np.testing.assert_array_equal(v.voltages, f.voltages)
        assert v.laser_on == f.laser_on and t.laser_on == f.laser_on
    # Voltages are the DAC's output and the views carry the steps' poses.
    np.testing.assert_array_equal(views[0].voltages, rig.dac.quantize(steps[0].voltages[0]))
    assert [v.pose_index for v in views] == [s.pose_index for s in steps
                                             for _ in range(s.frames)]
    assert not views[0].laser_on and views[-1].laser_on
    with pytest.raises(ValueError, match=r'steps\[0\]'):
        execute_in_process(Simulator(rig, load_scene('plane')), ['step'])


def test_the_registry_is_the_one_table_of_stages():
    """Every stage has one registry entry (plan, options, solver); unknown names are refused."""
    import ast
    from pathlib import Path

    from calibration_tools import registry, stage_runner
    from calibration_tools.stages import CELL_STAGE, HAND_EYE_STAGE, KNOWN_STAGES, STAGES

    assert tuple(registry.REGISTRY) == KNOWN_STAGES == (*STAGES, CELL_STAGE, HAND_EYE_STAGE)
    for name in ('focus', '', None, 3):
        with pytest.raises(ValueError, match='unknown'):
            registry.plan(name, None)
        with pytest.raises(ValueError, match='unknown'):
            stage_runner.compute(name, [], None)
    with pytest.raises(TypeError):
        registry.REGISTRY['intrinsics'].options['board'] = None
    # no other module of the package branches on a stage variable (`if stage == 'x'`)
    package = Path(registry.__file__).parent
    for path in package.glob('*.py'):
        if path.name == 'registry.py':
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Compare):
                continue
            sides = [node.left, *node.comparators]
            named = [ast.unparse(c) for c in sides if isinstance(c, (ast.Name, ast.Attribute))]
            names = {c.value for c in sides if isinstance(c, ast.Constant)}
            assert not (any('stage' in n for n in named) and names & set(STAGES)), \
                f'{path.name}:{node.lineno} branches on a stage name'


def test_a_stage_computed_twice_on_the_same_views_gives_the_same_result_to_the_bit():
    """OpenCV's parallel loops sum in an order that varies from run to run: without
    ``stage_runner.opencv_single_thread`` two computes of these views differed in the 14th
    digit, which the dynamic-camera fit carried to about 1 um in l. Here the intrinsics stage
    (its circle-grid calibration is OpenCV's) must repeat exactly, with OpenCV allowed
    several threads outside the stage."""
    import cv2

    from calibration_tools import stage_runner

    rig = load_rig('reference')
    cal = nominal_calibration(rig)
    views, _ = execute_in_process(Simulator(rig, load_scene('plane'), seed=5),
                                  plan('intrinsics', cal, quick=True))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(max(threads, 4))
    try:
        first, second = (stage_runner.compute('intrinsics', views, cal) for _ in range(2))
        assert cv2.getNumThreads() == max(threads, 4)  # restored after each compute
    finally:
        cv2.setNumThreads(threads)
    assert first.updates == second.updates
    assert first.residuals == second.residuals
    assert first.covariance == second.covariance
