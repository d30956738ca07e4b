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
    'driver_idle': (['benchmarks/driver_idle.py', '--seconds', '10'], True,
                    'CPU of an idle driver against a bare rclpy node'),
    'firmware_simavr': (['benchmarks/firmware_simavr.py'], True,
                        'the board firmware in simavr: 10,000 triggers at 500 Hz, watchdog, '
                        'interlock'),
    'twin_scan': (['benchmarks/twin_scan.py', '--positions', '18'], False,
                  'a stair scan through the twin (firmware in simavr, GigE Vision camera '
                  'path) against the same scan on the sim backend, 18 stair positions'),
    'materials': (['benchmarks/materials.py'], False,
                  'stair, plate and outliers per material, countermeasures off and on'),
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
                         '10', '--distances', 'none', '--out', 'out/operator_family', '--jobs',
                         '2', '--resume'], False,
                        'the reference rig and drawn rigs calibrated through the simulated '
                        'operator, against the zero-error operator'),
    'joint_bundle': (['benchmarks/joint_bundle.py'], False,
                     'one bundle over camera and laser against the staged calibration'),
    'hosts_apart': (['benchmarks/hosts_apart.py'], False,
                    'the image path across a network link (root: network namespaces)'),
}
ACCURACY = ('rig_family', 'operator_family', 'uncertainty_check', 'calibration_seeds',
            'joint_bundle', 'materials')

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
)
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
            raise ValueError(f"exit code {proc.returncode}: {''.join(err).strip()[-400:]}")
        entry['result'] = last_json(''.join(out))
    except ValueError as exc:
        entry['error'] = str(exc)
        print(f'[results] {name}: not measured: {exc}', flush=True)
    return entry


def record_demo(out: Path, command: str, wall_s: float | None) -> dict:
    metrics = json.loads((out / 'metrics.json').read_text())
    entry = {'command': command, 'date': now(), 'commit': commit(), 'machine': machine(),
             'wall_s': wall_s, 'metrics': metrics, 'plots': []}
    for plot in DEMO_PLOTS:
        if (out / plot).exists():
            shutil.copyfile(out / plot, RESULTS / plot)
            entry['plots'].append(plot)
    return entry


def _fmt(v) -> str:
    if v is None:
        return '–'
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


def _benchmark_section(name: str, e: dict | None) -> list[str]:
    args, quick, what = BENCHMARKS[name]
    lines = [f'### `{name}`: {what}', '']
    if e is None:
        lines += ['Not measured yet. Run '
                  f"`.venv/bin/python tools/gen_results.py --only {name}` "
                  f"(`.venv/bin/python {' '.join(args)}`"
                  + ('' if quick else ', a long run') + ').', '']
        return lines
    lines += _provenance(e) + ['']
    if 'error' in e:
        return lines + [f"Not measured: the run failed ({e['error']}).", '']
    lines += ['| figure | value |', '|---|---|']
    lines += [f'| `{k}` | {_fmt(v)} |' for k, v in _flat(e['result']).items()]
    return lines + ['']


def _flat(d: dict, prefix: str = '') -> dict:
    """Nested figures as ``a.b.c`` keys, so that each gets a row of its own."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


def render(store: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    banner = ('<!-- Written by tools/gen_results.py (`make results`) from results.json; do not '
              'edit by hand. -->')
    # accuracy
    lines = ['# Accuracy', '', banner, '',
             'Every figure here was measured on the simulated rig by the command named with it; '
             'no real rig has been measured yet. What each figure means: '
             '[evaluation.md](../evaluation.md).', '', '## The demo: the reference rig', '']
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

    (RESULTS / 'README.md').write_text('\n'.join([
        '# Results', '', banner, '',
        '- [Accuracy](accuracy.md): the demo on the simulated reference rig, and the benchmarks '
        'over many drawn rigs.',
        '- [Performance](performance.md): the timing benchmarks.', '',
        'Regenerate with `make results` (the demo and the benchmarks that take about a minute '
        'or less); `.venv/bin/python tools/gen_results.py --long` also runs the long ones, '
        '`--only NAME[,NAME]` one or a few.', '']))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--long', action='store_true', help='also the long benchmarks')
    p.add_argument('--only', help='comma-separated benchmark names (and/or "demo")')
    p.add_argument('--demo-out', type=Path,
                   help='record this finished demo run instead of running the demo')
    p.add_argument('--render', action='store_true', help='only rewrite the pages')
    args = p.parse_args(argv)
    store = load_store()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if not args.render:
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
    print(f'[results] wrote {RESULTS.relative_to(ROOT)}/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
