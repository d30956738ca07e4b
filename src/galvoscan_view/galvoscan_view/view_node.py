"""``galvoscan view``: join the running graph over DDS and serve it to Foxglove and a browser.

    galvoscan view [--ws-port 8765] [--http-port 8080] [--host 0.0.0.0] [--no-browser-page]
                   [--image-rate 10] [--operator-timeout 10]

Any host on the graph's ``ROS_DOMAIN_ID`` can run it. It serves a **Foxglove WebSocket**
(:mod:`galvoscan_view.foxglove_server`; Foxglove and Lichtblick open
``ws://HOST:8765`` as they open foxglove_bridge) and the browser page of
:mod:`galvoscan_view.web` (``http://HOST:8080``, unless ``--no-browser-page``).

Subscribes (raw: the CDR bytes are forwarded unchanged, and read in place where the page
needs them)

    points               sensor_msgs/PointCloud2    reliable       -> Foxglove (lossy), page
    points/scan          sensor_msgs/PointCloud2    transient-local -> Foxglove (lossy, latched)
    camera/image_raw     sensor_msgs/Image          best effort    -> Foxglove (lossy, sampled)
    stripe/centers       galvoscan_msgs/StripeCenters best effort  -> Foxglove (lossy)
    galvo/state          galvoscan_msgs/GalvoState  reliable       -> Foxglove, page
    markers              visualization_msgs/MarkerArray reliable   -> Foxglove
    diagnostics          diagnostic_msgs/DiagnosticArray reliable  -> Foxglove, page (progress)
    /tf, /tf_static      tf2_msgs/TFMessage (when tf2_msgs is installed; /tf_static
                         transient-local)                          -> Foxglove, page
    calibration/instruction  galvoscan_msgs/CalibrationInstruction transient-local
                                                                   -> Foxglove (latched), page
    calibration/progress galvoscan_msgs/CalibrationProgress transient-local
                                                                   -> Foxglove (latched), page

and calls the calibration node's ``calibration/operator`` (galvoscan_msgs/OperatorAction)
for the page's placed / undo / skip / done buttons (:meth:`ViewNode.operator_action`: one
request per press, never resent, answered or refused within ``--operator-timeout``).

The page's calibration view shows the last view of ``calibration/progress`` on its own
camera frame: the last ``RECENT_FRAMES`` camera images are kept by stamp, and the view's
detected points are paired with the image whose stamp is the view's ``view_stamp`` (within
``VIEW_STAMP_TOLERANCE_NS``; if that frame was never received, e.g. the view started after
it, the newest image stands in and the page says so).

and publishes to Foxglove ``/camera/image_stripe`` (sensor_msgs/Image rgb8): the sampled
camera image with its extracted stripe centres drawn in red, the same frame as on the page.
A rendered image rather than a foxglove.ImageAnnotations channel: it shows in any Image
panel of Foxglove or Lichtblick with no panel settings, and image and centres are paired
exactly by header stamp here, not by the viewer's message synchronisation.

The camera runs at up to 1000 fps: the newest image is taken ``--image-rate`` times a second
(for both image channels and the page); the galvo state goes to the page at up to
``STATE_RATE_HZ`` and every message to Foxglove. The ``points`` clouds of a running scan are
gathered for the page (at most ``MAX_VIEW_POINTS``, decimated beyond) until ``points/scan``
brings the whole scan. The scan progress shown on the page comes from the driver's
diagnostics (``scan/state``, ``scan/done``, ``scan/total``, ``scan/dropped``).

Every callback is a boundary (:func:`~galvoscan_common.boundary.guard_subscription`): a
malformed message is logged, counted and skipped.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections import OrderedDict

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from galvoscan_msgs.msg import (
    CalibrationInstruction,
    CalibrationProgress,
    GalvoState,
    StripeCenters,
)
from galvoscan_msgs.srv import OperatorAction
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from galvoscan_common import cdr
from galvoscan_common.boundary import CallbackErrors, guard_subscription
from galvoscan_common.executor import run_node
from galvoscan_common.tf_tree import transform_from_tq
from galvoscan_view.foxglove_server import DEFAULT_WS_PORT, ChannelSpec, FoxgloveServer
from galvoscan_view.state import (
    MAX_VIEW_POINTS,
    CalibrationView,
    CloudView,
    GalvoView,
    ImageView,
    TransformView,
    ViewState,
)

try:
    from tf2_msgs.msg import TFMessage
except ImportError:   # the tf2_msgs interfaces are not installed: no TF shown
    TFMessage = None

#: Default port of the browser page.
DEFAULT_HTTP_PORT = 8080
#: Default rate at which the newest camera image is taken [Hz], and its bounds.
IMAGE_RATE_HZ, IMAGE_RATE_RANGE_HZ = 10.0, (0.1, 100.0)
#: Rate at which the galvo state on the page is updated [Hz].
STATE_RATE_HZ = 50.0
#: Period at which the gathered clouds of a running scan go to the page [s].
CLOUD_PERIOD_S = 0.2
#: A pause in ``points`` this long starts a new gathered scan [s].
SCAN_GAP_S = 1.0
#: Centres messages kept to pair with an image that arrives after them.
RECENT_CENTRES = 64
#: Camera images kept by stamp, to show a calibration view on its own frame.
RECENT_FRAMES = 64
#: A frame is a view's own when their stamps differ by at most this [ns]: a stamp sent as
#: float seconds loses ~0.2 us at today's epoch; frames are >= 1 ms apart (1000 fps at most).
VIEW_STAMP_TOLERANCE_NS = 200_000
#: Default wait for the calibration node's answer to an operator action [s], and its bounds.
OPERATOR_TIMEOUT_S, OPERATOR_TIMEOUT_RANGE_S = 10.0, (0.5, 300.0)
#: The operator's actions (galvoscan_msgs/OperatorAction ``action``).
OPERATOR_ACTIONS = ('placed', 'undo', 'skip', 'done')
#: Largest coverage grid and number of detected points a progress message may carry.
MAX_GRID_CELLS, MAX_VIEW_FEATURES = 65_536, 100_000
#: Colour of the drawn stripe centres (rgb8).
STRIPE_RGB = (255, 0, 0)
#: diagnostic_msgs/DiagnosticStatus levels.
DIAGNOSTIC_LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}

_RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
_LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
_TF_STATIC = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
_SAMPLED = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)
_CENTRES = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)

#: Foxglove channels: topic, ROS type, lossy, latched messages.
CHANNELS = (
    ChannelSpec('/points', 'sensor_msgs/msg/PointCloud2', lossy=True),
    ChannelSpec('/points/scan', 'sensor_msgs/msg/PointCloud2', lossy=True, latched=1),
    ChannelSpec('/camera/image_raw', 'sensor_msgs/msg/Image', lossy=True),
    ChannelSpec('/camera/image_stripe', 'sensor_msgs/msg/Image', lossy=True),
    ChannelSpec('/stripe/centers', 'galvoscan_msgs/msg/StripeCenters', lossy=True),
    ChannelSpec('/galvo/state', 'galvoscan_msgs/msg/GalvoState'),
    ChannelSpec('/markers', 'visualization_msgs/msg/MarkerArray'),
    ChannelSpec('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray'),
    ChannelSpec('/calibration/instruction', 'galvoscan_msgs/msg/CalibrationInstruction',
                latched=1),
    ChannelSpec('/calibration/progress', 'galvoscan_msgs/msg/CalibrationProgress', latched=1),
)
TF_CHANNELS = (
    ChannelSpec('/tf', 'tf2_msgs/msg/TFMessage'),
    ChannelSpec('/tf_static', 'tf2_msgs/msg/TFMessage', latched=100),
)

log = logging.getLogger('galvoscan_view')


# ---- decoding (pure) -----------------------------------------------------------------------


def cloud_xyz(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 x, y, z [m] and (N,) float32 intensity (zeros without that field) of
    the finite points of a structured array of :func:`galvoscan_common.cdr.parse_point_cloud`."""
    names = points.dtype.names or ()
    if not {'x', 'y', 'z'} <= set(names):
        raise ValueError(f'PointCloud2 without x, y, z fields (has {", ".join(names)})')
    xyz = np.column_stack([points[c] for c in 'xyz']).astype(np.float32, copy=False)
    intensity = (points['intensity'].astype(np.float32) if 'intensity' in names
                 else np.zeros(len(points), np.float32))
    keep = np.isfinite(xyz).all(axis=1)
    return xyz[keep], intensity[keep]


