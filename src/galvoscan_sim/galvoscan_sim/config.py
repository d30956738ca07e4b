"""Validated reading of the simulator's YAML files (rigs and scenes).

Every problem raises :class:`ConfigError`, whose message names the file, the key (as a
dotted path such as ``g1.l`` or ``objects[2].type``) and what was expected. Numbers carry
a plausible range in SI units so that a value given in the wrong unit (for example
``l: 83.45`` where metres are expected) is caught instead of silently simulated.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

#: Largest rig or scene file read [bytes]: a bigger one is not a rig or scene description.
MAX_FILE_BYTES = 16 * 2**20


class ConfigError(ValueError):
    """A rig or scene file is missing a key, has a wrong value or an unknown entry."""

    def __init__(self, source: str, key: str, expected: str, got=None, has_got=False):
        self.source = source
        self.key = key
        self.expected = expected
        msg = f'{source}: key {key!r}: expected {expected}'
        if has_got:
            msg += f', got {got!r}'
        super().__init__(msg)


_MISSING = object()


def _as_number(value):
    """PyYAML (YAML 1.1) reads ``3.5e7`` (no exponent sign) as a string; accept it."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def read_yaml_text(text: str, source: str) -> dict:
    """Parse YAML text whose top level must be a mapping."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(source, '<file>', f'valid YAML ({exc})') from exc
    if not isinstance(data, dict):
        raise ConfigError(source, '<top level>', 'a mapping of keys', type(data).__name__,
                          True)
    return data


def read_yaml_file(path: Path) -> dict:
    """The mapping of a UTF-8 YAML file; ConfigError naming the file for anything else."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(str(path), '<file>', f'a readable file ({exc.strerror})') from exc
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(str(path), '<file>', f'a YAML file under {MAX_FILE_BYTES} bytes',
                          len(data), True)
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), '<file>', f'UTF-8 YAML text (byte {exc.start} is '
                          f'0x{data[exc.start]:02x}: a binary or UTF-16 file?)') from None
    if '\x00' in text:
        raise ConfigError(str(path), '<file>', 'YAML text (it holds NUL bytes: a binary file?)')
    return read_yaml_text(text, str(path))


def read_shipped_or_file(name_or_path, directory: Path) -> tuple[dict, str]:
    """(data, source) of a YAML file shipped in ``directory`` (by name) or at a path."""
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = directory / f'{name_or_path}.yaml'
    return read_yaml_file(path), str(path)


def shipped_names(directory: Path) -> list[str]:
    """Names of the YAML files shipped in ``directory``."""
    return sorted(p.stem for p in directory.glob('*.yaml'))


class Section:
    """A mapping from a YAML file, read with typed, range-checked accessors.

    Keys are consumed as they are read; :meth:`finish` rejects any key left over (a typo
    or an option this format does not have).
    """

    def __init__(self, data, source: str, path: str = ''):
        if not isinstance(data, dict):
            raise ConfigError(source, path or '<top level>', 'a mapping of keys',
                              type(data).__name__, True)
        self.data = data
        self.source = source
        self.path = path
        self._used: set[str] = set()

    def key(self, name: str) -> str:
        return f'{self.path}.{name}' if self.path else name

    def error(self, name: str, expected: str, got=_MISSING) -> ConfigError:
        if got is _MISSING:
            return ConfigError(self.source, self.key(name), expected)
        return ConfigError(self.source, self.key(name), expected, got, True)

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str, expected: str, default=_MISSING):
        self._used.add(name)
        if name not in self.data:
            if default is not _MISSING:
                return default
            raise self.error(name, f'{expected} (the key is missing)')
        return self.data[name]

    def section(self, name: str, default_empty: bool = False) -> Section:
        value = self.raw(name, 'a mapping of keys', {} if default_empty else _MISSING)
        return Section(value, self.source, self.key(name))

    def number(self, name: str, lo: float, hi: float, unit: str, default=_MISSING,
               hint: str = '') -> float:
        """A real number in [lo, hi] (SI ``unit``)."""
        expected = f'a number in [{lo:g}, {hi:g}] {unit}'
        value = _as_number(self.raw(name, expected, default))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(name, expected, value)
        value = float(value)
        if not math.isfinite(value):
            raise self.error(name, expected, value)
        if not lo <= value <= hi:
            extra = f' ({hint})' if hint else ''
            raise self.error(
                name, f'{expected}: the value is implausible in SI units{extra}', value)
        return value

    def integer(self, name: str, lo: int, hi: int, unit: str = '', default=_MISSING) -> int:
        expected = f'an integer in [{lo}, {hi}] {unit}'.rstrip()
        value = self.raw(name, expected, default)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise self.error(name, expected, value)
        return int(value)

    def boolean(self, name: str, default=_MISSING) -> bool:
        value = self.raw(name, 'true or false', default)
        if not isinstance(value, bool):
            raise self.error(name, 'true or false', value)
        return value

    def string(self, name: str, choices=None, default=_MISSING) -> str:
        expected = 'one of: ' + ', '.join(sorted(choices)) if choices else 'a string'
        value = self.raw(name, expected, default)
        if not isinstance(value, str) or (choices and value not in choices):
            raise self.error(name, expected, value)
        return value

    def vector(self, name: str, n: int, lo: float, hi: float, unit: str, default=_MISSING,
               hint: str = '') -> np.ndarray:
        """A list of ``n`` numbers, each in [lo, hi] (SI ``unit``)."""
        expected = f'a list of {n} numbers, each in [{lo:g}, {hi:g}] {unit}'
        value = self.raw(name, expected, default)
        if isinstance(value, (list, tuple)):
            value = [_as_number(v) for v in value]
        if not isinstance(value, (list, tuple)) or len(value) != n or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise self.error(name, expected, value)
        arr = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise self.error(name, expected, value)
        if np.any(arr < lo) or np.any(arr > hi):
            extra = f' ({hint})' if hint else ''
            raise self.error(
                name, f'{expected}: a value is implausible in SI units{extra}', value)
        return arr

    def header(self, version: int) -> str:
        """Read a file's ``format_version`` (must equal ``version``), ``name`` and optional
        ``description``; returns the name."""
        got = self.integer('format_version', 1, 1000)
        if got != version:
            raise self.error('format_version', f'{version}', got)
        name = self.string('name')
        self.raw('description', 'a string', '')
        return name

    def finish(self) -> None:
        """Reject keys that were never read."""
        extra = sorted(set(self.data) - self._used)
        if extra:
            known = ', '.join(sorted(self._used)) or '(none)'
            raise self.error(extra[0], f'no such key here; known keys: {known}')
