"""docs/reference.md is what the code declares, no more and no less.

The page is regenerated from the nodes themselves (``tools/gen_reference.py``) and compared
with the committed one: a parameter, topic or service added in the code but not in the page
fails, and so does one left in the page after the code dropped it. A second check reads the
node sources for every literal ``declare_parameter('name'`` and finds each in the page, so
that the generator itself cannot miss a parameter unnoticed.
"""

from __future__ import annotations

import difflib
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / 'docs' / 'reference.md'
pytestmark = pytest.mark.dds


def _generator():
    spec = importlib.util.spec_from_file_location('gen_reference',
                                                  ROOT / 'tools' / 'gen_reference.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope='module')
def generated():
    return _generator().generate()


def test_the_reference_is_the_code(generated):
    committed = REFERENCE.read_text()
    gen = _generator()
    wrote_with = re.search(r'as Python (\d+\.\d+) prints it', committed)
    if wrote_with is None or wrote_with.group(1) != gen.PYTHON:
        # argparse words --help differently on another Python: compare the nodes' part only
        committed = committed.split(gen.COMMANDS_HEADING)[0]
        generated = generated.split(gen.COMMANDS_HEADING)[0]
    if committed != generated:
        diff = ''.join(list(difflib.unified_diff(
            committed.splitlines(True), generated.splitlines(True), 'docs/reference.md',
            'from the code'))[:80])
        pytest.fail('docs/reference.md is out of date; regenerate it with\n'
                    '    .venv/bin/python tools/gen_reference.py\n' + diff)


def test_every_declared_parameter_is_in_the_reference(generated):
    sources = {
        'galvo_driver': ROOT / 'src/galvo_driver/galvo_driver/driver_node.py',
        'stripe_extractor': ROOT / 'src/stripe_extractor/stripe_extractor/extractor_node.py',
        'reconstructor': ROOT / 'src/reconstructor/reconstructor/reconstructor_node.py',
        'calibration': ROOT / 'src/calibration_tools/calibration_tools/calibration_node.py',
    }
    sections = dict(zip(*[iter(re.split(r'^## `(\w+)`\s*$', generated, flags=re.M)[1:])] * 2,
                        strict=True))
    for node, path in sources.items():
        text = path.read_text()
        names = set(re.findall(r"declare_parameter\(\s*'(\w+)'", text))
        names |= set(re.findall(r"^\s+d\('(\w+)'", text, flags=re.M))
        assert names, f'no parameter found in {path}'
        for name in names:
            assert f'| `{name}` |' in sections[node], f'{node}.{name} is not in the reference'


def test_every_service_and_subcommand_is_in_the_reference(generated):
    from galvoscan.cli import DELEGATED

    for service in ('/scan/start', '/scan/stop', '/scan/progress', '/sim/set_scene',
                    '/reconstructor/reload_calibration', '/reconstructor/save_scan',
                    '/calibration/capture', '/calibration/compute', '/calibration/load',
                    '/calibration/save'):
        assert f'| `{service}` |' in generated, service
    for command in ('run', *DELEGATED, 'demo'):
        assert f'### `galvoscan {command}`' in generated, command
    assert 'usage: galvoscan scan' in generated
