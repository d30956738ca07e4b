"""The calibration file: YAML, SI units, a format version, atomic writes.

Layout (``format_version: 1``)::

    format_version: 1
    units: SI (m, rad, V, px)
    created: 2026-11-21T09:00:00+00:00      # UTC, ISO 8601
    source: calibrated                       # or simulator_truth (tests/demos only)
    model: {...}                             # RigModel.to_dict(), every parameter in SI
    stages:                                  # per calibration stage, what made it
      dynamic_camera:
        created: ...
        bags: [{path: ..., sha256: ...}]
        residuals: {reprojection_rms_px: 0.1, ...}
    joint_correction: {...}                  # optional, see calibration_tools
    cell_T_v0: [[...], [...], [...], [0, 0, 0, 1]]  # optional: pose of V0 in the robot
                                             # cell (4x4 rigid, row by row, metres)

Loading validates structure, units (plausible magnitudes) and consistency and fails with a
ValueError that names the file and the key. Writing goes to a temporary file in the same
folder, is fsynced, then renamed over the target, so a crash never leaves half a file.
The reconstructor loads this file; the calibration node writes it. No rclpy here.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime as _dt
import hashlib
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from galvoscan_common.yamlfile import read_yaml_text
from reconstructor.correction import CorrectionTable
from reconstructor.model import RigModel
from reconstructor.tf_frames import check_cell_T_v0

FORMAT_VERSION = 1
SOURCES = ('calibrated', 'simulator_truth')

# key -> (low, high, unit, hint when the value looks like another unit). Magnitudes a real
# rig of this kind can have; values outside are refused as a likely unit mistake.
_PLAUSIBLE = {
    'l': (0.005, 0.5, 'm', 'millimetres'),
    'd': (0.002, 0.2, 'm', 'millimetres'),
    'intrinsics.fx': (100.0, 1e5, 'px', None),
    'intrinsics.fy': (100.0, 1e5, 'px', None),
    'g1_pan.theta0': (-math.pi, math.pi, 'rad', 'degrees'),
    'g1_tilt.theta0': (-math.pi, math.pi, 'rad', 'degrees'),
    'g2_tilt.theta0': (-math.pi, math.pi, 'rad', 'degrees'),
    'g1_pan.k': (-0.2, 0.2, 'rad/V', 'degrees per volt'),
    'g1_tilt.k': (-0.2, 0.2, 'rad/V', 'degrees per volt'),
    'g2_tilt.k': (-0.2, 0.2, 'rad/V', 'degrees per volt'),
}
_MAX_AXIS_POINT_M = 10.0


@dataclass
class Calibration:
    """A loaded (or to-be-saved) calibration file."""

    model: RigModel
    source: str = 'calibrated'
    stages: dict = field(default_factory=dict)
    joint_correction: dict | None = None
    cell_T_v0: np.ndarray | None = None  # (4, 4) [m]: V0 in the robot cell, when known
    created: str = ''
    path: str = ''
    content_hash: str = ''

    def to_dict(self) -> dict:
        data = {
            'format_version': FORMAT_VERSION,
            'units': 'SI (m, rad, V, px)',
            'created': self.created or now_iso(),
            'source': self.source,
            'model': self.model.to_dict(),
            'stages': copy.deepcopy(self.stages),
        }
        if self.joint_correction is not None:
            data['joint_correction'] = copy.deepcopy(self.joint_correction)
        if self.cell_T_v0 is not None:  # as it is: validate() judges it
            cell = self.cell_T_v0
            data['cell_T_v0'] = cell.tolist() if isinstance(cell, np.ndarray) else \
                copy.deepcopy(cell)
        return data


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


def _get(data, dotted):
    for part in dotted.split('.'):
        data = data[part]
    return data


def validate(data, origin='calibration') -> Calibration:
    """Check a parsed calibration document and build a :class:`Calibration`.

    Raises
    ------
    ValueError
        Naming ``origin`` and the key: missing key, wrong version, NaN, wrong shape or an
        implausible magnitude (e.g. millimetres where metres belong).
    """
    if not isinstance(data, dict):
        raise ValueError(f'{origin}: expected a YAML mapping at the top level')
    for key in ('format_version', 'model'):
        if key not in data:
            raise ValueError(f"{origin}: missing key '{key}'")
    version = data['format_version']
    if version != FORMAT_VERSION:
        raise ValueError(f"{origin}: format_version is {version!r}; this software reads "
                         f'version {FORMAT_VERSION}')
    source = data.get('source', 'calibrated')
    if source not in SOURCES:
        raise ValueError(f"{origin}: source must be one of {', '.join(SOURCES)}, got {source!r}")
    try:
        model = RigModel.from_dict(data['model'])
    except ValueError as exc:
        raise ValueError(f'{origin}: in model: {exc}') from None
    model_dict = data['model']
    for key, (lo, hi, unit, hint) in _PLAUSIBLE.items():
        value = float(_get(model_dict, key))
        if not lo <= value <= hi:
            extra = f'; it looks like {hint}' if hint else ''
            raise ValueError(f'{origin}: model.{key} = {value:g} is outside the plausible range '
                             f'[{lo:g}, {hi:g}] {unit}{extra}')
    point = model_dict['laser_axis_point']
    if max(abs(float(v)) for v in point) > _MAX_AXIS_POINT_M:
        raise ValueError(f'{origin}: model.laser_axis_point {point} is more than '
                         f'{_MAX_AXIS_POINT_M:g} m from V0; it looks like millimetres')
    offset = float(model_dict['laser_plane_v0'][3])
    if abs(offset) > _MAX_AXIS_POINT_M:
        raise ValueError(f'{origin}: model.laser_plane_v0[3] = {offset:g} puts the laser plane '
                         f'more than {_MAX_AXIS_POINT_M:g} m from V0 (it is the plane offset '
                         f'in metres); it looks like millimetres')
    stages = data.get('stages', {}) or {}
    if not isinstance(stages, dict):
        raise ValueError(f"{origin}: 'stages' must be a mapping of stage name to metadata")
    jc = data.get('joint_correction')
    if jc is not None:
        if not isinstance(jc, dict):
            raise ValueError(f"{origin}: 'joint_correction' must be a mapping")
        try:
            table = CorrectionTable.from_dict(jc)
        except ValueError as exc:
            raise ValueError(f'{origin}: in joint_correction: {exc}') from None
        model = dataclasses.replace(model, correction=table)
    cell_T_v0 = None
    if data.get('cell_T_v0') is not None:
        cell_T_v0 = _cell_T_v0(data['cell_T_v0'], origin)
    return Calibration(model=model, source=source, stages=stages, joint_correction=jc,
                       cell_T_v0=cell_T_v0, created=str(data.get('created', '')))


def _cell_T_v0(value, origin) -> np.ndarray:
    """The file's ``cell_T_v0``: 4 rows of 4 numbers, rigid, translation under 100 m."""
    rows_ok = isinstance(value, list) and len(value) == 4 and all(
        isinstance(row, list) and len(row) == 4 for row in value)
    if not rows_ok:
        raise ValueError(f'{origin}: cell_T_v0 must be a 4x4 matrix: 4 rows of 4 numbers, '
                         f'got {value!r}')
    for i, row in enumerate(value):
        for j, v in enumerate(row):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f'{origin}: cell_T_v0[{i}][{j}] must be a number, got {v!r}')
    try:
        return check_cell_T_v0(value)
    except ValueError as exc:
        raise ValueError(f'{origin}: {exc}') from None


def load(path) -> Calibration:
    """Read and validate a calibration file; errors name the file and the key."""
    path = Path(path)
    text = read_yaml_text(path, 'calibration file')
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: not valid YAML: {exc}') from None
    cal = validate(data, origin=str(path))
    cal.path = str(path.resolve())
    cal.content_hash = hashlib.sha256(text.encode()).hexdigest()
    return cal


def save(cal: Calibration, path) -> str:
    """Validate, then write ``cal`` atomically to ``path``. Returns the content sha256."""
    path = Path(path)
    data = cal.to_dict()
    validate(data, origin=str(path))  # never write a file we would refuse to load
    text = '# galvoscan calibration file (SI units: m, rad, V; pixels for intrinsics)\n'
    text += yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, 'w') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    cal.path = str(path.resolve())
    cal.content_hash = hashlib.sha256(text.encode()).hexdigest()
    return cal.content_hash
