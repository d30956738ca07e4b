"""The reconstructor's tf2 frames: where V0 sits in the cell and where the camera looks.

The tree (names are the node's parameters; defaults shown)::

    world ──static── v0 ──/tf, per frame── v ──static, identity── camera_optical
    (cell_frame)     (frame_id: the clouds)  (virtual_camera_frame) (camera_frame)

- ``world -> v0``: ``cell_T_v0``, the pose of the scanner's fixed output frame V0 in the
  robot cell: the calibration file's ``cell_T_v0`` when it has one, else the node's
  ``cell_T_v0`` parameter (identity by default).
- ``v0 -> v``: ``V0_T_V`` at the frame's G1 voltages (docs/design.md section 2), followed by the
  joint correction when the model has one, so that a point in ``v`` maps to where the
  clouds put it. ``v`` is the virtual camera: the camera as seen through both G1 mirrors.
- ``v -> camera_optical``: identity. V already has the optical convention of REP 103 (z
  along the line of sight, x right along the image rows, y down the columns: a pixel's ray
  is ``((u - cx) / fx, (v - cy) / fy, 1)`` in V), and ``camera_optical`` is the frame_id the
  driver stamps on the images and the camera info. The pixel rays of those images live in
  V, not in the real camera C (which sits still behind the mirrors), so a viewer that draws
  the camera's frustum or projects the clouds into the image needs exactly this frame.

No rclpy: the node turns these into ``tf2_msgs/TFMessage``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from galvoscan_common.tf_tree import check_frame_name, check_rigid
from reconstructor.geometry.rig import v0_T_v_scalar
from reconstructor.model import RigModel

#: A cell extrinsic whose translation is this long or longer is refused [m].
MAX_CELL_TRANSLATION_M = 100.0


@dataclass(frozen=True)
class FrameNames:
    """The frame ids of the tree (see the module docstring)."""

    cell: str = 'world'
    v0: str = 'v0'
    v: str = 'v'
    camera: str = 'camera_optical'  # '' publishes no camera frame

    def __post_init__(self):
        names = [('cell_frame', self.cell), ('frame_id', self.v0),
                 ('virtual_camera_frame', self.v)]
        if self.camera:
            names.append(('camera_frame', self.camera))
        for what, name in names:
            check_frame_name(name, what)
        values = [n for _, n in names]
        if len(set(values)) != len(values):
            listed = ', '.join(f'{w}={n!r}' for w, n in names)
            raise ValueError(f'frame names must differ: {listed}')


@dataclass(frozen=True)
class Edge:
    """One transform to publish: ``parent_T_child`` (4, 4) [m]."""

    parent: str
    child: str
    parent_T_child: np.ndarray


def check_cell_T_v0(T, name: str = 'cell_T_v0') -> np.ndarray:
    """``T`` as a (4, 4) rigid transform with a translation under 100 m, or ValueError.

    Parameters
    ----------
    T : array_like, shape (4, 4) or 16 numbers (row-major), metres
    name : str
        What the error names.

    Returns
    -------
    ndarray, shape (4, 4)
    """
    T = check_rigid(T, name)
    length = float(np.linalg.norm(T[:3, 3]))
    if not length < MAX_CELL_TRANSLATION_M:
        raise ValueError(f'{name}: translation of {length:g} m is not under '
                         f'{MAX_CELL_TRANSLATION_M:g} m; it is in metres (millimetres?)')
    return T


def cell_T_v0_source(from_file, from_parameter) -> tuple[np.ndarray, str]:
    """The cell extrinsic to publish and where it came from ('calibration file'/'parameter').

    Parameters
    ----------
    from_file : ndarray, shape (4, 4), or None
        The calibration file's ``cell_T_v0`` (already checked when it was loaded).
    from_parameter : sequence of 16 float
        The node's ``cell_T_v0`` parameter (row-major).

    Returns
    -------
    ndarray, shape (4, 4), and str
    """
    if from_file is not None:
        return check_cell_T_v0(from_file), 'calibration file'
    return check_cell_T_v0(from_parameter, 'parameter cell_T_v0'), 'parameter'


def static_edges(names: FrameNames, cell_T_v0) -> list[Edge]:
    """The ``/tf_static`` transforms: ``cell -> v0`` and ``v -> camera`` (identity)."""
    edges = [Edge(names.cell, names.v0, check_cell_T_v0(cell_T_v0))]
    if names.camera:
        edges.append(Edge(names.v, names.camera, np.eye(4)))
    return edges


def virtual_camera_edge(names: FrameNames, model: RigModel, u1_pan: float,
                        u1_tilt: float) -> Edge:
    """The ``/tf`` transform ``v0 -> v`` at the G1 voltages (joint correction included).

    Parameters
    ----------
    names : FrameNames
    model : RigModel
    u1_pan, u1_tilt : float, volts

    Returns
    -------
    Edge
        ``parent_T_child`` is the cloud frame's ``V0_T_V`` (4, 4).
    """
    if not (math.isfinite(u1_pan) and math.isfinite(u1_tilt)):
        raise ValueError(f'G1 voltages must be finite, got {u1_pan}, {u1_tilt}')
    T = v0_T_v_scalar(model, float(u1_pan), float(u1_tilt))  # the triangulation's own path
    if model.correction is not None:
        T = np.asarray(model.correction.V0c_T_V0(u1_pan, u1_tilt), dtype=np.float64) @ T
    return Edge(names.v0, names.v, T)


class RateLimiter:
    """At most ``rate_max`` sends per second; the newest withheld item goes out when due.

    :meth:`offer` is called per frame, :meth:`due` from a timer: a scan that stops between
    two sends still leaves its last pose on ``/tf``. ``rate_max <= 0`` sends nothing.
    """

    def __init__(self):
        self.last_sent = -math.inf
        self.pending = None

    def _may_send(self, now: float, rate_max: float) -> bool:
        # (1 - 1e-9): frame times that are exact multiples of the period still qualify
        return rate_max > 0.0 and now - self.last_sent >= (1.0 - 1e-9) / rate_max

    def offer(self, item, now: float, rate_max: float):
        """``item`` if it may go out now [``now`` in s, ``rate_max`` in Hz], else None."""
        if rate_max <= 0.0:
            self.pending = None
            return None
        if self._may_send(now, rate_max):
            self.last_sent, self.pending = now, None
            return item
        self.pending = item
        return None

    def due(self, now: float, rate_max: float):
        """The withheld item once its turn has come, else None."""
        if self.pending is None or not self._may_send(now, rate_max):
            return None
        item, self.pending, self.last_sent = self.pending, None, now
        return item
