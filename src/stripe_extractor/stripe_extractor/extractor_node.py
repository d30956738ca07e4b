"""``stripe_extractor`` node: camera images + galvo states in, stripe centres out.

Topics
------
- subscribes ``camera/image_raw`` (sensor_msgs/Image, ``qos_profile_sensor_data``): mono8,
  8UC1, mono16 or 16UC1;
- subscribes ``galvo/state`` (galvoscan_msgs/GalvoState, best effort, depth 50: compatible
  with reliable and best-effort publishers);
- publishes ``stripe/centers`` (galvoscan_msgs/StripeCenters, reliable, depth 50): the
  image's header, the frame's GalvoState, the centres, the parameters used (``min_strength``
  as the threshold applied, in the image's DN) and the frame's saturated fraction and peak
  level (:func:`~stripe_extractor.exposure.frame_levels`; of the long exposure for an HDR
  pair);
- publishes ``diagnostics`` (diagnostic_msgs/DiagnosticArray) every ``diagnostics_period``
  seconds with the node's counters.

Image and state are paired by header stamp (the driver stamps the state with the image's
stamp); either may arrive first (:class:`~stripe_extractor.pairing.StampPairer`). Bad images
are logged once per cause, counted and skipped; the node never dies on input.

Data path: the image and state subscriptions are raw, and the serialised CDR is read in place
(:mod:`galvoscan_common.cdr`: ``parse_image_cdr``, ``image_to_array``, ``parse_galvo_state``),
with no rclpy Image and no copy of the pixels; the centres are written as CDR and published
as bytes (a malformed state is counted as ``skipped_malformed_state``).

Where extraction runs (parameter ``extraction_thread``):
- ``true``: every paired frame goes to one extraction thread
  (:class:`~stripe_extractor.worker.SerialWorker`); the numba kernels release the GIL, so
  extraction runs on another core while the executor thread serves the other nodes. Frames
  arriving while ``IMAGE_QUEUE_DEPTH`` frames already wait are dropped and counted
  (``dropped_busy``).
- ``false``: on the executor thread, in the subscription callback. No thread hand-off, so
  the lowest latency while the executor thread has time to spare.
- ``auto`` (the default): on the executor thread while that thread can carry it, on the
  extraction thread once it cannot (:class:`~stripe_extractor.worker.OffloadPolicy`): once
  the executor thread's CPU time per frame, extraction included, exceeds
  ``AUTO_OFFLOAD_ABOVE`` of the mean interval between frames (1000 fps; or 500 fps with the
  other nodes on the same executor on a loaded machine), and back below
  ``AUTO_INLINE_BELOW`` once the thread has finished every frame it holds, so the output
  stays in order. Frames extracted on the thread are counted (``frames_offloaded``).

Composition: ``StripeExtractorNode`` does not call ``rclpy.init``; pass ``context=...`` or
other ``Node`` keyword arguments and add it to any executor together with other nodes
(``galvoscan run --one-process`` puts every node on one EventsExecutor).

In-process hand-off (parameter ``intra_process``, read-only, default false): the node takes
``camera/image_raw`` and ``galvo/state`` from the in-process bus of its context
(:mod:`galvoscan_common.intra`) instead of subscribing over DDS: a driver or player in the
same process hands it the CDR bytes directly, with no copy of the image. It then hears only
publishers in its own process, on the executor that serves them. ``galvoscan run
--one-process`` sets it when the driver runs in the same process.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from galvoscan_msgs.msg import GalvoState, StripeCenters
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.qos import (
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from sensor_msgs.msg import Image

from galvoscan_common import cdr, intra
from galvoscan_common.boundary import CallbackErrors, guard_subscription
from galvoscan_common.diagnostics import status as diagnostic_status
from galvoscan_common.executor import run_node

from .config import (
    AMBIGUITY_RATIO_RANGE,
    BIT_DEPTHS,
    LINE_WIDTH_RANGE_PX,
    MAX_OFFSET_RANGE_PX,
    METHODS,
    MIN_STRENGTH_RANGE_DN,
    ORIENTATIONS,
    PEAK_MODES,
    ROI_HALF_HEIGHT_RANGE_PX,
    WIDTH_ADAPT_NARROWER,
    WIDTH_ADAPT_WIDER,
    ExtractorConfig,
    white_level,
)
from .exposure import frame_levels, merge_hdr
from .extractor import extract, warm_up
from .pairing import StampPairer
from .selection import COUNT_NAMES
from .worker import OffloadPolicy, SerialWorker

PAIRING_BUFFER_RANGE = (1, 1000)
DIAGNOSTICS_PERIOD_RANGE_S = (0.1, 60.0)


def _same_position(first: cdr.GalvoState, second: cdr.GalvoState) -> bool:
    """The second state is the next in sequence at the same voltages (an HDR pair)."""
    return (second.seq == first.seq + 1 and first.laser_on and second.laser_on
            and (first.g1_pan_voltage, first.g1_tilt_voltage, first.g2_pan_voltage,
                 first.g2_tilt_voltage) == (second.g1_pan_voltage, second.g1_tilt_voltage,
                                           second.g2_pan_voltage, second.g2_tilt_voltage))


def centers_cdr(header: cdr.Header, state: cdr.GalvoState, result,
                levels: tuple[float, float] = (0.0, 0.0)) -> bytes:
    """The serialised StripeCenters of one extraction result (image header, its state) and
    its frame's (saturated fraction [1], peak level [share of the white level])."""
    cfg = result.config
    h, w = result.image_shape
    return cdr.serialize_stripe_centers(cdr.StripeCenters(
        header, state, w, h, result.u, result.v, result.width, result.strength, cfg.method,
        float(cfg.sigma), float(cfg.threshold_dn(result.white_level)),
        int(cfg.roi_half_height),
        StripeCenters.ORIENTATION_VERTICAL if cfg.orientation == 'vertical'
        else StripeCenters.ORIENTATION_HORIZONTAL, int(result.rejected_secondary),
        float(levels[0]), float(levels[1]) * result.white_level))


