"""Is the calibration's predicted uncertainty honest? Drawn rigs, calibrated on the simulator,
prediction against the error measured against the truth.

Run: ``.venv/bin/python benchmarks/uncertainty_check.py [--rigs 10] [--seed-start 0]
[--quick] [--reference] [--out DIR]``

For each seed: ``galvoscan_sim.rig_family.draw_rig(seed)`` (``--reference``: the reference
rig with simulator seed = seed) is calibrated by ``galvoscan calibrate all --sim`` in a
process of its own (every stage, the physical model). Then, over a 9 x 9 grid of G1 views
within +-8 V on a wall at the depth where the calibrated laser plane crosses V0's axis
(``capture_plans.laser_crossing_depth``):

- predicted: the RMS 1-sigma point error (shape) that the calibration's joint covariance
  and the galvos' frame noise its stages measured give (``reconstructor.uncertainty``, as
  ``galvoscan evaluate`` reports it), and the calibration's part alone;
- measured: the simulator's exact stripe pixels of the same views triangulated with the
  calibration, against the true points, after the best rigid motion
  (``galvoscan.sim_scores.reconstruction_errors``): on the rig as it is (its galvos scatter
  from frame to frame), and on the same rig without that scatter (the calibration's error).

The target is the prediction within a factor of 2 of the measured error on at least 80 %
of the rigs. Both pairs are checked: the point error (total) and the calibration's part.
One line per rig; the last line of stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import yaml

from reconstructor.uncertainty import prediction_summary

ROOT = Path(__file__).resolve().parents[1]
FACTOR = 2.0


def run(seed: int, folder: Path, quick: bool, reference: bool) -> dict:
    from calibration_tools.capture_plans import laser_crossing_depth
    from galvoscan.evaluate import predicted_uncertainty
    from galvoscan_sim import load_rig
    from galvoscan_sim.rig_family import draw_rig
    from reconstructor import calibration_file

    folder.mkdir(parents=True, exist_ok=True)
    if reference:
        rig_arg = 'reference'
    else:
        rig_arg = str(folder / 'rig.yaml')
        Path(rig_arg).write_text(yaml.safe_dump(draw_rig(seed), sort_keys=False))
    cal_path = folder / 'calibration.yaml'
    cmd = [str(ROOT / '.venv/bin/galvoscan'), 'calibrate', 'all', '--sim', '--rig', rig_arg,
           '--seed', str(seed), '--calibration', str(cal_path)] + (['--quick'] if quick else [])
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    (folder / 'calibrate.log').write_text(proc.stdout + proc.stderr)
    row = {'seed': seed, 'calibrate_s': time.monotonic() - t0}
    if proc.returncode != 0:
        row['failed'] = (proc.stdout + proc.stderr).strip().splitlines()[-1:]
        return row
    cal = calibration_file.load(cal_path)
    depth = laser_crossing_depth(cal.model)
    rig = load_rig(rig_arg)
    u = predicted_uncertainty(cal, rig, depth)
    row.update({k: v for k, v in u.items() if not isinstance(v, dict)})
    row['depth_mm'] = depth * 1e3
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rigs', type=int, default=10)
    p.add_argument('--seed-start', type=int, default=0)
    p.add_argument('--quick', action='store_true', help='reduced capture plans')
    p.add_argument('--reference', action='store_true',
                   help='the reference rig with simulator seeds, not drawn rigs')
    p.add_argument('--out', default='/tmp/galvoscan_uncertainty_check')
    args = p.parse_args(argv)
    if not 1 <= args.rigs <= 200:
        p.error('--rigs must be 1..200')
    t0 = time.monotonic()
    rows = []
    for i, seed in enumerate(range(args.seed_start, args.seed_start + args.rigs), 1):
        row = run(seed, Path(args.out) / f'seed_{seed:03d}', args.quick, args.reference)
        rows.append(row)
        if 'failed' in row:
            print(f'rig {i}/{args.rigs} seed {seed}: calibration FAILED: {row["failed"]}',
                  flush=True)
            continue
        q = row.get('uncertainty_ratio', math.nan)
        qc = row.get('uncertainty_ratio_calibration', math.nan)
        print(f"rig {i}/{args.rigs} seed {seed} ({row['depth_mm']:.0f} mm): predicted "
              f"{row['predicted_uncertainty_mm']:.4f} mm, measured "
              f"{row['measured_shape_error_mm']:.4f} mm, ratio {q:.2f}"
              f"{'' if 1 / FACTOR <= q <= FACTOR else ' (outside 2x)'}; calibration's part "
              f"{row.get('predicted_calibration_uncertainty_mm', math.nan):.4f} mm, measured "
              f"without frame noise {row.get('measured_systematic_error_mm', math.nan):.4f} "
              f"mm, ratio {qc:.2f}{'' if 1 / FACTOR <= qc <= FACTOR else ' (outside 2x)'}; "
              f"frame noise {row.get('predicted_frame_noise_mm', math.nan):.4f} mm; "
              f"{row.get('uncertainty_modes_effective', math.nan):.2f} effective modes "
              f"[{row['calibrate_s']:.0f} s]", flush=True)
    summary = {'rigs': len(rows), 'reference': args.reference, 'quick': args.quick}
    figures, lines = prediction_summary(rows, FACTOR)
    summary.update(figures)
    print('\n' + '\n'.join(lines))
    summary['wall_s'] = time.monotonic() - t0
    print(json.dumps(summary, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
