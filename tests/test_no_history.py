"""The project's files speak of the product, never of how it was developed.

Code, comments, docstrings and documentation state a design reason as a reason; they do not
cite development sessions or tracker numbers. This test greps every ``*.py`` and ``*.md`` file
of the repository (outside the virtual environment, build output and third-party files) for
the pattern below and lists each hit as ``file:line: text``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: what must not appear (case-insensitive)
HISTORY = re.compile(r'(first|second|third|[a-z]+th) session|issue [0-9]+', re.IGNORECASE)

#: directory names never searched: environments, build and demo output, third-party files
SKIP_DIRS = {'.venv', '.git', 'node_modules', 'build', 'install', 'log', 'out', '__pycache__',
             '.pytest_cache', '.ruff_cache', '.hypothesis', 'vendor', 'third_party',
             'third-party'}
#: paths (relative to the root) of third-party files kept in the tree
SKIP_PATHS = {'tests/data'}
SUFFIXES = ('.py', '.md')


def project_files(root: Path = ROOT):
    """Every ``*.py`` and ``*.md`` file under ``root`` that the project itself wrote."""
    for dirpath, dirnames, filenames in os.walk(root):
        rel = Path(dirpath).relative_to(root)
        dirnames[:] = sorted(d for d in dirnames if d not in SKIP_DIRS
                             and (rel / d).as_posix() not in SKIP_PATHS
                             and not d.endswith('.egg-info'))
        for name in sorted(filenames):
            if name.endswith(SUFFIXES):
                yield Path(dirpath) / name


def history_hits(files, root: Path = ROOT) -> list[str]:
    """``file:line: text`` of every line matching :data:`HISTORY`."""
    hits = []
    for path in files:
        try:
            text = path.read_text(encoding='utf-8', errors='replace')
        except OSError as exc:
            hits.append(f'{path.relative_to(root)}: unreadable: {exc}')
            continue
        lines = text.splitlines()
        for number, line in enumerate(lines, 1):
            # a phrase wrapped onto the next line (comment and quote marks dropped) counts too
            after = lines[number].strip().lstrip('#*>"\'').strip() if number < len(lines) else ''
            if HISTORY.search(line) or (HISTORY.search(f'{line.rstrip()} {after}')
                                        and not HISTORY.search(after)):
                hits.append(f'{path.relative_to(root)}:{number}: {line.strip()[:160]}')
    return hits


def test_no_file_mentions_development_history():
    files = list(project_files())
    assert any(p.name == 'README.md' for p in files), 'README.md was not searched'
    hits = history_hits(files)
    assert not hits, ('development history in the project files (state the reason, not the '
                      'history):\n' + '\n'.join(hits))


def test_the_search_finds_what_it_must_and_skips_what_it_may(tmp_path):
    # the words are assembled here so that this file itself stays clean
    bad = 'as measured in the fif' + 'th sess' + 'ion'
    (tmp_path / 'pkg').mkdir()
    (tmp_path / 'pkg' / 'mod.py').write_text(f'x = 1\n# {bad}\n')
    (tmp_path / 'guide.md').write_text('see Iss' + 'ue 20 for the range\n')
    (tmp_path / 'pkg' / 'wrapped.py').write_text('# as measured in the fif' + 'th\n# sess'
                                                 + 'ion, on the reference rig\n')
    (tmp_path / 'notes.txt').write_text(bad)                      # not a searched suffix
    for skipped in ('.venv/lib', 'node_modules/three', 'build/msgs', 'tests/data'):
        (tmp_path / skipped).mkdir(parents=True)
        (tmp_path / skipped / 'x.md').write_text(bad)
    (tmp_path / 'protocol.md').write_text('a board link lasts from one HELLO to the next\n')
    hits = history_hits(project_files(tmp_path), tmp_path)
    assert hits == [f'guide.md:1: see Iss{"ue"} 20 for the range', f'pkg/mod.py:2: # {bad}',
                    f'pkg/wrapped.py:1: # as measured in the fif{"th"}']
