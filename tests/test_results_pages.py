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
