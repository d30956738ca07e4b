"""The stripe extractor's filter width against the stripe's own: the flat plate's noise and
the extraction time with the width stated and with the width adapted to the image.

Run: ``.venv/bin/python benchmarks/extractor_width.py [--rig RIG.yaml | --seed N] [--grid 7]
[--widths 4.7,10]``

The rig is the reference rig, a rig description (``--rig``), or the family's rig of seed N
(``--seed``: ``galvoscan_sim.rig_family.draw_rig(N)``, as ``benchmarks/rig_family.py`` draws
it).

The evaluation's flat plate at the rig's working point is crossed by the true laser sheet at a
``--grid`` x ``--grid`` lattice (``plate_stages.plate_frames``). Each rendered frame's stripe is
extracted (``stripe_extractor.extractor.extract``, oriented as the laser stages orient it) with
each stated ``line_width_px`` of ``--widths``, once as stated (``adapt_line_width`` off) and
once adapted, and triangulated by the true rig: so the plate's RMS distance from its plane
[mm] is the extraction's alone (and the galvos' frame-to-frame scatter, the ``exact`` row:
the simulator's exact stripe pixels). Also printed: the stripe's FWHM measured in the frames
(``stripe_extractor.width.stripe_fwhm``, median and range over the frames), the width each
extraction used (median over the frames), the frames extracted again, and its mean time
per frame [ms]. The last line is one JSON object: each row, and ``ratio_adapted_to_stated``,
the adapted plate RMS over the stated one at the first width, measured in the same run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from importlib.resources import files

import numpy as np
import yaml
from plate_stages import plate_frames, plate_rms_mm

from calibration_tools.laser_plane import stripe_extractor_config
from galvoscan.simulated_rig import truth_model
from galvoscan_sim.rig import rig_from_dict
from galvoscan_sim.rig_family import draw_rig
from reconstructor.model import triangulate
from stripe_extractor.extractor import ExtractorConfig, extract, warm_up
from stripe_extractor.width import stripe_fwhm


def run(rig, grid: int, widths) -> dict:
    truth = truth_model(rig, kind='physical')
    frames = list(plate_frames(rig, truth, grid))
    if len(frames) < 3:
        raise RuntimeError(f'the plate is crossed in {len(frames)} view(s) within reach')
    base = stripe_extractor_config(truth)
    warm_up()

    def plate(stripes):
        pts = []
        for (q, _), s in zip(frames, stripes, strict=True):
            uv = np.column_stack([s.u, s.v]).astype(np.float64)
            res = triangulate(truth, uv, q[0], q[1], q[3])
            pts.append(res.p_v0[res.valid])
        return plate_rms_mm(pts), int(sum(len(p) for p in pts))

    rms, n = plate([f.truth.stripe for _, f in frames])
    rows = [{'extraction': 'exact', 'plate_rms_mm': rms, 'points': n}]
    measured = []
    for w in widths:
        for adapt in (False, True):
            cfg = dataclasses.replace(base, line_width_px=w, adapt_line_width=adapt,
                                      roi_half_height=max(base.roi_half_height,
                                                          int(np.ceil(w))))
            t0 = time.perf_counter()
            stripes = [extract(f.image, cfg) for _, f in frames]
            ms = (time.perf_counter() - t0) / len(frames) * 1e3
            if not measured:
                measured = [stripe_fwhm(f.image, s)
                            for (_, f), s in zip(frames, stripes, strict=True) if len(s.u)]
            rms, n = plate(stripes)
            used = [s.config.line_width_px for s in stripes]
            rows.append({'extraction': 'adapted' if adapt else 'stated',
                         'line_width_px': w, 'plate_rms_mm': rms, 'points': n,
                         'width_used_px_median': float(np.median(used)),
                         'frames_extracted_again': int(sum(s.config is not cfg
                                                           for s in stripes)),
                         'ms_per_frame': ms})
    stated0 = next(r for r in rows if r['extraction'] == 'stated')
    adapted0 = next(r for r in rows if r['extraction'] == 'adapted')
    return {'frames': len(frames), 'measured_fwhm_px_median': float(np.nanmedian(measured)),
            'measured_fwhm_px_range': [float(np.nanmin(measured)), float(np.nanmax(measured))],
            'rows': rows,
            'ratio_adapted_to_stated': adapted0['plate_rms_mm'] / stated0['plate_rms_mm']}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = p.add_mutually_exclusive_group()
    which.add_argument('--rig', help='simulated rig YAML (default: the reference rig)')
    which.add_argument('--seed', type=int, help="the rig family's rig of this seed")
    p.add_argument('--grid', type=int, default=7, help='points per side of the plate')
    p.add_argument('--widths', default=f'{ExtractorConfig().line_width_px},10',
                   help='stated line_width_px values [px], comma-separated')
    args = p.parse_args(argv)
    try:
        widths = [float(x) for x in args.widths.split(',')]
    except ValueError:
        p.error(f'--widths: expected numbers separated by commas, got {args.widths!r}')
    if args.grid < 2:
        p.error('--grid must be >= 2')
    if args.seed is not None:
        name = f'draw_rig({args.seed})'
        rig = rig_from_dict(draw_rig(args.seed), name)
    else:
        path = args.rig or str(files('galvoscan_sim') / 'rigs' / 'reference.yaml')
        name = args.rig or 'the reference rig'
        with open(path) as f:
            rig = rig_from_dict(yaml.safe_load(f), path)
    out = run(rig, args.grid, widths)
    out['rig'] = name
    lo, hi = out['measured_fwhm_px_range']
    print(f"{out['frames']} frames; the stripe's FWHM measured: "
          f"{out['measured_fwhm_px_median']:.2f} px ({lo:.2f} to {hi:.2f})")
    for r in out['rows']:
        extra = ('' if r['extraction'] == 'exact' else
                 f" at {r['line_width_px']:.1f} px (used {r['width_used_px_median']:.1f} px, "
                 f"{r['frames_extracted_again']} frames again), "
                 f"{r['ms_per_frame']:.2f} ms/frame")
        print(f"{r['extraction']:>8}{extra}: plate {r['plate_rms_mm']:.4f} mm, "
              f"{r['points']} points")
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
