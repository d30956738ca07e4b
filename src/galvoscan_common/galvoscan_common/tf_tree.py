"""A minimal tf2 buffer in numpy: a tree of frames, static and stamped transforms, lookups.

tf2_ros is not on PyPI, so the tests and tools that listen to ``/tf`` and ``/tf_static`` fill
a :class:`TfBuffer` instead. It follows tf2's rules where they matter:

- Every frame has at most one parent. A transform ``parent_T_child`` (4x4, maps points in
  the child frame to the parent frame) is the edge ``parent -> child``; a ``/tf_static``
  transform holds at every time, a ``/tf`` transform is a sample at its stamp.
- :meth:`TfBuffer.lookup` walks from both frames up to their common ancestor and returns
  ``target_T_source``. At a given time each stamped edge is interpolated between its two
  neighbouring samples (translation linearly, rotation by slerp); with no time, at the latest
  time every stamped edge of the chain has (tf2's ``Time(0)``).
- Unknown frames, frames in two separate trees, a transform that would close a loop and a
  time outside a stamped edge's samples (by more than ``extrapolation_tolerance``) are
  errors that say which frame and which times. A refused transform changes nothing.
- Each stamped edge keeps a bounded history: at most ``max_history`` samples and none older
  than ``cache_time`` before its newest (tf2 keeps 10 s).

Times are integer nanoseconds (``sec * 10**9 + nanosec`` of a ``builtin_interfaces/Time``).
The conversions between a 4x4 transform and (translation, quaternion x y z w) of a
``geometry_msgs/Transform`` live here, once. No rclpy.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

#: How far a rotation block may be from orthonormal (max |R^T R - I|) and a quaternion's
#: squared norm from 1 before they are refused (tf2 refuses |q|^2 off by more than 1e-2).
RIGID_TOL = 1e-6
QUATERNION_NORM_TOL = 1e-2
#: tf2's default length of the stamped history [ns].
DEFAULT_CACHE_TIME_NS = 10 * 10**9


class TfError(ValueError):
    """A lookup or an insertion that the tree cannot answer or accept."""


class UnknownFrameError(TfError):
    """A frame that no transform names."""


class ConnectivityError(TfError):
    """Two frames in separate trees."""


class LoopError(TfError):
    """A transform that would make a frame its own ancestor."""


class ExtrapolationError(TfError):
    """A time outside a stamped edge's samples, by more than the tolerance."""


