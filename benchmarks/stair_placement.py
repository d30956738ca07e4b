"""The stair block placed for the laser's side against the block of a laser below.

Run: ``.venv/bin/python benchmarks/stair_placement.py --rig RIG.yaml --calibration CAL.yaml
[--frames 8] [--grid 6 5]``

With a rig and a calibration of it (e.g. ``galvoscan evaluate``'s ``calibration.yaml``), the
stair block is placed at each position of the evaluation's grid (``Site.stair_grid``) twice:
turned to the rig's stripe layout (``eval_scenes.stair(..., layout=)``, as ``galvoscan
evaluate`` places it) and as set up for a laser below. Each is swept as the evaluation sweeps
it (three views, ``material_scores.stair_sweeps``), rendered in process by the simulator,
extracted, triangulated with the calibration; the figure is the step error [mm]. For a laser
beside the camera the unturned block's riser runs along the stripe. One line per position;
the last line is a JSON object with the RMS and largest error of each placement and the
ratio of the turned RMS to the unturned one, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import yaml

from calibration_tools.laser_plane import stripe_extractor_config
from galvoscan import eval_scenes, material_scores, metrics
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.rig import rig_from_dict
from reconstructor import calibration_file
from reconstructor.model import triangulate
from reconstructor.planning import stripe_layout
from stripe_extractor.extractor import extract


def step_error_mm(sim, model, position, layout, frames) -> float:
    """The stair block at ``position`` (W) [m], placed for ``layout`` (None: a laser below):
    its step error [mm]."""
    text, info = eval_scenes.stair(position, layout=layout)
    sim.set_scene(load_scene_text(text, 'stair'))
    V0_T_W = np.linalg.inv(sim.W_T_V0)
    config = stripe_extractor_config(model)
    points = []
    for sweep in material_scores.stair_sweeps(model, V0_T_W, info, frames):
        for v in sweep:
            volts = sim.rig.dac.quantize(v[None])[0]
            stripe = extract(sim.render(volts).image, config)
            res = triangulate(model, np.column_stack([stripe.u, stripe.v]).astype(np.float64),
                              volts[0], volts[1], volts[3])
            points.append(res.p_v0[res.valid])
    O_T_V0 = np.linalg.inv(info['W_T_O']) @ sim.W_T_V0
    res = metrics.stair_step(metrics.to_frame(O_T_V0, np.vstack(points)), info['size'],
                             info['step_height'])
    return res.error * 1e3


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rig', required=True, help='rig description YAML')
    p.add_argument('--calibration', required=True, help='calibration YAML of that rig')
    p.add_argument('--frames', type=int, default=8, help='stripes per view (evaluate: 8)')
    p.add_argument('--grid', type=int, nargs=2, default=(6, 5), help='positions in x and y')
    args = p.parse_args(argv)
    with open(args.rig) as f:
        rig = rig_from_dict(yaml.safe_load(f), args.rig)
    model = calibration_file.load(args.calibration).model
    layout = stripe_layout(model)
    sim = Simulator(rig, load_scene_text(eval_scenes.wall()[0], 'wall'), seed=1)
    errors = {'turned': [], 'below': []}
    for pos in eval_scenes.site_of(rig).stair_grid(*args.grid):
        row = []
        for name, lay in (('turned', layout), ('below', None)):
            try:
                e = step_error_mm(sim, model, pos, lay, args.frames)
            except ValueError:
                e = math.nan
            errors[name].append(e)
            row.append(f'{name} {e:+.4f} mm')
        print(f'stair at {np.round(pos, 3).tolist()} m: ' + ', '.join(row), flush=True)
    out = {'laser': {'orientation': layout.orientation, 'side': layout.side,
                     'turn_deg': math.degrees(layout.turn)}, 'frames': args.frames}
    for name, v in errors.items():
        f = np.array([x for x in v if math.isfinite(x)])
        out[name] = {'rmse_mm': float(np.sqrt(np.mean(f ** 2))) if f.size else None,
                     'max_mm': float(np.abs(f).max()) if f.size else None,
                     'positions': int(f.size), 'of': len(v)}
    if out['turned']['rmse_mm'] and out['below']['rmse_mm']:
        out['ratio_turned_to_below'] = out['turned']['rmse_mm'] / out['below']['rmse_mm']
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
