"""A rosbags type store for ROS 2 Jazzy plus the galvoscan_msgs interfaces.

The galvoscan_msgs ``.msg`` files are looked up, in this order, under
``<prefix>/share/galvoscan_msgs/msg`` for every prefix in ``AMENT_PREFIX_PATH`` (colcon or apt
installs), then under ``<sys.prefix>/share/galvoscan_msgs/msg`` (the venv's cmake install), then
in the repository's ``msgs/msg`` (a source checkout). No rclpy here.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

#: ROS package name of the galvoscan interfaces.
MSGS_PACKAGE = 'galvoscan_msgs'


def msg_dir_candidates() -> list[Path]:
    """Directories searched for the galvoscan_msgs ``.msg`` files, in search order."""
    candidates = []
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / 'share' / MSGS_PACKAGE / 'msg')
    candidates.append(Path(sys.prefix) / 'share' / MSGS_PACKAGE / 'msg')
    # src/galvoscan_bag/galvoscan_bag/typestore.py -> repository root is parents[3].
    candidates.append(Path(__file__).resolve().parents[3] / 'msgs' / 'msg')
    return candidates


def find_msg_dir() -> Path:
    """Return the first candidate directory that holds galvoscan_msgs ``.msg`` files.

    Raises
    ------
    FileNotFoundError
        If no candidate directory holds any ``.msg`` file.
    """
    candidates = msg_dir_candidates()
    for candidate in candidates:
        if candidate.is_dir() and any(candidate.glob('*.msg')):
            return candidate
    searched = ', '.join(str(c) for c in candidates)
    raise FileNotFoundError(f'no {MSGS_PACKAGE} .msg files found; searched: {searched}')


def make_typestore(msg_dir: Path | str | None = None) -> Typestore:
    """Build a new type store: ROS 2 Jazzy types plus every ``.msg`` in ``msg_dir``.

    Parameters
    ----------
    msg_dir : path, optional
        Directory of galvoscan_msgs ``.msg`` files; default :func:`find_msg_dir`.

    Returns
    -------
    Typestore
        A fresh, independent store (callers may register more types in it).
    """
    directory = find_msg_dir() if msg_dir is None else Path(msg_dir)
    files = sorted(directory.glob('*.msg'))
    if not files:
        raise ValueError(f'msg_dir {directory} holds no .msg files')
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in files:
        types.update(
            get_types_from_msg(path.read_text(encoding='utf8'), f'{MSGS_PACKAGE}/msg/{path.stem}')
        )
    store.register(types)
    return store


@functools.lru_cache(maxsize=1)
def default_typestore() -> Typestore:
    """The shared type store of :func:`make_typestore` (built once). Do not register into it."""
    return make_typestore()
