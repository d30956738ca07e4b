"""Stopping on standard-error targets: the prediction falls as placements are kept, the
advice is the candidate that lowers the worst sigma/target most, and the full plans meet
the targets on the reference rig."""

import math

import numpy as np
import pytest

from calibration_tools import capture_plans as cp
from calibration_tools import operator_flow as of
from calibration_tools import stopping
from calibration_tools.registry import plan
from galvoscan.simulated_rig import nominal_calibration

CAL = nominal_calibration('reference')
MODEL = cp.current_model(CAL)
TARGETS = cp.choose_targets(MODEL)


def _places(stage, quick=False):
    return of.placements(stage, plan(stage, CAL, quick=quick))


@pytest.mark.parametrize('stage', stopping.PREDICTED)
def test_targets_are_stated_and_sigma_falls_as_placements_are_kept(stage):
    places = _places(stage)
    a = stopping.assess(stage, MODEL, TARGETS, [], places, places)
    assert len(a.names) == len(a.units) == len(a.target) >= 2
    assert np.all(np.isfinite(a.target)) and np.all(a.target > 0)
    assert not a.targets_met and a.best is not None and a.advice.startswith('next: ')
    kept, worst = [], math.inf
    for p in places:
        kept.append((p, p.V0_T_target))
        # corners as the simulator's views show them (their own fits: 0.03-0.04 px)
        a = stopping.assess(stage, MODEL, TARGETS, kept, [], places, noise_px=0.04)
        if np.all(np.isfinite(a.sigma)):
            assert a.worst <= worst * (1 + 1e-9), (stage, len(kept))
            worst = a.worst
    # the whole plan at the poses asked for meets every target on the reference rig, and
    # noisier corners need more
    assert a.targets_met, (stage, a.table())
    if stage == 'intrinsics':
        assert not stopping.assess(stage, MODEL, TARGETS, kept, [], places).targets_met
    assert 'meets its target' in a.advice


def test_advice_is_the_candidate_that_lowers_the_worst_ratio_most():
    places = _places('intrinsics')
    kept = [(p, p.V0_T_target) for p in places[:6]]
    cands = places[6:]
    # a repeat of a kept placement is a candidate too: it must not win over new tilts
    cands = [places[0], *cands]
    a = stopping.assess('intrinsics', MODEL, TARGETS, kept, cands, places)
    ratios = []
    for p in cands:
        b = stopping.assess('intrinsics', MODEL, TARGETS, kept + [(p, p.V0_T_target)], [],
                            places)
        ratios.append(b.worst)
    assert a.best == int(np.argmin(ratios))
    assert a.best_ratio == pytest.approx(min(ratios))
    assert a.best != 0 and f'placement {cands[a.best].index + 1}:' in a.advice


def test_structured_stages_take_their_plan_and_say_so():
    places = _places('joint_correction', quick=True)
    a = stopping.assess('joint_correction', MODEL, TARGETS, [], places, places)
    assert a.names == [] and not a.targets_met and a.best == 0
    assert 'every placement of its plan' in a.advice
    assert stopping.stage_max('intrinsics', 100) == stopping.MAX_PLACEMENTS['intrinsics']
    assert stopping.stage_max('intrinsics', 8) == 8


def test_coverage_grids_count_features_and_views():
    prog = stopping.Progress('laser_axis', MODEL, 10)
    prog.keep(0, [np.array([[10.0, 10.0], [700.0, 530.0]])], [np.array([[0, 0, 0, 2.0]])])
    img, volt = prog.image_coverage(), prog.voltage_coverage()
    assert img.shape == (stopping.IMAGE_GRID[1], stopping.IMAGE_GRID[0]) and img.sum() == 2
    assert img[0, 0] == 1 and img[-1, -1] == 1
    assert volt.sum() == 1 and prog.axes == 'u1x,u2'
    prog.forget(0)
    assert prog.image_coverage().sum() == 0


