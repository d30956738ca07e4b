"""A robot's flange poses for hand-eye calibration: files, messages' fields, and stillness.

The hand-eye stage (:mod:`calibration_tools.hand_eye`) needs ``base_T_flange`` (the robot
controller's report of its flange in its base frame) at every capture. They come from

- a file the operator hands in (:func:`read_robot_poses`), YAML::

      base_frame: base_link          # the frame the robot reports in
      flange_frame: tool0            # the frame the scanner is bolted to
      unit: m                        # positions in metres; anything else is refused
      poses:                         # in capture order: pose 0, 1, ...
        - position: [0.512, -0.103, 0.634]          # metres
          orientation: [0.0, 0.7071068, 0.0, 0.7071068]  # unit quaternion x y z w

  or CSV, one pose a line (``#`` starts a comment line)::

      base_frame,flange_frame,x,y,z,qx,qy,qz,qw
      base_link,tool0,0.512,-0.103,0.634,0.0,0.7071068,0.0,0.7071068

- or, in the calibration node, a ``geometry_msgs/PoseStamped`` topic: the node turns each
  message into a pose with :func:`pose_matrix`, keeps the latest in a :class:`PoseWatch`
  (is it fresh, did the robot stay still during the step) and writes what it recorded
  with :func:`write_robot_poses`, in the YAML format above, so that the offline command
  reads it back.

Refused, naming the key or line: NaN or infinite numbers, positions beyond
:data:`MAX_REACH_M` (millimetres given for metres), quaternions whose norm is off 1 by more
than :data:`QUATERNION_NORM_TOL` (not a rotation, or w first), fewer than
:data:`MIN_POSES` poses, unknown keys or columns, frames that differ between lines.

No rclpy.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The fewest robot poses hand-eye calibration accepts (:mod:`calibration_tools.hand_eye`).
MIN_POSES = 5
#: Largest distance of a flange position from the robot base accepted [m]: a larger one is
#: almost certainly millimetres given for metres.
MAX_REACH_M = 10.0
#: How far from 1 a quaternion's norm may be (rounding in a controller's printout); the
#: quaternion is normalised.
QUATERNION_NORM_TOL = 1e-3
#: The CSV header, in this order.
CSV_COLUMNS = ('base_frame', 'flange_frame', 'x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')
_YAML_KEYS = {'base_frame', 'flange_frame', 'unit', 'poses'}
_POSE_KEYS = {'position', 'orientation'}


@dataclass(frozen=True, eq=False)
class RobotPoses:
    """Flange poses reported by a robot.

    Attributes
    ----------
    base_frame, flange_frame : str
    base_T_flange : ndarray, shape (n, 4, 4), metres
    keys : tuple of int
        Each pose's number (its capture's robot pose; ``0..n-1`` for a file).
    source : str
        Where they came from (file path, topic), for messages.
    """

    base_frame: str
    flange_frame: str
    base_T_flange: np.ndarray
    keys: tuple
    source: str = ''

    def by_key(self) -> dict:
        """``{key: base_T_flange (4, 4)}``."""
        return dict(zip(self.keys, self.base_T_flange, strict=True))


def frame_name(value, what: str) -> str:
    """``value`` as a frame name (non-empty, no white space), or ValueError naming ``what``."""
    if not isinstance(value, str) or not value or any(c.isspace() for c in value):
        raise ValueError(f'{what}: expected a frame name, got {value!r}')
    return value


def _numbers(values, n: int, what: str) -> np.ndarray:
    if isinstance(values, (str, bytes, dict)) or not hasattr(values, '__len__') \
            or len(values) != n:
        raise ValueError(f'{what}: expected {n} numbers, got {values!r}')
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f'{what}: expected {n} numbers, got {values!r}')
        out.append(float(v))
    a = np.array(out)
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{what}: not finite: {values!r}')
    return a


def pose_matrix(position, orientation_xyzw, what: str = 'pose') -> np.ndarray:
    """``base_T_flange`` (4, 4) from a position [m] and a unit quaternion (x, y, z, w).

    Parameters
    ----------
    position : sequence of 3 float, metres
    orientation_xyzw : sequence of 4 float
        Normalised here when its norm is within :data:`QUATERNION_NORM_TOL` of 1.
    what : str
        What the error names (``'poses[3]'``, ``'line 5'``).

    Raises
    ------
    ValueError
        Wrong counts, non-finite numbers, a position beyond :data:`MAX_REACH_M` or a
        quaternion that is not a unit one.
    """
    from galvoscan_common.tf_tree import transform_from_tq

    p = _numbers(position, 3, f'{what}: position')
    q = _numbers(orientation_xyzw, 4, f'{what}: orientation')
    reach = float(np.linalg.norm(p))
    if reach > MAX_REACH_M:
        raise ValueError(f'{what}: position {reach:g} m from the base, beyond {MAX_REACH_M:g} '
                         'm: positions are in metres (millimetres given?)')
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise ValueError(f'{what}: orientation is not a unit quaternion (norm {norm:.6g}); '
                         'give x, y, z, w with w last')
    return transform_from_tq(p, q / norm)


def pose_fields(T) -> tuple[list, list]:
    """``(position [m], quaternion x y z w)`` of a (4, 4) rigid transform, as plain floats."""
    from galvoscan_common.tf_tree import quaternion_from_matrix

    T = np.asarray(T, dtype=np.float64)
    q = quaternion_from_matrix(T)  # w >= 0
    return [float(v) for v in T[:3, 3]], [float(v) for v in q]


def _checked(base_frame, flange_frame, poses: list, source: str) -> RobotPoses:
    if len(poses) < MIN_POSES:
        raise ValueError(f'{source}: {len(poses)} poses: hand-eye calibration needs at least '
                         f'{MIN_POSES}')
    return RobotPoses(base_frame, flange_frame, np.stack(poses), tuple(range(len(poses))),
                      str(source))


def read_robot_poses(path) -> RobotPoses:
    """The flange poses of a YAML file, or of a CSV file (``.csv``): see the module's text.

    Raises
    ------
    ValueError
        Unreadable file, unknown or missing keys or columns, another unit than ``m``,
        non-finite numbers, millimetres, non-unit quaternions, frames that differ between
        CSV lines, or fewer than :data:`MIN_POSES` poses; the key or line is named.
    """
    path = Path(path)
    if path.suffix.lower() == '.csv':
        return _read_csv(path)
    from galvoscan_common.yamlfile import read_yaml_mapping

    data = read_yaml_mapping(path, 'robot poses file')
    unknown = set(data) - _YAML_KEYS
    if unknown:
        raise ValueError(f'{path}: unknown keys {sorted(unknown)} (known: {sorted(_YAML_KEYS)})')
    if data.get('unit') != 'm':
        raise ValueError(f"{path}: unit: positions must be in metres ('m'), got "
                         f"{data.get('unit')!r}")
    try:
        base = frame_name(data.get('base_frame'), 'base_frame')
        flange = frame_name(data.get('flange_frame'), 'flange_frame')
    except ValueError as err:
        raise ValueError(f'{path}: {err}') from None
    entries = data.get('poses')
    if not isinstance(entries, list):
        raise ValueError(f'{path}: poses: expected a list of {{position: [x, y, z], '
                         f'orientation: [qx, qy, qz, qw]}}, got {type(entries).__name__}')
    poses = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise ValueError(f'{path}: poses[{i}]: expected a mapping with position and '
                             f'orientation, got {entry!r}')
        unknown = set(entry) - _POSE_KEYS
        missing = _POSE_KEYS - set(entry)
        if unknown or missing:
            raise ValueError(f'{path}: poses[{i}]: ' + (
                f'unknown keys {sorted(unknown)}' if unknown else f'missing {sorted(missing)}')
                + ' (expected position and orientation)')
        try:
            poses.append(pose_matrix(entry['position'], entry['orientation'], f'poses[{i}]'))
        except ValueError as err:
            raise ValueError(f'{path}: {err}') from None
    return _checked(base, flange, poses, path)


def _read_csv(path: Path) -> RobotPoses:
    from galvoscan_common.yamlfile import read_yaml_text

    text = read_yaml_text(path, 'robot poses CSV file')  # the same size / UTF-8 / NUL checks
    rows = [(n, row) for n, row in enumerate(csv.reader(io.StringIO(text)), start=1)
            if row and not row[0].lstrip().startswith('#') and any(c.strip() for c in row)]
    if not rows:
        raise ValueError(f'{path}: no header line: expected {",".join(CSV_COLUMNS)}')
    n, header = rows[0]
    header = [c.strip() for c in header]
    if tuple(header) != CSV_COLUMNS:
        unknown = sorted(set(header) - set(CSV_COLUMNS))
        raise ValueError(f'{path}: line {n}: columns {header}' +
                         (f' (unknown {unknown})' if unknown else '') +
                         f': expected {",".join(CSV_COLUMNS)}')
    base = flange = None
    poses = []
    for n, row in rows[1:]:
        row = [c.strip() for c in row]
        if len(row) != len(CSV_COLUMNS):
            raise ValueError(f'{path}: line {n}: {len(row)} fields, expected '
                             f'{len(CSV_COLUMNS)} ({",".join(CSV_COLUMNS)})')
        try:
            frames = (frame_name(row[0], f'line {n}: base_frame'),
                      frame_name(row[1], f'line {n}: flange_frame'))
            values = []
            for name, cell in zip(CSV_COLUMNS[2:], row[2:], strict=True):
                try:
                    values.append(float(cell))
                except ValueError:
                    raise ValueError(f'line {n}: {name}: not a number: {cell!r}') from None
            T = pose_matrix(values[:3], values[3:], f'line {n}')
        except ValueError as err:
            raise ValueError(f'{path}: {err}') from None
        if base is None:
            base, flange = frames
        elif frames != (base, flange):
            raise ValueError(f'{path}: line {n}: frames {frames[0]} -> {frames[1]} differ from '
                             f'the first line\'s {base} -> {flange}')
        poses.append(T)
    return _checked(base or '', flange or '', poses, path)


def write_robot_poses(poses: RobotPoses, path) -> None:
    """Write ``poses`` as a YAML robot poses file (:func:`read_robot_poses` reads it back;
    replaced atomically). A file of fewer than :data:`MIN_POSES` poses is written, but reading it
    is refused until it holds enough."""
    import os

    lines = [f'base_frame: {poses.base_frame}', f'flange_frame: {poses.flange_frame}',
             'unit: m', f'# from {poses.source}' if poses.source else '', 'poses:']
    for T in poses.base_T_flange:
        p, q = pose_fields(T)
        lines.append(f'  - {{position: {[round(v, 9) for v in p]}, '
                     f'orientation: {[round(v, 12) for v in q]}}}')
    path = Path(path)
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text('\n'.join(line for line in lines if line) + '\n')
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- streams
def _turn(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return float(math.acos(min(1.0, max(-1.0, c))))


class PoseWatch:
    """The latest pose of a robot's pose stream: is it fresh, and did the robot stay still?

    The calibration node feeds it every message (:meth:`add`, or :meth:`reject` for one it
    could not read) and asks it at every capture step of the hand-eye stage. Times are
    seconds on one clock (the node's), ``stamp`` is the message's header stamp.

    Parameters
    ----------
    max_age : float, seconds
        The latest pose must be stamped no longer ago than this (the robot's driver streams
        its pose; a pose older than this is not where the robot is now).
    still_m, still_rad : float, metres, radians
        How far the flange may move while the scanner measures (a still robot's report
        jitters by micrometres).
    """

    def __init__(self, max_age: float, still_m: float, still_rad: float):
        self.set_limits(max_age, still_m, still_rad)
        self.latest = None  # (T, stamp, frame)
        self.received = 0
        self.rejected = 0
        self._held = None
        self._moved = (0.0, 0.0)
        self._bad = ''
        self._unreadable = (0, '')  # since the latest pose: how many, and the last reason

    def set_limits(self, max_age: float, still_m: float, still_rad: float) -> None:
        """The age [s] and motion [m, rad] limits (see the class), each a number > 0."""
        for name, v in (('max_age', max_age), ('still_m', still_m), ('still_rad', still_rad)):
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v)
                                           and v > 0):
                raise ValueError(f'{name} must be a number > 0, got {v!r}')
        self.max_age, self.still_m, self.still_rad = float(max_age), float(still_m), \
            float(still_rad)

    def add(self, T, stamp: float, frame: str) -> None:
        """A pose received: ``T`` (4, 4) from :func:`pose_matrix`, its stamp [s] and frame."""
        self.latest = (np.asarray(T, dtype=np.float64), float(stamp), str(frame))
        self.received += 1
        self._unreadable = (0, '')
        if self._held is not None:
            ref = self._held[0]
            d = float(np.linalg.norm(self.latest[0][:3, 3] - ref[:3, 3]))
            a = _turn(ref[:3, :3].T @ self.latest[0][:3, :3])
            self._moved = (max(self._moved[0], d), max(self._moved[1], a))
            if frame != self._held[2]:
                self._bad = self._bad or f'frame changed from {self._held[2]} to {frame}'

    def reject(self, reason: str) -> None:
        """A message that could not be read (``reason``): a step it falls in is refused."""
        self.rejected += 1
        self._unreadable = (self._unreadable[0] + 1, reason)
        if self._held is not None:
            self._bad = self._bad or f'an unreadable pose arrived ({reason})'

    def fresh(self, now: float, topic: str = 'the pose topic'):
        """The latest pose ``(T, stamp, frame)`` if it is fresh, else ValueError saying why."""
        n, reason = self._unreadable
        unreadable = f'; {n} later message(s) could not be read ({reason})' if n else ''
        if self.latest is None:
            raise ValueError(f'no robot pose received on {topic}: is the robot driver '
                             f'publishing?{unreadable}')
        age = now - self.latest[1]
        if age > self.max_age:
            raise ValueError(f'the latest robot pose on {topic} is stamped {age:.2f} s ago, '
                             f'older than robot_pose_max_age {self.max_age:g} s: the robot '
                             f'driver must stream its pose while the scanner measures'
                             f'{unreadable}')
        if age < -self.max_age:
            raise ValueError(f'the latest robot pose on {topic} is stamped {-age:.2f} s in '
                             'the future: the robot\'s clock and this node\'s differ')
        return self.latest

    def hold(self, now: float, topic: str = 'the pose topic'):
        """Start a measurement at the latest (fresh) pose; returns it ``(T, stamp, frame)``."""
        latest = self.fresh(now, topic)
        self._held, self._moved, self._bad = latest, (0.0, 0.0), ''
        return latest

    def check_still(self, now: float, what: str, topic: str = 'the pose topic') -> None:
        """ValueError if, since :meth:`hold`, the stream went stale, a pose could not be read,
        the frame changed or the flange moved beyond ``still_m`` / ``still_rad``."""
        if self._held is None:
            raise ValueError('check_still before hold')
        try:
            self.fresh(now, topic)
        except ValueError as err:
            raise ValueError(f'{what}: {err}') from None
        if self._bad:
            raise ValueError(f'{what}: {self._bad}')
        d, a = self._moved
        if d > self.still_m or a > self.still_rad:
            raise ValueError(f'{what}: the robot moved by {d * 1e3:.3f} mm and '
                             f'{math.degrees(a):.4f} deg while the scanner measured '
                             f'(robot_still_m {self.still_m * 1e3:g} mm, robot_still_rad '
                             f'{self.still_rad:g} rad): keep it still until the step ends')

    def release(self) -> None:
        self._held = None
