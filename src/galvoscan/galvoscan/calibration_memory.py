"""Which calibration ``galvoscan demo`` or ``galvoscan calibrate`` wrote last, and for which rig.

``galvoscan run`` on a simulated rig gives the reconstructor that calibration when its
parameters name none, so that a first run after ``make demo`` gives calibrated clouds. The
record is one small YAML file in the user's state directory (``$GALVOSCAN_STATE_DIR``, else
``$XDG_STATE_HOME/galvoscan``, else ``~/.local/state/galvoscan``), never in the repository:

    path: /abs/path/out/calibration.yaml
    rig: reference          # the simulated rig it was made for (name, or a rig file's path)
    written_by: galvoscan demo
    written_at: '2026-11-27T19:40:00+00:00'

A record whose file has gone, or that was made for another rig, is not used.
"""

from __future__ import annotations

import argparse
import datetime
import os
from pathlib import Path

import yaml

RECORD = 'last_calibration.yaml'


def state_dir() -> Path:
    """The directory the record lives in (see the module docstring)."""
    if os.environ.get('GALVOSCAN_STATE_DIR'):
        return Path(os.environ['GALVOSCAN_STATE_DIR'])
    base = os.environ.get('XDG_STATE_HOME') or str(Path.home() / '.local' / 'state')
    return Path(base) / 'galvoscan'


def rig_key(rig: str | os.PathLike | None) -> str | None:
    """A rig's identity: a shipped rig's name as given, a rig file by its absolute path."""
    if rig is None:
        return None
    rig = str(rig)
    path = Path(rig)
    if rig.endswith(('.yaml', '.yml')) or path.exists():
        return str(path.resolve())
    return rig


def remember(path, rig, written_by: str) -> Path | None:
    """Record ``path`` as the last calibration of simulated rig ``rig``; returns the record.

    Nothing is recorded (``None``) when ``path`` does not exist. A record that cannot be
    written is not an error of the command that made the calibration: ``None`` too.
    """
    path = Path(path)
    if not path.is_file():
        return None
    record = {'path': str(path.resolve()), 'rig': rig_key(rig), 'written_by': written_by,
              'written_at': datetime.datetime.now(datetime.timezone.utc).isoformat(
                  timespec='seconds')}
    target = state_dir() / RECORD
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_suffix('.tmp')
        tmp.write_text(yaml.safe_dump(record, sort_keys=False))
        tmp.replace(target)
    except OSError:
        return None
    return target


def last(rig) -> dict | None:
    """The record of the last calibration made for simulated rig ``rig``, or ``None``.

    ``None`` when there is no record, it cannot be read, its calibration file has gone, or it
    was made for another rig.
    """
    try:
        record = yaml.safe_load((state_dir() / RECORD).read_text())
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(record, dict) or not isinstance(record.get('path'), str):
        return None
    if record.get('rig') is None or record.get('rig') != rig_key(rig):
        return None
    if not Path(record['path']).is_file():
        return None
    return record


def remember_from_command(command: str, argv) -> Path | None:
    """After ``galvoscan demo`` or ``galvoscan calibrate`` succeeded: record what it wrote.

    ``demo`` writes ``<--out>/calibration.yaml`` for ``--rig`` (default: the reference rig);
    ``calibrate`` writes ``--calibration FILE``, for ``--rig`` (with ``--sim``, default the
    reference rig). A calibration from bags with no ``--rig`` is not tied to a simulated rig and
    is not recorded. Other commands record nothing.
    """
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument('--out', default='out')
    p.add_argument('--rig')
    p.add_argument('--calibration')
    p.add_argument('--sim', action='store_true')
    p.add_argument('--truth-calibration', action='store_true')
    args, _ = p.parse_known_args(list(argv))
    if command == 'demo' and not args.truth_calibration:
        return remember(Path(args.out) / 'calibration.yaml', args.rig or 'reference',
                        'galvoscan demo')
    if command == 'calibrate' and args.calibration:
        rig = args.rig or ('reference' if args.sim else None)
        if rig is not None:
            return remember(args.calibration, rig, 'galvoscan calibrate')
    return None
