"""The laser axis from two or four lit frames per board: how much the galvos' per-frame
jitter leaves in the laser calibration.

Run: ``.venv/bin/python benchmarks/laser_axis_lit_frames.py [--rigs 1] [--seeds 3]``

On the reference rig and ``--rigs`` drawn rigs (``galvoscan_sim.rig_family.draw_rig``,
seeds 0, 1, ...): the laser axis plan's boards at the two ends of every row (one near, one
far: what the stopping rule keeps) are put exactly where the plan asks, captured in
process as the operator flow aims them (``operator_flow.views_for``), lit at the plan's
voltages (:data:`capture_plans.LASER_AXIS_LIT_OFFSETS`, four frames) and again at two
(+-0.05 V). The stage is solved from each with the camera at its true values and started
from the true laser, so what is left is what the data leave; the score is the shape error
of a wall scanned at the working depth with the result
(``galvoscan.sim_scores.reconstruction_errors``, aligned). Every lit frame is one draw of
the simulated galvos' per-frame jitter (each rig's ``jitter``), which moves its whole
stripe off the sheet at once. ``--seeds`` simulator seeds per rig. One line per rig and
seed; the last line is a JSON object with the medians and the ratio of four frames to two
measured in the same run.
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np
import yaml

from calibration_tools import capture_plans as cp
from calibration_tools import operator_flow as of
from calibration_tools.laser_axis import run_laser_axis
from calibration_tools.registry import plan
from calibration_tools.stages import apply_result
from galvoscan.operator import scene_text
from galvoscan.sim_scores import reconstruction_errors
from galvoscan.simulated_rig import execute_in_process, nominal_calibration, truth_model
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.rig import load_rig, load_rig_text
from galvoscan_sim.rig_family import draw_rig, working_point
from reconstructor import calibration_file

TWO = (-0.05, 0.05)


def lit_at(p, offsets):
    """Placement ``p`` with its lit frames at its row's voltage plus ``offsets`` [V]."""
    q = copy.copy(p)
    row = of.lit_voltage(p)
    views, lit_done = [], False
    for v, lit, rate in p.views:
        if lit:
            if lit_done:
                continue
            lit_done = True
            first = np.asarray(v, dtype=np.float64)[0]
            v = np.array([[*first[:3], row + o] for o in offsets])
        views.append((v, lit, rate))
    q.views = views
    return q


def ends_of_rows(cal):
    """The laser axis plan's boards at the two ends of its rows."""
    return [p for p in of.placements('laser_axis', plan('laser_axis', cal))
            if p.row_end is not None]


def shape_error(rig, boards, offsets, seed: int) -> float:
    """Shape error [m] of the laser axis solved from ``boards`` lit at ``offsets``."""
    truth = calibration_file.Calibration(model=truth_model(rig, kind='physical'))
    targets = cp.choose_targets(truth.model)
    sim = Simulator(rig, load_scene_text(scene_text('sphere', {'radius': 0.01}, np.eye(4)),
                                         'start'), seed=seed)
    views = []
    for p in boards:
        q = lit_at(p, offsets)
        spec = yaml.safe_load(of.instruction_fields(q, 'place', '')['target_spec'])
        sim.set_scene(load_scene_text(scene_text(q.kind, spec, q.V0_T_target), 'board'))
        views += execute_in_process(sim, of.views_for(truth.model, q, q.V0_T_target,
                                                      targets))[0]
    result = run_laser_axis(views, truth, board=boards[0].target)
    model = apply_result(truth, result).model
    depth = float(working_point(rig)[2])
    return reconstruction_errors(model, rig, depth=depth, seed=seed)['aligned_rms_m']


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--rigs', type=int, default=1, help='drawn rigs besides the reference')
    ap.add_argument('--seeds', type=int, default=3, help='simulator seeds per rig')
    args = ap.parse_args(argv)
    rigs = [('reference', 'reference', load_rig('reference'))]
    for k in range(args.rigs):
        desc = draw_rig(k)
        rigs.append((f'seed {k}', desc, load_rig_text(yaml.safe_dump(desc), f'drawn-{k}')))
    four = cp.LASER_AXIS_LIT_OFFSETS
    rows, t0 = [], time.monotonic()
    for name, desc, rig in rigs:
        boards = ends_of_rows(nominal_calibration(desc))
        for seed in range(1, args.seeds + 1):
            two_m = shape_error(rig, boards, TWO, seed)
            four_m = shape_error(rig, boards, four, seed)
            rows.append((name, seed, two_m, four_m))
            print(f'{name}, simulator seed {seed}: {len(boards)} boards; shape error '
                  f'{two_m * 1e6:.1f} um from 2 lit frames each, {four_m * 1e6:.1f} um from '
                  f'{len(four)}', flush=True)
    two = float(np.median([r[2] for r in rows]))
    fourm = float(np.median([r[3] for r in rows]))
    print(json.dumps({
        'rigs': len(rigs), 'seeds_per_rig': args.seeds,
        'shape_error_um_two_lit_median': two * 1e6,
        'shape_error_um_four_lit_median': fourm * 1e6,
        'ratio_four_to_two': fourm / two,
        'four_better': sum(r[3] < r[2] for r in rows), 'runs': len(rows),
        'wall_s': time.monotonic() - t0}))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
