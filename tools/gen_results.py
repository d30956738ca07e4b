#!/usr/bin/env python3
"""Measure, and write docs/results/: accuracy and performance, each figure with its command.

    .venv/bin/python tools/gen_results.py                 # the demo and the quick benchmarks
    .venv/bin/python tools/gen_results.py --long          # also the long ones (an hour or more)
    .venv/bin/python tools/gen_results.py --only triangulation,extractor
    .venv/bin/python tools/gen_results.py --demo-out out  # take a finished `make demo` run
    .venv/bin/python tools/gen_results.py --render        # rewrite the pages from results.json

``make results`` runs the first form. Every measurement is kept in docs/results/results.json
with the command that made it, the date, the commit and the machine; the pages are written
from that file, so a run of some benchmarks leaves the others' last measurements (with their
own date and commit) in place. A benchmark never run says so on the page, with its command.
Each benchmark prints one JSON object on its last line; that object is what is recorded.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'docs' / 'results'
STORE = RESULTS / 'results.json'
PY = sys.executable

#: name -> (arguments after the interpreter, quick (about a minute or less), what it measures)
BENCHMARKS = {
    'triangulation': (['benchmarks/triangulation.py'], True,
                      'one frame of 720 stripe points triangulated on one core'),
    'extractor': (['benchmarks/extractor.py'], True,
                  'stripe extraction per 720x540 frame, and its accuracy'),
    'simulator': (['benchmarks/simulator.py'], True, 'simulated frames per second, one core'),
    'bag_write': (['benchmarks/bag_write.py'], True, 'writing a 720x540 image to a bag'),
    'bag_read': (['benchmarks/bag_read.py', '--images', '300'], True,
                 'reading a 720x540 image from a bag'),
    'protocol_fuzz': (['benchmarks/protocol_fuzz.py'], True,
                      'the board protocol decoder under 10^6 random and damaged frames'),
    'protocol_fuzz_firmware': (['benchmarks/protocol_fuzz.py', '--frames', '100000',
                                '--firmware', '20000'], True,
                               'the same decoder under 10^5 frames, and the board firmware in '
                               'simavr under 20,000 of them'),
    'driver_idle': (['benchmarks/driver_idle.py', '--seconds', '10'], True,
                    'CPU of an idle driver against a bare rclpy node'),
    'firmware_simavr': (['benchmarks/firmware_simavr.py'], True,
                        'the board firmware in simavr: 10,000 triggers at 500 Hz, watchdog, '
                        'interlock'),
    'twin_scan': (['benchmarks/twin_scan.py', '--positions', '18'], False,
                  'a stair scan through the twin (firmware in simavr, GigE Vision camera '
                  'path) against the same scan on the sim backend, 18 stair positions'),
    'twin_evaluate': (['-m', 'galvoscan.cli', 'evaluate', '--twin', '--quick', '--distances',
                       'none', '--no-paper-method', '--out', 'out/twin_evaluate'], False,
                      'the reference rig calibrated through the twin by the simulated '
                      'operator (quick plans), then the test objects scanned through it'),
    'stripe_tilt': (['benchmarks/stripe_tilt.py'], True,
                    'stripe centres normal to a stripe turned off the image rows, no speckle'),
    'stripe_tilt_speckle': (['benchmarks/stripe_tilt.py', '--speckle'], True,
                            "the same with the rig's laser speckle"),
    'laser_axis_lit_frames': (['benchmarks/laser_axis_lit_frames.py', '--rigs', '2'], True,
                              "the laser axis from four lit frames per board against two: "
                              "the galvos' per-frame jitter left in its shape error"),
    'extractor_width': (['benchmarks/extractor_width.py'], True,
                        "the flat plate's noise with the stripe filter at the stated width "
                        "and at the stripe's own, the reference rig"),
    'extractor_width_wide': (['benchmarks/extractor_width.py', '--seed', '6'], True,
                             'the same on the family rig of seed 6 (a 1.6 mm laser sheet at '
                             '975 mm: a stripe 2.5 times the stated width)'),
    'materials': (['benchmarks/materials.py'], False,
                  'stair, plate and outliers per material, countermeasures off and on'),
    'materials_graph': (['-m', 'galvoscan.cli', 'evaluate', '--materials', '--quick',
                         '--truth-calibration', '--out', 'out/materials_graph'], False,
                        'every material through the graph, each countermeasure off and on '
                        '(the true parameters as calibration)'),
    'operator_stages': (['benchmarks/operator_stages.py', '--seed', '1'], False,
                        "each calibration stage's errors with a person's imprecision and "
                        'with exact placements, quick plans, in one process'),
    'calibration_chain': (['benchmarks/calibration_chain.py'], False,
                          'the whole calibration chain in-process, quick and full plans'),
    'camera_trigger': (['benchmarks/camera_trigger.py'], False,
                       'frames paired with the board\'s trigger events, faults injected'),
    'pipeline': (['benchmarks/pipeline.py'], False,
                 'frames lost and latency through extractor and reconstructor at 500/1000 fps'),
    'calibration_seeds': (['benchmarks/calibration_seeds.py'], False,
                          'two seeds of one rig against their stated uncertainty'),
    'uncertainty_check': (['benchmarks/uncertainty_check.py', '--rigs', '10'], False,
                          'predicted uncertainty against the measured error, drawn rigs'),
    'rig_family': (['benchmarks/rig_family.py', '--rigs', '20', '--distances', 'none',
                    '--jobs', '2', '--resume'], False,
                   'drawn rigs calibrated and evaluated through the graph, at their own '
                   'working distance'),
    'operator_family': (['benchmarks/rig_family.py', '--operator', '--reference-rig', '--rigs',
                         '10', '--repeats', '3', '--distances', 'none', '--out',
                         'out/operator_family', '--jobs', '2', '--resume'], False,
                        'the reference rig and drawn rigs calibrated through the simulated '
                        'operator, against the zero-error operator'),
    'joint_bundle': (['benchmarks/joint_bundle.py'], False,
                     'one bundle over camera and laser against the staged calibration'),
    'hosts_apart': (['benchmarks/hosts_apart.py'], False,
                    'the image path across a network link (root: network namespaces)'),
}
ACCURACY = ('rig_family', 'operator_family', 'operator_stages', 'uncertainty_check',
            'calibration_seeds', 'joint_bundle', 'materials', 'materials_graph', 'stripe_tilt',
            'stripe_tilt_speckle', 'extractor_width', 'extractor_width_wide', 'twin_evaluate',
            'laser_axis_lit_frames')

#: metrics.json keys shown on the accuracy page, with the paper's figure where it gives one
DEMO_ROWS = (
    ('stair_step_error_rmse_mm', 'stair block, 30 mm step: RMSE over 30 positions [mm]', 0.165),
    ('stair_step_error_max_mm', 'stair block: worst position [mm]', None),
    ('plate_flatness_rmse_mm', '740 mm flat plate, edge to edge: RMS from its plane [mm]',
     0.281),
    ('plate_coverage_fraction', 'flat plate: fraction of 20 mm cells covered', None),
    ('sphere_radius_error_mm', 'calibration sphere: radius error [mm]', None),
    ('transfer_matrix_error_rmse_mm', 'dynamic camera transfer-matrix error, 36 positions [mm]',
     1.231),
    ('joint_error_before_mm', 'joint correction: error before [mm]', 4.928),
    ('joint_error_after_mm', 'joint correction: error after [mm]', 0.197),
    ('predicted_uncertainty_mm', 'predicted 1-sigma point error over G1 ±8 V (shape) [mm]', None),
    ('predicted_calibration_uncertainty_mm', '  of which the calibration [mm]', None),
    ('predicted_frame_noise_mm', "  of which the galvos' frame noise [mm]", None),
    ('measured_shape_error_mm', 'measured point error there against the truth [mm]', None),
    ('measured_systematic_error_mm', "the same without the galvos' frame noise [mm]", None),
    ('range_x_mm', 'range covered at the working depth, x [mm]', 1100),
    ('range_y_mm', 'range covered at the working depth, y [mm]', 1300),
    ('cell_extrinsic_error_mm', "the scanner's pose in its cell: position error [mm]", None),
)
#: the demo's calibration through the simulated operator, per stage (metrics.json `operator`)
DEMO_OPERATOR = (('placements', 'placements made (retakes included)'),
                 ('placements_kept', 'placements kept'),
                 ('instructions', 'instructions given'),
                 ('search_views', 'search views'),
                 ('views_rejected', 'views rejected'),
                 ('wall_s', 'capture and compute [s]'))
DEMO_PLOTS = ('plate_deviation_map.png', 'stair_error_by_distance.png', 'uncertainty_map.png')


def machine() -> dict:
    cpu = ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return {'cpu': cpu, 'cores': os.cpu_count(), 'system': platform.platform(),
            'python': platform.python_version(), 'load_average': [round(x, 2) for x in
                                                                   os.getloadavg()]}


def commit() -> str:
    try:
        rev = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=ROOT, text=True,
                             capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', 'src', 'benchmarks',
                                'msgs'], cwd=ROOT, text=True, capture_output=True).stdout
        return rev + ('+changes' if dirty.strip() else '')
    except (OSError, subprocess.CalledProcessError):
        return 'unknown'


def now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')


def last_json(stdout: str) -> dict:
    for line in reversed(stdout.strip().splitlines()):
        line = line.strip()
        if line.startswith('{'):
            return json.loads(line)
    raise ValueError('no JSON object on the last lines of its output')


def load_store() -> dict:
    if STORE.exists():
        return json.loads(STORE.read_text())
    return {'demo': None, 'benchmarks': {}}


def save_entry(section: str, entry: dict, name: str | None = None) -> dict:
    """Write one entry into results.json as it is on disk now (another run may have written
    its own entry meanwhile); the store as written."""
    store = load_store()
    if name is None:
        store[section] = entry
    else:
        store.setdefault(section, {})[name] = entry
    STORE.write_text(json.dumps(store, indent=1) + '\n')
    return store


def run_benchmark(name: str) -> dict:
    """Run benchmark ``name``; its entry (the result, or the error it ended with)."""
    args, _, _ = BENCHMARKS[name]
    command = '.venv/bin/python ' + ' '.join(args)
    print(f'[results] {command}', flush=True)
    t0 = time.monotonic()
    # the benchmark's progress lines are shown as they come (a long run reports each step)
    with subprocess.Popen([PY, *args], cwd=ROOT, text=True, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE) as proc:
        err = []
        reader = threading.Thread(target=lambda: err.extend(proc.stderr), daemon=True)
        reader.start()
        out = []
        for line in proc.stdout:
            out.append(line)
            print(f'[{name}] {line}', end='', flush=True)
        proc.wait()
        reader.join()
    entry = {'command': command, 'date': now(), 'commit': commit(), 'machine': machine(),
             'wall_s': round(time.monotonic() - t0, 1)}
    try:
        if proc.returncode != 0:
            raise ValueError(f"exit code {proc.returncode}: "
                             f"{_failure_reason(args, ''.join(err))}")
        entry['result'] = last_json(''.join(out))
    except ValueError as exc:
        entry['error'] = str(exc)
        print(f'[results] {name}: not measured: {exc}', flush=True)
    return entry


def _failure_reason(args: list[str], stderr: str) -> str:
    """Why a run failed: the stage and message `galvoscan evaluate` leaves in its output
    folder's failure.json, else the end of its stderr."""
    if '--out' in args[:-1]:
        try:
            failure = json.loads((ROOT / args[args.index('--out') + 1] / 'failure.json')
                                 .read_text())
            return f"stage {failure.get('stage') or '?'}: {failure.get('message')}"
        except (OSError, ValueError, AttributeError):
            pass
    return stderr.strip()[-400:]


