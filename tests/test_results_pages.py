"""docs/results/ is what tools/gen_results.py writes from its measurements, not hand edits.

The pages are rendered again from docs/results/results.json (no benchmark is run) and compared
with the committed ones; every figure on them therefore comes with the command, date, commit
and machine of the run that measured it, and every plot a page shows is there.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'docs' / 'results'


def _generator():
    spec = importlib.util.spec_from_file_location('gen_results', ROOT / 'tools' / 'gen_results.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_pages_are_rendered_from_the_measurements(tmp_path, monkeypatch):
    gen = _generator()
    monkeypatch.setattr(gen, 'RESULTS', tmp_path)
    gen.render(json.loads((RESULTS / 'results.json').read_text()))
    for page in ('README.md', 'accuracy.md', 'performance.md'):
        assert (tmp_path / page).read_text() == (RESULTS / page).read_text(), (
            f'docs/results/{page} differs from what tools/gen_results.py writes: '
            'regenerate it (.venv/bin/python tools/gen_results.py --render, or make results)')


def test_every_measurement_names_its_command_date_commit_and_machine():
    store = json.loads((RESULTS / 'results.json').read_text())
    entries = [store['demo'], *store['benchmarks'].values()] if store['demo'] else \
        list(store['benchmarks'].values())
    assert entries
    for e in entries:
        assert e['command'] and e['date'] and e['commit'] and e['machine']['cores']
        assert 'result' in e or 'error' in e or 'metrics' in e
    for page in RESULTS.glob('*.md'):
        for image in re.findall(r'!\[[^\]]*\]\(([^)]+)\)', page.read_text()):
            assert (RESULTS / image).is_file(), f'{page.name}: {image} is missing'


def _entry(result: dict) -> dict:
    return {'command': '.venv/bin/python benchmarks/x.py', 'date': '2026-01-01 00:00 UTC',
            'commit': 'abc1234', 'wall_s': 1.0, 'result': result,
            'machine': {'cpu': 'cpu', 'cores': 2, 'system': 'Linux', 'python': '3.11',
                        'load_average': [1.0, 1.0, 1.0]}}


def _section(text: str, name: str) -> str:
    start = text.index(f'<a id="{name}"></a>')
    end = text.find('<a id="', start + 1)
    return text[start:end if end > 0 else None]


def _rows(section: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip('|').split('|')] for line in section.splitlines()
            if line.startswith('|') and not line.startswith('|---')]


def test_the_families_are_drawn_as_tables_per_rig(tmp_path, monkeypatch):
    """A synthetic store (not the real page): the rig family per rig with its build and
    verdict, the build counts and the summary; the operator's family per rig against the
    zero-error operator, the placements per stage and the ratio limit."""
    gen = _generator()
    monkeypatch.setattr(gen, 'RESULTS', tmp_path)
    build = {'sensor': 'IMX273', 'bit_depth': 10, 'head': 'WIDE25', 'laser': 'left'}
    family = {
        'rigs': 2, 'completed': 1, 'passed': 1, 'distances_finite': 1, 'at_family_level': 1,
        'quick': False, 'stair_rmse_mm_median': 0.0217, 'stair_rmse_mm_p90': 0.0311,
        'stair_rmse_mm_max': 0.0322, 'wall_s': 1234.0,
        'builds': {'laser': {'left': {'drawn': 1, 'completed': 1, 'passed': 1},
                             'above': {'drawn': 1, 'completed': 0, 'passed': 0}}},
        'failures': [{'seed': 4, 'distance': None, 'stage': 'laser_axis'}],
        'rows': [{'seed': 3, 'completed': True, 'passed': True, 'build': build,
                  'working_distance_mm': 577.25, 'stair_rmse_mm': 0.0217,
                  'plate_rmse_mm': 0.0764, 'transfer_matrix_error_rmse_mm': 0.1234},
                 {'seed': 4, 'completed': False, 'passed': False,
                  'build': {**build, 'laser': 'above'}, 'working_distance_mm': 301.0,
                  'failures': [{'distance': None, 'stage': 'laser_axis', 'message': 'x'}]}]}
    operator = {
        'rigs': 2, 'completed': 2, 'stair_ratio_max': 1.31, 'plate_ratio_max': 1.22,
        'ratio_limit': 1.25, 'placements_max': 22, 'calibration_sigma_ratio_max': 0.954,
        'placements_within_limit': True,
        'placement_limit': '2 x kept + 2 per stage', 'quick': False, 'distances': 'none',
        'rows': [{'seed': 0, 'rig': 'reference', 'completed': True, 'stair_mm': 0.0249,
                  'stair_exact_mm': 0.019, 'stair_ratio': 1.31, 'plate_mm': 0.08,
                  'plate_exact_mm': 0.0656, 'plate_ratio': 1.22,
                  'calibration_sigma_mm': 0.062, 'calibration_sigma_exact_mm': 0.065,
                  'calibration_sigma_ratio': 0.954, 'calibration_error_mm': 0.069,
                  'calibration_error_exact_mm': 0.029,
                  'placements': {'intrinsics': 12, 'laser_axis': 22}},
                 {'seed': 1, 'rig': 'seed 1', 'completed': True, 'stair_mm': 0.03,
                  'stair_exact_mm': 0.03, 'stair_ratio': 1.0, 'plate_mm': 0.05,
                  'plate_exact_mm': 0.05, 'plate_ratio': 1.0,
                  'placements': {'intrinsics': 9, 'laser_axis': 14}}]}
    gen.render({'demo': None, 'benchmarks': {'rig_family': _entry(family),
                                             'operator_family': _entry(operator)}})
    page = (tmp_path / 'accuracy.md').read_text()

    rows = _rows(_section(page, 'rig_family'))
    assert ['3', 'IMX273, 10 bit, WIDE25, laser left', '577.2', '0.0217', '0.0764', '0.1234',
            'yes'] in rows
    assert ['4', 'IMX273, 10 bit, WIDE25, laser above', '301', '–', '–', '–',
            'failed: laser_axis'] in rows
    assert ['laser', 'above', '1', '0', '0'] in rows and ['laser', 'left', '1', '1', '1'] in rows
    assert ['stair step error RMSE [mm]', '0.0217', '0.0311', '0.0322'] in rows
    assert '2 rigs, 1 completed, 1 passed, 1 at the family' in _section(page, 'rig_family')

    section = _section(page, 'operator_family')
    rows = _rows(section)
    assert ['reference', '0.0249', '0.019', '1.31', '0.08', '0.0656', '1.22', 'no'] in rows
    assert ['seed 1', '0.03', '0.03', '1', '0.05', '0.05', '1', 'yes'] in rows
    assert ['rig', 'intrinsics', 'laser_axis'] in rows and ['reference', '12', '22'] in rows
    assert 'largest ratio 1.31 (stair) and 1.22 (plate) against the limit 1.25' in section
    assert ['reference', '0.062', '0.065', '0.954', '0.069', '0.029'] in rows
    assert ['seed 1', '–', '–', '–', '–', '–'] in rows
    assert 'largest ratio of predicted calibration uncertainties 0.954' in section
    assert 'mean of' not in section and 'one zero-error run' not in section

    # repeated runs: the table holds means, and the worst single pairing is said beside them
    operator.update(repeats=3, stair_ratio_single_max=1.6, plate_ratio_single_max=1.4)
    gen.render({'demo': None, 'benchmarks': {'operator_family': _entry(operator)}})
    section = _section((tmp_path / 'accuracy.md').read_text(), 'operator_family')
    assert 'each the mean of 3 runs' in section
    assert 'one operator run to one zero-error run 1.6 (stair) and 1.4 (plate)' in section
    assert 'How far' not in section             # no scatter recorded: nothing claimed of it

    # with the runs' scatter: each ratio's interval and verdict, and the family's ratio
    operator.update(ratio_confidence=0.9, stair_run_spread=0.21, stair_run_spread_dof=22,
                    plate_run_spread=0.1, plate_run_spread_dof=22, stair_ratio_family=0.92,
                    stair_ratio_family_interval=[0.82, 1.04], plate_ratio_family=0.97,
                    plate_ratio_family_interval=[0.92, 1.01], stair_beyond_limit=[],
                    stair_undecided=['reference'], plate_beyond_limit=['reference'],
                    plate_undecided=[])
    operator['rows'][0].update(stair_ratio_interval=[0.9, 1.9], stair_verdict='undecided',
                               plate_ratio_interval=[1.26, 1.5], plate_verdict='beyond')
    gen.render({'demo': None, 'benchmarks': {'operator_family': _entry(operator)}})
    section = _section((tmp_path / 'accuracy.md').read_text(), 'operator_family')
    assert 'scatters between draws by 21 % (stair) and 10 % (plate)' in section
    assert ['reference', '0.9 to 1.9', 'undecided', '1.26 to 1.5', 'beyond'] in _rows(section)
    assert ['seed 1', '–', '–', '–', '–'] in _rows(section)
    assert 'stair 0.92 (90 %: 0.82 to 1.04)' in section
    assert 'Beyond the limit: stair none, plate reference' in section
    assert 'stair_run_spread' not in section    # said in words, not again as a raw figure

    # a run without per-rig rows (an older benchmark) says so instead of drawing an empty table
    del family['rows']
    gen.render({'demo': None, 'benchmarks': {'rig_family': _entry(family)}})
    assert 'recorded no per-rig rows' in _section((tmp_path / 'accuracy.md').read_text(),
                                                  'rig_family')


def test_rows_from_a_runs_rigs_json_are_attached_with_the_benchmarks_pass_rule(tmp_path,
                                                                               monkeypatch):
    gen = _generator()
    monkeypatch.setattr(gen, 'RESULTS', tmp_path)
    monkeypatch.setattr(gen, 'STORE', tmp_path / 'results.json')
    summary = {'rigs': 2, 'completed': 2, 'passed': 1, 'builds': {}}
    store = {'demo': None, 'benchmarks': {'rig_family': _entry(summary)}}
    gen.STORE.write_text(json.dumps(store))
    build = {'sensor': 'IMX287', 'bit_depth': 8, 'head': 'GVS011', 'laser': 'below'}
    rows = [{'seed': s, 'completed': True, 'build': build, 'working_distance_mm': 650.0,
             'stair_rmse_mm': stair, 'plate_rmse_mm': 0.05, 'distances': [],
             'by_distance_mm': {}, 'failures': []} for s, stair in ((0, 0.03), (1, 0.2))]
    rigs = tmp_path / 'rigs.json'

    rigs.write_text('{"not": "rows"}')  # bad input: a clear error, and the store unchanged
    with pytest.raises(SystemExit):
        gen.main(['--only', 'rig_family', '--attach-rows', str(rigs)])
    assert json.loads(gen.STORE.read_text()) == store

    rigs.write_text(json.dumps(rows))
    assert gen.main(['--only', 'rig_family', '--attach-rows', str(rigs)]) == 0
    table = _rows(_section((tmp_path / 'accuracy.md').read_text(), 'rig_family'))
    assert table[1][0] == '0' and table[1][-1] == 'yes'  # within 0.165 mm and 0.281 mm
    assert table[2][0] == '1' and table[2][-1] == 'no'  # stair over the paper's 0.165 mm
    assert json.loads(gen.STORE.read_text())['benchmarks']['rig_family']['rows_from'] == str(rigs)


def test_a_failed_run_is_recorded_with_the_reason_it_left(tmp_path, monkeypatch):
    """A run that fails is stored as an error (never as figures), with the stage and message
    of the failure.json its output folder holds (what `galvoscan evaluate` writes)."""
    gen = _generator()
    out = tmp_path / 'o'
    script = ('import json, pathlib, sys; d = pathlib.Path(sys.argv[2]); d.mkdir(); '
              "(d / 'failure.json').write_text(json.dumps({'stage': 'intrinsics', "
              "'message': 'link lost'})); print('{\"stair_mm\": 1.0}'); sys.exit(1)")
    monkeypatch.setattr(gen, 'BENCHMARKS', {'x': (['-c', script, '--out', str(out)], True, 'x')})
    entry = gen.run_benchmark('x')
    assert entry['error'] == 'exit code 1: stage intrinsics: link lost'
    assert 'result' not in entry


def test_the_family_benchmarks_last_line_carries_the_rows_the_page_draws(tmp_path, monkeypatch,
                                                                         capsys):
    """benchmarks/rig_family.py's last line (plain mode) holds every rig's row with its
    verdict, and the page draws them; the rigs' evaluations are replaced by their rows here
    (the benchmark runs `galvoscan evaluate` for each, minutes a rig)."""
    spec = importlib.util.spec_from_file_location('rig_family_bench',
                                                  ROOT / 'benchmarks' / 'rig_family.py')
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    build = {'sensor': 'PYTHON500', 'bit_depth': 8, 'head': 'WIDE25', 'laser': 'above'}

    def evaluated(seed, folder, quick, timeout, model='physical', extra=(), rig_name=None,
                  **_):
        return {'seed': seed, 'completed': True, 'failures': [], 'wall_s': 1.0,
                'working_distance_mm': 587.0, 'build': build, 'distances': (),
                'by_distance_mm': {}, 'stair_rmse_mm': 0.04 + 0.2 * seed,
                'plate_rmse_mm': 0.156, 'transfer_matrix_error_rmse_mm': 0.73}

    monkeypatch.setattr(bench, 'run_rig', evaluated)
    assert bench.main(['--rigs', '2', '--distances', 'none', '--out', str(tmp_path)]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [(r['seed'], r['passed']) for r in last['rows']] == [(0, True), (1, False)]

    gen = _generator()
    monkeypatch.setattr(gen, 'RESULTS', tmp_path)
    gen.render({'demo': None, 'benchmarks': {'rig_family': _entry(last)}})
    rows = _rows(_section((tmp_path / 'accuracy.md').read_text(), 'rig_family'))
    assert ['0', 'PYTHON500, 8 bit, WIDE25, laser above', '587', '0.04', '0.156', '0.73',
            'yes'] in rows
    assert ['1', 'PYTHON500, 8 bit, WIDE25, laser above', '587', '0.24', '0.156', '0.73',
            'no'] in rows