def test_dynamic_camera_prediction_carries_the_pinhole_prior_and_its_views():
    """The dynamic camera's l and d: a loosely known pinhole (the intrinsics stage's
    standard errors) widens them, a board placed off the plan is predicted at the pose the
    scanner measured (finite, its views re-planned around it), and a placement with half
    its views knows l less well."""
    import copy

    places = _places('dynamic_camera')
    kept = [(p, p.V0_T_target) for p in places]
    tight = stopping.assess('dynamic_camera', MODEL, TARGETS, kept, [], places,
                            prior_sigma={n: 0.2 for n in ('fx', 'fy', 'cx', 'cy')})
    loose = stopping.assess('dynamic_camera', MODEL, TARGETS, kept, [], places,
                            prior_sigma={n: 20.0 for n in ('fx', 'fy', 'cx', 'cy')})
    assert tight.names == ['l', 'd'] and tight.units == ['m', 'm']
    assert np.all(np.isfinite(tight.sigma)) and np.all(loose.sigma > tight.sigma)
    off = places[1].V0_T_target.copy()
    off[:3, 3] += [0.05, -0.04, 0.03]
    moved = stopping.assess('dynamic_camera', MODEL, TARGETS, [(places[1], off)], [], places)
    assert np.all(np.isfinite(moved.sigma))
    half = copy.deepcopy(places[1])
    half.views = [(v[: len(v) // 2], lit, rate) for v, lit, rate in half.views]
    fewer = stopping.assess('dynamic_camera', MODEL, TARGETS, [(half, half.V0_T_target)], [],
                            places)
    full = stopping.assess('dynamic_camera', MODEL, TARGETS,
                           [(places[1], places[1].V0_T_target)], [], places)
    assert fewer.sigma[0] > full.sigma[0]


def _axis_rows(places):
    rows: dict = {}
    for p in places:
        rows.setdefault(stopping._row(p), []).append(p)
    near_far = {}
    for r, row in rows.items():
        z = [float(p.V0_T_target[2, 3]) for p in row]
        near_far[r] = ([p for p, zp in zip(row, z, strict=True) if zp < np.mean(z)],
                       [p for p, zp in zip(row, z, strict=True) if zp > np.mean(z)])
    return near_far


def _along(p):
    """Where a laser-axis board of the reference plan stands along its stripe (V0 x)."""
    return float(p.V0_T_target[0, 3])


def _ends_pair(near, far):
    """A near and a far board of one row at its two ends along the stripe."""
    return min(((n, f) for n in near for f in far), key=lambda nf: -abs(_along(nf[0])
                                                                        - _along(nf[1])))


def test_laser_axis_rows_need_boards_at_both_depths_of_their_plan():
    """Two boards of a row at one depth leave its plane's lean to the stripes' own depth:
    the laser axis does not stop on them, and asks next for a board at the depth missing."""
    places = _places('laser_axis')
    rows = _axis_rows(places)
    assert len(rows) >= 3 and all(len(n) >= 2 and len(f) >= 2 for n, f in rows.values())
    near_only = [p for n, _ in rows.values() for p in n[:2]]
    cands = [p for p in places if p not in near_only]
    a = stopping.assess('laser_axis', MODEL, TARGETS, [(p, p.V0_T_target) for p in near_only],
                        cands, places, noise_px=0.04)
    assert not a.targets_met and np.all(np.isnan(a.sigma))
    far = {p.index for _, f in rows.values() for p in f}
    assert cands[a.best].index in far, a.advice
    # one board at each depth of every row, at the two ends of the row: the rows count
    both = [p for n, f in rows.values() for p in _ends_pair(n, f)]
    a = stopping.assess('laser_axis', MODEL, TARGETS, [(p, p.V0_T_target) for p in both],
                        [p for p in places if p not in both], places, noise_px=0.04)
    assert np.all(np.isfinite(a.sigma)), a.table()
    # a row whose far boards were all left out (skipped) blocks nothing: its near boards
    # count once they fit a plane
    r0 = next(iter(rows))
    kept = [p for p in both if stopping._row(p) != r0] + rows[r0][0][:2]
    cands = [p for p in places if p not in kept and p not in rows[r0][1]]
    a = stopping.assess('laser_axis', MODEL, TARGETS, [(p, p.V0_T_target) for p in kept],
                        cands, places, noise_px=0.04)
    assert np.all(np.isfinite(a.sigma)), a.table()


def test_dynamic_camera_counts_only_the_views_that_showed_the_board():
    """Views that missed the board (a pose misread, a board moved off them) bring nothing:
    given the views that showed it, the prediction is that of those views alone."""
    from calibration_tools.operator_flow import views_for

    places = _places('dynamic_camera')
    kept = [(p, p.V0_T_target) for p in places]
    planned = [np.vstack([s.voltages[:, :2] for s in views_for(MODEL, p, p.V0_T_target,
                                                               TARGETS)]) for p in places]
    every = stopping.assess('dynamic_camera', MODEL, TARGETS, kept, [], places)
    said = stopping.assess('dynamic_camera', MODEL, TARGETS,
                           [(p, T, U) for (p, T), U in zip(kept, planned, strict=True)], [],
                           places)
    assert np.allclose(said.sigma, every.sigma)
    # the side placements' views off their board's far half: l and d are known less well
    part = [(p, T, U if k == 0 else U[: len(U) // 3])
            for k, ((p, T), U) in enumerate(zip(kept, planned, strict=True))]
    fewer = stopping.assess('dynamic_camera', MODEL, TARGETS, part, [], places)
    assert np.all(fewer.sigma > every.sigma * 1.02), (fewer.sigma, every.sigma)
    # a placement none of whose views showed it is no placement
    none = stopping.assess('dynamic_camera', MODEL, TARGETS,
                           [*kept[:-1], (kept[-1][0], kept[-1][1], np.zeros((0, 2)))], [],
                           places)
    fewer_one = stopping.assess('dynamic_camera', MODEL, TARGETS, kept[:-1], [], places)
    assert np.allclose(none.sigma, fewer_one.sigma, equal_nan=True)


def test_laser_axis_rows_need_boards_at_both_ends_along_the_stripe():
    """A near and a far board standing side by side pin the plane's lean but leave its turn
    about the depth axis loose: the row does not count, and the advice asks for the board
    at the far end of the row, at the depth it lacks when it lacks one."""
    places = _places('laser_axis')
    rows = _axis_rows(places)
    span = {r: max(map(_along, n + f)) - min(map(_along, n + f)) for r, (n, f) in rows.items()}
    assert min(span.values()) > 0.15
    # every row: its near board at one end, its far board beside it (a third of the span)
    close = []
    for n, f in rows.values():
        a = min(n, key=_along)
        b = min(f, key=lambda q, a=a: abs(_along(q) - _along(a)))
        assert abs(_along(b) - _along(a)) < 0.4 * span[stopping._row(a)]
        close += [a, b]
    cands = [p for p in places if p not in close]
    a = stopping.assess('laser_axis', MODEL, TARGETS, [(p, p.V0_T_target) for p in close],
                        cands, places, noise_px=0.04)
    assert not a.targets_met and np.all(np.isnan(a.sigma)), a.table()
    nxt = cands[a.best]
    mine = [p for p in close if stopping._row(p) == stopping._row(nxt)]
    assert min(abs(_along(nxt) - _along(p)) for p in mine) > 0.6 * span[stopping._row(nxt)]
    # the third board at the far end completes its row: it lacks nothing more
    row_of = stopping._row(nxt)
    kept = [p for p in close if stopping._row(p) == row_of]
    before = stopping._row_needs('laser_axis', places, kept, [nxt])
    after = stopping._row_needs('laser_axis', places, kept + [nxt], [])
    assert before[row_of][1] is not None and after[row_of] == (True, None)
    # with only a near board of a row kept, the one its row asks for next is the far board
    # at the other end (one placement brings both)
    n, f = next(iter(rows.values()))
    first = min(n, key=_along)
    cands = [p for p in places if p is not first]
    helps = stopping._row_needs('laser_axis', places, [first], cands)[stopping._row(first)][1]
    asked = [p for p in cands if stopping._row(p) == stopping._row(first) and helps(p)]
    assert asked == [max(f, key=_along)]
    # rows at both ends and both depths count
    both = [p for n, f in rows.values() for p in _ends_pair(n, f)]
    a = stopping.assess('laser_axis', MODEL, TARGETS, [(p, p.V0_T_target) for p in both],
                        [p for p in places if p not in both], places, noise_px=0.04)
    assert np.all(np.isfinite(a.sigma)), a.table()