def record_demo(out: Path, command: str, wall_s: float | None) -> dict:
    metrics = json.loads((out / 'metrics.json').read_text())
    entry = {'command': command, 'date': now(), 'commit': commit(), 'machine': machine(),
             'wall_s': wall_s, 'metrics': metrics, 'plots': []}
    for plot in DEMO_PLOTS:
        if (out / plot).exists():
            shutil.copyfile(out / plot, RESULTS / plot)
            entry['plots'].append(plot)
    return entry


def attach_rows(entry: dict | None, rigs_json: Path) -> dict:
    """The stored rig-family entry with the rows of its run's ``rigs.json``, each with its
    verdict by benchmarks/rig_family.py's own rule."""
    if not entry or 'result' not in entry:
        raise ValueError('no rig_family result is stored to attach rows to')
    rows = json.loads(rigs_json.read_text())
    if not isinstance(rows, list) or not all(isinstance(r, dict) and 'seed' in r for r in rows):
        raise ValueError('not a rigs.json of benchmarks/rig_family.py (a list of rigs)')
    spec = importlib.util.spec_from_file_location('rig_family', ROOT / 'benchmarks' /
                                                  'rig_family.py')
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = {**entry['result'], 'rows': [{**r, 'passed': bench._passes(r)} for r in rows]}
    seeds = len({r['seed'] for r in rows})
    if seeds != result.get('rigs', seeds):
        raise ValueError(f"{seeds} rigs in the file, but the stored run had "
                         f"{result.get('rigs')}")
    return {**entry, 'result': result, 'rows_from': str(rigs_json)}