def decimated(xyz: np.ndarray, intensity: np.ndarray, limit: int = MAX_VIEW_POINTS):
    """Every k-th point so that at most ``limit`` remain (k the smallest that does)."""
    if len(xyz) <= limit:
        return xyz, intensity
    k = -(-len(xyz) // limit)
    return xyz[::k], intensity[::k]


def stripe_overlay(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 rgb of a mono ``image`` with the centres ``uv`` (M, 2) [px] in red.

    16-bit images are scaled to their maximum; each centre marks its pixel and the four
    next to it (visible at any zoom).
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        top = float(img.max()) or 1.0
        img = (img.astype(np.float32) * (255.0 / top)).astype(np.uint8)
    rgb = np.repeat(img[:, :, None], 3, axis=2)
    h, w = img.shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    uv = uv[np.isfinite(uv).all(axis=1)]
    cols, rows = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    for dr, dc in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rows + dr, cols + dc
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        rgb[r[ok], c[ok]] = STRIPE_RGB
    return rgb


def serialize_rgb8(rgb: np.ndarray, header: cdr.Header) -> bytes:
    """A sensor_msgs/Image (rgb8) of an (H, W, 3) uint8 array, by rosbags' type store."""
    from galvoscan_bag.typestore import default_typestore

    store = default_typestore()
    Image_, Header_, Time_ = (store.types[t] for t in (
        'sensor_msgs/msg/Image', 'std_msgs/msg/Header', 'builtin_interfaces/msg/Time'))
    h, w, _ = rgb.shape
    msg = Image_(header=Header_(stamp=Time_(sec=header.sec, nanosec=header.nanosec),
                                frame_id=header.frame_id),
                 height=h, width=w, encoding='rgb8', is_bigendian=0, step=3 * w,
                 data=np.ascontiguousarray(rgb, np.uint8).reshape(-1))
    return bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/Image'))


def deserialize(data, msgtype: str):
    """A rosbags message of ``msgtype`` from CDR bytes (the low-rate types: TF, diagnostics)."""
    from galvoscan_bag.typestore import default_typestore

    return default_typestore().deserialize_cdr(bytes(data), msgtype)


def transform_views(data, static: bool) -> list[TransformView]:
    """The transforms of a serialised tf2_msgs/TFMessage, ``parent_T_child`` (4, 4) [m]."""
    out = []
    for tf in deserialize(data, 'tf2_msgs/msg/TFMessage').transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        parent_T_child = transform_from_tq((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))
        out.append(TransformView(tf.header.frame_id, tf.child_frame_id, _stamp(tf.header),
                                 parent_T_child, static))
    return out


def diagnostic_statuses(data) -> tuple[dict, dict | None]:
    """The statuses of a serialised diagnostic_msgs/DiagnosticArray, and the scan progress.

    Returns ``{status name: {key: value, ..., 'level': 'OK'|'WARN'|'ERROR'|'STALE',
    'message': str}}`` and, when a status carries the driver's ``scan/*`` values,
    ``{'state', 'frames_done', 'frames_total', 'frames_dropped'}`` (else ``None``).
    """
    statuses, progress = {}, None
    for status in deserialize(data, 'diagnostic_msgs/msg/DiagnosticArray').status:
        values = {kv.key: kv.value for kv in status.values}
        statuses[status.name] = {
            **values, 'level': DIAGNOSTIC_LEVELS.get(int(status.level), str(status.level)),
            'message': status.message}
        if {'scan/state', 'scan/done', 'scan/total'} <= values.keys():
            progress = {'state': values['scan/state'], 'frames_done': int(values['scan/done']),
                        'frames_total': int(values['scan/total']),
                        'frames_dropped': int(values.get('scan/dropped', 0))}
    return statuses, progress


def _finite_or_none(values) -> list:
    """Floats, NaN and infinities as ``None`` (JSON has no NaN)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, float).ravel()]


def instruction_fields(data) -> dict:
    """The fields of a serialised galvoscan_msgs/CalibrationInstruction as plain values.

    Keys as the message's fields (``stamp`` [s] and ``frame_id`` from its header); the
    rejected views by reason as ``rejected`` ``{reason: count}``. A message whose
    ``rejected_reasons`` and ``rejected_counts`` differ in length, or with a non-finite
    number, raises ``ValueError``.
    """
    m = deserialize(data, 'galvoscan_msgs/msg/CalibrationInstruction')
    if len(m.rejected_reasons) != len(m.rejected_counts):
        raise ValueError(f'calibration/instruction: {len(m.rejected_reasons)} rejected_reasons '
                         f'but {len(m.rejected_counts)} rejected_counts')
    numbers = {k: np.asarray(getattr(m, k), float).ravel()
               for k in ('centre', 'extents', 'orientation', 'tilt', 'tilt_tolerance', 'move')}
    bad = [k for k, v in numbers.items() if not np.isfinite(v).all()]
    if bad:
        raise ValueError(f'calibration/instruction: non-finite {", ".join(bad)}')
    return {
        'stamp': _stamp(m.header), 'frame_id': m.header.frame_id, 'sequence': int(m.sequence),
        'stage': m.stage, 'state': m.state, 'placement': int(m.placement),
        'placements_planned': int(m.placements_planned),
        'placements_done': int(m.placements_done), 'target': m.target,
        'target_spec': m.target_spec, 'centre': numbers['centre'].tolist(),
        'extents': numbers['extents'].tolist(), 'orientation': numbers['orientation'].tolist(),
        'tilt': float(m.tilt), 'tilt_tolerance': float(m.tilt_tolerance),
        'on_laser_line': bool(m.on_laser_line), 'hold_still': bool(m.hold_still),
        'by_robot': bool(m.by_robot), 'move': numbers['move'].tolist(),
        'direction': m.direction, 'text': m.text, 'views_captured': int(m.views_captured),
        'views_rejected': int(m.views_rejected),
        'rejected': {str(r): int(c) for r, c in zip(m.rejected_reasons, m.rejected_counts,
                                                   strict=True)},
        'searches': int(m.searches)}


def _grid(name: str, cols: int, rows: int, cells) -> dict:
    cells = np.asarray(cells, np.int64).ravel()
    if cols * rows > MAX_GRID_CELLS:
        raise ValueError(f'calibration/progress: {name} grid of {cols} x {rows} cells is over '
                         f'{MAX_GRID_CELLS}')
    if len(cells) != cols * rows:
        raise ValueError(f'calibration/progress: {name}_coverage has {len(cells)} cells, '
                         f'not {name}_grid_rows x cols = {rows} x {cols}')
    return {'cols': int(cols), 'rows': int(rows), 'cells': cells.tolist()}


def progress_fields(data) -> tuple[dict, tuple[int, np.ndarray, bool, str]]:
    """A serialised galvoscan_msgs/CalibrationProgress as plain values, and its last view.

    Returns the progress (``parameters``: one ``{name, unit, sigma, target, met}`` per
    parameter, ``sigma`` ``None`` where NaN (not yet estimable); ``image_coverage`` and
    ``voltage_coverage`` as ``{cols, rows, cells}`` row-major; ``voltage_axes`` as a list of
    two names) and the view: (image stamp [ns], detected centres (N, 2) [px] (column, row),
    accepted, reason). Arrays of different lengths where they must agree, a coverage grid
    of the wrong size, or non-finite points raise ``ValueError``.
    """
    m = deserialize(data, 'galvoscan_msgs/msg/CalibrationProgress')
    n = len(m.parameter_names)
    lengths = {k: len(getattr(m, k)) for k in ('parameter_units', 'sigma', 'sigma_target')}
    if any(v != n for v in lengths.values()):
        raise ValueError(f'calibration/progress: {n} parameter_names but '
                         + ', '.join(f'{v} {k}' for k, v in lengths.items()))
    if len(m.view_points_u) != len(m.view_points_v):
        raise ValueError(f'calibration/progress: {len(m.view_points_u)} view_points_u but '
                         f'{len(m.view_points_v)} view_points_v')
    if len(m.view_points_u) > MAX_VIEW_FEATURES:
        raise ValueError(f'calibration/progress: {len(m.view_points_u)} view points is over '
                         f'{MAX_VIEW_FEATURES}')
    uv = np.column_stack([np.asarray(m.view_points_u, float), np.asarray(m.view_points_v, float)])
    if not np.isfinite(uv).all():
        raise ValueError('calibration/progress: non-finite view_points_u / view_points_v')
    extent = np.asarray(m.voltage_extent, float)
    sigma, target = np.asarray(m.sigma, float), np.asarray(m.sigma_target, float)
    parameters = [{'name': m.parameter_names[i], 'unit': m.parameter_units[i],
                   'sigma': _finite_or_none([sigma[i]])[0],
                   'target': _finite_or_none([target[i]])[0],
                   'met': bool(np.isfinite(sigma[i]) and sigma[i] <= target[i])}
                  for i in range(n)]
    progress = {
        'stamp': _stamp(m.header), 'stage': m.stage,
        'placements_done': int(m.placements_done), 'placements_max': int(m.placements_max),
        'parameters': parameters, 'targets_met': bool(m.targets_met), 'advice': m.advice,
        'image_coverage': _grid('image', int(m.image_grid_cols), int(m.image_grid_rows),
                                m.image_coverage),
        'voltage_axes': [a.strip() for a in m.voltage_axes.split(',')] if m.voltage_axes
        else [],
        'voltage_extent': _finite_or_none(extent),
        'voltage_coverage': _grid('voltage', int(m.voltage_grid_cols),
                                  int(m.voltage_grid_rows), m.voltage_coverage),
        'view_stamp': m.view_stamp.sec + m.view_stamp.nanosec * 1e-9,
        'view_points': len(uv), 'view_accepted': bool(m.view_accepted),
        'view_reason': m.view_reason}
    view_ns = int(m.view_stamp.sec) * 1_000_000_000 + int(m.view_stamp.nanosec)
    return progress, (view_ns, uv, bool(m.view_accepted), m.view_reason)


def _stamp(header) -> float:
    """Seconds of a ``std_msgs/Header`` stamp (cdr or rosbags)."""
    stamp = getattr(header, 'stamp', header)
    return stamp.sec + stamp.nanosec * 1e-9


# ---- the node ------------------------------------------------------------------------------
class _ScanCloud:
    """The ``points`` clouds of the running scan, gathered for the page.

    Every ``stride``-th point is kept; the stride doubles (and the kept points are thinned
    by two) whenever more than ``MAX_VIEW_POINTS`` would be kept.
    """

    def __init__(self):
        self.parts, self.n, self.stride, self.frame_id = [], 0, 1, ''
        self.stamp, self.last_frame, self.dirty = 0.0, -np.inf, False

    def add(self, xyz, intensity, frame_id: str, stamp: float, now: float) -> None:
        if now - self.last_frame > SCAN_GAP_S or frame_id != self.frame_id:
            self.parts, self.n, self.stride = [], 0, 1
        self.last_frame, self.frame_id, self.stamp = now, frame_id, stamp
        self.parts.append((xyz[::self.stride], intensity[::self.stride]))
        self.n += len(xyz)
        self.dirty = True

    def view(self) -> CloudView:
        self.dirty = False
        if not self.parts:
            return CloudView(self.frame_id, self.stamp, np.zeros((0, 3), np.float32),
                             np.zeros(0, np.float32), 0)
        xyz, intensity = (np.concatenate(a) for a in zip(*self.parts, strict=True))
        while len(xyz) > MAX_VIEW_POINTS:
            xyz, intensity, self.stride = xyz[::2], intensity[::2], 2 * self.stride
        self.parts = [(xyz, intensity)]   # one array from here on: the next view copies less
        return CloudView(self.frame_id, self.stamp, xyz, intensity, self.n)


class ViewNode(Node):
    """Subscribes to the graph, fills ``state`` and forwards to ``server`` (module docstring)."""

    def __init__(self, state: ViewState, server: FoxgloveServer,
                 image_rate: float = IMAGE_RATE_HZ, **kwargs):
        super().__init__('galvoscan_view', **kwargs)
        self.state, self.server = state, server
        self.callback_errors = CallbackErrors()
        self._scan = _ScanCloud()
        self._latest = {'image': None, 'galvo': None}   # newest raw bytes, not yet taken
        self._pending = None            # (stamp ns, header, image) awaiting its centres
        self._recent = OrderedDict()    # stamp ns -> raw centres, to pair a later image
        self._frames = OrderedDict()    # stamp ns -> raw image, the last RECENT_FRAMES
        self._view = None               # the last calibration view not yet on its own frame
        self._operator = self.create_client(OperatorAction, 'calibration/operator')
        for msg_type, topic, qos, callback in (
                (PointCloud2, 'points', _RELIABLE, self._on_points),
                (PointCloud2, 'points/scan', _LATCHED, self._on_scan),
                (Image, 'camera/image_raw', _SAMPLED, self._on_image),
                (StripeCenters, 'stripe/centers', _CENTRES, self._on_centres),
                (GalvoState, 'galvo/state', _RELIABLE, self._on_galvo),
                (MarkerArray, 'markers', QoSProfile(depth=10, reliability=_RELIABLE.reliability),
                 self._forward),
                (DiagnosticArray, 'diagnostics', _RELIABLE, self._on_diagnostics),
                (CalibrationInstruction, 'calibration/instruction', _LATCHED,
                 self._on_instruction),
                (CalibrationProgress, 'calibration/progress', _LATCHED,
                 self._on_calibration_progress),
                *(((TFMessage, '/tf', QoSProfile(depth=100, reliability=_RELIABLE.reliability),
                    self._on_tf), (TFMessage, '/tf_static', _TF_STATIC, self._on_tf))
                  if TFMessage is not None else ())):
            self._subscribe(msg_type, topic, qos, callback)
        if TFMessage is None:
            self.get_logger().warning('tf2_msgs is not installed: TF is not shown')
        for period, callback, name in ((1.0 / image_rate, self._take_image, 'image_timer'),
                                       (1.0 / STATE_RATE_HZ, self._take_galvo, 'galvo_timer'),
                                       (CLOUD_PERIOD_S, self._flush_scan, 'cloud_timer')):
            guarded = guard_subscription(name, lambda _tick, cb=callback: cb(),
                                         self.get_logger(), self.callback_errors)
            self.create_timer(period, lambda g=guarded: g(None))

    def _subscribe(self, msg_type, topic: str, qos, callback) -> None:
        name = self.resolve_topic_name(topic)   # the Foxglove channel's topic

        def on_message(data):
            self.state.count(name)
            callback(name, data)

        self.create_subscription(msg_type, topic, guard_subscription(
            topic, on_message, self.get_logger(), self.callback_errors), qos, raw=True)

    # -- forwarded as they come ---------------------------------------------------------
    def _forward(self, topic: str, data) -> None:
        self.server.log(topic, data)

    def _on_points(self, topic: str, data) -> None:
        self.server.log(topic, data)
        header, points = cdr.parse_point_cloud(data)
        self._scan.add(*cloud_xyz(points), header.frame_id, _stamp(header), time.monotonic())

    def _on_scan(self, topic: str, data) -> None:
        self.server.log(topic, data)
        header, points = cdr.parse_point_cloud(data)
        xyz, intensity = cloud_xyz(points)
        self._scan = _ScanCloud()   # the scan is whole: gather the next one afresh
        self.state.set_cloud(CloudView(header.frame_id, _stamp(header),
                                       *decimated(xyz, intensity), len(xyz)))

    def _flush_scan(self) -> None:
        if self._scan.dirty:
            self.state.set_cloud(self._scan.view())

    def _on_galvo(self, topic: str, data) -> None:
        self.server.log(topic, data)
        self._latest['galvo'] = data

    def _take_galvo(self) -> None:
        data, self._latest['galvo'] = self._latest['galvo'], None
        if data is not None:
            g = cdr.parse_galvo_state(data)
            self.state.set_galvo(GalvoView(
                g.seq, _stamp(g.header), np.array([g.g1_pan_voltage, g.g1_tilt_voltage,
                                                   g.g2_pan_voltage, g.g2_tilt_voltage]),
                g.laser_on, g.status))

    def _on_diagnostics(self, topic: str, data) -> None:
        self.server.log(topic, data)
        statuses, progress = diagnostic_statuses(data)
        for name, values in statuses.items():
            self.state.set_diagnostics(name, values)
        if progress is not None:
            self.state.set_progress(progress)

    def _on_tf(self, topic: str, data) -> None:
        self.server.log(topic, data)
        for tf in transform_views(data, static=topic == '/tf_static'):
            self.state.set_transform(tf)

    # -- calibration -------------------------------------------------------------------------
    def _on_instruction(self, topic: str, data) -> None:
        self.server.log(topic, data)
        self.state.set_instruction(instruction_fields(data))

    def _on_calibration_progress(self, topic: str, data) -> None:
        self.server.log(topic, data)
        progress, view = progress_fields(data)
        self.state.set_calibration_progress(progress)
        self._view = view if view[0] or len(view[1]) else None
        if self._view is not None:
            self._show_view()

    def _show_view(self) -> None:
        """The pending view on its own frame if kept, else on the newest frame (unmatched)."""
        stamp_ns, uv, accepted, reason = self._view
        data = self._frames.get(stamp_ns)
        if data is None and self._frames:
            nearest = min(self._frames, key=lambda s: abs(s - stamp_ns))
            if abs(nearest - stamp_ns) <= VIEW_STAMP_TOLERANCE_NS:
                data = self._frames[nearest]
        matched = data is not None
        if not matched and self._frames:
            data = next(reversed(self._frames.values()))
        image, image_stamp = None, 0.0
        if data is not None:
            raw = cdr.parse_image_cdr(data)
            image = cdr.image_to_array(raw)
            image_stamp = raw.stamp_sec + raw.stamp_nanosec * 1e-9
        self.state.set_calibration_view(CalibrationView(
            stamp_ns * 1e-9, uv, accepted, reason, image, image_stamp, matched))
        if matched:
            self._view = None

    def operator_action(self, action: str, placement: int,
                        timeout: float = OPERATOR_TIMEOUT_S) -> tuple[bool, str]:
        """Send one operator action to ``calibration/operator`` and wait for its answer.

        Called from the page's HTTP threads (the executor answers the future). One request,
        never resent: a repeated "placed" could answer the next instruction.

        Returns
        -------
        (accepted, message) of the calibration node's answer.

        Raises
        ------
        ValueError
            ``action`` is not one of OPERATOR_ACTIONS, or ``placement`` not a uint32.
        LookupError
            No ``calibration/operator`` service on the graph.
        TimeoutError
            No answer within ``timeout`` [s] (the request is withdrawn).
        """
        if action not in OPERATOR_ACTIONS:
            raise ValueError(f'unknown action {action!r}; one of {", ".join(OPERATOR_ACTIONS)}')
        if isinstance(placement, bool) or not isinstance(placement, int) \
                or not 0 <= placement < 2**32:
            raise ValueError(f'placement must be an integer in 0..{2**32 - 1}, got {placement!r}')
        client = self._operator
        if not client.wait_for_service(timeout_sec=min(timeout, 5.0)):
            raise LookupError(f'{client.srv_name} is not available: no calibration node on '
                              'this ROS domain (galvoscan run --nodes ...,calibration)')
        answered = threading.Event()
        future = client.call_async(OperatorAction.Request(action=action, placement=placement))
        future.add_done_callback(lambda _f: answered.set())
        if not answered.wait(timeout):
            if not future.done():
                future.cancel()
                client.remove_pending_request(future)
            raise TimeoutError(f'{client.srv_name} did not answer within {timeout:g} s')
        resp = future.result()
        if resp is None:
            raise TimeoutError(f'{client.srv_name}: the request was withdrawn')
        return bool(resp.accepted), str(resp.message)

    # -- camera image and its stripe ------------------------------------------------------
    def _on_image(self, topic: str, data) -> None:
        self._latest['image'] = data
        stamp_ns = cdr.read_header(cdr.Reader(data)).stamp_ns
        self._frames[stamp_ns] = data
        self._frames.move_to_end(stamp_ns)
        while len(self._frames) > RECENT_FRAMES:
            self._frames.popitem(last=False)
        if self._view is not None and abs(self._view[0] - stamp_ns) <= VIEW_STAMP_TOLERANCE_NS:
            self._show_view()

    def _take_image(self) -> None:
        """The newest image: to Foxglove and the page; its stripe drawn once it is known."""
        data, self._latest['image'] = self._latest['image'], None
        if data is None:
            return
        if self._view is not None:   # its own frame never came: on the newest frame
            self._show_view()
        self.server.log('/camera/image_raw', data)
        raw = cdr.parse_image_cdr(data)
        image = cdr.image_to_array(raw)
        header = cdr.Header(raw.stamp_sec, raw.stamp_nanosec, raw.frame_id)
        if self._pending is not None:    # its centres never came: shown without a stripe
            self._publish_overlay(*self._pending, np.zeros((0, 2), np.float32))
        self.state.set_image(ImageView(header.stamp_ns, _stamp(header), image,
                                       np.zeros((0, 2), np.float32)))
        self._pending = (header.stamp_ns, header, image)
        centres = self._recent.pop(header.stamp_ns, None)
        if centres is not None:
            self._pair(centres)

    def _on_centres(self, topic: str, data) -> None:
        self.server.log(topic, data)
        stamp_ns = cdr.read_header(cdr.Reader(data)).stamp_ns
        if self._pending is not None and self._pending[0] == stamp_ns:
            self._pair(data)
        else:
            self._recent[stamp_ns] = data
            while len(self._recent) > RECENT_CENTRES:
                self._recent.popitem(last=False)

    def _pair(self, data) -> None:
        centres = cdr.parse_stripe_centers(data)
        stamp_ns, header, image = self._pending
        self._pending = None
        n = min(len(centres.u), len(centres.v))
        uv = np.column_stack([centres.u[:n], centres.v[:n]]).astype(np.float32)
        self.state.set_stripe(stamp_ns, uv)
        self._publish_overlay(stamp_ns, header, image, uv)

    def _publish_overlay(self, stamp_ns: int, header, image, uv) -> None:
        self._pending = None
        if self.server.has_subscribers('/camera/image_stripe'):
            self.server.log('/camera/image_stripe',
                            serialize_rgb8(stripe_overlay(image, uv), header))


# ---- the command ---------------------------------------------------------------------------
def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a port number') from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f'{port} is outside 0..65535 (0: any free port)')
    return port


def _rate(text: str) -> float:
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    lo, hi = IMAGE_RATE_RANGE_HZ
    if not lo <= rate <= hi:
        raise argparse.ArgumentTypeError(f'{text} Hz is outside {lo}..{hi} Hz')
    return rate


def _timeout(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    lo, hi = OPERATOR_TIMEOUT_RANGE_S
    if not lo <= value <= hi:
        raise argparse.ArgumentTypeError(f'{text} s is outside {lo}..{hi} s')
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='galvoscan view', description=(
        'Serve the running graph to Foxglove / Lichtblick (Foxglove WebSocket) and a browser.'))
    p.add_argument('--ws-port', type=_port, default=DEFAULT_WS_PORT,
                   help='Foxglove WebSocket port (default %(default)s, as foxglove_bridge)')
    p.add_argument('--http-port', type=_port, default=DEFAULT_HTTP_PORT,
                   help='browser page port (default %(default)s)')
    p.add_argument('--host', default='0.0.0.0',
                   help='address to listen on (default %(default)s: every interface)')
    p.add_argument('--no-browser-page', action='store_true', help='serve Foxglove only')
    p.add_argument('--image-rate', type=_rate, default=IMAGE_RATE_HZ,
                   help='camera images taken per second [Hz] (default %(default)s)')
    p.add_argument('--operator-timeout', type=_timeout, default=OPERATOR_TIMEOUT_S,
                   help="longest wait for the calibration node's answer to a button of the "
                        'calibration view [s] (default %(default)s)')
    return p


def main(argv=None) -> int:
    """Run the view until Ctrl-C or SIGTERM; 2 on bad arguments or a port that is taken."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='[%(name)s] %(levelname)s %(message)s')
    for noisy in ('foxglove', 'websockets'):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    channels = CHANNELS + (TF_CHANNELS if TFMessage is not None else ())
    try:
        server = FoxgloveServer(channels, host=args.host, port=args.ws_port)
    except OSError as exc:
        print(f'galvoscan view: cannot serve Foxglove WebSocket on {args.host}:{args.ws_port}: '
              f'{exc.strerror or exc}', file=sys.stderr)
        return 2
    state, page = ViewState(), None
    try:
        if not args.no_browser_page:
            try:
                from galvoscan_view.web import serve_page
            except ImportError as exc:
                print(f'galvoscan view: the browser page is not part of this install ({exc}); '
                      'run with --no-browser-page for Foxglove only', file=sys.stderr)
                return 2
            try:
                page = serve_page(state, args.host, args.http_port)
            except OSError as exc:
                print(f'galvoscan view: cannot serve the browser page on {args.host}:'
                      f'{args.http_port}: {exc.strerror or exc}', file=sys.stderr)
                return 2
        print(f'galvoscan view: Foxglove WebSocket on ws://{args.host}:{server.port}'
              + ('' if page is None else f', browser page on http://{args.host}:'
                 f'{getattr(page, "port", args.http_port)}'), flush=True)
        def make_node():
            node = ViewNode(state, server, image_rate=args.image_rate)
            if page is not None:
                page.operator = lambda action, placement: node.operator_action(
                    action, placement, args.operator_timeout)
            return node

        run_node(make_node)
    finally:
        if page is not None:
            page.shutdown()
        server.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
