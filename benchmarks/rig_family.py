"""Drawn rigs of the family, each calibrated and evaluated through the graph.

Run: ``.venv/bin/python benchmarks/rig_family.py [--rigs 20] [--seed-start 0] [--quick]
[--out DIR] [--timeout S] [--jobs N] [--resume]
[--operator [--reference-rig] [--repeats N]]
[--distances MM,..|none]``

A full-plan rig takes 6 to 10 minutes on two cores: ``--jobs 2`` evaluates two rigs at once
(each graph in a ROS domain of its own), and ``--resume`` lets a stopped run go on where it
stopped, reusing the rigs completed on the same source tree with the same arguments.

For each seed from ``--seed-start``: ``galvoscan_sim.rig_family.draw_rig(seed)`` (a rig of
the family, at a working distance drawn in 100..1000 mm) is written to
``DIR/seed_NNN/rig.yaml`` and ``galvoscan evaluate --rig`` runs on it in a process of its
own: the graph is brought up, every calibration stage runs through the calibration node
(full plans; quick with ``--quick``), the scenes are scanned around the rig's working
point, and the by-distance evaluation re-sets, calibrates and scans the rig at each of the
paper's six distances. A rig that fails (a stage, a crash, the timeout) is recorded and the
next one runs.

A rig's recorded calibration bags (``calibration_data`` folders, 0.37 GB a rig and model)
are deleted once it has passed, unless ``--keep-bags``; a rig that did not pass keeps them
to be looked into. Metrics, reports, plots, logs and calibrations are always kept.

One progress line per rig. At the end: the completion and pass rates (pass: completed, stair
RMSE <= 0.165 mm and plate RMSE <= 0.281 mm at the rig's own distance, a finite stair figure
at every distance), median / p90 / max of the stair, plate, sphere-radius and
transfer-matrix errors, and which stage failed on which rig (and at which distance). Times
are wall-clock on a shared machine. The last line of stdout is one JSON object.

``--operator``: every rig (and the reference rig first, with ``--reference-rig``) is
evaluated twice, both times calibrated through the simulated operator
(:mod:`galvoscan.operator`, seeded by the rig's seed): once with a person's imprecision and
mistakes, once with the zero-error operator (``evaluate --exact-operator``: every target
exactly where asked). Per rig it prints both stair and plate errors and their ratios
(operator over zero-error), and the placements each stage took; the last line's JSON
holds ``rigs``, ``completed`` (rigs where both runs completed), ``stair_ratio_max``,
``plate_ratio_max``, ``placements_max`` (most placements one stage took, retakes
included), ``placements_within_limit`` (every stage took at most
:data:`PLACEMENT_FACTOR` x its kept placements plus :data:`PLACEMENT_SLACK`),
``calibration_sigma_ratio_max`` and the rows. With ``--repeats N`` each rig runs N times
each way: the same rig, with the simulator's noise and the operator's errors drawn from
another ``evaluate --seed`` each time (:data:`REPEAT_SEED_STEP`; a run with the same seed
repeats its calibration exactly). The ratios are then of the mean errors, and
``stair_ratio_single_max`` and ``plate_ratio_single_max`` give the worst ratio of one
operator run to one zero-error run. The runs' own scatter says how far that settles
the limit (:func:`ratio_statistics`): each rig's ratio gets a 90 % interval and a verdict
(``within``, ``beyond`` or ``undecided``), and the summary gives the family's geometric-mean
ratio with its interval, ``stair_beyond_limit`` and ``stair_undecided`` (and the plate's).
Each row also carries both runs' predicted
calibration uncertainty (the calibration's own covariance over G1's range) and their
measured calibration error against the truth: the stair and plate errors of one run are one
draw of the calibration's random error, so their ratio scatters from run to run by about as
much as the two measured errors differ, while the predicted ratio says whether the
operator's placements left the calibration less determined.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

from galvoscan_common.runtime import RUN_DOMAINS
from galvoscan_sim.rig_family import build_of, draw_rig, working_distance
from reconstructor.uncertainty import prediction_summary

#: The issue's acceptance thresholds at a rig's own distance [mm] (the paper's figures).
STAIR_LIMIT_MM = 0.165
PLATE_LIMIT_MM = 0.281
#: The family's own level [mm]: every build kind (sensor, bit depth, head, laser side) at
#: its own distance; ``at_family_level`` counts the rigs that completed within both.
FAMILY_STAIR_LIMIT_MM = 0.05
FAMILY_PLATE_LIMIT_MM = 0.12
DISTANCES = ('100', '200', '350', '400', '650', '1000')
#: With ``--operator``: the stated bound on the placements one stage takes, retakes and
#: re-placements included: this many times the placements it kept, plus the slack.
PLACEMENT_FACTOR = 2.0
PLACEMENT_SLACK = 2
#: The operator's stair and plate errors may be this many times the zero-error operator's.
OPERATOR_RATIO_LIMIT = 1.25
#: ``--repeats``: repeat r of a rig evaluates it with ``evaluate --seed`` = its seed + r x
#: this (a run is repeatable: the same rig and seed give the same calibration, draw for draw).
REPEAT_SEED_STEP = 100_000
#: ``--repeats``: the two-sided confidence of each ratio's interval (0.90: its upper end is
#: a 95 % one-sided bound, the side the limit is about).
RATIO_CONFIDENCE = 0.90
FIGURES = (  # (metrics key, short name, absolute value)
    ('stair_step_error_rmse_mm', 'stair_rmse_mm', False),
    ('plate_flatness_rmse_mm', 'plate_rmse_mm', False),
    ('plate_flatness_rmse_mm_range_scaled', 'plate_range_scaled_rmse_mm', False),
    ('sphere_radius_error_mm', 'sphere_radius_error_mm', True),
    ('transfer_matrix_error_rmse_mm', 'transfer_matrix_error_rmse_mm', False),
    ('predicted_uncertainty_mm', 'predicted_uncertainty_mm', False),
    ('measured_shape_error_mm', 'measured_shape_error_mm', False),
    ('uncertainty_ratio', 'uncertainty_ratio', False),
    ('uncertainty_within_2x_probability', 'uncertainty_within_2x_probability', False),
    ('predicted_calibration_uncertainty_mm', 'predicted_calibration_uncertainty_mm', False),
    ('predicted_frame_noise_mm', 'predicted_frame_noise_mm', False),
    ('measured_systematic_error_mm', 'measured_systematic_error_mm', False),
    ('uncertainty_ratio_calibration', 'uncertainty_ratio_calibration', False),
    ('uncertainty_calibration_within_2x_probability',
     'uncertainty_calibration_within_2x_probability', False),
    ('uncertainty_modes_effective', 'uncertainty_modes_effective', False),
)
#: The predicted uncertainty is honest on a rig when it is within this factor of the error
#: measured against the truth (on at least 80 % of the rigs).
UNCERTAINTY_FACTOR = 2.0


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def source_tree() -> str | None:
    """The git tree of ``src/`` (the code a rig's figures come from), or None when it has
    uncommitted changes or is not in git: then no earlier rig's result is reused."""
    root = Path(__file__).resolve().parents[1]
    try:
        tree = subprocess.run(['git', 'rev-parse', 'HEAD:src'], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', 'src'], cwd=root,
                               text=True, capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return None if dirty else tree


def run_rig(seed: int, folder: Path, quick: bool, timeout: float,
            model: str = 'physical', extra=(), rig_name: str | None = None,
            resume: bool = False, domain: int | None = None,
            sim_seed: int | None = None) -> dict:
    """Draw rig ``seed`` (or use the shipped rig ``rig_name``) and evaluate it with the extra
    ``evaluate`` arguments; never raises (a failure is recorded). ``evaluate --seed`` (the
    simulator's noise and the simulated operator's errors) is ``sim_seed``, default ``seed``.

    The row is kept in ``folder/row.json`` with what it was measured with (the source tree,
    the plans, the model and the arguments). With ``resume``, a completed row measured with
    the same is returned as it is instead of evaluating the rig again, so that a long run
    that was stopped goes on where it stopped. ``domain``: the graph's ROS domain (evaluate
    draws a private one when None)."""
    key = {'src': source_tree(), 'quick': bool(quick), 'model': model, 'extra': list(extra),
           'rig': rig_name, 'seed': seed}
    if sim_seed is not None:
        key['sim_seed'] = sim_seed
    cached = _read_json(folder / 'row.json') if resume and key['src'] else None
    if cached and cached.get('key') == key and cached.get('row', {}).get('completed'):
        return {**cached['row'], 'resumed': True}
    row = _evaluate_rig(seed, folder, quick, timeout, model, extra, rig_name, domain,
                        sim_seed)
    try:
        (folder / 'row.json').write_text(json.dumps({'key': key, 'row': row}, indent=1,
                                                    default=float))
    except OSError:
        pass
    return row


def _evaluate_rig(seed, folder, quick, timeout, model, extra, rig_name, domain,
                  sim_seed=None) -> dict:
    t0 = time.monotonic()
    row = {'seed': seed, 'completed': False, 'failures': []}
    if sim_seed is not None:
        row['sim_seed'] = sim_seed
    if _STOP.is_set():
        return _stopped(row, t0)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if rig_name is not None:
            from galvoscan_sim.config import read_yaml_file
            from galvoscan_sim.rig import RIG_DIR

            description = read_yaml_file(RIG_DIR / f'{rig_name}.yaml')
            row['rig'] = rig_name
        else:
            description = draw_rig(seed)
        row['working_distance_mm'] = working_distance(description) * 1e3
        row['build'] = build_of(description)
        rig_path = folder / 'rig.yaml'
        rig_path.write_text(yaml.safe_dump(description, sort_keys=False))
    except (ValueError, RuntimeError, OSError) as exc:
        row['failures'].append({'distance': None, 'stage': 'draw', 'message': str(exc)})
        row['wall_s'] = time.monotonic() - t0
        return row
    out = folder / 'evaluation'
    argv = [sys.executable, '-m', 'galvoscan.cli', 'evaluate', '--rig', str(rig_path),
            '--out', str(out), '--seed', str(seed if sim_seed is None else sim_seed),
            '--model', model, '--no-paper-method'] \
        + (['--quick'] if quick else []) + list(extra)
    env = os.environ.copy()
    if domain is not None:
        env['ROS_DOMAIN_ID'] = str(domain)
    with open(folder / 'evaluate.log', 'w') as log, _RUNNING_LOCK:
        if _STOP.is_set():
            return _stopped(row, t0)
        proc = _start(argv, log, env)
        _RUNNING.add(proc)
    try:
        rc = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        rc = None
    finally:
        with _RUNNING_LOCK:
            _RUNNING.discard(proc)
    if _STOP.is_set() and rc != 0:
        return _stopped(row, t0)
    row['wall_s'] = time.monotonic() - t0
    metrics = _read_json(out / 'metrics.json')
    if rc != 0 or metrics is None:
        failure = _read_json(out / 'failure.json') or {}
        row['failures'].append({
            'distance': None, 'stage': failure.get('stage'),
            'message': failure.get('message') or (
                f'timed out after {timeout:.0f} s' if rc is None
                else f'exit status {rc}, see {folder / "evaluate.log"}')})
        return row
    row['completed'] = True
    row['distances'] = _distances_asked(extra)
    for key, name, absolute in FIGURES:
        v = metrics.get(key)
        row[name] = abs(v) if absolute and _finite(v) else v
    row['by_distance_mm'] = metrics.get('stair_step_error_rmse_mm_by_distance', {})
    row['operator'] = metrics.get('operator')
    details = _read_json(out / 'details.json') or {}
    for mm, d in (details.get('stair_by_distance') or {}).items():
        if d.get('error_mm') is None:
            row['failures'].append({'distance': mm, 'stage': d.get('failed_stage'),
                                    'message': d.get('reason', '').removeprefix(
                                        'not measured: ')})
    return row


#: Set when the run is asked to stop (Ctrl-C, SIGTERM): no rig starts after it, the running
#: evaluations are stopped, and the rigs finished so far are summarised.
_STOP = threading.Event()
_RUNNING: set = set()
_RUNNING_LOCK = threading.Lock()


def _start(argv, log, env) -> subprocess.Popen:
    """One rig's ``galvoscan evaluate``, its output to ``log``."""
    return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)


def _stopped(row: dict, t0: float) -> dict:
    row.update(stopped=True, wall_s=time.monotonic() - t0)
    row['failures'].append({'distance': None, 'stage': None,
                            'message': 'not evaluated to the end: the run was stopped'})
    return row


def stop_run(*_) -> None:
    """Stop the run: no further rig starts, and the running evaluations get Ctrl-C (each
    stops its graph)."""
    if _STOP.is_set():
        return
    _STOP.set()
    print('\nstopping: the rigs finished so far are summarised', flush=True)
    with _RUNNING_LOCK:
        for proc in _RUNNING:
            proc.send_signal(signal.SIGINT)


def finished_rows(rows) -> list[dict]:
    """The rows of rigs evaluated to the end (not stopped part-way by :func:`stop_run`)."""
    return [r for r in rows if r is not None and not r.get('stopped')]


def run_many(specs, jobs: int, done=None) -> list[dict]:
    """``run_rig(**spec)`` for every spec, ``jobs`` at a time (each evaluation is a graph of
    its own in a ROS domain of its own); the rows in the specs' order. ``done(i, row)`` is
    called as each finishes."""
    domains = random.Random(len(specs)).sample(range(RUN_DOMAINS[0], RUN_DOMAINS[1] + 1),
                                              max(jobs, 1))
    rows = [None] * len(specs)
    slots = list(domains)
    lock = threading.Lock()

    def one(i):
        with lock:
            domain = slots.pop()
        try:
            row = run_rig(**specs[i], domain=domain if jobs > 1 else None)
        finally:
            with lock:
                slots.append(domain)
        rows[i] = row
        if done is not None:
            with lock:
                done(i, row)
        return row

    with ThreadPoolExecutor(max_workers=max(jobs, 1)) as pool:
        list(pool.map(one, range(len(specs))))
    return rows


def drop_bags(folder: Path) -> int:
    """Delete the ``calibration_data`` folders (recorded bags) under ``folder``; bytes freed."""
    freed = 0
    for data in sorted(Path(folder).rglob('calibration_data')):
        if data.is_dir() and not data.is_symlink():
            freed += sum(f.stat().st_size for f in data.rglob('*') if f.is_file())
            shutil.rmtree(data)
    return freed


def build_counts(rows) -> dict:
    """Rigs (drawn, completed, passed) per build kind: bit depth, sensor class, head class,
    laser side."""
    out = {}
    for kind in ('bit_depth', 'sensor', 'head', 'laser'):
        counts = {}
        for r in rows:
            if 'build' not in r:
                continue
            c = counts.setdefault(str(r['build'].get(kind)),
                                  {'drawn': 0, 'completed': 0, 'passed': 0})
            c['drawn'] += 1
            c['completed'] += bool(r['completed'])
            c['passed'] += _passes(r)
        out[kind] = dict(sorted(counts.items()))
    return out


def _distances_asked(extra) -> tuple[str, ...]:
    """The re-set distances [mm] an ``evaluate`` argument list asks for (the paper's six
    unless ``--distances`` says otherwise; none with ``--distances none``)."""
    extra = list(extra)
    if '--distances' not in extra:
        return DISTANCES
    value = extra[extra.index('--distances') + 1]
    return () if value == 'none' else tuple(v.strip() for v in value.split(','))


def _passes(row) -> bool:
    by = row.get('by_distance_mm') or {}
    return (row['completed'] and _finite(row.get('stair_rmse_mm'))
            and row['stair_rmse_mm'] <= STAIR_LIMIT_MM
            and _finite(row.get('plate_rmse_mm')) and row['plate_rmse_mm'] <= PLATE_LIMIT_MM
            and all(_finite(by.get(mm)) for mm in row.get('distances', DISTANCES)))


def _stats(values) -> dict:
    v = np.array([x for x in values if _finite(x)], dtype=np.float64)
    if v.size == 0:
        return {'median': None, 'p90': None, 'max': None, 'n': 0}
    return {'median': float(np.median(v)), 'p90': float(np.percentile(v, 90)),
            'max': float(v.max()), 'n': int(v.size)}


def _f(v) -> str:
    return f'{v:.3f}' if _finite(v) else 'n/a'


def _short(text: str, limit: int = 240) -> str:
    return text if len(text) <= limit else text[:limit - 3] + '...'


def _line(i, n, row) -> str:
    head = f"rig {i}/{n} seed {row['seed']}"
    if 'working_distance_mm' in row:
        b = row['build']
        head += (f" (working distance {row['working_distance_mm']:.0f} mm, {b['sensor']} "
                 f"{b['bit_depth']} bit, {b['head']} head, laser {b.get('laser')})")
    if not row['completed']:
        f = row['failures'][0]
        return (f"{head}: FAILED at {f['stage'] or '?'}: {_short(f['message'])} "
                f"[{row['wall_s']:.0f} s]")
    by = row.get('by_distance_mm') or {}
    asked = row.get('distances', DISTANCES)
    finite = sum(_finite(by.get(mm)) for mm in asked)
    return (f"{head}: stair {_f(row.get('stair_rmse_mm'))} mm, plate "
            f"{_f(row.get('plate_rmse_mm'))} mm (scaled with depth "
            f"{_f(row.get('plate_range_scaled_rmse_mm'))} mm), sphere "
            f"{_f(row.get('sphere_radius_error_mm'))} mm, transfer "
            f"{_f(row.get('transfer_matrix_error_rmse_mm'))} mm, predicted "
            f"{_f(row.get('predicted_uncertainty_mm'))} / measured "
            f"{_f(row.get('measured_shape_error_mm'))} mm, distances {finite}/{len(asked)} "
            f"finite{' PASS' if _passes(row) else ' FAIL'} [{row['wall_s']:.0f} s]")


def summarise(rows, wall_s: float, quick: bool) -> dict:
    """The benchmark's summary (printed and returned as the last line's JSON)."""
    n = len(rows)
    completed = sum(r['completed'] for r in rows)
    passed = sum(_passes(r) for r in rows)
    finite = sum(r['completed'] and all(_finite((r.get('by_distance_mm') or {}).get(mm))
                                        for mm in r.get('distances', DISTANCES)) for r in rows)
    print(f'\n{n} rigs: {completed} completed ({100 * completed / max(n, 1):.0f} %), '
          f'{passed} passed ({100 * passed / max(n, 1):.0f} %), {finite} with a finite stair '
          f'figure at every re-set distance asked')
    family = sum(r['completed'] and _finite(r.get('stair_rmse_mm'))
                 and r['stair_rmse_mm'] <= FAMILY_STAIR_LIMIT_MM
                 and _finite(r.get('plate_rmse_mm'))
                 and r['plate_rmse_mm'] <= FAMILY_PLATE_LIMIT_MM for r in rows)
    print(f'{family} of {n} rigs completed at stair <= {FAMILY_STAIR_LIMIT_MM} mm and plate '
          f'<= {FAMILY_PLATE_LIMIT_MM} mm')
    summary = {'rigs': n, 'completed': completed, 'passed': passed, 'distances_finite': finite,
               'resumed': sum(bool(r.get('resumed')) for r in rows),
               'at_family_level': int(family), 'quick': quick, 'builds': build_counts(rows)}
    for kind, counts in summary['builds'].items():
        print(f'  {kind:32s} ' + ', '.join(f'{k}: {v}' for k, v in counts.items()))
    for _, name, _ in FIGURES:
        s = _stats(r.get(name) for r in rows)
        print(f"  {name:32s} median {_f(s['median'])}  p90 {_f(s['p90'])}  max "
              f"{_f(s['max'])}  (n = {s['n']})")
        for k in ('median', 'p90', 'max'):
            summary[f'{name}_{k}'] = s[k]
    for mm in DISTANCES:
        s = _stats((r.get('by_distance_mm') or {}).get(mm) for r in rows)
        if s['n'] == 0:
            continue
        print(f"  stair at {mm:>4s} mm (re-set)         median {_f(s['median'])}  max "
              f"{_f(s['max'])}  (n = {s['n']})")
        summary[f'stair_rmse_mm_at_{mm}_median'] = s['median']
    figures, lines = prediction_summary(rows, UNCERTAINTY_FACTOR)
    summary.update({f'uncertainty_{k}': v for k, v in figures.items()})
    for line in lines:
        print(f'  uncertainty, {line}')
    failures = [{'seed': r['seed'], **f} for r in rows for f in r['failures']]
    if failures:
        print('failures:')
    for f in failures:
        where = f"at {f['distance']} mm" if f['distance'] else 'own distance'
        print(f"  seed {f['seed']} ({where}): stage {f['stage'] or '?'}: "
              f"{_short(f['message'])}")
    summary['failures'] = [{k: f[k] for k in ('seed', 'distance', 'stage')} for f in failures]
    summary['wall_s'] = wall_s
    return summary


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rigs', type=int, default=20, help='number of rigs (default 20)')
    p.add_argument('--seed-start', type=int, default=0, help='first draw seed (default 0)')
    p.add_argument('--quick', action='store_true', help='quick capture plans and scans')
    p.add_argument('--out', default='out/rig_family', help='output folder')
    p.add_argument('--timeout', type=float, default=3600.0,
                   help='per-rig time limit [s] (default 3600)')
    p.add_argument('--model', choices=('paper', 'physical', 'both'), default='physical',
                   help="model form the calibrations fit (both: every rig with each, and the "
                        "rigs the physical model does worse on)")
    p.add_argument('--operator', action='store_true',
                   help='each rig calibrated through the simulated operator and through the '
                        'zero-error operator, compared (see the module)')
    p.add_argument('--reference-rig', action='store_true',
                   help='with --operator: the reference rig first, then the drawn rigs')
    p.add_argument('--repeats', type=int, default=1,
                   help='with --operator: runs of each rig each way, compared by their mean '
                        'errors (default 1)')
    p.add_argument('--distances', default=None, metavar='MM[,MM..]|none',
                   help="evaluate's --distances (default: the paper's six)")
    p.add_argument('--jobs', type=int, default=1,
                   help='rigs evaluated at once, each a graph of its own (default 1; on a '
                        'machine with cores to spare, 2 or more shortens a long run)')
    p.add_argument('--resume', action='store_true',
                   help="reuse the rows of rigs already completed in --out with the same source "
                        "tree and arguments (a stopped run goes on where it stopped)")
    p.add_argument('--keep-bags', action='store_true',
                   help="keep every rig's recorded calibration bags (default: only of the rigs "
                        'that did not pass)')
    args = p.parse_args(argv)
    if args.rigs < (0 if args.operator and args.reference_rig else 1) \
            or args.seed_start < 0 or args.timeout <= 0 or not 1 <= args.jobs <= 16 \
            or not 1 <= args.repeats <= 10:
        p.error('--rigs must be >= 1 (>= 0 with --operator --reference-rig), --seed-start '
                '>= 0, --timeout > 0, --jobs in 1..16 and --repeats in 1..10')
    t0 = time.monotonic()
    previous = {sig: signal.signal(sig, stop_run) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return operator_family(args, t0) if args.operator else family(args, t0)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def family(args, t0: float) -> int:
    """Every rig evaluated once per model form asked for."""
    models = ('paper', 'physical') if args.model == 'both' else (args.model,)
    extra = ['--distances', args.distances] if args.distances else []
    seeds = range(args.seed_start, args.seed_start + args.rigs)
    specs = [dict(seed=seed, folder=Path(args.out) / f'seed_{seed:03d}' / (
                      m if len(models) > 1 else ''),
                  quick=args.quick, timeout=args.timeout, model=m, extra=extra,
                  resume=args.resume)
             for seed in seeds for m in models]

    def report(i, row):
        row['model'] = specs[i]['model']
        print(f"[{row['model']}] " + _line(i // len(models) + 1, args.rigs, row), flush=True)
        if _passes(row) and not args.keep_bags:
            row['bags_deleted_bytes'] = drop_bags(specs[i]['folder'])

    all_rows = run_many(specs, args.jobs, report)
    # the rigs every model evaluated to the end (a stopped run leaves some part-way)
    seeds_done = [seed for seed in seeds if all(
        r['seed'] != seed or not r.get('stopped') for r in all_rows)]
    rows = {m: [r for r in finished_rows(all_rows) if r['model'] == m
                and r['seed'] in seeds_done] for m in models}
    wall = time.monotonic() - t0
    summary = {}
    for m in models:
        if len(models) > 1:
            print(f'\n== model {m}')
        summary[m] = summarise(rows[m], wall, args.quick)
    (Path(args.out) / 'rigs.json').write_text(
        json.dumps([r for m in models for r in rows[m]], indent=1, default=float))
    # the rows (each with its verdict) ride on the last line, for the results page
    every = [{**r, 'passed': _passes(r)} for m in models for r in rows[m]]
    if len(models) == 1:
        summary = {**summary[models[0]], 'rows': every}
    else:
        summary = {**summary['physical'], 'paper': summary['paper'],
                   **compare(rows['paper'], rows['physical'])}
        summary['wall_s'] = wall
        summary['rows'] = every
    summary.update(rigs_asked=args.rigs, stopped=_STOP.is_set())
    if _STOP.is_set():
        print(f'stopped: {len(seeds_done)} of {args.rigs} rigs evaluated to the end')
    print(json.dumps(summary, default=float))
    return 0


def _ratio(a, b):
    return a / b if _finite(a) and _finite(b) and b > 0 else None


def _mean(values):
    vals = [v for v in values if _finite(v)]
    return float(np.mean(vals)) if vals and len(vals) == len(values) else None


def operator_row(persons, exacts) -> dict:
    """One rig's operator runs against its zero-error runs (one of each, or ``--repeats``
    of each: the errors are their means, each run's kept beside them)."""
    persons, exacts = list(persons), list(exacts)
    placed, limit_ok = {}, True
    for person in persons:
        op = person.get('operator') or {}
        for stage, n in (op.get('placements') or {}).items():
            kept = (op.get('placements_kept') or {}).get(stage, 0)
            placed[stage] = max(placed.get(stage, 0), n)
            limit_ok = limit_ok and n <= PLACEMENT_FACTOR * kept + PLACEMENT_SLACK

    def both(key):
        a, b = [r.get(key) for r in persons], [r.get(key) for r in exacts]
        return _mean(a), _mean(b), a, b

    stair, stair_x, stair_runs, stair_x_runs = both('stair_rmse_mm')
    plate, plate_x, plate_runs, plate_x_runs = both('plate_rmse_mm')
    sigma, sigma_x, _, _ = both('predicted_calibration_uncertainty_mm')
    error, error_x, _, _ = both('measured_systematic_error_mm')
    first = persons[0]
    row = {'seed': first['seed'], 'rig': first.get('rig', f"seed {first['seed']}"),
           'completed': all(r['completed'] for r in persons + exacts),
           'runs': len(persons),
           'stair_mm': stair, 'stair_exact_mm': stair_x, 'plate_mm': plate,
           'plate_exact_mm': plate_x, 'stair_ratio': _ratio(stair, stair_x),
           'plate_ratio': _ratio(plate, plate_x),
           # what each calibration predicts of itself (its covariance over G1's range) and
           # the error it has against the truth: one run's error is one draw of that spread
           'calibration_sigma_mm': sigma, 'calibration_sigma_exact_mm': sigma_x,
           'calibration_sigma_ratio': _ratio(sigma, sigma_x),
           'calibration_error_mm': error, 'calibration_error_exact_mm': error_x,
           'placements': placed, 'placements_within_limit': limit_ok,
           'views_rejected': (first.get('operator') or {}).get('views_rejected'),
           'mistakes': (first.get('operator') or {}).get('mistakes_whole_run'),
           'wall_s': sum(r.get('wall_s', 0.0) for r in persons + exacts),
           'failures': [f for r in persons + exacts for f in r['failures']]}
    if len(persons) > 1:
        row.update(stair_runs_mm=stair_runs, stair_exact_runs_mm=stair_x_runs,
                   plate_runs_mm=plate_runs, plate_exact_runs_mm=plate_x_runs,
                   # the worst ratio any one operator run makes with any one zero-error run
                   stair_ratio_single_max=_worst_pair(stair_runs, stair_x_runs),
                   plate_ratio_single_max=_worst_pair(plate_runs, plate_x_runs))
    return row


def ratio_statistics(rows, name: str, limit: float = OPERATOR_RATIO_LIMIT,
                     confidence: float = RATIO_CONFIDENCE) -> dict:
    """How far ``--repeats`` pins down the ``name`` (``stair`` or ``plate``) ratios.

    One run's error is one draw: the spread between the runs of one rig and one way (the
    log of each run's error about their mean, pooled over every rig and both ways) is the
    error of a single run. From it, each completed row gets ``{name}_ratio_interval``
    (``confidence``, two-sided, Student's t on the pooled degrees of freedom: the ratio of
    two means of n draws) and ``{name}_verdict``: ``within`` the limit (the interval ends
    at or below it), ``beyond`` it (the interval starts above it) or ``undecided``. The
    family's ratio is the geometric mean over the rigs, with its interval from their
    scatter (t on rigs - 1 degrees of freedom).

    Returns the summary's fields (an empty dict with fewer than two runs a way).
    """
    from scipy.stats import t as student

    done = [r for r in rows if r.get('completed')]
    ss, dof = 0.0, 0
    for r in done:
        for key in (f'{name}_runs_mm', f'{name}_exact_runs_mm'):
            v = [x for x in r.get(key) or [] if _finite(x) and x > 0]
            if len(v) > 1:
                lv = np.log(v)
                ss, dof = ss + float(np.sum((lv - lv.mean()) ** 2)), dof + len(v) - 1
    if dof == 0:
        return {}
    spread = math.sqrt(ss / dof)

    def quantile(dof):
        return float(student.ppf(0.5 + confidence / 2, dof))

    q = quantile(dof)
    verdicts = {}
    for r in done:
        n_a, n_b = len(r[f'{name}_runs_mm']), len(r[f'{name}_exact_runs_mm'])
        ratio = r.get(f'{name}_ratio')
        if ratio is None:
            continue
        half = q * spread * math.sqrt(1 / n_a + 1 / n_b)
        lo, hi = ratio * math.exp(-half), ratio * math.exp(half)
        r[f'{name}_ratio_interval'] = [lo, hi]
        r[f'{name}_verdict'] = verdicts[r['rig']] = (
            'within' if hi <= limit else 'beyond' if lo > limit else 'undecided')
    logs = np.log([r[f'{name}_ratio'] for r in done if r.get(f'{name}_ratio')])
    family = float(np.exp(logs.mean()))
    interval = None
    if len(logs) > 1:
        half = quantile(len(logs) - 1) * float(logs.std(ddof=1)) / math.sqrt(len(logs))
        interval = [family * math.exp(-half), family * math.exp(half)]
    return {f'{name}_run_spread': spread, f'{name}_run_spread_dof': dof,
            f'{name}_ratio_family': family, f'{name}_ratio_family_interval': interval,
            f'{name}_beyond_limit': [k for k, v in verdicts.items() if v == 'beyond'],
            f'{name}_undecided': [k for k, v in verdicts.items() if v == 'undecided']}


def _worst_pair(a, b):
    vals = [_ratio(x, y) for x in a for y in b]
    return max(vals) if vals and None not in vals else None


def operator_family(args, t0: float) -> int:
    """``--operator``: every rig through the simulated operator and the zero-error one,
    ``--repeats`` times each."""
    extra = ['--distances', args.distances] if args.distances else []
    runs = ([(None, 'reference')] if args.reference_rig else []) + [
        (s, None) for s in range(args.seed_start, args.seed_start + args.rigs)]
    n = args.repeats
    specs = []
    for seed, name in runs:
        folder = Path(args.out) / (name or f'seed_{seed:03d}')
        for sub, more in (('operator', []), ('exact_operator', ['--exact-operator'])):
            for r in range(n):  # a repeat: the same rig, another simulator and operator seed
                rig_seed = 0 if seed is None else seed
                specs.append(dict(seed=rig_seed,
                                  folder=folder / (sub if r == 0 else f'{sub}_{r + 1}'),
                                  quick=args.quick, timeout=args.timeout, model=args.model,
                                  extra=extra + more, rig_name=name, resume=args.resume,
                                  sim_seed=rig_seed + REPEAT_SEED_STEP * r if r else None))
    finished = {}
    rows = [None] * len(runs)

    def report(k, one):
        finished[k] = one
        i = k // (2 * n)
        mine = range(2 * n * i, 2 * n * (i + 1))
        if not all(j in finished for j in mine):
            return
        persons = [finished[j] for j in mine[:n]]
        exacts = [finished[j] for j in mine[n:]]
        row = rows[i] = operator_row(persons, exacts)
        if any(finished[j].get('stopped') for j in mine):
            row['stopped'] = True
            return
        each = ''
        if n > 1:
            each = (f" (runs: stair {'/'.join(_f(v) for v in row['stair_runs_mm'])} against "
                    f"{'/'.join(_f(v) for v in row['stair_exact_runs_mm'])}, plate "
                    f"{'/'.join(_f(v) for v in row['plate_runs_mm'])} against "
                    f"{'/'.join(_f(v) for v in row['plate_exact_runs_mm'])})")
        print(f"[{i + 1}/{len(runs)}] {row['rig']}: " + (
            f"stair {_f(row['stair_mm'])} mm (zero-error operator {_f(row['stair_exact_mm'])}, "
            f"ratio {_f(row['stair_ratio'])}), plate {_f(row['plate_mm'])} mm "
            f"({_f(row['plate_exact_mm'])}, ratio {_f(row['plate_ratio'])}){each}; "
            f"predicted calibration uncertainty {_f(row['calibration_sigma_mm'])} mm "
            f"({_f(row['calibration_sigma_exact_mm'])}); placements "
            f"{row['placements']}; {row['wall_s']:.0f} s" if row['completed'] else
            'not completed: ' + _short('; '.join(f"{f.get('stage')}: {f.get('message')}"
                                                 for f in row['failures']))), flush=True)
        if not args.keep_bags:
            for j in mine:
                drop_bags(specs[j]['folder'])

    run_many(specs, args.jobs, report)
    rows = finished_rows(rows)
    done = [r for r in rows if r['completed']]

    def worst(key):
        vals = [r[key] for r in done if r.get(key) is not None]
        return max(vals) if vals else None

    summary = {'rigs': len(rows), 'completed': len(done), 'repeats': n,
               'stair_ratio_max': worst('stair_ratio'), 'plate_ratio_max': worst('plate_ratio'),
               'ratio_limit': OPERATOR_RATIO_LIMIT,
               'calibration_sigma_ratio_max': worst('calibration_sigma_ratio'),
               'placements_max': max((n for r in rows for n in r['placements'].values()),
                                     default=None),
               'placements_within_limit': all(r['placements_within_limit'] for r in done),
               'placement_limit': f'{PLACEMENT_FACTOR:g} x kept + {PLACEMENT_SLACK} per stage',
               'quick': bool(args.quick), 'distances': args.distances or 'paper six',
               'resumed': sum(bool(r.get('resumed')) for r in finished.values()),
               'rigs_asked': len(runs), 'stopped': _STOP.is_set(),
               'wall_s': time.monotonic() - t0, 'rows': rows}
    if n > 1:
        summary.update(stair_ratio_single_max=worst('stair_ratio_single_max'),
                       plate_ratio_single_max=worst('plate_ratio_single_max'),
                       ratio_confidence=RATIO_CONFIDENCE,
                       **ratio_statistics(rows, 'stair'), **ratio_statistics(rows, 'plate'))
    for name in ('stair', 'plate'):  # with --repeats: what the runs' scatter settles
        if summary.get(f'{name}_run_spread') is None:
            continue
        fam = summary[f'{name}_ratio_family_interval'] or [None, None]
        print(f"{name}: one run scatters by {100 * summary[f'{name}_run_spread']:.0f} % "
              f"(log sd, {summary[f'{name}_run_spread_dof']} degrees of freedom); the "
              f"family's ratio {_f(summary[f'{name}_ratio_family'])} "
              f"({RATIO_CONFIDENCE:.0%}: {_f(fam[0])} to {_f(fam[1])}); beyond "
              f"{OPERATOR_RATIO_LIMIT:g}: {summary[f'{name}_beyond_limit'] or 'none'}; "
              f"undecided by {n} runs: {summary[f'{name}_undecided'] or 'none'}", flush=True)
    (Path(args.out) / 'operator_rigs.json').write_text(json.dumps(rows, indent=1,
                                                                  default=float))
    print(json.dumps(summary, default=float))
    return 0


def compare(paper_rows, physical_rows) -> dict:
    """Per rig, the physical model's stair and plate against the paper's (same draw)."""
    worse = {'stair_rmse_mm': [], 'plate_rmse_mm': []}
    both = 0
    for a, b in zip(paper_rows, physical_rows, strict=True):
        if not (a['completed'] and b['completed']):
            continue
        both += 1
        for key in worse:
            if _finite(a.get(key)) and _finite(b.get(key)) and b[key] > a[key]:
                worse[key].append({'seed': a['seed'], 'paper': a[key], 'physical': b[key]})
    print(f'\nphysical against paper on {both} rigs both completed: stair worse on '
          f"{len(worse['stair_rmse_mm'])}, plate worse on {len(worse['plate_rmse_mm'])}")
    for key, items in worse.items():
        for w in items:
            print(f"  seed {w['seed']}: {key} {w['paper']:.3f} -> {w['physical']:.3f}")
    return {'compared': both, 'physical_stair_worse': len(worse['stair_rmse_mm']),
            'physical_plate_worse': len(worse['plate_rmse_mm']), 'worse': worse}


if __name__ == '__main__':
    sys.exit(main())