def _fmt(v) -> str:
    if v is None:
        return '–'
    if isinstance(v, float) and v != v:
        return 'n/a'
    if isinstance(v, float):
        return f'{v:.4g}' if abs(v) < 1e4 else f'{v:.0f}'
    if isinstance(v, (list, dict)):
        return '`' + json.dumps(v)[:200] + '`'
    return str(v)


def _provenance(e: dict) -> list[str]:
    m = e['machine']
    wall = f", {e['wall_s']:.0f} s" if e.get('wall_s') else ''
    return [f"- command: `{e['command']}`",
            f"- date: {e['date']}, commit `{e['commit']}`{wall}",
            f"- machine: {m['cpu'] or 'unknown CPU'}, {m['cores']} cores, {m['system']}, "
            f"Python {m['python']}, load average {', '.join(map(str, m['load_average']))}"]


def _anchor(name: str) -> str:
    """The link target of a section: guides link ``accuracy.md#NAME`` to quote its figures."""
    return f'<a id="{name}"></a>'


def _benchmark_section(name: str, e: dict | None) -> list[str]:
    args, quick, what = BENCHMARKS[name]
    lines = [_anchor(name), f'### `{name}`: {what}', '']
    if e is None:
        lines += ['Not measured yet. Run '
                  f"`.venv/bin/python tools/gen_results.py --only {name}` "
                  f"(`.venv/bin/python {' '.join(args)}`"
                  + ('' if quick else ', a long run') + ').', '']
        return lines
    lines += _provenance(e) + ['']
    if 'error' in e:
        # on one line: a log's lines would break the page's layout
        return lines + [f"Not measured: the run failed ({' '.join(e['error'].split())}).", '']
    return lines + RENDERERS.get(name, _figures)(e['result']) + ['']


