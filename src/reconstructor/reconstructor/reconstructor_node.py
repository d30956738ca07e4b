"""``reconstructor``: stripe centres in, PointCloud2 in V0 out.

Subscribes
    stripe/centers   galvoscan_msgs/StripeCenters
Publishes
    points           sensor_msgs/PointCloud2, one per frame, in ``frame_id`` (default v0), metres;
                     fields x, y, z, intensity (stripe strength, DN), width (stripe width, px)
    points/scan      sensor_msgs/PointCloud2, the accumulated cloud of the last scan
                     (transient-local, depth 1), published when frames stop for
                     ``scan_end_timeout`` seconds, or as soon as it holds
                     ``scan_max_points`` (then the scan goes on in the next cloud)
    markers          visualization_msgs/MarkerArray: the current laser plane and the camera's
                     field of view, for an rviz-style viewer
    /tf_static       tf2_msgs/TFMessage (tf2's static QoS): ``cell_frame`` -> ``frame_id``
                     (the calibration file's ``cell_T_v0``, else the parameter) and
                     ``virtual_camera_frame`` -> ``camera_frame``; re-sent whole when the
                     calibration or these parameters change
    /tf              tf2_msgs/TFMessage: ``frame_id`` -> ``virtual_camera_frame`` at each
                     frame's G1 voltages and stamp, at most ``tf_rate_max`` times a second
                     (the tree: :mod:`reconstructor.tf_frames`)
Services
    reconstructor/reload_calibration  galvoscan_msgs/LoadCalibration (empty path: same file)
    reconstructor/save_scan           galvoscan_msgs/SaveScan (.ply or .pcd, via open3d)

Bad input (malformed CDR, mismatched array lengths, non-finite or out-of-range voltages, no
calibration) is logged once per cause, counted and skipped; the node never dies on input.

Data path: the centres subscription is raw and the clouds are published as bytes, both read
and written by :mod:`galvoscan_common.cdr` (no rclpy message objects per frame).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from galvoscan_msgs.msg import StripeCenters
from galvoscan_msgs.srv import LoadCalibration, SaveScan
from geometry_msgs.msg import Point, TransformStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from galvoscan_common import cdr
from galvoscan_common.boundary import CallbackErrors, guard_service, guard_subscription
from galvoscan_common.diagnostics import publish_periodically
from galvoscan_common.executor import run_node
from galvoscan_common.frame import VOLTAGE_LIMIT
from galvoscan_common.tf_tree import tq_from_transform
from reconstructor import calibration_file, tf_frames
from reconstructor.cloud import CLOUD_DTYPE, save_cloud, xyz
from reconstructor.consistency import agreeing
from reconstructor.model import laser_plane_v0, triangulate, v0_T_v

#: The parameters the TF tree is built from (see reconstructor.tf_frames).
TF_PARAMETERS = ('cell_frame', 'frame_id', 'virtual_camera_frame', 'camera_frame', 'cell_T_v0')

#: Default bound of the accumulated scan cloud [points]: 20 bytes each, so 200 MB, about
#: 28 s of continuous scanning at 500 fps with 720 points per frame.
SCAN_MAX_POINTS = 10_000_000


class ReconstructorNode(Node):
    """Triangulates stripe centres against the calibrated model."""

    def __init__(self, **kwargs):
        super().__init__('reconstructor', **kwargs)
        self.declare_parameter('calibration_file', '', ParameterDescriptor(
            description='calibration YAML (galvoscan format_version 1)'))
        self.declare_parameter('frame_id', 'v0', ParameterDescriptor(
            description='frame_id of the published clouds (the fixed frame V0)'))
        self.declare_parameter('min_ray_plane_angle', 1e-3, ParameterDescriptor(
            description='rays closer than this to parallel with the laser plane are dropped [rad]',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=0.5, step=0.0)]))
        self.declare_parameter('scan_end_timeout', 0.5, ParameterDescriptor(
            description='a pause in frames this long ends a scan [s]',
            floating_point_range=[FloatingPointRange(from_value=0.05, to_value=60.0, step=0.0)]))
        self.declare_parameter('scan_max_points', SCAN_MAX_POINTS, ParameterDescriptor(
            description='a scan cloud holding this many points is published and a new one '
                        'begins (bounds the memory of continuous scanning) [points]',
            integer_range=[IntegerRange(from_value=1000, to_value=100_000_000, step=0)]))
        self.declare_parameter('marker_period', 0.1, ParameterDescriptor(
            description='minimum time between marker updates [s] (0 disables markers)',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0, step=0.0)]))
        self.declare_parameter('marker_range', 0.65, ParameterDescriptor(
            description='distance at which the field of view is drawn [m]',
            floating_point_range=[FloatingPointRange(from_value=0.05, to_value=10.0, step=0.0)]))
        self.declare_parameter('multi_view_tolerance', 0.0, ParameterDescriptor(
            description='two-view consistency: a frame followed by one of the same G2 tilt '
                        'from another G1 position (reconstructor.consistency.two_view_sweep) '
                        'keeps, in both, only the points the other triangulates within this '
                        'distance [m]; 0: off',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=0.01, step=0.0)]))
        self._declare_tf_parameters()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._cache_parameters)
        self._cache_parameters()

        self.counters = {'frames': 0, 'points': 0, 'invalid_points': 0, 'scans': 0,
                         'scan_splits': 0, 'skipped': {},
                         'multi_view': {'pairs': 0, 'unpaired': 0, 'dropped_points': 0}}
        #: multi_view_tolerance: the frame waiting for its second view (volts, cloud, header)
        self._pending = None
        self._warned = set()
        self.model = None
        self.calibration = None
        path = self.get_parameter('calibration_file').value
        if path:
            self._log_outcome(*self._load(path))
        else:
            self.get_logger().error('no calibration_file given: frames are skipped until '
                                    'reconstructor/reload_calibration loads one')

        self._scan_parts = []
        self._scan_points = 0
        self._last_scan = None
        self._last_frame_time = None
        self._last_marker = 0.0
        self.callback_errors = CallbackErrors()
        log = self.get_logger()
        self.create_subscription(
            StripeCenters, 'stripe/centers',
            guard_subscription('stripe/centers', self._on_centers, log, self.callback_errors),
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE), raw=True)
        # a deep history: a reliable writer drops what a slow reader has not acknowledged
        # once KEEP_LAST overflows, and frames come at up to 1 kHz
        self._pub_points = self.create_publisher(
            PointCloud2, 'points', QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._pub_scan = self.create_publisher(PointCloud2, 'points/scan', latched)
        self._pub_markers = self.create_publisher(MarkerArray, 'markers', 10)
        # tf2's QoS: the static broadcaster's (latched, depth 1) and the broadcaster's
        self._pub_tf_static = self.create_publisher(TFMessage, '/tf_static', latched)
        self._pub_tf = self.create_publisher(
            TFMessage, '/tf', QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self._tf_limiter = tf_frames.RateLimiter()
        self._publish_static_tf()
        for srv_type, name, callback in (
                (LoadCalibration, 'reconstructor/reload_calibration', self._on_reload),
                (SaveScan, 'reconstructor/save_scan', self._on_save)):
            self.create_service(srv_type, name, guard_service(
                name, callback, log, self.callback_errors))
        self.create_timer(0.05, guard_subscription(
            'scan_end_check', self._check_scan_end, log, self.callback_errors))
        self.create_timer(0.05, guard_subscription(
            'tf_flush', self._flush_tf, log, self.callback_errors))
        publish_periodically(
            self, 'reconstruction', lambda: self.counters, self.callback_errors,
            message=lambda: (f"{self.counters['frames']} frames, {self.counters['points']} "
                             f"points, {self.counters['scans']} scans"
                             + ('' if self.model is not None else '; no calibration loaded')),
            warn=tuple(f'skipped/{c}' for c in (
                'malformed_cdr', 'exception', 'array_length_mismatch', 'nonfinite_voltage',
                'voltage_out_of_range')))

    # -- configuration ----------------------------------------------------------------
    def _declare_tf_parameters(self):
        self.declare_parameter('cell_frame', 'world', ParameterDescriptor(
            description='frame of the robot cell; /tf_static carries cell_frame -> frame_id'))
        self.declare_parameter('cell_T_v0', np.eye(4).ravel().tolist(), ParameterDescriptor(
            description='pose of V0 in cell_frame, 16 numbers row by row (rigid, metres), '
                        "used when the calibration file has no 'cell_T_v0'",
            dynamic_typing=True))
        self.declare_parameter('virtual_camera_frame', 'v', ParameterDescriptor(
            description='frame of the virtual camera V (moves with G1, on /tf)'))
        self.declare_parameter('camera_frame', 'camera_optical', ParameterDescriptor(
            description="the images' frame_id: V in the optical convention ('' for none)"))
        self.declare_parameter('tf_rate_max', 50.0, ParameterDescriptor(
            description='most /tf messages per second (one per frame up to it; 0: none) [Hz]',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10000.0,
                                                     step=0.0)]))

    def _on_set_parameters(self, params):
        for p in params:
            if p.type_ == p.Type.DOUBLE and not math.isfinite(p.value):
                return SetParametersResult(successful=False, reason=f'{p.name} must be finite')
        values = {p.name: p.value for p in params if p.name in TF_PARAMETERS}
        if values:
            if 'cell_T_v0' in values and next(p for p in params if p.name == 'cell_T_v0') \
                    .type_ not in (Parameter.Type.DOUBLE_ARRAY, Parameter.Type.INTEGER_ARRAY):
                return SetParametersResult(successful=False,
                                           reason='cell_T_v0 must be a list of 16 numbers')
            problem = self._tf_problem({**self._tf_values(), **values})
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def _tf_values(self):
        return {name: self.get_parameter(name).value for name in TF_PARAMETERS}

    @staticmethod
    def _tf_problem(values) -> str:
        """Why these TF parameter values cannot be used ('' when they can)."""
        try:
            tf_frames.FrameNames(values['cell_frame'], values['frame_id'],
                                 values['virtual_camera_frame'], values['camera_frame'])
            tf_frames.check_cell_T_v0(list(values['cell_T_v0']), 'cell_T_v0')
        except ValueError as exc:
            return str(exc)
        return ''

    def _cache_parameters(self, _params=None):
        # read per frame: a dict lookup instead of rclpy's get_parameter
        self._p = {name: self.get_parameter(name).value for name in (
            'frame_id', 'min_ray_plane_angle', 'scan_end_timeout', 'scan_max_points',
            'marker_period', 'marker_range', 'tf_rate_max', 'multi_view_tolerance')}
        values = self._tf_values()
        problem = self._tf_problem(values)
        if problem:  # only a start-up value can be bad here; later sets are refused
            self.get_logger().error(f'no TF published: {problem}')
            self._frames = None
        else:
            self._frames = tf_frames.FrameNames(values['cell_frame'], values['frame_id'],
                                                values['virtual_camera_frame'],
                                                values['camera_frame'])
            self._cell_T_v0_param = list(values['cell_T_v0'])
        if hasattr(self, '_pub_tf_static'):
            self._publish_static_tf()

    def _load(self, path):
        try:
            cal = calibration_file.load(path)
        except ValueError as exc:
            return False, f'calibration not loaded: {exc}'
        self.calibration, self.model = cal, cal.model
        if hasattr(self, '_pub_tf_static'):
            self._publish_static_tf()
        note = ' (SIMULATOR TRUTH, not a calibration)' if cal.source == 'simulator_truth' else ''
        return True, f'calibration loaded from {cal.path}{note}'

    def _log_outcome(self, ok: bool, message: str) -> None:
        # one call site per severity: rclpy refuses a second severity from one line
        # ("Logger severity cannot be changed between calls")
        if ok:
            self.get_logger().info(message)
        else:
            self.get_logger().error(message)

    def _skip(self, cause, detail=''):
        skipped = self.counters['skipped']
        skipped[cause] = skipped.get(cause, 0) + 1
        if cause not in self._warned:
            self._warned.add(cause)
            self.get_logger().warning(f'skipping frame: {cause} {detail} (logged once; counted)')

    # -- frames -----------------------------------------------------------------------
    def _on_centers(self, data: bytes):
        try:
            msg = cdr.parse_stripe_centers(data)
        except cdr.CdrError as exc:
            return self._skip('malformed_cdr', str(exc))
        try:
            self._process(msg)
        except Exception as exc:  # noqa: BLE001 - a node never dies on input
            self._skip('exception', repr(exc))

    def _process(self, msg):
        if self.model is None:
            return self._skip('no_calibration')
        g = msg.galvo
        volts = (g.g1_pan_voltage, g.g1_tilt_voltage, g.g2_pan_voltage, g.g2_tilt_voltage)
        if not all(math.isfinite(v) for v in volts):
            return self._skip('nonfinite_voltage')
        if max(abs(v) for v in volts) > VOLTAGE_LIMIT:
            return self._skip('voltage_out_of_range', f'{volts}')
        u, v = msg.u, msg.v
        n = u.shape[0]
        if not (v.shape[0] == n == msg.width.shape[0] == msg.strength.shape[0]):
            return self._skip('array_length_mismatch')
        self._last_frame_time = time.monotonic()
        self.counters['frames'] += 1
        self._offer_tf(msg.header, g.g1_pan_voltage, g.g1_tilt_voltage)
        if not g.laser_on:
            return self._skip('laser_off')
        res = triangulate(self.model, np.column_stack([u, v]), g.g1_pan_voltage,
                          g.g1_tilt_voltage, g.g2_tilt_voltage,
                          min_angle=self._p['min_ray_plane_angle'])
        # x, y, z, intensity, width as the columns of one float32 block, then viewed as records
        block = np.empty((n, 5), np.float32)
        block[:, :3] = res.p_v0
        block[:, 3] = msg.strength
        block[:, 4] = msg.width
        if not res.valid.all():
            block = block[res.valid]
        cloud = block.view(CLOUD_DTYPE).reshape(-1)
        self.counters['invalid_points'] += n - cloud.shape[0]
        header = cdr.Header(msg.header.sec, msg.header.nanosec, self._p['frame_id'])
        if self._p['multi_view_tolerance'] > 0:
            for item in self._two_views(volts, cloud, header):
                self._emit(*item)
        else:
            self._emit(volts, cloud, header)

    def _two_views(self, volts, cloud, header):
        """The frames to publish now under multi_view_tolerance: a pair filtered by
        :func:`reconstructor.consistency.agreeing`, or a frame that found no partner."""
        pending, self._pending = self._pending, None
        mv = self.counters['multi_view']
        if pending is not None and pending[0][3] == volts[3] and pending[0][:2] != volts[:2]:
            keep_a, keep_b = agreeing(xyz(pending[1]), xyz(cloud),
                                      self._p['multi_view_tolerance'])
            mv['pairs'] += 1
            mv['dropped_points'] += int((~keep_a).sum() + (~keep_b).sum())
            return [(pending[0], pending[1][keep_a], pending[2]), (volts, cloud[keep_b], header)]
        self._pending = (volts, cloud, header)
        if pending is not None:
            mv['unpaired'] += 1
            return [pending]
        return []

    def _emit(self, volts, cloud, header):
        """Publish one frame's cloud on points and add it to the scan."""
        self.counters['points'] += cloud.shape[0]
        # invalid points are dropped, never sent as NaN: the cloud is dense
        self._pub_points.publish(cdr.serialize_point_cloud(cloud, header))
        if cloud.shape[0]:
            if self._scan_points + cloud.shape[0] > self._p['scan_max_points'] and \
                    self._scan_parts:
                self.counters['scan_splits'] += 1
                self._publish_scan('reached scan_max_points; the scan goes on in a new cloud')
            self._scan_parts.append(cloud)
            self._scan_points += cloud.shape[0]
        self._maybe_markers(header, volts)

    def _check_scan_end(self):
        timeout = self._p['scan_end_timeout']
        if self._last_frame_time is None or time.monotonic() - self._last_frame_time < timeout:
            return
        self._last_frame_time = None
        if self._pending is not None:  # the last frame found no second view
            self.counters['multi_view']['unpaired'] += 1
            self._emit(*self._pending)
            self._pending = None
        self._publish_scan('scan ended')

    def _publish_scan(self, why):
        """Publish the accumulated cloud on points/scan and start an empty one.

        The parts are written into the message one after the other: for 7 million points
        in 10,000 parts, concatenating them and then writing the message took 0.76 s of the
        executor thread here, writing the parts directly 0.09 s.
        """
        parts = self._scan_parts or [np.zeros(0, CLOUD_DTYPE)]
        points = self._scan_points
        self._scan_parts = []
        self._scan_points = 0
        self._last_scan = parts
        self.counters['scans'] += 1
        sec, nanosec = divmod(self.get_clock().now().nanoseconds, 1_000_000_000)
        header = cdr.Header(sec, nanosec, self._p['frame_id'])
        self._pub_scan.publish(cdr.serialize_point_cloud(parts, header))
        self.get_logger().info(f'{why}: {points} points on points/scan')

    # -- tf ---------------------------------------------------------------------------
    def _publish_static_tf(self):
        """All static transforms in one message (a new one replaces the latched one)."""
        if self._frames is None:
            return
        from_file = self.calibration.cell_T_v0 if self.calibration is not None else None
        cell_T_v0, source = tf_frames.cell_T_v0_source(from_file, self._cell_T_v0_param)
        sec, nanosec = divmod(self.get_clock().now().nanoseconds, 1_000_000_000)
        self._pub_tf_static.publish(_tf_message(
            tf_frames.static_edges(self._frames, cell_T_v0), sec, nanosec))
        self.get_logger().info(f'/tf_static: {self._frames.cell} -> {self._frames.v0} from the '
                               f'{source}')

    def _offer_tf(self, header, u1_pan, u1_tilt):
        item = (header.sec, header.nanosec, u1_pan, u1_tilt)
        if self._tf_limiter.offer(item, time.monotonic(), self._p['tf_rate_max']):
            self._publish_tf(item)

    def _flush_tf(self):
        item = self._tf_limiter.due(time.monotonic(), self._p['tf_rate_max'])
        if item:
            self._publish_tf(item)

    def _publish_tf(self, item):
        sec, nanosec, u1_pan, u1_tilt = item
        if self._frames is None or self.model is None:
            return
        edge = tf_frames.virtual_camera_edge(self._frames, self.model, u1_pan, u1_tilt)
        self._pub_tf.publish(_tf_message([edge], sec, nanosec))

    # -- markers ----------------------------------------------------------------------
    def _maybe_markers(self, header, volts):
        period = self._p['marker_period']
        now = time.monotonic()
        if period <= 0 or now - self._last_marker < period:
            return
        self._last_marker = now
        ros_header = Header(frame_id=header.frame_id)
        ros_header.stamp.sec, ros_header.stamp.nanosec = header.sec, header.nanosec
        self._pub_markers.publish(self.markers(ros_header, volts))

    def markers(self, header: Header, volts):
        """The laser plane patch and the camera field-of-view frustum, in V0."""
        model, rng = self.model, self._p['marker_range']
        intr = model.intrinsics
        T = v0_T_v(model, volts[0], volts[1])
        corners = np.array([[0, 0], [intr.width, 0], [intr.width, intr.height],
                            [0, intr.height]], float)
        rays = np.column_stack([(corners[:, 0] - intr.cx) / intr.fx,
                                (corners[:, 1] - intr.cy) / intr.fy, np.ones(4)])
        far = (T @ np.column_stack([rays * rng, np.ones(4)]).T).T[:, :3]
        origin = T[:3, 3]
        fov = Marker(header=header, ns='camera_fov', id=0, type=Marker.LINE_LIST)
        fov.scale.x = 0.002
        fov.color.r, fov.color.g, fov.color.b, fov.color.a = 0.2, 0.6, 1.0, 1.0
        pts = [p for c in far for p in (origin, c)]
        pts += [p for i in range(4) for p in (far[i], far[(i + 1) % 4])]
        fov.points = [Point(x=float(q[0]), y=float(q[1]), z=float(q[2])) for q in pts]
        # laser plane: a square patch centred on the point nearest the view centre
        plane = laser_plane_v0(model, volts[3])
        nrm, e = plane[:3], plane[3]
        centre = origin + (T[:3, 2] * rng)
        centre = centre - (nrm @ centre + e) * nrm
        a = np.cross(nrm, [0.0, 1.0, 0.0] if abs(nrm[1]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(nrm, a)
        half = 0.5 * rng
        quad = [centre + half * (sa * a + sb * b) for sa, sb in
                ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        laser = Marker(header=header, ns='laser_plane', id=1, type=Marker.TRIANGLE_LIST)
        laser.scale.x = laser.scale.y = laser.scale.z = 1.0
        laser.color.r, laser.color.g, laser.color.b, laser.color.a = 1.0, 0.1, 0.1, 0.35
        laser.points = [Point(x=float(q[0]), y=float(q[1]), z=float(q[2]))
                        for q in (quad[0], quad[1], quad[2], quad[0], quad[2], quad[3])]
        return MarkerArray(markers=[fov, laser])

    # -- services ---------------------------------------------------------------------
    def _on_reload(self, req, resp):
        path = req.path or self.get_parameter('calibration_file').value
        if not path:
            resp.success, resp.message = False, 'no path given and no calibration_file set'
            return resp
        ok, message = self._load(path)  # on failure the previous calibration stays active
        self._log_outcome(ok, message)
        resp.success, resp.message = ok, message
        if ok:
            resp.path, resp.content_hash = self.calibration.path, self.calibration.content_hash
            resp.stages = list(self.calibration.stages)
        return resp

    def _on_save(self, req, resp):
        parts = self._last_scan if self._last_scan is not None else self._scan_parts
        scan = np.concatenate(parts) if parts else None
        if scan is None or scan.shape[0] == 0:
            resp.success, resp.message = False, 'no scan cloud to save yet'
            return resp
        try:
            path = save_cloud(scan, req.path)
        except (ValueError, OSError) as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        resp.success, resp.path, resp.points = True, str(Path(path).resolve()), scan.shape[0]
        resp.message = f'saved {scan.shape[0]} points to {resp.path}'
        return resp


def _tf_message(edges, sec: int, nanosec: int) -> TFMessage:
    """A tf2_msgs/TFMessage of :class:`reconstructor.tf_frames.Edge` s, all at one stamp."""
    out = TFMessage()
    for edge in edges:
        tf = TransformStamped()
        tf.header.stamp.sec, tf.header.stamp.nanosec = int(sec), int(nanosec)
        tf.header.frame_id, tf.child_frame_id = edge.parent, edge.child
        t, q = tq_from_transform(edge.parent_T_child)
        tr, rot = tf.transform.translation, tf.transform.rotation
        tr.x, tr.y, tr.z = (float(v) for v in t)
        rot.x, rot.y, rot.z, rot.w = (float(v) for v in q)
        out.transforms.append(tf)
    return out


def main(args=None):
    run_node(ReconstructorNode, args)


if __name__ == '__main__':
    main()
