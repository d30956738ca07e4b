"""``galvoscan evaluate --materials``: accuracy per surface material through the graph, with
and without each countermeasure (not part of the demo).

The graph (driver on the sim backend, stripe_extractor, reconstructor; the calibration node
unless ``--truth-calibration``) is started and calibrated as ``galvoscan evaluate`` does
(``--quick`` plans with ``--quick``). Then, for every named material
(:func:`galvoscan.material_scores.materials`) and every setting of :data:`SETTINGS`, the
stair block at the rig's working point (three views) and the flat plate (one view) are
placed through ``sim/set_scene`` and scanned through the graph; the clouds the
reconstructor publishes are scored against the scene's truth
(:mod:`galvoscan.material_scores`):

- stair error: measured minus true step [mm];
- plate flatness: RMSE about a RANSAC plane [mm];
- outliers: the share of points farther than 0.5 mm from the true surface (the nearest
  point of the scene's faces; all points of the stair and the plate);
- coverage: points over the matte part's points in the same scans with the same setting.

Settings (each the graph's own parameters, nothing computed beside it):

- ``off``: the defaults;
- ``peak_selection``: the extractor's ``peak_mode`` ``unambiguous``: a column whose second
  peak reaches ``ambiguity_ratio`` (0.3) of the first gives no centre. The graph has no
  prior of the part's shape, which ``nearest`` needs to tell the stripe from a reflection;
- ``two_view``: every stripe seen again from a second G1 position
  (:func:`reconstructor.consistency.two_view_sweep`, G1 pan + :data:`TWO_VIEW_PAN_V`), the
  reconstructor keeping the points both views put within :data:`TWO_VIEW_TOLERANCE_M`
  (``multi_view_tolerance``); twice the frames;
- ``exposure``: the driver's auto exposure (a 5-frame pre-scan per scan; the laser power
  raised up to :data:`MAX_LASER_POWER` where the frame period caps the exposure);
- ``all``: the three together.

Writes ``materials.json`` (every figure, per material and setting) and ``materials.md`` (the
table) into ``--out``; prints the JSON on its last line.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from galvoscan import eval_scenes, material_scores, metrics
from reconstructor.cloud import CLOUD_DTYPE, xyz
from reconstructor.planning import stripe_layout

#: The countermeasures of each setting.
SETTINGS = {
    'off': (),
    'peak_selection': ('peak_selection',),
    'two_view': ('two_view',),
    'exposure': ('exposure',),
    'all': ('peak_selection', 'two_view', 'exposure'),
}
#: ``two_view``: the second view's G1 pan beside the first [V] (views that still overlap).
TWO_VIEW_PAN_V = 0.35
#: ``two_view``: the reconstructor's ``multi_view_tolerance`` [m]: a little above the
#: points' noise and a pixel's footprint at the working distance.
TWO_VIEW_TOLERANCE_M = 0.15e-3
#: ``exposure``: auto exposure may raise the laser power up to this (relative to the
#: rig's), as in benchmarks/materials.py.
MAX_LASER_POWER = 2.0
#: Frames per stair view and of the plate's view (half with ``--quick``).
STAIR_FRAMES, PLATE_FRAMES = 20, 40
TABLE_COLUMNS = [('material', 'material', 's'), ('setting', 'countermeasures', 's'),
                 ('stair_error_mm', 'stair error [mm]', '+.3f'),
                 ('plate_flatness_mm', 'plate flatness [mm]', '.3f'),
                 ('outlier_percent', 'outliers [%]', '.3f'),
                 ('coverage_vs_matte', 'coverage (vs matte)', '.3f'),
                 ('points', 'points', 'd'), ('frames', 'frames', 'd')]


class MaterialRun:
    """The scans of every material and setting through a running graph."""

    def __init__(self, graph, model, W_T_V0, site, frame_rate, quick, progress):
        self.graph, self.client = graph, graph.client
        self.model, self.W_T_V0 = model, W_T_V0
        self.V0_T_W = np.linalg.inv(W_T_V0)
        self.site, self.frame_rate, self.progress = site, frame_rate, progress
        self.frames = (STAIR_FRAMES // 2, PLATE_FRAMES // 2) if quick else (STAIR_FRAMES,
                                                                          PLATE_FRAMES)
        self.driver = {'auto_exposure': False, 'max_laser_power': 1.0}

    # ---- the graph's settings ---------------------------------------------------------
    def apply(self, setting: str) -> None:
        """Set the graph's parameters for ``setting`` (the driver re-configured only when
        its configure-time exposure parameters change)."""
        on = SETTINGS[setting]
        peak = 'peak_selection' in on
        self.graph._set_parameters('stripe_extractor',
                                   peak_mode='unambiguous' if peak else 'strongest')
        self.graph._set_parameters('reconstructor', multi_view_tolerance=(
            TWO_VIEW_TOLERANCE_M if 'two_view' in on else 0.0))
        driver = {'auto_exposure': 'exposure' in on,
                  'max_laser_power': MAX_LASER_POWER if 'exposure' in on else 1.0}
        if driver != self.driver:
            self.graph._lifecycle('deactivate', 'cleanup')
            self.graph._set_parameters('galvo_driver', **driver)
            self.graph._lifecycle('configure', 'activate')
            self.driver = driver

    # ---- scans ------------------------------------------------------------------------
    def _scan(self, text: str, sweeps: list, two_view: bool):
        """Place the scene, scan the sweeps, return (points (n, 3) V0 [m], frames)."""
        from reconstructor.consistency import two_view_sweep

        self.client.set_scene(text)
        rows = []
        for s in sweeps:
            if two_view:
                s = two_view_sweep(s, (s[0, 0] + TWO_VIEW_PAN_V, s[0, 1]))
            rows.append(s)
        volts = np.vstack(rows)
        clouds, n = self.client.scan(volts, frame_rate=self.frame_rate)
        cloud = np.concatenate(clouds) if clouds else np.zeros(0, CLOUD_DTYPE)
        return xyz(cloud), n

    def measure(self, mat: str, setting: str) -> dict:
        """The stair block and the plate in ``mat`` with ``setting``: the figures."""
        from galvoscan_sim import load_scene_text

        two = 'two_view' in SETTINGS[setting]
        stair_frames, plate_frames = self.frames
        text, info = eval_scenes.stair(self.site.offset((0.0, 0.0, 0.0)), material=mat,
                                       layout=stripe_layout(self.model))
        sweeps = material_scores.stair_sweeps(self.model, self.V0_T_W, info, stair_frames)
        stair_p, n1 = self._scan(text, sweeps, two)
        stair_off = material_scores.surface_offsets(load_scene_text(text), self.W_T_V0,
                                                    stair_p)
        try:
            stair_err = material_scores.stair_error_mm(self.W_T_V0, info, stair_p, stair_off)
        except ValueError:
            stair_err = float('nan')
        ptext, pinfo = eval_scenes.plate(0, self.site, material=mat)
        sweeps = material_scores.aimed_sweep(self.model, self.V0_T_W, pinfo['W_T_O'][:3, 3],
                                             plate_frames)
        plate_p, n2 = self._scan(ptext, sweeps, two)
        plate_off = material_scores.surface_offsets(load_scene_text(ptext), self.W_T_V0,
                                                    plate_p)
        offsets = np.concatenate((stair_off, plate_off))
        return {'material': mat, 'setting': setting,
                'stair_error_mm': stair_err,
                'plate_flatness_mm': material_scores.flatness_mm(plate_p),
                'outlier_fraction': material_scores.outlier_fraction(offsets),
                'outlier_percent': 100.0 * material_scores.outlier_fraction(offsets),
                'points': int(len(offsets)), 'stair_points': int(len(stair_p)),
                'plate_points': int(len(plate_p)), 'frames': int(n1 + n2)}


def run(args, rig, site, out: Path, graph, progress) -> dict:
    """Calibrate the running graph and measure every material and setting; the results."""
    cal, _ = graph.calibrate(args, rig, quick=args.quick)
    runner = MaterialRun(graph, cal.model, rig.W_T_V0, site, args.frame_rate, args.quick,
                         progress)
    mats = material_scores.materials()
    rows = []
    for setting in SETTINGS:  # the driver is re-configured at most once per setting
        runner.apply(setting)
        for mat in mats:
            r = runner.measure(mat, setting)
            rows.append(r)
            progress.log(f"materials: {mat} {setting}: stair {r['stair_error_mm']:+.3f} mm, "
                         f"flatness {r['plate_flatness_mm']:.3f} mm, outliers "
                         f"{r['outlier_percent']:.3f} %, {r['points']} points")
    matte = {r['setting']: r['points'] for r in rows if r['material'] == 'matte_paint'}
    for r in rows:
        r['coverage_vs_matte'] = r['points'] / max(matte[r['setting']], 1)
    by = {(r['material'], r['setting']): r for r in rows}
    summary = {
        'matte_stair_error_mm': by[('matte_paint', 'off')]['stair_error_mm'],
        'aluminium_stair_error_mm_off': by[('machined_aluminium', 'off')]['stair_error_mm'],
        'aluminium_stair_error_mm_all': by[('machined_aluminium', 'all')]['stair_error_mm'],
        'aluminium_outlier_fraction_off': by[('machined_aluminium', 'off')]['outlier_fraction'],
        'aluminium_outlier_fraction_all': by[('machined_aluminium', 'all')]['outlier_fraction'],
        'black_coverage_vs_matte_off': by[('black_anodised', 'off')]['coverage_vs_matte'],
        'black_coverage_vs_matte_exposure': by[('black_anodised', 'exposure')]
        ['coverage_vs_matte'],
    }
    return {'summary': summary, 'rows': rows, 'calibration_source': cal.source,
            'stair_errors_rmse_mm': {s: metrics.rmse([r['stair_error_mm'] for r in rows
                                                     if r['setting'] == s
                                                     and np.isfinite(r['stair_error_mm'])])
                                     for s in SETTINGS}}


def write(out: Path, result: dict, args) -> None:
    """``materials.json`` and ``materials.md`` in ``out``."""
    (out / 'materials.json').write_text(json.dumps(result, indent=1, default=float))
    cmd = 'galvoscan evaluate --materials' + (' --quick' if args.quick else '') + (
        ' --truth-calibration' if args.truth_calibration else '') + f' --seed {args.seed}'
    text = ['# Accuracy per material, through the graph', '',
            f'Measured with `{cmd}` (calibration: {result["calibration_source"]}); see '
            '`galvoscan.materials_eval` for the settings.', '',
            material_scores.table_markdown(result['rows'], TABLE_COLUMNS), '']
    (out / 'materials.md').write_text('\n'.join(text))


def main(args, Graph, load, write_failure) -> int:
    """``galvoscan evaluate --materials``: ``args`` from ``evaluate.build_parser``; the
    evaluation's graph (``evaluate.Graph``), rig loader and failure writer, handed in by
    ``evaluate`` (which imports this module)."""
    from galvoscan.progress import Progress
    from galvoscan_common.runtime import private_domain

    t0 = time.monotonic()
    try:
        rig, _description, site, _wd, out = load(args)
    except (ValueError, OSError) as exc:
        print(f'galvoscan evaluate --materials: {exc}', file=sys.stderr)
        return 2
    progress = Progress()
    domain = os.environ.get('ROS_DOMAIN_ID') or str(private_domain())
    env = {**os.environ, 'ROS_DOMAIN_ID': domain, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    (out / 'materials.json').unlink(missing_ok=True)
    try:
        with Graph(args, args.rig, out, env, progress, quick=args.quick) as graph:
            result = run(args, rig, site, out, graph, progress)
    except (RuntimeError, ValueError) as exc:
        progress.log(f'materials evaluation failed: {exc}')
        write_failure(out, exc)
        return 1
    result['runtime_s'] = time.monotonic() - t0
    write(out, result, args)
    progress.log(f'wrote {out}/materials.json and materials.md in {result["runtime_s"]:.0f} s')
    print(json.dumps(result['summary'], default=float))
    return 0
