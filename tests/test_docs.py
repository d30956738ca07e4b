"""The guides' commands run as written, and their links lead somewhere.

A fenced block opened with ```` ```sh runnable ```` is run as a bash script (``set -e``) from
the repository root with the venv's ``bin/`` first on PATH, as a reader who typed
``source .venv/bin/activate`` would. Only quick commands that need no running graph are
marked runnable; the tour's commands are covered by tests/test_first_run_dds.py.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / 'README.md', *sorted((ROOT / 'docs').rglob('*.md'))]
RUNNABLE = re.compile(r'^```sh runnable\n(.*?)^```', re.M | re.S)
LINK = re.compile(r'\]\(([^)\s]+)\)')

#: pages other guides link to that are written on their own (their authors add them)
WRITTEN_ELSEWHERE = {'docs/hardware.md', 'docs/board-protocol.md', 'docs/calibrate-real-rig.md',
                     'docs/materials.md'}


def runnable_blocks():
    for page in PAGES:
        text = page.read_text()
        for m in RUNNABLE.finditer(text):
            line = text.count('\n', 0, m.start()) + 1
            yield pytest.param(m.group(1), id=f'{page.relative_to(ROOT)}:{line}')


def test_there_are_runnable_blocks():
    assert len(list(runnable_blocks())) >= 3


@pytest.mark.parametrize('script', list(runnable_blocks()))
def test_a_runnable_block_runs_as_written(script, tmp_path):
    env = dict(os.environ, PATH=f'{Path(sys.executable).parent}:{os.environ["PATH"]}',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.run(['bash', '-e', '-c', script], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, f'{script}\n--- output ---\n{proc.stdout}\n{proc.stderr}'


def test_every_relative_link_leads_to_a_file():
    broken = []
    for page in PAGES:
        text = re.sub(r'```.*?```', '', page.read_text(), flags=re.S)
        for target in LINK.findall(text):
            if re.match(r'[a-z]+:', target) or target.startswith('#'):
                continue
            path = (page.parent / target.split('#')[0]).resolve()
            rel = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path)
            if not path.exists() and rel not in WRITTEN_ELSEWHERE:
                broken.append(f'{page.relative_to(ROOT)}: {target}')
    assert not broken, 'links to nothing:\n' + '\n'.join(broken)


def test_the_readme_stays_short_with_the_two_commands_first():
    lines = (ROOT / 'README.md').read_text().splitlines()
    assert len(lines) <= 300, len(lines)
    first_block = next(i for i, line in enumerate(lines) if line.startswith('```'))
    assert lines[first_block + 1].startswith('make demo')
    assert lines[first_block + 2].startswith('make test')