def _figures(result: dict, skip=()) -> list[str]:
    """Every figure of a result as a ``figure | value`` row (nested keys as ``a.b``)."""
    rows = {k: v for k, v in _flat(result).items() if k.split('.')[0] not in skip}
    if not rows:
        return []
    return ['| figure | value |', '|---|---|'] + [f'| `{k}` | {_fmt(v)} |'
                                                  for k, v in rows.items()]


def _table(header, rows) -> list[str]:
    """A Markdown table; cells that are not text are formatted as figures."""
    return (['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
            + ['| ' + ' | '.join(c if isinstance(c, str) else _fmt(c) for c in r) + ' |'
               for r in rows])


def _yes(v) -> str:
    return 'yes' if v else 'no'


def _build(b: dict | None) -> str:
    if not b:
        return '–'
    return (f"{b.get('sensor')}, {b.get('bit_depth')} bit, {b.get('head')}, "
            f"laser {b.get('laser')}")


def _failure(row: dict) -> str:
    f = (row.get('failures') or [{}])[0]
    where = f" at {f['distance']} mm" if f.get('distance') else ''
    return f"failed{where}: {f.get('stage') or '?'}"


#: figures of the family's summary shown as median / p90 / max, with their labels
FAMILY_STATS = (('stair_rmse_mm', 'stair step error RMSE [mm]'),
                ('plate_rmse_mm', 'plate flatness RMSE [mm]'),
                ('plate_range_scaled_rmse_mm', 'plate flatness, scaled with depth [mm]'),
                ('sphere_radius_error_mm', 'sphere radius error [mm]'),
                ('transfer_matrix_error_rmse_mm', 'transfer-matrix error RMSE [mm]'),
                ('predicted_uncertainty_mm', 'predicted uncertainty [mm]'),
                ('measured_shape_error_mm', 'measured shape error [mm]'))


def _rig_family(r: dict) -> list[str]:
    """Per rig (when the run recorded its rows), the build counts, then the summary."""
    lines = []
    rows = r.get('rows')
    both = len({x.get('model') for x in rows or []}) > 1  # --model both: each rig twice
    if rows:
        lines += ['Per rig (pass: stair <= 0.165 mm and plate <= 0.281 mm at its own working '
                  'distance, the paper\'s figures):', '']
        lines += _table(
            ('seed', 'build: sensor, bit depth, head, laser side', 'working distance [mm]',
             'stair [mm]', 'plate [mm]', 'transfer [mm]', 'pass'),
            [(str(x.get('seed')) + (f" ({x.get('model')})" if both else ''),
              _build(x.get('build')), x.get('working_distance_mm'),
              x.get('stair_rmse_mm'), x.get('plate_rmse_mm'),
              x.get('transfer_matrix_error_rmse_mm'),
              _yes(x.get('passed')) if x.get('completed') else _failure(x))
             for x in rows]) + ['']
    else:
        lines += ['The run recorded no per-rig rows (its `rigs.json` holds them).', '']
    builds = r.get('builds') or {}
    if builds:
        lines += ['Rigs per build kind:', '']
        lines += _table(('kind', 'value', 'drawn', 'completed', 'passed'),
                        [(kind, str(value), c.get('drawn'), c.get('completed'), c.get('passed'))
                         for kind, counts in builds.items() for value, c in counts.items()])
        lines += ['']
    lines += [f"Summary: {r.get('rigs')} rigs, {r.get('completed')} completed, "
              f"{r.get('passed')} passed, {r.get('at_family_level')} at the family's level "
              "(stair <= 0.05 mm and plate <= 0.12 mm); "
              f"{r.get('distances_finite')} with a finite stair figure at every re-set "
              'distance asked.', '']
    stats = [(label, r.get(f'{k}_median'), r.get(f'{k}_p90'), r.get(f'{k}_max'))
             for k, label in FAMILY_STATS if f'{k}_median' in r]
    if stats:
        lines += _table(('figure', 'median', 'p90', 'max'), stats) + ['']
    shown = {'rows', 'builds', 'rigs', 'completed', 'passed', 'at_family_level',
             'distances_finite', *(f'{k}_{s}' for k, _ in FAMILY_STATS
                                   for s in ('median', 'p90', 'max'))}
    rest = _figures(r, skip=shown)
    return lines + (['Every other figure of the run:', ''] + rest if rest else [])


def _operator_family(r: dict) -> list[str]:
    """Per rig the operator against the zero-error operator, placements per stage, summary."""
    rows = r.get('rows') or []
    limit = r.get('ratio_limit')
    repeats = r.get('repeats') or 1
    each = (f', each the mean of {repeats} runs (the same drawn rig, the simulator\'s noise '
            'and the operator\'s errors drawn from another seed each run)' if repeats > 1
            else '')
    lines = [f'Per rig: stair and plate errors [mm] calibrated through the simulated operator '
             f'and through the zero-error operator{each}, and their ratios (limit '
             f'{_fmt(limit)}):', '']
    lines += _table(
        ('rig', 'stair', 'stair, zero-error', 'stair ratio', 'plate', 'plate, zero-error',
         'plate ratio', f'within {_fmt(limit)}'),
        [(str(x.get('rig')), x.get('stair_mm'), x.get('stair_exact_mm'), x.get('stair_ratio'),
          x.get('plate_mm'), x.get('plate_exact_mm'), x.get('plate_ratio'),
          (_yes(limit is not None and all(x.get(k) is not None and x[k] <= limit
                                          for k in ('stair_ratio', 'plate_ratio')))
           if x.get('completed') else _failure(x)))
         for x in rows]) + ['']
    lines += _ratio_intervals(r, rows, limit)
    if any(x.get('calibration_sigma_mm') is not None for x in rows):
        lines += ["Each calibration's predicted uncertainty (its own covariance over G1's "
                  'range, 1 sigma) and its measured error against the truth [mm]: one run\'s '
                  'stair and plate errors are one draw of that spread, so where the two '
                  'measured errors differ by more than the predictions do, the ratios above '
                  'are chance:', '']
        lines += _table(
            ('rig', 'predicted', 'predicted, zero-error', 'predicted ratio', 'measured',
             'measured, zero-error'),
            [(str(x.get('rig')), x.get('calibration_sigma_mm'),
              x.get('calibration_sigma_exact_mm'), x.get('calibration_sigma_ratio'),
              x.get('calibration_error_mm'), x.get('calibration_error_exact_mm'))
             for x in rows]) + ['']
    stages = list(dict.fromkeys(s for x in rows for s in (x.get('placements') or {})))
    if stages:
        lines += ["Placements each stage took under the operator (retakes included):", '']
        lines += _table(('rig', *stages),
                        [(str(x.get('rig')), *((x.get('placements') or {}).get(s)
                                               for s in stages)) for x in rows]) + ['']
    lines += [f"Summary: {r.get('rigs')} rigs, {r.get('completed')} completed both ways; "
              f"largest ratio {_fmt(r.get('stair_ratio_max'))} (stair) and "
              f"{_fmt(r.get('plate_ratio_max'))} (plate) against the limit {_fmt(limit)}; "
              + (f"largest ratio of predicted calibration uncertainties "
                 f"{_fmt(r.get('calibration_sigma_ratio_max'))}; "
                 if r.get('calibration_sigma_ratio_max') is not None else '')
              + (f"the worst ratio of one operator run to one zero-error run "
                 f"{_fmt(r.get('stair_ratio_single_max'))} (stair) and "
                 f"{_fmt(r.get('plate_ratio_single_max'))} (plate); " if repeats > 1 else '')
              + f"most placements one stage took {_fmt(r.get('placements_max'))}, every stage "
              f"within {r.get('placement_limit')}: "
              f"{_yes(r.get('placements_within_limit'))}.", '']
    rest = _figures(r, skip={'rows', 'rigs', 'completed', 'stair_ratio_max', 'plate_ratio_max',
                             'ratio_limit', 'placements_max', 'placements_within_limit',
                             'placement_limit', 'calibration_sigma_ratio_max', 'repeats',
                             'stair_ratio_single_max', 'plate_ratio_single_max',
                             'ratio_confidence',
                             *(f'{n}_{k}' for n in ('stair', 'plate')
                               for k in ('run_spread', 'run_spread_dof', 'ratio_family',
                                         'ratio_family_interval', 'beyond_limit',
                                         'undecided'))})
    return lines + (['Every other figure of the run:', ''] + rest if rest else [])


def _interval(v) -> str:
    return f'{_fmt(v[0])} to {_fmt(v[1])}' if v else '–'


def _ratio_intervals(r: dict, rows: list, limit) -> list[str]:
    """With repeats: what the runs' own scatter settles about each ratio and the family's."""
    if r.get('stair_run_spread') is None:
        return []
    conf = f"{100 * (r.get('ratio_confidence') or 0):.0f} %"
    lines = [f"How far {r.get('repeats')} runs settle each ratio: one run's error scatters "
             f"between draws by {100 * r['stair_run_spread']:.0f} % (stair) and "
             f"{100 * (r.get('plate_run_spread') or 0):.0f} % (plate), the log's standard "
             f"deviation pooled over every rig and both ways "
             f"({r.get('stair_run_spread_dof')} degrees of freedom). Each ratio's {conf} "
             f"interval follows from it; a rig is within {_fmt(limit)} or beyond it only "
             'where the whole interval is:', '']
    lines += _table(
        ('rig', f'stair ratio, {conf}', 'stair', f'plate ratio, {conf}', 'plate'),
        [(str(x.get('rig')), _interval(x.get('stair_ratio_interval')),
          x.get('stair_verdict') or '–', _interval(x.get('plate_ratio_interval')),
          x.get('plate_verdict') or '–') for x in rows if x.get('completed')]) + ['']
    lines += [f"The family's ratio (the geometric mean over its rigs, the interval from their "
              f"scatter): stair {_fmt(r.get('stair_ratio_family'))} ({conf}: "
              f"{_interval(r.get('stair_ratio_family_interval'))}), plate "
              f"{_fmt(r.get('plate_ratio_family'))} ({conf}: "
              f"{_interval(r.get('plate_ratio_family_interval'))}). Beyond the limit: stair "
              f"{', '.join(r.get('stair_beyond_limit') or []) or 'none'}, plate "
              f"{', '.join(r.get('plate_beyond_limit') or []) or 'none'}; undecided by "
              f"{r.get('repeats')} runs: stair "
              f"{', '.join(r.get('stair_undecided') or []) or 'none'}, plate "
              f"{', '.join(r.get('plate_undecided') or []) or 'none'}.", '']
    return lines


def _materials(r: dict) -> list[str]:
    """The per-material table (outliers in per cent), then the run's summary figures."""
    per = r.get('per_material') or {}
    lines = []
    if per:
        lines += _table(
            ('material, countermeasures', 'stair error RMSE [mm]', 'plate flatness [mm]',
             'outliers [%]', 'coverage', 'own bias [mm]'),
            [(name.replace('_on', ', on').replace('_off', ', off'), m.get('stair_rmse_mm'),
              m.get('plate_flatness_mm'),
              None if m.get('outlier_fraction') is None else 100 * m['outlier_fraction'],
              m.get('coverage'), m.get('material_bias_mm')) for name, m in per.items()])
        lines += ['', 'Summary figures (fractions, not per cent):', '']
    return lines + _figures(r, skip={'per_material'})


def _stripe_tilt(r: dict) -> list[str]:
    angles = r.get('angles') or {}
    lines = [f"{r.get('frames')} frames per angle, speckle "
             f"{'on' if r.get('speckle') else 'off'}:", '']
    return lines + _table(
        ('G2 head turned [deg]', 'stripe off the rows or columns [deg]', 'centres',
         'bias [px]', 'RMS [px]', 'RMS over 0 deg'),
        [(k, a.get('tilt_deg'), a.get('points'), a.get('bias_px'), a.get('rms_px'),
          a.get('rms_ratio_to_0_deg')) for k, a in angles.items()])


def _extractor_width(r: dict) -> list[str]:
    lines = [f"{r.get('frames')} frames of the flat plate on {r.get('rig')}; the stripe's FWHM "
             f"measured at half maximum: {_fmt(r.get('measured_fwhm_px_median'))} px (median; "
             f"{' to '.join(_fmt(x) for x in r.get('measured_fwhm_px_range') or [])} px over "
             'the frames). Points triangulated by the true rig, so the plate RMS is the '
             "extraction's (the exact row: the simulator's exact stripe pixels).", '']
    return lines + _table(
        ('extraction', 'line_width_px stated', 'width used (median) [px]',
         'frames extracted again', 'points', 'plate RMS [mm]', 'time [ms/frame]'),
        [(x.get('extraction'), x.get('line_width_px'), x.get('width_used_px_median'),
          x.get('frames_extracted_again'), x.get('points'), x.get('plate_rms_mm'),
          x.get('ms_per_frame'))
         for x in r.get('rows') or []])


def _operator_stages(r: dict) -> list[str]:
    """Each stage's placements and errors against the truth, person against exact."""
    person = {x['stage']: x for x in r.get('person') or []}
    exact = {x['stage']: x for x in r.get('exact') or []}
    rows = []
    for stage in dict.fromkeys([*person, *exact]):
        a, b = person.get(stage, {}), exact.get(stage, {})
        rows.append((stage, 'placements kept of planned',
                     f"{a.get('kept')} of {a.get('planned')}",
                     f"{b.get('kept')} of {b.get('planned')}"))
        for k in dict.fromkeys([*(a.get('errors') or {}), *(b.get('errors') or {})]):
            rows.append((stage, k, (a.get('errors') or {}).get(k),
                         (b.get('errors') or {}).get(k)))
    lines = [f"Rig {r.get('rig')}, seed {r.get('seed')}, "
             f"{'full' if r.get('full') else 'quick'} plans; errors against the simulator's "
             'truth:', '']
    lines += _table(('stage', 'figure', "a person's imprecision", 'exact placements'), rows)
    off = r.get('sheet_offset_error_mm') or {}
    return lines + ['', f"Laser sheet offset error at the working point: {_fmt(off.get('person'))}"
                    f" mm against {_fmt(off.get('exact'))} mm (ratio {_fmt(r.get('ratio'))})."]


#: sections drawn as tables of their own; every other result is a ``figure | value`` table
RENDERERS = {'rig_family': _rig_family, 'operator_family': _operator_family,
             'materials': _materials, 'stripe_tilt': _stripe_tilt,
             'stripe_tilt_speckle': _stripe_tilt, 'operator_stages': _operator_stages,
             'extractor_width': _extractor_width, 'extractor_width_wide': _extractor_width}


def _flat(d: dict, prefix: str = '') -> dict:
    """Nested figures as ``a.b.c`` keys, so that each gets a row of its own."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


def _demo_operator(op: dict | None) -> list[str]:
    """The demo's own calibration through the simulated operator, per stage."""
    if not op or not op.get('placements'):
        return []
    stages = list(op['placements'])

    def cell(key, stage):
        v = (op.get(key) or {}).get(stage)
        if isinstance(v, dict):  # views rejected, by reason
            return ', '.join(f'{n} {k}' for k, n in v.items()) or '0'
        return v

    lines = ['', _anchor('demo-operator'),
             f"The rig's calibration through the simulated operator (seed {op.get('seed')}), "
             'per stage:', '']
    lines += _table(('', *stages), [(label, *(cell(key, s) for s in stages))
                                    for key, label in DEMO_OPERATOR])
    mistakes = op.get('mistakes_whole_run') or {}
    if mistakes:
        lines += ['', f"The operator's mistakes over the whole run "
                  f"({op.get('placements_whole_run')} placements): "
                  + ', '.join(f'{k.replace("_", " ")} {n}' for k, n in mistakes.items()) + '.']
    return lines


def render(store: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    banner = ('<!-- Written by tools/gen_results.py (`make results`) from results.json; do not '
              'edit by hand. -->')
    # accuracy
    lines = ['# Accuracy', '', banner, '',
             'Every figure here was measured on the simulated rig by the command named with it; '
             'no real rig has been measured yet. What each figure means: '
             '[evaluation.md](../evaluation.md).', '', _anchor('demo'),
             '## The demo: the reference rig', '']
    demo = store.get('demo')
    if demo is None:
        lines += ['Not measured yet: run `make results` (or `make demo`, then '
                  '`.venv/bin/python tools/gen_results.py --demo-out out`).', '']
    else:
        metrics = demo['metrics']
        lines += _provenance(demo) + ['']
        paper = metrics.get('paper_method') or {}
        lines += ['| figure | galvoscan (physical model) | paper\'s method on the same rig | '
                  'the paper reports |', '|---|---|---|---|']
        for key, label, reported in DEMO_ROWS:
            if key not in metrics:
                continue
            lines.append(f'| {label} | {_fmt(metrics.get(key))} | {_fmt(paper.get(key))} | '
                         f'{_fmt(reported)} |')
        by_distance = metrics.get('stair_step_error_rmse_mm_by_distance')
        if isinstance(by_distance, dict) and by_distance:
            keys = list(by_distance)
            lines += ['', 'Stair step error by working distance, the rig re-set and calibrated '
                      'there [mm]:', '', '| distance [mm] | ' + ' | '.join(keys) + ' |',
                      '|---|' + '---|' * len(keys),
                      '| RMSE | ' + ' | '.join(_fmt(by_distance[k]) for k in keys) + ' |']
        lines += _demo_operator(metrics.get('operator'))
        lines += ['', "The whole `metrics.json` of this run: [demo_metrics.json]"
                  "(demo_metrics.json).", '']
        (RESULTS / 'demo_metrics.json').write_text(json.dumps(metrics, indent=2) + '\n')
        for plot in demo.get('plots', []):
            lines += [f'![{plot[:-4].replace("_", " ")}]({plot})', '']
    lines += ['## Benchmarks over many rigs', '']
    for name in ACCURACY:
        lines += _benchmark_section(name, store['benchmarks'].get(name))
    (RESULTS / 'accuracy.md').write_text('\n'.join(lines).rstrip() + '\n')

    # performance
    lines = ['# Performance', '', banner, '',
             'Timings from `benchmarks/`, each run by the command named with it; the machine it '
             'ran on and how loaded it was are part of each figure. Where a benchmark measures '
             'a reference in the same run, its `ratio` compares the two.', '']
    for name in BENCHMARKS:
        if name not in ACCURACY:
            lines += _benchmark_section(name, store['benchmarks'].get(name))
    (RESULTS / 'performance.md').write_text('\n'.join(lines).rstrip() + '\n')

    index = ['- [the demo: the reference rig](accuracy.md#demo), and '
             '[its calibration through the simulated operator](accuracy.md#demo-operator)']
    for name in (*ACCURACY, *(n for n in BENCHMARKS if n not in ACCURACY)):
        page = 'accuracy.md' if name in ACCURACY else 'performance.md'
        measured = store['benchmarks'].get(name)
        when = (f" ({measured['date']})" if measured and 'error' not in measured
                else ' (not measured yet)')
        index.append(f'- [`{name}`]({page}#{name}): {BENCHMARKS[name][2]}{when}')
    (RESULTS / 'README.md').write_text('\n'.join([
        '# Results', '', banner, '',
        '- [Accuracy](accuracy.md): the demo on the simulated reference rig, and the benchmarks '
        'over many drawn rigs.',
        '- [Performance](performance.md): the timing benchmarks.', '',
        'Regenerate with `make results` (the demo and the benchmarks that take about a minute '
        'or less); `.venv/bin/python tools/gen_results.py --long` also runs the long ones, '
        '`--only NAME[,NAME]` one or a few. A guide that quotes a figure links the section that '
        'holds it (`accuracy.md#NAME`); `tests/test_doc_figures.py` checks that the figure is '
        'there.', '', '## Sections', '', *index, '']))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--long', action='store_true', help='also the long benchmarks')
    p.add_argument('--only', help='comma-separated benchmark names (and/or "demo")')
    p.add_argument('--demo-out', type=Path,
                   help='record this finished demo run instead of running the demo')
    p.add_argument('--render', action='store_true', help='only rewrite the pages')
    p.add_argument('--attach-rows', metavar='FILE',
                   help="with --only rig_family: add the per-rig rows of that run's rigs.json "
                        '(with the benchmark\'s own pass rule) to the stored result of a run '
                        'whose last line had none, and rewrite the pages')
    args = p.parse_args(argv)
    store = load_store()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.attach_rows:
        if args.only != 'rig_family':
            p.error('--attach-rows goes with --only rig_family')
        try:
            store = save_entry('benchmarks', attach_rows(store['benchmarks'].get('rig_family'),
                                                         Path(args.attach_rows)), 'rig_family')
        except (OSError, ValueError, KeyError) as exc:
            p.error(f'--attach-rows {args.attach_rows}: {exc}')
    elif not args.render:
        wanted = (args.only.split(',') if args.only else
                  ['demo', *(n for n, (_, quick, _) in BENCHMARKS.items()
                             if quick or args.long)])
        unknown = set(wanted) - set(BENCHMARKS) - {'demo'}
        if unknown:
            p.error(f"unknown: {', '.join(sorted(unknown))}; known: demo, "
                    f"{', '.join(BENCHMARKS)}")
        if args.demo_out:
            store = save_entry('demo', record_demo(args.demo_out, 'make demo', None))
        elif 'demo' in wanted:
            out = ROOT / 'build' / 'results_demo'
            # the demo's main job, and the paper's method calibrated again on the same rig
            # for the comparison column (the re-set distances are `galvoscan evaluate`'s)
            evaluate = ['evaluate', '--out', str(out.relative_to(ROOT)), '--distances', 'none']
            command = '.venv/bin/galvoscan ' + ' '.join(evaluate)
            print(f'[results] {command}', flush=True)
            t0 = time.monotonic()
            rc = subprocess.run([str(Path(PY).with_name('galvoscan')), *evaluate],
                                cwd=ROOT).returncode
            if rc != 0:
                print(f'[results] the evaluation failed (exit code {rc}); its page is unchanged')
            else:
                store = save_entry('demo', record_demo(out, command,
                                                       round(time.monotonic() - t0, 1)))
        for name in wanted:
            if name != 'demo':
                store = save_entry('benchmarks', run_benchmark(name), name)
    render(store)
    print(f'[results] wrote {os.path.relpath(RESULTS, ROOT)}/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
