"""Input readers shared by :mod:`rig` and :mod:`scene`: kinds of YAML file (where they are
shipped, their format version), the pose sections both kinds hold (on top of
:mod:`config`), and ray bundles passed to the tracers."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Section, read_shipped_or_file, read_yaml_text, shipped_names
from .spatial import make_transform, rotation_from_vector

#: Hint of a length given in millimetres where metres are expected.
MM_HINT = 'metres expected, not millimetres'


@dataclass(frozen=True)
class FileKind:
    """One kind of YAML input file (rigs, scenes).

    Attributes
    ----------
    version : int
        The ``format_version`` a file must declare.
    directory : Path
        Folder of the files shipped with the package.
    """

    version: int
    directory: Path

    def open(self, data: dict, source: str) -> tuple[Section, str]:
        """The top section of a parsed file and its ``name`` (checks the header)."""
        top = Section(data, source)
        return top, top.header(self.version)

    def read(self, name_or_path) -> tuple[dict, str]:
        """(parsed data, source) of a shipped name or a path to a YAML file."""
        return read_shipped_or_file(name_or_path, self.directory)

    def read_text(self, text: str, source: str) -> tuple[dict, str]:
        """(parsed data, source) of YAML text."""
        return read_yaml_text(text, source), source

    def shipped(self) -> list[str]:
        """Names of the shipped files."""
        return shipped_names(self.directory)


def read_pose(p: Section, max_translation: float, **rotation) -> np.ndarray:
    """Pose section ``{translation [m], rotation_vector [rad]}`` as a (4, 4) transform.

    ``translation`` must lie within +-``max_translation``; ``rotation`` is passed on to the
    ``rotation_vector`` read (e.g. a ``default``). The section is finished (unknown keys
    are rejected).
    """
    t = p.vector('translation', 3, -max_translation, max_translation, 'm', hint=MM_HINT)
    r = p.vector('rotation_vector', 3, -4.0 * math.pi, 4.0 * math.pi, 'rad', **rotation)
    p.finish()
    return make_transform(rotation_from_vector(r), t)


def as_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """A ray bundle as float64 arrays (o, d), each of shape (n, 3).

    Raises
    ------
    ValueError
        Naming the argument of the wrong shape.
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f'origins: expected shape (n, 3), got {o.shape}')
    if d.shape != o.shape:
        raise ValueError(f'directions: expected shape {o.shape}, got {d.shape}')
    return o, d
