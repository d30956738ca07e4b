"""The family benchmark deletes a passed rig's recorded bags and keeps everything else."""

import importlib.util
import math
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    'rig_family_bench', Path(__file__).parents[1] / 'benchmarks' / 'rig_family.py')
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_drop_bags_deletes_only_calibration_data(tmp_path):
    ev = tmp_path / 'seed_000' / 'evaluation'
    keep = [ev / 'metrics.json', ev / 'calibration.yaml', ev / 'logs' / 'driver.log',
            ev / 'by_distance' / '650' / 'metrics.json']
    bags = [ev / 'calibration_data' / 'dynamic_camera' / 'bag_0.mcap',
            ev / 'by_distance' / '650' / 'calibration_data' / 'laser' / 'bag_0.mcap']
    for i, f in enumerate(keep + bags):
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b'x' * (100 + i))
    freed = bench.drop_bags(tmp_path / 'seed_000')
    assert freed == sum(100 + i for i in range(len(keep), len(keep) + len(bags)))
    assert all(f.exists() for f in keep)
    assert not any(p.name == 'calibration_data' for p in tmp_path.rglob('*'))
    assert bench.drop_bags(tmp_path / 'seed_000') == 0  # nothing left to delete


def test_build_counts_count_drawn_completed_and_passed_per_kind():
    full = {mm: 0.05 for mm in bench.DISTANCES}
    rows = [
        {'seed': 0, 'completed': True, 'stair_rmse_mm': 0.02, 'plate_rmse_mm': 0.07,
         'by_distance_mm': full, 'build': {'bit_depth': 12, 'sensor': 'IMX273',
                                           'head': 'WIDE25', 'laser': 'left'}},
        {'seed': 1, 'completed': True, 'stair_rmse_mm': 0.5, 'plate_rmse_mm': 0.07,
         'by_distance_mm': full, 'build': {'bit_depth': 8, 'sensor': 'IMX273',
                                           'head': 'TSH8310', 'laser': 'below'}},
        {'seed': 2, 'completed': False, 'failures': [],
         'build': {'bit_depth': 12, 'sensor': 'PYTHON300', 'head': 'WIDE25', 'laser': 'left'}},
        {'seed': 3, 'completed': False, 'failures': []},          # failed at the draw
    ]
    counts = bench.build_counts(rows)
    assert counts['bit_depth'] == {'12': {'drawn': 2, 'completed': 1, 'passed': 1},
                                   '8': {'drawn': 1, 'completed': 1, 'passed': 0}}
    assert counts['sensor']['IMX273'] == {'drawn': 2, 'completed': 2, 'passed': 1}
    assert counts['head']['WIDE25'] == {'drawn': 2, 'completed': 1, 'passed': 1}
    assert counts['laser'] == {'below': {'drawn': 1, 'completed': 1, 'passed': 0},
                               'left': {'drawn': 2, 'completed': 1, 'passed': 1}}


def test_operator_row_compares_the_operator_with_the_zero_error_one():
    person = {'seed': 3, 'completed': True, 'failures': [], 'stair_rmse_mm': 0.03,
              'plate_rmse_mm': 0.12, 'wall_s': 10.0,
              'predicted_calibration_uncertainty_mm': 0.06,
              'measured_systematic_error_mm': 0.07,
              'operator': {'placements': {'intrinsics': 9, 'laser_axis': 20},
                           'placements_kept': {'intrinsics': 8, 'laser_axis': 6}}}
    exact = {'seed': 3, 'completed': True, 'failures': [], 'stair_rmse_mm': 0.025,
             'plate_rmse_mm': 0.1, 'wall_s': 8.0,
             'predicted_calibration_uncertainty_mm': 0.05,
             'measured_systematic_error_mm': 0.03}
    row = bench.operator_row([person], [exact])
    assert row['completed'] and row['wall_s'] == 18.0
    assert abs(row['stair_ratio'] - 1.2) < 1e-12 and abs(row['plate_ratio'] - 1.2) < 1e-12
    assert row['placements'] == {'intrinsics': 9, 'laser_axis': 20}
    assert abs(row['calibration_sigma_ratio'] - 1.2) < 1e-12
    assert (row['calibration_error_mm'], row['calibration_error_exact_mm']) == (0.07, 0.03)
    assert not row['placements_within_limit']  # 20 > 2 x 6 + 2
    failed = bench.operator_row([person], [{**exact, 'completed': False,
                                            'stair_rmse_mm': None}])
    assert not failed['completed'] and failed['stair_ratio'] is None