#: frames the image subscription, and the extraction queue, hold while the extractor is busy
#: (about 12 MB each at 720x540)
IMAGE_QUEUE_DEPTH = 30
#: ``extraction_thread`` auto: the executor thread's CPU time per frame, extraction included,
#: over the frame interval, above which frames go to the extraction thread, and below which
#: they return to the executor thread
AUTO_OFFLOAD_ABOVE, AUTO_INLINE_BELOW = 0.9, 0.7
EXTRACTION_THREAD_CHOICES = (True, False, 'auto')


class StripeExtractorNode(Node):
    """Thin adapter around :func:`stripe_extractor.extractor.extract` (see module docstring)."""

    def __init__(self, extraction_thread_default: bool | str = 'auto',
                 intra_process_default: bool = False, **kwargs):
        super().__init__('stripe_extractor', **kwargs)
        self._declare_extractor_parameters()
        self._declare_node_parameters(extraction_thread_default, intra_process_default)

        self._config = self._config_from({})
        self._pairer = StampPairer(self.get_parameter('pairing_buffer_size').value)
        # written by the executor thread
        self.callback_errors = CallbackErrors()
        self._counts = {'images_received': 0, 'states_received': 0, 'dropped_busy': 0,
                        'frames_offloaded': 0}
        self._counts.update({f'skipped_{c}': 0
                             for c in (*cdr.BAD_IMAGE_CAUSES, 'malformed_state')})
        # written only by the extracting thread
        self._extract_counts = {'frames_extracted': 0, 'centers_published': 0,
                                'rejected_secondary': 0, 'extraction_errors': 0,
                                'publish_errors': 0, 'frames_width_adapted': 0}
        self._extract_counts.update({f'peaks_{k}': 0 for k in COUNT_NAMES})
        # the previous frame's centre row per column (peak_mode nearest), and the last
        # frame's saturated fraction and peak level
        self._previous_rows = None
        self._levels = (0.0, 0.0)
        #: the last frame's filter width: line_width_px, or the stripe's where adapted [px]
        self._width_used = float(self.get_parameter('line_width_px').value)
        #: bit_depth 0: the highest white level the frames have shown, by pixel size [DN]
        self._white_seen: dict[int, int] = {}
        self._extract_counts.update(hdr_merged=0, hdr_unpaired=0, hdr_from_short=0)
        #: hdr_pairs: the long exposure waiting for its short one (raw, image, state, result)
        self._hdr_held = None
        self._logged_causes: set[str] = set()
        self._extract_s = 0.0
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        warm_up()       # compile / load the numba kernels before the first frame arrives

        self._pub = self.create_publisher(
            StripeCenters, 'stripe/centers',
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE,
                       history=HistoryPolicy.KEEP_LAST))
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self._start_extraction_thread(self.get_parameter('extraction_thread').value)
        self._subscribe_inputs()
        self._diag_timer = self.create_timer(
            self.get_parameter('diagnostics_period').value, self._publish_diagnostics_guarded)
        self.get_logger().info(
            f'ready: {self._config}' + (' (images and states handed over in-process)'
                                        if self._bus_subs else ''))

    # ---- construction steps -----------------------------------------------------------
    def _declare_extractor_parameters(self) -> None:
        """Declare the parameters of :class:`ExtractorConfig`, its defaults and ranges."""
        defaults = ExtractorConfig()
        self.declare_parameter('method', defaults.method, ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING,
            description='Centre extraction method',
            additional_constraints=f'one of: {", ".join(METHODS)}'))
        self.declare_parameter('line_width_px', defaults.line_width_px, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE,
            description='Expected stripe FWHM [px]; sets the Gaussian scale sigma',
            floating_point_range=[FloatingPointRange(
                from_value=LINE_WIDTH_RANGE_PX[0], to_value=LINE_WIDTH_RANGE_PX[1])]))
        self.declare_parameter('adapt_line_width', defaults.adapt_line_width,
                               ParameterDescriptor(
                                   type=ParameterType.PARAMETER_BOOL,
                                   description='Extract a frame again at its stripe\'s '
                                               'measured FWHM when that is over '
                                               f'{WIDTH_ADAPT_WIDER}x line_width_px or under '
                                               f'1/{WIDTH_ADAPT_NARROWER} of it (set '
                                               'line_width_px to the width the diagnostics '
                                               'report to save the second pass)'))
        self.declare_parameter('min_strength', defaults.min_strength, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE,
            description='Weakest accepted smoothed peak above background [DN at 8 bits]: '
                        'stated for an 8-bit image (white level 255) and scaled by the '
                        "image's white level (bit_depth), so the same share of full scale "
                        'at every bit depth (20 = 20 DN in Mono8, 321 DN in Mono12)',
            floating_point_range=[FloatingPointRange(
                from_value=MIN_STRENGTH_RANGE_DN[0], to_value=MIN_STRENGTH_RANGE_DN[1])]))
        self.declare_parameter('bit_depth', defaults.bit_depth, ParameterDescriptor(
            type=ParameterType.PARAMETER_INTEGER,
            description="Bit depth of the camera's codes [bit], which sets the white level "
                        '2**bit_depth - 1 that min_strength and the saturated fraction '
                        'refer to; 0: mono8 is 8, mono16 the shallowest of 10, 12, 16 that '
                        "holds the brightest pixel of the frames so far (set it: the first "
                        "frames of a dim scene are otherwise held to a shallower camera's "
                        'threshold)',
            additional_constraints=f'one of: {", ".join(map(str, BIT_DEPTHS))}'))
        self.declare_parameter('roi_half_height', defaults.roi_half_height,
                               ParameterDescriptor(
                                   type=ParameterType.PARAMETER_INTEGER,
                                   description='Half height of the window searched around '
                                               "each column's candidate peak [px]; "
                                               '>= ceil(line_width_px)',
                                   integer_range=[IntegerRange(
                                       from_value=ROI_HALF_HEIGHT_RANGE_PX[0],
                                       to_value=ROI_HALF_HEIGHT_RANGE_PX[1], step=1)]))
        self.declare_parameter('orientation', defaults.orientation, ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING,
            description='Stripe direction in the image: horizontal = one centre per column, '
                        'vertical = one centre per row',
            additional_constraints=f'one of: {", ".join(ORIENTATIONS)}'))
        self.declare_parameter('peak_mode', defaults.peak_mode, ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING,
            description='Which of two peaks in a column is the stripe: strongest, nearest '
                        '(the expected_row, else the previous frame\'s centre of the '
                        'column), widest, or unambiguous (none when the second reaches '
                        'ambiguity_ratio of the first)',
            additional_constraints=f'one of: {", ".join(PEAK_MODES)}'))
        self.declare_parameter('ambiguity_ratio', defaults.ambiguity_ratio,
                               ParameterDescriptor(
                                   type=ParameterType.PARAMETER_DOUBLE,
                                   description='peak_mode unambiguous: share of the first '
                                               "peak's strength at which a second peak "
                                               'makes the column ambiguous [1]',
                                   floating_point_range=[FloatingPointRange(
                                       from_value=AMBIGUITY_RATIO_RANGE[0],
                                       to_value=AMBIGUITY_RATIO_RANGE[1])]))
        self.declare_parameter('max_offset_px', defaults.max_offset_px, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE,
            description='peak_mode nearest: drop a centre farther than this from the '
                        'expected row [px]; 0: no limit',
            floating_point_range=[FloatingPointRange(
                from_value=MAX_OFFSET_RANGE_PX[0], to_value=MAX_OFFSET_RANGE_PX[1])]))
        self.declare_parameter('hdr_pairs', False, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='HDR: a frame followed by the next in sequence at the same voltages '
                        '(the driver\'s hdr_ratio: long, then short exposure) gives one '
                        'stripe, the long one\'s centres where its stripe is not clipped, '
                        'else the short one\'s'))
        self.declare_parameter('expected_row', -1.0, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE,
            description='peak_mode nearest: the row where the stripe is expected [px] '
                        '(vertical stripes: the column); -1: the previous frame\'s centre '
                        'of each column',
            floating_point_range=[FloatingPointRange(from_value=-1.0, to_value=65535.0)]))

    def _declare_node_parameters(self, extraction_thread_default: bool | str,
                                 intra_process_default: bool) -> None:
        """Declare the node's own parameters: pairing, threading, hand-off, diagnostics."""
        self.declare_parameter('pairing_buffer_size', 50, ParameterDescriptor(
            type=ParameterType.PARAMETER_INTEGER,
            description='Frames and states each kept waiting for their partner [1]',
            integer_range=[IntegerRange(from_value=PAIRING_BUFFER_RANGE[0],
                                        to_value=PAIRING_BUFFER_RANGE[1], step=1)]))
        self.declare_parameter(
            'extraction_thread', extraction_thread_default, ParameterDescriptor(
                dynamic_typing=True, read_only=True,
                description='Where to extract: true = on a separate thread (another core), '
                            'false = on the executor thread, auto = on the executor thread '
                            'while it is busy under 70 % of the frame interval, extraction '
                            'included, on the separate thread above 90 %',
                additional_constraints='true, false or auto'))
        self.declare_parameter('intra_process', bool(intra_process_default), ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL, read_only=True,
            description='Take images and galvo states from publishers in this process, handed '
                        'over directly (galvoscan_common.intra), instead of over DDS'))
        self.declare_parameter('diagnostics_period', 1.0, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE,
            description='Period of the diagnostics message with the counters [s]',
            floating_point_range=[FloatingPointRange(
                from_value=DIAGNOSTICS_PERIOD_RANGE_S[0],
                to_value=DIAGNOSTICS_PERIOD_RANGE_S[1])]))

    def _start_extraction_thread(self, mode) -> None:
        """Set where frames are extracted (``extraction_thread`` true, false or 'auto').

        Starts the extraction thread unless ``mode`` is false; 'auto' also makes the
        :class:`OffloadPolicy` that chooses per frame.
        """
        if mode not in EXTRACTION_THREAD_CHOICES or isinstance(mode, (int, float)) and \
                not isinstance(mode, bool):
            raise ValueError(f'extraction_thread must be true, false or auto, got {mode!r}')
        self._policy = (OffloadPolicy(AUTO_OFFLOAD_ABOVE, AUTO_INLINE_BELOW)
                        if mode == 'auto' else None)
        self._worker = None
        if mode is not False:
            self._worker = SerialWorker(self._extract_and_publish, IMAGE_QUEUE_DEPTH,
                                        'stripe_extraction', on_error=self._skip_log_error)

    def _subscribe_inputs(self) -> None:
        """Take images and galvo states from the in-process bus or from raw DDS subscriptions.

        Over DDS the images come with sensor-data QoS (best effort, volatile) with room for a
        burst of ``IMAGE_QUEUE_DEPTH`` frames.
        """
        self._bus, self._bus_subs = intra.bus_for(self.context), []
        log = self.get_logger()
        on_image = guard_subscription('camera/image_raw', self._on_image, log,
                                      self.callback_errors)
        on_state = guard_subscription('galvo/state', self._on_state, log, self.callback_errors)
        if self.get_parameter('intra_process').value:
            self._bus_subs = [
                self._bus.subscribe(self.resolve_topic_name('camera/image_raw'), on_image),
                self._bus.subscribe(self.resolve_topic_name('galvo/state'), on_state)]
        else:
            image_qos = QoSProfile(depth=IMAGE_QUEUE_DEPTH,
                                   reliability=qos_profile_sensor_data.reliability,
                                   durability=qos_profile_sensor_data.durability,
                                   history=HistoryPolicy.KEEP_LAST)
            self.create_subscription(Image, 'camera/image_raw', on_image, image_qos, raw=True)
            self.create_subscription(
                GalvoState, 'galvo/state', on_state,
                QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT,
                           history=HistoryPolicy.KEEP_LAST), raw=True)

    # ---- parameters -------------------------------------------------------------------
    def _config_from(self, changes: dict) -> ExtractorConfig:
        names = ('method', 'line_width_px', 'min_strength', 'roi_half_height', 'orientation',
                 'peak_mode', 'ambiguity_ratio', 'max_offset_px', 'bit_depth',
                 'adapt_line_width')
        values = {n: changes.get(n, self.get_parameter(n).value) for n in names}
        return ExtractorConfig(**values)

    def _validate_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        try:
            self._config_from(changes)
            if 'pairing_buffer_size' in changes and changes['pairing_buffer_size'] < 1:
                raise ValueError('pairing_buffer_size must be >= 1')
            if 'diagnostics_period' in changes and not (
                    DIAGNOSTICS_PERIOD_RANGE_S[0] <= changes['diagnostics_period']
                    <= DIAGNOSTICS_PERIOD_RANGE_S[1]):
                raise ValueError(f'diagnostics_period must be in {DIAGNOSTICS_PERIOD_RANGE_S}')
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params) -> None:
        self._config = self._config_from({})
        self._white_seen = {}
        for p in params:
            if p.name == 'pairing_buffer_size':
                self._pairer.capacity = p.value
            elif p.name == 'diagnostics_period':
                self._diag_timer.cancel()
                self.destroy_timer(self._diag_timer)
                self._diag_timer = self.create_timer(p.value, self._publish_diagnostics_guarded)
        self.get_logger().info(f'parameters now {self._config}')

    # ---- data path --------------------------------------------------------------------
    def _skip(self, cause: str, detail: str) -> None:
        self._counts[f'skipped_{cause}'] += 1
        if cause not in self._logged_causes:
            self._logged_causes.add(cause)
            self.get_logger().warning(
                f'skipped {cause}: {detail} (logged once per cause; see diagnostics)')

    def _on_image(self, data: bytes) -> None:
        self._counts['images_received'] += 1
        try:
            raw = cdr.parse_image_cdr(data)
            img = cdr.image_to_array(raw)
        except cdr.BadImageError as exc:
            self._skip(exc.cause, str(exc))
            return
        pair = self._pairer.add_frame(raw.stamp_ns, (raw, img))
        if pair is not None:
            self._submit(*pair)

    def _on_state(self, data: bytes) -> None:
        self._counts['states_received'] += 1
        try:
            state = cdr.parse_galvo_state(data)
        except cdr.CdrError as exc:
            self._skip('malformed_state', str(exc))
            return
        pair = self._pairer.add_state(state.header.stamp_ns, state, seq=state.seq)
        if pair is not None:
            self._submit(*pair)

    def _submit(self, frame, state: cdr.GalvoState) -> None:
        job = (frame, state, self._config)
        if self._policy is not None:
            offload = self._policy.decide(time.monotonic(), time.thread_time(),
                                          self._worker.idle)
        else:
            offload = self._worker is not None
        if not offload:
            self._extract_and_publish(job)
            return
        self._counts['frames_offloaded'] += 1
        if not self._worker.submit(job):
            self._counts['dropped_busy'] += 1
            if 'dropped_busy' not in self._logged_causes:
                self._logged_causes.add('dropped_busy')
                self.get_logger().warning(
                    f'extraction queue full ({IMAGE_QUEUE_DEPTH} frames): frame dropped '
                    '(logged once; counted as dropped_busy)')

    def _skip_log_error(self, exc: BaseException) -> None:
        if 'extraction_error' not in self._logged_causes:
            self._logged_causes.add('extraction_error')
            self.get_logger().error(f'skipped extraction_error: {exc!r} (logged once)')

    def _extract_and_publish(self, job) -> None:
        """Extract one paired frame and publish its centres (on the extracting thread)."""
        (raw, img), state, config = job
        counts = self._extract_counts
        t0, cpu0 = time.perf_counter(), time.thread_time()
        try:
            expected = None
            if config.peak_mode == 'nearest':
                row = float(self.get_parameter('expected_row').value)
                expected = row if row >= 0 else self._previous_rows
                n_cols = img.shape[1 if config.orientation == 'horizontal' else 0]
                if expected is not None and np.ndim(expected) and len(expected) != n_cols:
                    expected = None
            if config.bit_depth == 0:
                # the stream's white level: the deepest any of its frames has shown, so a
                # dim frame of a 12-bit camera keeps the 12-bit threshold
                key = img.dtype.itemsize
                white = max(self._white_seen.get(key, 0), white_level(img))
                self._white_seen = {key: white}
                config = dataclasses.replace(config, bit_depth=white.bit_length())
            result = extract(img, config, expected)
            levels = frame_levels(img, result.white_level, config.orientation == 'vertical')
            self._levels = levels
            self._width_used = result.config.line_width_px
            if result.config is not config:
                counts['frames_width_adapted'] += 1
        except Exception as exc:  # noqa: BLE001 - the node must survive any input
            counts['extraction_errors'] += 1
            self._skip_log_error(exc)
            return
        self._extract_s += time.perf_counter() - t0
        if self._policy is not None:
            # CPU time: on the extraction thread the wall time also holds the wait for the GIL
            self._policy.note_extraction(time.thread_time() - cpu0)
        counts['frames_extracted'] += 1
        counts['rejected_secondary'] += result.rejected_secondary
        for k, v in result.selection.items():
            counts[f'peaks_{k}'] += v
        if config.peak_mode == 'nearest':
            h, w = result.image_shape
            along, across = (result.u, result.v) if config.orientation == 'horizontal' \
                else (result.v, result.u)
            prev = np.full(w if config.orientation == 'horizontal' else h, np.nan, np.float32)
            prev[np.rint(along).astype(np.int64)] = across
            self._previous_rows = prev
        if self.get_parameter('hdr_pairs').value:
            held, self._hdr_held = self._hdr_held, None
            if held is not None and _same_position(held[2], state):
                u, v, w, s, n_short = merge_hdr(held[3], result, held[1])
                counts['hdr_merged'] += 1
                counts['hdr_from_short'] += n_short
                result = dataclasses.replace(held[3], u=u, v=v, width=w, strength=s)
                raw, state, levels = held[0], held[2], held[4]
            else:
                self._hdr_held = (raw, img, state, result, levels)
                if held is None:
                    return
                counts['hdr_unpaired'] += 1
                raw, state, result, levels = held[0], held[2], held[3], held[4]
        self._publish_centers(raw, state, result, levels)

    def _publish_centers(self, raw, state, result, levels) -> None:
        counts = self._extract_counts
        header = cdr.Header(raw.stamp_sec, raw.stamp_nanosec, raw.frame_id)
        try:
            self._pub.publish(centers_cdr(header, state, result, levels))
        except Exception as exc:  # noqa: BLE001 - e.g. the context shut down meanwhile
            counts['publish_errors'] += 1
            if 'publish_error' not in self._logged_causes:
                self._logged_causes.add('publish_error')
                self.get_logger().error(f'publishing stripe/centers failed: {exc!r} '
                                        '(logged once; counted)')
            return
        counts['centers_published'] += 1

    def destroy_node(self):
        """Let the extraction thread finish what is queued, then destroy the node."""
        for sub in self._bus_subs:
            self._bus.unsubscribe(sub)
        self._bus_subs = []
        if self._worker is not None and not self._worker.stop():
            self.get_logger().error('extraction thread did not stop within 5 s')
        return super().destroy_node()

    # ---- counters ---------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Snapshot of every counter [1] (also published on ``diagnostics``)."""
        c = dict(self._counts)
        c.update(self._extract_counts)
        c['extraction_thread_errors'] = self._worker.errors if self._worker else 0
        pc = self._pairer.counters
        c['unmatched_images_dropped'] = pc.unmatched_frames_dropped
        c['unmatched_states_dropped'] = pc.unmatched_states_dropped
        c['duplicate_stamps'] = pc.duplicate_stamps
        c['state_seq_gaps'] = pc.state_seq_gaps
        c['skipped_total'] = sum(v for k, v in self._counts.items() if k.startswith('skipped_'))
        return c

    def _publish_diagnostics_guarded(self) -> None:
        guard_subscription('diagnostics', self.publish_diagnostics, self.get_logger(),
                           self.callback_errors)()

    def publish_diagnostics(self) -> None:
        c = self.counters()
        bad = c['skipped_total'] + c['extraction_errors'] + c['dropped_busy']
        mean_ms = 1e3 * self._extract_s / max(c['frames_extracted'], 1)
        status = diagnostic_status(
            f'{self.get_name()}: stripe extraction', c, self.callback_errors,
            f'{c["centers_published"]} published, {bad} frames skipped or dropped, '
            f'{mean_ms:.3f} ms mean extraction',
            warn=('skipped_total', 'extraction_errors', 'dropped_busy'))
        status.values.append(KeyValue(key='extraction_ms_mean', value=f'{mean_ms:.4f}'))
        sat, peak = self._levels
        status.values.append(KeyValue(key='saturated_fraction_last', value=f'{sat:.6f}'))
        status.values.append(KeyValue(key='peak_level_last', value=f'{peak:.4f}'))
        status.values.append(KeyValue(key='line_width_px_last',
                                      value=f'{self._width_used:.3f}'))
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        self._diag_pub.publish(msg)


def main(args=None):
    run_node(StripeExtractorNode, args)


if __name__ == '__main__':
    main()
