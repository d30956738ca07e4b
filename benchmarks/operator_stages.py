"""The calibration chain in one process, targets placed by a simulated person or exactly:
which stage's parameters the operator's imprecision moves.

Run: ``.venv/bin/python benchmarks/operator_stages.py [--rig reference] [--seed 1]
[--full] [--truth-intrinsics]``

Each stage of the chain, from the rig's design values: every placement its plan asks for
(in the order and number the stopping rule of :mod:`calibration_tools.stopping` takes)
is put in the simulator by :func:`galvoscan.operator.draw_placement` (a person's
imprecision, no mistakes) or exactly where asked, found by the scanner's search
(:func:`calibration_tools.operator_flow.search`, followed moves included), its views
planned around the measured pose and rendered in process; then the stage is computed and
merged. Both chains run from the same seed; each stage's errors against the simulator's
truth (the physical model's parameters) are printed per chain, and the last line's JSON
holds both, with the ratio of the laser sheet's offset error at the working point.
``--truth-intrinsics`` starts both chains from the true intrinsics (the dynamic camera
and the laser stages alone). Timings are not the point (in process, no DDS).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import yaml

from calibration_tools import capture_plans as cp
from calibration_tools import operator_flow as of
from calibration_tools import stage_runner, stopping
from calibration_tools.registry import plan
from calibration_tools.stages import STAGES, CaptureStep, apply_result
from galvoscan.operator import EXACT, Person, draw_placement, scene_text
from galvoscan.simulated_rig import execute_in_process, nominal_calibration, truth_model
from galvoscan_sim import Simulator, load_rig
from galvoscan_sim.scene import load_scene_text
from reconstructor.model import laser_plane_v0

MAX_MOVES = 6


def _errors(stage, model, truth, depth) -> dict:
    """The stage's parameters against the truth, in mm, px and mrad."""
    at = np.array([0.0, 0.0, depth, 1.0])
    if stage == 'intrinsics':
        i, t = model.intrinsics, truth.intrinsics
        return {'fx_px': i.fx - t.fx, 'fy_px': i.fy - t.fy, 'cx_px': i.cx - t.cx,
                'cy_px': i.cy - t.cy}
    if stage == 'dynamic_camera':
        return {'l_mm': (model.l - truth.l) * 1e3, 'd_mm': (model.d - truth.d) * 1e3}
    if stage == 'laser_plane':
        a, b = np.asarray(model.laser_plane_v0), np.asarray(truth.laser_plane_v0)
        return {'sheet_offset_at_working_point_mm': float((a - b) @ at) * 1e3,
                'sheet_normal_mrad': float(np.arccos(min(1.0, abs(a[:3] @ b[:3])))) * 1e3}
    if stage == 'laser_axis':
        return {f'sheet_offset_mm_at_{u:+g}V': float(
            (laser_plane_v0(model, u) - laser_plane_v0(truth, u)) @ at) * 1e3
            for u in (-4.0, 0.0, 4.0)}
    return {}


def chain(rig_name: str, seed: int, person, quick: bool, truth_intrinsics: bool) -> list:
    rig = load_rig(rig_name)
    truth = truth_model(rig, kind='physical')
    cal = nominal_calibration(rig_name)
    if truth_intrinsics:
        cal = dataclasses.replace(cal, model=dataclasses.replace(
            cal.model, intrinsics=truth.intrinsics))
    sim = Simulator(rig, load_scene_text(scene_text('sphere', {'radius': 0.01}, np.eye(4)),
                                         'start'), seed=seed)
    rng = np.random.default_rng(seed)

    def look(volts, lit=False):
        return execute_in_process(sim, [CaptureStep(0, None, volts, lit)])[0]

    rows = []
    for stage in STAGES:
        if truth_intrinsics and stage == 'intrinsics':
            continue
        t0 = time.monotonic()
        model = cp.current_model(cal)
        steps = plan(stage, cal, quick=quick)
        targets = getattr(steps, 'targets', None) or cp.choose_targets(model)
        places = of.placements(stage, steps)
        order, kept, views, measured = list(range(len(places))), [], [], {}
        most, least = (stopping.stage_max(stage, len(places)),
                       stopping.stage_min(stage, len(places)))
        skipped = 0
        while order and len(kept) < most:
            p = places[order[0]]
            instr = of.instruction_fields(p, 'place', '')
            spec = yaml.safe_load(instr['target_spec'])
            T = draw_placement(instr, rng, person).T
            for _ in range(MAX_MOVES + 1):
                sim.set_scene(load_scene_text(scene_text(p.kind, spec, T), 'operator'))
                loc, move = of.search(model, p, targets, look, None,
                                      lambda v: look(v, True))
                if move is None:
                    try:
                        got = of.views_for(model, p, loc.V0_T_target, targets)
                        break
                    except ValueError as exc:
                        move = of.reach_move(model, p, loc.V0_T_target[:3, 3], str(exc))
                if move.reason == 'not_found':  # placed again, as a person would
                    T = draw_placement(instr, rng, person).T
                else:
                    T = T.copy()
                    T[:3, 3] += move.move
            else:
                order.pop(0)
                skipped += 1
                continue
            frames = execute_in_process(sim, got)[0]
            for v in frames:
                v.pose_index = p.index
            views += frames
            kept.append((p, loc.V0_T_target))
            measured[p.index] = loc.V0_T_target
            order.pop(0)
            a = stopping.assess(stage, model, targets, kept, [places[k] for k in order],
                                places)
            if len(kept) >= least and a.targets_met:
                break
            if a.best is not None and order:
                order.insert(0, order.pop(a.best))
        inputs = {'measured_poses': measured} if stage == 'dynamic_camera' else {}
        result = stage_runner.compute(stage, views, cal, inputs=inputs)
        cal = apply_result(cal, result)
        row = {'stage': stage, 'kept': len(kept), 'planned': len(places),
               'skipped': skipped, 'seconds': round(time.monotonic() - t0, 1),
               'errors': _errors(stage, cal.model, truth, targets.depth)}
        rows.append(row)
        print(json.dumps({'operator': 'exact' if person is EXACT else 'person', **row},
                         default=float), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--rig', default='reference')
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--full', action='store_true', help='full plans (default: quick)')
    p.add_argument('--truth-intrinsics', action='store_true')
    args = p.parse_args(argv)
    out = {}
    for name, person in (('person', Person(mistake_rate=0.0)), ('exact', EXACT)):
        out[name] = chain(args.rig, args.seed, person, not args.full, args.truth_intrinsics)

    def offset(rows):
        row = next((r for r in rows if r['stage'] == 'laser_plane'), None)
        return None if row is None else abs(row['errors']['sheet_offset_at_working_point_mm'])

    a, b = offset(out['person']), offset(out['exact'])
    print(json.dumps({'rig': args.rig, 'seed': args.seed, 'full': args.full,
                      'truth_intrinsics': args.truth_intrinsics,
                      'sheet_offset_error_mm': {'person': a, 'exact': b},
                      'ratio': (a / b) if a is not None and b else None, **out},
                     default=float))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