def test_rigs_run_in_parallel_in_their_own_domains_and_a_stopped_run_resumes(tmp_path,
                                                                           monkeypatch):
    import threading
    import time

    calls, active, seen = [], set(), []
    lock = threading.Lock()

    def evaluate(seed, folder, quick, timeout, model, extra, rig_name, domain, sim_seed):
        with lock:
            assert domain not in active, 'two graphs at once in one domain'
            active.add(domain)
            seen.append(len(active))
            calls.append(seed)
        time.sleep(0.05)
        with lock:
            active.discard(domain)
        return {'seed': seed, 'completed': seed != 2, 'failures': [], 'stair_rmse_mm': seed}

    monkeypatch.setattr(bench, '_evaluate_rig', evaluate)
    monkeypatch.setattr(bench, 'source_tree', lambda: 'tree-a')
    specs = [dict(seed=s, folder=tmp_path / f'seed_{s:03d}', quick=False, timeout=10.0,
                  resume=True) for s in range(5)]
    for spec in specs:
        spec['folder'].mkdir()
    order = []
    rows = bench.run_many(specs, 2, lambda i, row: order.append(i))
    assert [r['seed'] for r in rows] == list(range(5)) and sorted(order) == list(range(5))
    assert sorted(calls) == list(range(5)) and max(seen) == 2
    # resumed: the completed rigs are not evaluated again, the one that failed is
    calls.clear()
    rows = bench.run_many(specs, 2)
    assert calls == [2]
    assert [r.get('resumed', False) for r in rows] == [True, True, False, True, True]
    # other code, or other arguments: everything again
    monkeypatch.setattr(bench, 'source_tree', lambda: 'tree-b')
    calls.clear()
    bench.run_many(specs, 1)
    assert sorted(calls) == list(range(5))
    calls.clear()
    bench.run_many([{**s, 'quick': True} for s in specs], 1)
    assert sorted(calls) == list(range(5))
    # a tree with uncommitted changes never reuses
    monkeypatch.setattr(bench, 'source_tree', lambda: None)
    calls.clear()
    bench.run_many(specs, 1)
    assert sorted(calls) == list(range(5))


