"""Reading a small YAML file that a user hands in, safely (no rclpy).

The checks every such file gets, in one place: a size cap (a YAML description is never
megabytes), UTF-8 text (a binary or UTF-16 file is named as such), no NUL bytes, valid
YAML, and a mapping at the top. Every failure is a ``ValueError`` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import yaml

#: Largest YAML file read [bytes].
MAX_YAML_BYTES = 16 * 2**20


def read_yaml_text(path, what: str = 'YAML file') -> str:
    """The text of the file at ``path``, checked to be small UTF-8 text without NUL bytes.

    Raises
    ------
    ValueError
        Unreadable, larger than :data:`MAX_YAML_BYTES`, not UTF-8 text, or NUL bytes; the
        message names the file and ``what`` it should be.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_YAML_BYTES:
            raise ValueError(f'{path}: not a {what}: {size} bytes (at most {MAX_YAML_BYTES})')
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f'{path}: cannot read {what}: {exc.strerror}') from None
    try:
        text = raw.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ValueError(f'{path}: not a {what}: not UTF-8 text (byte {exc.start}: '
                         f'{exc.reason}); is it binary, or saved as UTF-16?') from None
    if '\x00' in text:
        raise ValueError(f'{path}: not a {what}: it holds NUL bytes (binary data)')
    return text


def read_yaml_mapping(path, what: str = 'YAML file') -> dict:
    """The top-level mapping of the UTF-8 YAML file at ``path``.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file should be, for the messages (e.g. ``'cell reference'``).

    Raises
    ------
    ValueError
        As :func:`read_yaml_text`, or invalid YAML, or not a mapping at the top.
    """
    try:
        data = yaml.safe_load(read_yaml_text(path, what))
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: {what} is not valid YAML: {exc}') from None
    if not isinstance(data, dict):
        raise ValueError(f'{path}: {what}: expected a mapping of keys at the top, got '
                         f'{type(data).__name__}')
    return data