# ---- conversions ------------------------------------------------------------------------------
def check_rigid(T, name: str = 'transform', tol: float = RIGID_TOL) -> np.ndarray:
    """Return ``T`` as a float64 (4, 4) rigid transform, or raise ValueError naming it.

    Parameters
    ----------
    T : array_like, shape (4, 4) (or 16 numbers, row-major)
        Translation in metres.
    name : str
        What the error messages call it.
    tol : float
        Largest allowed ``|R^T R - I|`` entry and ``|det R - 1|`` [1].

    Returns
    -------
    ndarray, shape (4, 4), float64 (a new array)
    """
    try:
        a = np.array(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be a 4x4 matrix of numbers: {exc}') from None
    if a.shape == (16,):
        a = a.reshape(4, 4)
    if a.shape != (4, 4):
        raise ValueError(f'{name} must be a 4x4 matrix (or 16 numbers), got shape {a.shape}')
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{name} must be finite, got {a.tolist()}')
    if np.abs(a[3] - (0.0, 0.0, 0.0, 1.0)).max() > tol:
        raise ValueError(f'{name}: last row must be (0, 0, 0, 1), got {a[3].tolist()}')
    R = a[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > tol:
        raise ValueError(f'{name}: rotation block is not orthonormal (R^T R - I off by '
                         f'{off:.3g} > {tol:g})')
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > tol:
        raise ValueError(f'{name}: rotation block has determinant {det:.6g}, not +1 '
                         f'(a reflection is not a rigid transform)')
    a[3] = (0.0, 0.0, 0.0, 1.0)
    return a


def quaternion_from_matrix(R) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, with w >= 0.

    Parameters
    ----------
    R : array_like, shape (3, 3) (or a (4, 4) transform, whose rotation block is used)

    Returns
    -------
    ndarray, shape (4,)
    """
    m = np.asarray(R, dtype=np.float64)[:3, :3]
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    # Shepperd: divide by the largest of 4w^2, 4x^2, 4y^2, 4z^2
    if tr >= max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
        q = s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
        q = (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
        q = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s
    q = np.array(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def unit_quaternion(q, name: str = 'quaternion') -> np.ndarray:
    """``q`` (x, y, z, w) normalised; ValueError when non-finite or far from unit length.

    Parameters
    ----------
    q : array_like, shape (4,)

    Returns
    -------
    ndarray, shape (4,)
    """
    a = np.array(q, dtype=np.float64).reshape(-1)
    if a.shape != (4,) or not np.all(np.isfinite(a)):
        raise ValueError(f'{name} must be 4 finite numbers (x, y, z, w), got {a.tolist()}')
    n2 = float(a @ a)
    if abs(n2 - 1.0) > QUATERNION_NORM_TOL:
        raise ValueError(f'{name} {a.tolist()} is not normalised (|q|^2 = {n2:.6g})')
    return a / math.sqrt(n2)


def matrix_from_quaternion(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w).

    Parameters
    ----------
    q : array_like, shape (4,)
        Normalised here; refused (ValueError) if its squared norm is off 1 by more than
        ``QUATERNION_NORM_TOL``.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    x, y, z, w = unit_quaternion(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def transform_from_tq(translation, quaternion) -> np.ndarray:
    """4x4 transform from a translation [m] and a quaternion (x, y, z, w).

    Parameters
    ----------
    translation : array_like, shape (3,), metres
    quaternion : array_like, shape (4,)

    Returns
    -------
    ndarray, shape (4, 4)
    """
    t = np.array(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f'translation must be 3 finite numbers, got {t.tolist()}')
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(quaternion)
    T[:3, 3] = t
    return T


def tq_from_transform(T) -> tuple[np.ndarray, np.ndarray]:
    """Translation [m] and quaternion (x, y, z, w), w >= 0, of a rigid 4x4 transform.

    Parameters
    ----------
    T : array_like, shape (4, 4)

    Returns
    -------
    translation : ndarray, shape (3,), metres
    quaternion : ndarray, shape (4,)
    """
    a = np.asarray(T, dtype=np.float64)
    return a[:3, 3].copy(), quaternion_from_matrix(a[:3, :3])


def slerp(q0, q1, f: float) -> np.ndarray:
    """Quaternion ``f`` of the way from ``q0`` to ``q1`` along the shorter arc (x, y, z, w)."""
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear, then normalised
        q = q0 + f * (q1 - q0)
    else:
        theta = math.acos(min(dot, 1.0))
        q = (math.sin((1.0 - f) * theta) * q0 + math.sin(f * theta) * q1) / math.sin(theta)
    return q / np.linalg.norm(q)


def interpolate(T0, T1, f: float) -> np.ndarray:
    """The rigid transform ``f`` of the way from ``T0`` to ``T1`` (lerp and slerp), (4, 4)."""
    t0, q0 = tq_from_transform(T0)
    t1, q1 = tq_from_transform(T1)
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(slerp(q0, q1, f))
    T[:3, 3] = t0 + f * (t1 - t0)
    return T


def stamp_ns(stamp) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (any object with sec, nanosec)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def check_frame_name(name, what: str = 'frame') -> str:
    """A tf2 frame id: a non-empty string without a leading '/' (ValueError otherwise)."""
    if not isinstance(name, str) or not name:
        raise ValueError(f'{what} must be a non-empty string, got {name!r}')
    if name.startswith('/'):
        raise ValueError(f"{what} {name!r}: tf2 frame ids have no leading '/'")
    return name


# ---- the buffer -------------------------------------------------------------------------------
@dataclass
class _Edge:
    parent: str
    static: bool
    stamps: list = field(default_factory=list)  # ns, ascending (one entry, 0, if static)
    transforms: list = field(default_factory=list)  # parent_T_child (4, 4) per stamp


class TfBuffer:
    """Transforms received from ``/tf`` and ``/tf_static``; :meth:`lookup` chains them.

    Parameters
    ----------
    max_history : int
        Samples kept per stamped edge (the oldest go first).
    cache_time : int, nanoseconds
        Samples older than this before an edge's newest are dropped.
    extrapolation_tolerance : int, nanoseconds
        A lookup time this far before an edge's oldest or after its newest sample still
        gets that sample; further is an :class:`ExtrapolationError`.
    """

    def __init__(self, max_history: int = 1000, cache_time: int = DEFAULT_CACHE_TIME_NS,
                 extrapolation_tolerance: int = 0):
        if int(max_history) < 1 or int(cache_time) < 0 or int(extrapolation_tolerance) < 0:
            raise ValueError('max_history must be >= 1, cache_time and '
                             'extrapolation_tolerance >= 0')
        self.max_history = int(max_history)
        self.cache_time = int(cache_time)
        self.tolerance = int(extrapolation_tolerance)
        self._edges: dict[str, _Edge] = {}

    # -- filling ----------------------------------------------------------------------------
    def set_transform(self, parent: str, child: str, parent_T_child, stamp: int = 0,
                      static: bool = False) -> None:
        """Add the edge ``parent -> child``: ``parent_T_child`` (4, 4) [m] at ``stamp`` [ns].

        A static edge replaces whatever the child had. A stamped sample joins the child's
        history if the child already has this parent and is stamped; otherwise it starts a
        new history (the child is re-parented, as tf2 allows). Raises :class:`TfError`
        (changing nothing) for bad names, a non-rigid matrix or a loop.
        """
        check_frame_name(parent, 'parent frame')
        check_frame_name(child, 'child frame')
        if parent == child:
            raise TfError(f'transform from {child!r} to itself')
        try:
            T = check_rigid(parent_T_child, f'{parent}_T_{child}')
        except ValueError as exc:
            raise TfError(str(exc)) from None
        stamp = int(stamp)
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent:
            self._check_no_loop(parent, child)
        if static or edge is None or edge.static or edge.parent != parent:
            self._edges[child] = _Edge(parent, bool(static), [0 if static else stamp], [T])
            return
        i = bisect.bisect_left(edge.stamps, stamp)
        if i < len(edge.stamps) and edge.stamps[i] == stamp:
            edge.transforms[i] = T
        else:
            edge.stamps.insert(i, stamp)
            edge.transforms.insert(i, T)
        oldest_kept = edge.stamps[-1] - self.cache_time
        drop = max(len(edge.stamps) - self.max_history, bisect.bisect_left(edge.stamps,
                                                                           oldest_kept))
        if drop > 0:
            del edge.stamps[:drop], edge.transforms[:drop]

    def set_message(self, transforms: Iterable, static: bool = False) -> None:
        """Add every ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage``.

        ``transforms`` is the message's ``transforms`` list: objects with ``header.frame_id``,
        ``header.stamp.sec/nanosec``, ``child_frame_id`` and ``transform.translation.x/y/z``,
        ``transform.rotation.x/y/z/w`` (rclpy, rosbags or any alike). The message is checked
        whole first: a bad transform refuses all of it.
        """
        parsed = []
        for i, tf in enumerate(transforms):
            t, q = tf.transform.translation, tf.transform.rotation
            try:
                T = transform_from_tq((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))
            except ValueError as exc:
                raise TfError(f'transforms[{i}] ({tf.header.frame_id} -> '
                              f'{tf.child_frame_id}): {exc}') from None
            parsed.append((tf.header.frame_id, tf.child_frame_id, T, stamp_ns(tf.header.stamp)))
        saved = {k: _Edge(e.parent, e.static, list(e.stamps), list(e.transforms))
                 for k, e in self._edges.items()}
        try:
            for parent, child, T, stamp in parsed:
                self.set_transform(parent, child, T, stamp, static)
        except TfError:
            self._edges = saved
            raise

    def _check_no_loop(self, parent: str, child: str) -> None:
        frame, seen = parent, 0
        while frame in self._edges:
            frame = self._edges[frame].parent
            seen += 1
            if frame == child or seen > len(self._edges):
                raise LoopError(f'{parent} -> {child} would close a loop: {parent} already '
                                f'descends from {child}')

    # -- queries ----------------------------------------------------------------------------
    def frames(self) -> set[str]:
        """Every frame named by a transform."""
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def parent(self, frame: str) -> str | None:
        """The parent of ``frame`` (None for a root); UnknownFrameError for an unknown one."""
        self._known(frame)
        edge = self._edges.get(frame)
        return edge.parent if edge else None

    def _known(self, frame: str) -> None:
        if frame not in self._edges and frame not in self.frames():
            known = ', '.join(sorted(self.frames())) or 'none yet'
            raise UnknownFrameError(f'frame {frame!r} does not exist (known: {known})')

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        out = [frame]
        while out[-1] in self._edges:
            out.append(self._edges[out[-1]].parent)
        return out

    def _edge_at(self, child: str, time: int | None) -> np.ndarray:
        edge = self._edges[child]
        if edge.static:
            return edge.transforms[0]
        stamps = edge.stamps
        if time is None:
            time = stamps[-1]
        lo, hi, tol = stamps[0], stamps[-1], self.tolerance
        if time < lo - tol or time > hi + tol:
            side = 'before the oldest' if time < lo else 'after the newest'
            raise ExtrapolationError(
                f'{edge.parent} -> {child} at {time * 1e-9:.9f} s: {side} sample '
                f'({abs(time - (lo if time < lo else hi)) * 1e-9:.9f} s away; samples from '
                f'{lo * 1e-9:.9f} to {hi * 1e-9:.9f} s, tolerance {tol * 1e-9:g} s)')
        if time <= lo:
            return edge.transforms[0]
        if time >= hi:
            return edge.transforms[-1]
        i = bisect.bisect_right(stamps, time)
        f = (time - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        return interpolate(edge.transforms[i - 1], edge.transforms[i], f)

    def latest_common_time(self, target: str, source: str) -> int | None:
        """The newest time every stamped edge between the frames has [ns] (None: all static)."""
        up, down = self._path(target, source)
        return self._newest_common(up + down)

    def _newest_common(self, children: list[str]) -> int | None:
        newest = [self._edges[c].stamps[-1] for c in children if not self._edges[c].static]
        return min(newest) if newest else None

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Child frames of the edges from ``source`` up to the common ancestor, and from
        ``target`` up to it (each list in upward order)."""
        self._known(target)
        self._known(source)
        up_s, up_t = self._chain(source), self._chain(target)
        if up_s[-1] != up_t[-1]:
            raise ConnectivityError(
                f'{target!r} and {source!r} are not connected: {target!r} is in the tree of '
                f'{up_t[-1]!r}, {source!r} in the tree of {up_s[-1]!r}')
        on_t = set(up_t)
        common = next(f for f in up_s if f in on_t)
        return up_s[:up_s.index(common)], up_t[:up_t.index(common)]

    def lookup(self, target: str, source: str, time: int | None = None) -> np.ndarray:
        """``target_T_source`` (4, 4): maps points in ``source`` to ``target`` [m].

        Parameters
        ----------
        target, source : str
            Frame ids.
        time : int, nanoseconds, optional
            When to evaluate the stamped edges; None for the latest time they all have.

        Returns
        -------
        ndarray, shape (4, 4)

        Raises
        ------
        UnknownFrameError, ConnectivityError, ExtrapolationError
        """
        up, down = self._path(target, source)
        if time is None:
            time = self._newest_common(up + down)
        # common_T_frame = E(top) @ ... @ E(frame), E(child) = parent_T_child
        common_T_source, common_T_target = np.eye(4), np.eye(4)
        for child in reversed(up):
            common_T_source = common_T_source @ self._edge_at(child, time)
        for child in reversed(down):
            common_T_target = common_T_target @ self._edge_at(child, time)
        R, t = common_T_target[:3, :3], common_T_target[:3, 3]
        target_T_common = np.eye(4)
        target_T_common[:3, :3] = R.T
        target_T_common[:3, 3] = -R.T @ t
        return target_T_common @ common_T_source

    def can_transform(self, target: str, source: str, time: int | None = None) -> bool:
        """Whether :meth:`lookup` would succeed."""
        try:
            self.lookup(target, source, time)
        except TfError:
            return False
        return True