def test_a_stopped_run_summarises_the_rigs_finished(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM) part-way: the running evaluation is stopped, no rig starts after
    it, and the summary holds the rigs evaluated to the end, saying it was stopped."""
    import json
    import signal
    import subprocess
    import sys
    import threading

    started = []

    def start(argv, log, env):
        """Stands in for `galvoscan evaluate`: seed 0 finishes at once, seed 1 runs until it
        gets Ctrl-C (SIGINT), as a graph does."""
        seed = int(argv[argv.index('--seed') + 1])
        started.append(seed)
        if seed == 1:       # Ctrl-C while it runs
            threading.Timer(0.5, bench.stop_run).start()
        out = Path(argv[argv.index('--out') + 1])
        out.mkdir(parents=True, exist_ok=True)
        code = ('import json, pathlib, sys, time; '
                f'p = pathlib.Path({str(out)!r}); '
                + ("(p / 'metrics.json').write_text(json.dumps({"
                   "'stair_step_error_rmse_mm': 0.02, 'plate_flatness_rmse_mm': 0.06}))"
                   if seed == 0 else 'time.sleep(60)'))
        return subprocess.Popen([sys.executable, '-c', code], stdout=log, env=env)

    monkeypatch.setattr(bench, '_start', start)
    monkeypatch.setattr(bench, 'source_tree', lambda: 'tree-a')
    monkeypatch.setattr(bench, '_STOP', threading.Event())
    out = tmp_path / 'family'
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert bench.main(['--rigs', '4', '--distances', 'none', '--out', str(out)]) == 0
    # the handlers are the caller's again
    assert signal.getsignal(signal.SIGINT) is not bench.stop_run
    summary = json.loads(buf.getvalue().strip().splitlines()[-1])
    assert started == [0, 1]                      # seeds 2 and 3 never started
    assert summary['stopped'] and summary['rigs_asked'] == 4
    assert summary['rigs'] == 1 and summary['completed'] == 1 and summary['passed'] == 1


def test_operator_repeats_compare_each_rigs_mean_errors_and_keep_every_run(tmp_path,
                                                                         monkeypatch):
    """--repeats 2: each rig runs twice each way, in folders of their own (the first where
    a single run keeps it, so a longer run resumes a shorter one); the ratios are of the
    means, and the worst single pairing is kept beside them."""
    import contextlib
    import io
    import json

    stair = {('operator', 0): 0.03, ('operator', 1): 0.01,
             ('exact_operator', 0): 0.02, ('exact_operator', 1): 0.02}
    folders, sim_seeds = [], {}

    def evaluate(seed, folder, quick, timeout, model, extra, rig_name, domain, sim_seed):
        folders.append(folder.relative_to(tmp_path).as_posix())
        sim_seeds[folders[-1]] = sim_seed
        sub = folder.name.split('_2')[0]
        value = stair[(sub, int(folder.name.endswith('_2')))]
        return {'seed': seed, 'rig': rig_name or f'seed {seed}', 'completed': True,
                'failures': [], 'stair_rmse_mm': value, 'plate_rmse_mm': 2 * value,
                'predicted_calibration_uncertainty_mm': 0.05,
                'measured_systematic_error_mm': value,
                'operator': {'placements': {'intrinsics': 6 * len(folders)},
                             'placements_kept': {'intrinsics': 4}}}

    monkeypatch.setattr(bench, '_evaluate_rig', evaluate)
    monkeypatch.setattr(bench, 'source_tree', lambda: None)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert bench.main(['--operator', '--rigs', '1', '--repeats', '2', '--distances',
                           'none', '--out', str(tmp_path)]) == 0
    assert sorted(folders) == ['seed_000/exact_operator', 'seed_000/exact_operator_2',
                               'seed_000/operator', 'seed_000/operator_2']
    # the first runs are a single run's (so they resume); a repeat draws from another seed
    assert sim_seeds == {'seed_000/operator': None, 'seed_000/exact_operator': None,
                         'seed_000/operator_2': bench.REPEAT_SEED_STEP,
                         'seed_000/exact_operator_2': bench.REPEAT_SEED_STEP}
    summary = json.loads(buf.getvalue().strip().splitlines()[-1])
    row = summary['rows'][0]
    assert summary['repeats'] == 2 and row['runs'] == 2 and summary['completed'] == 1
    assert abs(row['stair_mm'] - 0.02) < 1e-12 and abs(row['stair_ratio'] - 1.0) < 1e-12
    assert sorted(row['stair_runs_mm']) == [0.01, 0.03]
    assert abs(summary['stair_ratio_single_max'] - 1.5) < 1e-12
    # the operator's runs scatter (0.03, 0.01), the zero-error ones do not: log sd on 2 dof
    assert summary['stair_run_spread_dof'] == 2
    assert abs(summary['stair_run_spread'] - abs(math.log(3)) / 2) < 1e-12
    assert row['stair_verdict'] == 'undecided' and summary['stair_undecided'] == ['seed 0']
    assert abs(summary['plate_ratio_max'] - 1.0) < 1e-12
    assert row['placements']['intrinsics'] == 6 * folders.index('seed_000/operator_2') + 6
    assert not row['placements_within_limit']     # the second run's 12 > 2 x 4 + 2
    import pytest

    with pytest.raises(SystemExit):             # an absurd request is refused
        bench.main(['--operator', '--rigs', '1', '--repeats', '0'])


def test_ratio_statistics_say_which_rigs_their_runs_settle():
    """Each rig's ratio gets an interval from the runs' pooled scatter: above the limit
    only where the whole interval is, within it only where the whole interval is, and
    undecided where the runs cannot tell; one run a way gives no statistics."""
    from scipy.stats import t as student

    d = 0.2                      # every side's two runs lie exp(+-d/2) about their mean

    def row(rig, ratio, completed=True):
        runs = [0.02 * math.exp(-d / 2), 0.02 * math.exp(d / 2)]
        return {'rig': rig, 'completed': completed, 'stair_ratio': ratio,
                'stair_runs_mm': runs, 'stair_exact_runs_mm': runs}

    rows = [row('worse', 2.0), row('alike', 1.0), row('better', 0.8),
            row('failed', 9.0, completed=False)]
    s = bench.ratio_statistics(rows, 'stair', limit=1.25, confidence=0.90)
    spread = d / math.sqrt(2)    # 6 sides x 2 runs x (d/2)^2 on 6 degrees of freedom
    assert s['stair_run_spread_dof'] == 6
    assert abs(s['stair_run_spread'] - spread) < 1e-12
    half = student.ppf(0.95, 6) * spread * math.sqrt(1 / 2 + 1 / 2)
    assert abs(rows[0]['stair_ratio_interval'][0] - 2.0 * math.exp(-half)) < 1e-12
    assert [r.get('stair_verdict') for r in rows] == ['beyond', 'undecided', 'within', None]
    assert s['stair_beyond_limit'] == ['worse'] and s['stair_undecided'] == ['alike']
    assert abs(s['stair_ratio_family'] - 1.6 ** (1 / 3)) < 1e-12
    lo, hi = s['stair_ratio_family_interval']
    assert lo < s['stair_ratio_family'] < hi
    single = [{'rig': 'one', 'completed': True, 'stair_ratio': 1.0,
               'stair_runs_mm': [0.02], 'stair_exact_runs_mm': [0.02]}]
    assert bench.ratio_statistics(single, 'stair') == {}
