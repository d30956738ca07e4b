"""Stripe extraction on a stripe turned off the image rows: how far an oblique stripe holds.

Run: ``.venv/bin/python benchmarks/stripe_tilt.py [--frames 5] [--speckle]``

The reference rig with its G2 head turned about the optical axis by 0 to 40 deg (the laser
moved round the camera; the sheet still crosses the axis at the working point) looks at a
grey plane there; the stripe is extracted along the nearer of the rows and columns
(``galvoscan_common.stripe_layout``) and each centre is compared with the simulator's true
stripe, as a distance normal to the stripe [px]. Speckle is off unless ``--speckle`` (it
dominates the error and hides the geometry's). One line per angle; the last line is a JSON
object with the RMS per angle and its ratio to the 0 deg RMS measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import yaml

from galvoscan_sim import Simulator
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig import RIG_DIR, load_rig_text
from galvoscan_sim.rig_family import _plane_scene, g2_turned, working_point
from stripe_extractor.extractor import ExtractorConfig, extract

ANGLES_DEG = (0, 10, 20, 30, 40)


def normal_errors(rig, frames: int) -> tuple[np.ndarray, object]:
    """Extracted minus true stripe centre, normal to the stripe [px], over ``frames``."""
    lay = rig.stripe_layout()
    sim = Simulator(rig, _plane_scene(working_point(rig)), seed=1)
    vertical = lay.orientation == 'vertical'
    errs = []
    for k in range(frames):
        f = sim.render(np.array([0.0, 0.0, 0.0, 0.02 * k]), frame_index=k)
        t = f.truth.stripe
        res = extract(f.image, ExtractorConfig(orientation=lay.orientation))
        a_t, c_t = (t.v, t.u) if vertical else (t.u, t.v)
        a_e, c_e = (res.v, res.u) if vertical else (res.u, res.v)
        o = np.argsort(a_t)
        errs.append((c_e - np.interp(a_e, a_t[o], c_t[o])) * math.cos(lay.tilt))
    return np.concatenate(errs), lay


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--frames', type=int, default=5)
    p.add_argument('--speckle', action='store_true', help="keep the rig's laser speckle")
    args = p.parse_args(argv)
    ref = read_yaml_file(RIG_DIR / 'reference.yaml')
    if not args.speckle:
        ref['imperfections']['image']['speckle_contrast'] = 0.0
    out = {}
    for deg in ANGLES_DEG:
        e, lay = normal_errors(load_rig_text(yaml.safe_dump(g2_turned(ref, deg))), args.frames)
        rms = float(np.sqrt(np.mean(e ** 2)))
        out[str(deg)] = {'tilt_deg': math.degrees(lay.tilt), 'points': int(e.size),
                         'bias_px': float(np.median(e)), 'rms_px': rms}
        print(f'{deg:3d} deg: stripe {math.degrees(lay.tilt):5.1f} deg off the '
              f"{'columns' if lay.orientation == 'vertical' else 'rows'}, {e.size} centres, "
              f'bias {np.median(e):+.3f} px, RMS {rms:.3f} px', flush=True)
    base = out['0']['rms_px']
    for v in out.values():
        v['rms_ratio_to_0_deg'] = v['rms_px'] / base if base > 0 else None
    print(json.dumps({'speckle': bool(args.speckle), 'frames': args.frames, 'angles': out}))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
