"""Pairing camera frames with the galvo board's trigger events (pure: no rclpy, no I/O).

On a real rig the galvo board triggers every exposure and reports each trigger as an
:class:`~galvo_driver.serial_link.protocol.Event` (boot id, scan id, trigger index, the
trigger instant on the board's microsecond clock, the DAC codes it output). The camera
delivers frames with its own frame id and its own nanosecond clock. :class:`TriggerPairer`
takes both streams as they arrive, in any interleaving, and answers, for every frame, which
trigger exposed it -- or that it cannot tell, in which case the frame is dropped and the
reason counted. It never guesses: a wrong pairing puts a stripe on the wrong laser plane.

How it pairs
------------
*Sequence.* Within a scan the camera's frame id and the board's trigger index advance
together: ``index = frame_id - k``. The scan's anchor fixes ``k``: the caller names the
frame id the camera will give the scan's first trigger (``first_frame_id`` of
:meth:`TriggerPairer.begin_scan`; by default the id after the last frame seen, or the first
frame of the scan if none was seen). A camera that loses a frame it exposed leaves a gap in
its frame ids (GigE Vision / USB3 Vision block ids), so ``k`` survives lost frames; a lost
event leaves a gap in the trigger indices, which are explicit.

*Timing.* Every pairing is verified against an online fit of the camera clock [ns] as an
affine function of the board clock [us] (:class:`ClockFit`: offset and drift, least squares
over the last ``window`` verified pairs with outliers removed). A frame pairs with the
event its sequence names only if

* the frame's exposure start, mapped to board time, is within the timing tolerance of the
  event's trigger time (plus ``trigger_delay_us``): ``sigma_factor`` robust deviations of
  the fitted pairs, between ``min_tolerance_us`` and ``tolerance`` periods;
* both neighbouring triggers (``index - 1``, ``index + 1``) are at least three tolerances
  away from it -- a late trigger followed at once by the next one could otherwise be
  confused. A lost neighbour's time is interpolated from the events around it only when
  those are regularly spaced; otherwise the frame is ambiguous;
* the fitted drift is within ``max_drift_ppm`` (an exposure delay that keeps growing
  looks like drift);
* event ``i`` is on the trigger schedule (below), or only late: the next trigger is back
  on it. A trigger off the schedule whose successor is off it too means the schedule
  moved -- a board clock step -- which the sequence cannot vouch for here: a step of ``n``
  periods and ``n`` triggers the camera missed at the same time put the frame of trigger
  ``i + n`` exactly where the stepped event ``i`` says, and nothing else differs. Such a
  frame is dropped (``timing_mismatch``) and agreement stops being enough, as below;
* for the pair that starts a fit, with ``camera_to_host`` (a coarse camera-to-host
  mapping): the exposure start is within ``host_tolerance_s`` of the trigger on the host
  clock too. This checks the scan's anchor, and finds the right trigger when the camera
  missed the scan's first ones.

The pairer waits for the neighbours' events before deciding, so a pair comes out about one
trigger period plus the transport latency after its frame and event arrived.

*When sequence and timing disagree* the change point between the last verified pair and
this frame tells what happened, measured against the trigger schedule (the board triggers
at a fixed period of its own clock; a trigger may be late, never early, so the schedule's
phase is the earliest trigger since the last board clock step -- a quantile of recent
triggers would follow a burst of late ones that a stalled board fires to catch up, and
put the on-time triggers whole periods off the schedule):

* the frame matches exactly one later trigger ``i + n`` on the unchanged clock fit, and that
  trigger is on the schedule: the camera missed ``n`` triggers (it did not expose, so its
  frame id did not advance); ``k`` is corrected by ``n`` (counted in ``resyncs``). A board
  clock step of whole periods also makes a later trigger match, but moves it off the
  schedule;
* the frame is where trigger ``i`` was due and event ``i`` is not: the board clock stepped;
  the clock fit restarts from this pair, ``k`` is kept (counted in ``clock_steps``);
* event ``i`` is on the schedule and the frame is early: the camera clock stepped back;
  likewise. A late frame is never taken for a camera clock step: its exposure may really
  have started late, under the next trigger's voltages;
* anything else (two faults at once, a timing outlier): the frame is dropped
  (``timing_mismatch``) and, until a frame and its event are seen on the old schedule again,
  agreeing sequence and timing are no longer enough to pair (a missed trigger and a board
  clock step of as many periods cancel out).

After a correction (and after the scan's anchor) pairs are held back until ``lock_pairs``
further frames confirm the new hypothesis; if one contradicts it, the held frames are dropped
as ``ambiguous`` and the previous hypothesis is restored -- as a suspect one: it was
contradicted too, by the frame that proposed the change, so two faults happened, and on
it they may cancel out (a board clock step of ``n`` periods, confirmed by fewer than
``lock_pairs`` frames, then ``n`` missed triggers: on the old clock fit the later frames
agree with their sequence, each ``n`` triggers off). Until a pair on the old schedule is
seen again, agreeing sequence and timing are not enough. A scan that ends during such a
probation drops the held frames too. When the refuted hypothesis is the scan's anchor
there is no previous one: with ``camera_to_host`` the next frame is anchored again (on the
host clock); without it every further frame of the scan is dropped (``timing_mismatch``),
since anchoring by sequence again would trust the sequence the refuting frame just
contradicted (a trigger missed while the anchor was on probation).

Refusing costs frames: after two faults that cancel out, the rest of the scan is dropped
(``timing_mismatch``), since nothing on the board or camera clocks tells the two readings
apart. A wrong tag would cost the scan.

What cannot be told apart without ``camera_to_host``: a camera that misses the very first
trigger of a scan looks exactly like a camera with one period more latency. And a camera
clock step of exactly ``n`` periods forward (within the tolerance) looks like ``n`` missed
triggers. These are documented limits, not handled cases.

*Sessions.* Events of another boot id (a board reset) end the pairing of the scan: no event
of it will follow, so frames waiting for one are decided (``frame_without_event``) and the
new boot's events are dropped (``outside_scan``) until the next :meth:`~TriggerPairer.begin_scan`.
A frame id that goes backwards (the camera was reopened; ids that wrap are unwrapped with
``frame_id_wrap``) does the same on the camera side (``camera_reset``).

Stamps
------
The stamp of a pair is the middle of the exposure: the frame's exposure start plus half the
exposure time, mapped from the camera clock to board time by the clock fit, then to the host
(ROS) time base by ``board_to_host``, a function the caller supplies (the serial backend's
board-to-host offset, from its lowest-round-trip GET_STATUS exchange). Without one the stamp
is board time in seconds.

Accounting
----------
Every frame given to :meth:`~TriggerPairer.add_frame` comes out exactly once, as a
:class:`PairedFrame` or as a :class:`Drop` with the frame; every trigger index of the scan
comes out exactly once, paired, or as a :class:`Drop` of kind ``event_without_frame`` (its
event arrived, no frame was paired with it) or ``event_lost`` (its event never arrived).
:attr:`TriggerPairer.counters` counts them by kind (see :data:`DROP_KINDS`). A pair's ``gap``
is the number of trigger indices since the previous pair of the scan that produced no frame:
the sequence gap ``GalvoState.seq`` shows.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Every kind of :class:`Drop`, with what it means.
DROP_KINDS = {
    'frame_without_event': 'a frame whose trigger event never arrived (or is outside the scan)',
    'event_without_frame': 'a trigger event no frame was paired with (a frame lost or dropped)',
    'event_lost': 'a trigger index whose event never arrived (a gap in the indices)',
    'duplicate_frame': 'a frame id seen twice; the second copy is dropped',
    'duplicate_event': 'an event seen twice; the second copy is dropped',
    'late_event': 'an event older than one already seen (out of order); dropped',
    'ambiguous': 'a frame that timing cannot assign to one trigger (or held, then refuted)',
    'timing_mismatch': 'a frame whose timing contradicts its sequence and no change explains',
    'outside_scan': 'a frame or event outside the current scan (no scan, other boot/scan)',
    'camera_reset': 'a frame after the camera restarted its frame ids or clock',
}

#: Trigger indices of the schedule-phase window, and events kept behind the last pair.
_PHASE_WINDOW = 32
_KEEP_EVENTS = 64

_WAIT = object()
_RETRY = object()
_DONE = object()


@dataclass(frozen=True)
class PairedFrame:
    """A camera frame and the trigger event that exposed it.

    Attributes
    ----------
    frame : object
        The camera frame (anything with ``frame_id`` and ``timestamp_ns``).
    event : object
        The board's trigger event (``boot_id``, ``scan_id``, ``index``, ``timestamp_us``,
        ``codes``, ``laser_on``, ``status``).
    seq : int
        ``seq_base`` of the scan + the trigger index: the frame sequence number [1].
    gap : int
        Trigger indices since the previous pair of this scan without a frame [1].
    stamp : float
        Middle of the exposure in the host time base of ``board_to_host`` [s].
    board_mid_us : float
        Middle of the exposure on the board clock [us].
    residual_us : float
        Frame exposure start minus trigger time, both on the board clock, minus the mean
        latency the clock fit absorbed [us]; small when the pairing is right.
    """

    frame: Any
    event: Any
    seq: int
    gap: int
    stamp: float
    board_mid_us: float
    residual_us: float

    @property
    def index(self) -> int:
        """Trigger index of the scan."""
        return self.event.index


@dataclass(frozen=True)
class Drop:
    """A frame or a trigger that produced no pair, and why.

    Attributes
    ----------
    kind : str
        One of :data:`DROP_KINDS`.
    frame : object or None
        The dropped frame, for frame-side kinds.
    event : object or None
        The event concerned, when there is one.
    index : int or None
        The trigger index concerned, when known.
    detail : str
        Human-readable reason, for logs.
    """

    kind: str
    frame: Any = None
    event: Any = None
    index: int | None = None
    detail: str = ''


class ClockFit:
    """Camera clock [ns] as an affine function of the board clock [us], fitted online.

    Least squares over the last ``window`` pairs, relative to the newest pair (so 64-bit
    clock values keep their precision); pairs more than three robust deviations off the
    line are left out of the second pass. With fewer than 3 pairs or a span shorter than
    ``min_span_us`` the slope is the nominal 1000 ns/us and only the offset is estimated.

    Parameters
    ----------
    window : int
        Number of pairs fitted.
    min_span_us : float
        Board-time span the pairs must cover before the drift is estimated [us].
    """

    def __init__(self, window: int = 512, min_span_us: float = 200_000.0):
        if int(window) < 2:
            raise ValueError(f'window: need at least 2 pairs, got {window}')
        self._pairs: deque[tuple[int, int]] = deque(maxlen=int(window))
        self.min_span_us = float(min_span_us)
        self._x0 = self._y0 = 0
        self._slope = 1000.0
        self._intercept = 0.0
        self._sigma = math.inf
        self._sigma_slope = math.inf
        self._xmean = 0.0
        self._n_kept = 0

    def __len__(self) -> int:
        return len(self._pairs)

    def clear(self) -> None:
        """Forget every pair."""
        self._pairs.clear()

    def state(self) -> tuple:
        """Everything needed to restore this fit with :meth:`restore`."""
        return (list(self._pairs), self._x0, self._y0, self._slope, self._intercept,
                self._sigma, self._sigma_slope, self._xmean, self._n_kept)

    def restore(self, state: tuple) -> None:
        """Go back to a state returned by :meth:`state`."""
        (pairs, self._x0, self._y0, self._slope, self._intercept, self._sigma,
         self._sigma_slope, self._xmean, self._n_kept) = state
        self._pairs.clear()
        self._pairs.extend(pairs)

    def add(self, board_us: int, camera_ns: int) -> None:
        """Add one verified pair: trigger time [us] and exposure start [ns]; refit."""
        self._pairs.append((int(board_us), int(camera_ns)))
        self._x0, self._y0 = self._pairs[-1]
        xs = np.array([x - self._x0 for x, _ in self._pairs], dtype=np.float64)
        ys = np.array([y - self._y0 for _, y in self._pairs], dtype=np.float64)
        keep = np.ones(len(xs), bool)
        for _ in range(2):
            slope, intercept = self._solve(xs[keep], ys[keep])
            resid = ys - (intercept + slope * xs)
            mad = float(np.median(np.abs(resid - np.median(resid))))
            keep = np.abs(resid) <= max(3.0 * 1.4826 * mad, 1000.0)  # >= 1 us
            if keep.sum() < 2:
                break
        self._slope, self._intercept = slope, intercept
        kept = resid[keep] if keep.sum() >= 2 else resid
        self._sigma = 1.4826 * float(np.median(np.abs(kept - np.median(kept))))
        xk = xs[keep] if keep.sum() >= 2 else xs
        self._xmean = float(xk.mean())
        self._n_kept = len(xk)
        sxx = float(np.sum((xk - xk.mean()) ** 2))
        self._sigma_slope = self._sigma / math.sqrt(sxx) if sxx > 0 else math.inf

    def _solve(self, xs: np.ndarray, ys: np.ndarray) -> tuple[float, float]:
        if len(xs) < 3 or float(np.ptp(xs)) < self.min_span_us:
            return 1000.0, float(np.median(ys - 1000.0 * xs))
        xm, ym = xs.mean(), ys.mean()
        slope = float(np.sum((xs - xm) * (ys - ym)) / np.sum((xs - xm) ** 2))
        return slope, float(ym - slope * xm)

    @property
    def sigma_us(self) -> float:
        """Robust standard deviation of the fitted pairs around the line [us] (inf with
        fewer than 16 pairs)."""
        return self._sigma / 1000.0 if len(self._pairs) >= 16 else math.inf

    def sigma_at_us(self, board_us: float) -> float:
        """Standard deviation of a camera time predicted at ``board_us``, in board
        microseconds: the scatter of the pairs plus the slope's uncertainty carried from
        the pairs to ``board_us`` (inf with fewer than 16 pairs)."""
        if len(self._pairs) < 16:
            return math.inf
        dx = board_us - (self._x0 + self._xmean)
        var = self._sigma ** 2 / self._n_kept + (self._sigma_slope * dx) ** 2
        return math.sqrt(self._sigma ** 2 + var) / 1000.0

    @property
    def span_us(self) -> float:
        """Board time the fitted pairs cover [us]."""
        return float(self._pairs[-1][0] - self._pairs[0][0]) if self._pairs else 0.0

    @property
    def slope(self) -> float:
        """Camera nanoseconds per board microsecond [ns/us] (1000 for equal rates)."""
        return self._slope

    @property
    def drift_ppm(self) -> float:
        """Camera clock rate relative to the board clock, minus one [ppm]."""
        return (self._slope / 1000.0 - 1.0) * 1e6

    def camera_ns(self, board_us: float) -> float:
        """Camera time [ns] of a board time [us] (needs at least one pair)."""
        return self._y0 + self._intercept + self._slope * (board_us - self._x0)

    def board_us(self, camera_ns: float) -> float:
        """Board time [us] of a camera time [ns] (needs at least one pair)."""
        return self._x0 + (camera_ns - self._y0 - self._intercept) / self._slope


@dataclass(frozen=True)
class _Frame:
    """A frame as the pairer sees it: ``frame_id`` unwrapped (monotonic across id wraps)."""

    raw: Any
    frame_id: int
    timestamp_ns: int


@dataclass
class _Scan:
    boot_id: int
    scan_id: int
    period_us: float
    n_rows: int | None
    first_frame_id: int | None
    seq_base: int


class TriggerPairer:
    """Pairs camera frames with the board's trigger events, counting every drop.

    Feed it with :meth:`add_event` and :meth:`add_frame` as they arrive; each returns the
    outcomes it could decide (a list of :class:`PairedFrame` and :class:`Drop`). See the
    module docstring for the rules.

    Parameters
    ----------
    exposure_s : float
        Exposure time [s]; the stamp is the exposure start plus half of it.
    board_to_host : callable, optional
        ``board_to_host(board_us: float) -> float``: a board time [us] in the host (ROS)
        time base [s]; the stamps are made with it (board clock steps the pairer detected
        are taken out first). Default: board time in seconds.
    trigger_delay_us : float
        The camera's delay from the trigger to the exposure start [us] (its trigger latency
        plus any ``TriggerDelay``), so that the clock fit maps camera time to board time of the
        same instant; it shifts every stamp, never a pairing.
    tolerance : float
        Largest timing residual that can verify a pairing, as a fraction of the trigger
        period (0 < tolerance <= 0.3): the tolerance while the fit has fewer than 16 pairs.
    sigma_factor, min_tolerance_us : float
        With 16 pairs or more the tolerance is ``sigma_factor`` standard deviations of the
        fit's prediction (:meth:`ClockFit.sigma_at_us`: the pairs' robust scatter and the
        slope's uncertainty over the time since them), at least ``min_tolerance_us`` [us],
        never above the ceiling above. A neighbouring trigger must be three tolerances away
        for a frame to pair.
    window : int
        Pairs in the clock fit.
    lock_pairs : int
        Confirmations a new hypothesis (scan anchor, resync, clock step) needs before its
        pairs are released.
    max_pending_frames : int
        Frames waiting for events beyond this are decided as if the awaited events were lost.
    camera_to_host : callable, optional
        ``camera_to_host(camera_ns: int) -> float``: a camera time in the host time base of
        ``board_to_host`` [s], known coarsely (a timestamp latch, or a camera that stamps
        with the host's clock). With it the pair that starts a clock fit (a scan's anchor,
        a clock step) must also hold on the host clock: exposure start within
        ``host_tolerance_s`` of the trigger; a scan's anchor that does not is moved to the
        one later trigger that does (the camera missed the scan's first triggers, which
        sequence alone cannot tell). Both mappings need only hold that well around the
        start of a scan (the serial backend syncs its board offset before each scan; a
        board clock 200 ppm fast is 1 ms off 5 s later).
    host_tolerance_s : float, optional
        Default: half a trigger period minus the timing tolerance.
    max_drift_ppm : float
        Largest rate difference of the two clocks believed [ppm]; a fit over at least a
        second beyond it (an exposure delay that keeps growing looks like drift) stops the
        pairing.
    frame_id_wrap : int, optional
        The camera's frame ids count 1 .. frame_id_wrap - 1 and start again at 1 (GigE
        Vision 1.x block ids: 65536); None: they never wrap. A frame id more than half the
        range behind the last one means the camera restarted.
    """

    def __init__(self, *, exposure_s: float = 0.0,
                 board_to_host: Callable[[float], float] | None = None,
                 trigger_delay_us: float = 0.0, tolerance: float = 0.25,
                 sigma_factor: float = 6.0, min_tolerance_us: float = 50.0,
                 window: int = 512, lock_pairs: int = 4, max_pending_frames: int = 256,
                 camera_to_host: Callable[[int], float] | None = None,
                 host_tolerance_s: float | None = None,
                 max_drift_ppm: float = 1000.0, frame_id_wrap: int | None = None):
        if not (math.isfinite(exposure_s) and exposure_s >= 0):
            raise ValueError(f'exposure_s: must be >= 0 s, got {exposure_s}')
        if not (math.isfinite(tolerance) and 0 < tolerance <= 0.3):
            raise ValueError(f'tolerance: must be in (0, 0.3] periods, got {tolerance}')
        for name, value in (('trigger_delay_us', trigger_delay_us),
                            ('max_drift_ppm', max_drift_ppm),
                            ('sigma_factor', sigma_factor),
                            ('min_tolerance_us', min_tolerance_us)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f'{name}: must be a finite number >= 0, got {value}')
        if int(lock_pairs) < 1 or int(max_pending_frames) < 1:
            raise ValueError('lock_pairs and max_pending_frames must be >= 1')
        if frame_id_wrap is not None and int(frame_id_wrap) < 4:
            raise ValueError(f'frame_id_wrap: expected None or >= 4, got {frame_id_wrap}')
        self.frame_id_wrap = None if frame_id_wrap is None else int(frame_id_wrap)
        self.exposure_ns = exposure_s * 1e9
        self.board_to_host = board_to_host or (lambda us: us * 1e-6)
        self.tolerance = float(tolerance)
        self.trigger_delay_us = float(trigger_delay_us)
        self.sigma_factor = float(sigma_factor)
        self.min_tolerance_us = float(min_tolerance_us)
        self.max_drift_ppm = float(max_drift_ppm)
        self.camera_to_host = camera_to_host
        if host_tolerance_s is not None and not (math.isfinite(host_tolerance_s)
                                                 and host_tolerance_s > 0):
            raise ValueError(f'host_tolerance_s: must be a positive time in s, got '
                             f'{host_tolerance_s}')
        self.host_tolerance_s = host_tolerance_s
        self.lock_pairs = int(lock_pairs)
        self.max_pending_frames = int(max_pending_frames)
        self.fit = ClockFit(window)
        self.counters = {k: 0 for k in DROP_KINDS}
        self.counters.update(paired=0, frames_in=0, events_in=0, resyncs=0, clock_steps=0,
                             board_resets=0, camera_resets=0, refuted=0)
        self._scan: _Scan | None = None
        self._fit_boot: int | None = None
        self._last_frame: Any = None
        self._camera_shift_ns = 0.0  # camera clock steps since it was opened [ns]
        self._frames: deque = deque()
        self._out: list = []
        self._reset_scan_state()

    # ------------------------------------------------------------------ public API
    def begin_scan(self, boot_id: int, scan_id: int, period_us: float, *,
                   n_rows: int | None = None, first_frame_id: int | None = None,
                   seq_base: int = 0) -> list:
        """Start pairing a new scan (ends the previous one first).

        Parameters
        ----------
        boot_id, scan_id : int
            The board's boot id and the scan's id, as its events will carry them.
        period_us : float
            Trigger period [us].
        n_rows : int, optional
            Triggers in the scan (indices 0..n_rows-1).
        first_frame_id : int, optional
            Frame id the camera will give the scan's first trigger. Default: the id after
            the last frame seen (the first frame of the scan when none was seen).
        seq_base : int
            Added to the trigger index to make ``PairedFrame.seq``.

        Returns
        -------
        list of PairedFrame and Drop
            What ending the previous scan decided.
        """
        if not (math.isfinite(period_us) and period_us > 0):
            raise ValueError(f'period_us: must be a positive period in us, got {period_us}')
        if n_rows is not None and int(n_rows) < 1:
            raise ValueError(f'n_rows: must be >= 1, got {n_rows}')
        out = self.end_scan() if self._scan is not None else []
        if first_frame_id is None and self._last_frame is not None:
            first_frame_id = self._last_frame.frame_id + 1
        elif first_frame_id is not None:
            first_frame_id = self._unwrap(first_frame_id)
        self._scan = _Scan(int(boot_id), int(scan_id), float(period_us),
                           None if n_rows is None else int(n_rows),
                           None if first_frame_id is None else int(first_frame_id),
                           int(seq_base))
        if self._fit_boot != self._scan.boot_id:
            self.fit.clear()  # a new boot restarted the board clock
            self._fit_boot = self._scan.boot_id
        self._reset_scan_state()
        return out

    def end_scan(self) -> list:
        """Decide everything still waiting: the scan's remaining events will not come.

        Returns
        -------
        list of PairedFrame and Drop
        """
        if self._scan is not None:
            self._complete = True
            self._process_frames(force=True)
            self._drop_held('the scan ended before the pairing was confirmed')
            n = self._scan.n_rows if self._scan.n_rows is not None else self._max_index + 1
            self._finalize_events(max(n, self._max_index + 1))
        else:
            while self._frames:
                self._drop_frame('outside_scan', self._frames.popleft(), None, 'no scan')
        self._scan = None
        return self._take()

    def add_event(self, event) -> list:
        """Take one trigger event from the board.

        Parameters
        ----------
        event : galvo_driver.serial_link.protocol.Event
            ``timestamp_us`` on the board clock [us].

        Returns
        -------
        list of PairedFrame and Drop
        """
        self.counters['events_in'] += 1
        scan = self._scan
        if scan is None:
            self._drop('outside_scan', event=event, index=event.index, detail='no scan')
        elif event.boot_id != scan.boot_id:
            self._on_board_reset(event.boot_id)
            self._drop('outside_scan', event=event, index=event.index,
                       detail=f'event of boot {event.boot_id:08x} after a board reset')
        elif event.scan_id != scan.scan_id or event.index < 0 or (
                scan.n_rows is not None and event.index >= scan.n_rows):
            self._drop('outside_scan', event=event, index=event.index,
                       detail=f'event of scan {event.scan_id} index {event.index}')
        else:
            self._store_event(event)
            self._process_frames()
        return self._take()

    def board_reset(self, boot_id: int) -> list:
        """The board announced a new boot (BOOT, STATUS): end the scan's event stream."""
        if self._scan is not None and boot_id != self._scan.boot_id:
            self._on_board_reset(boot_id)
            self._process_frames()
        return self._take()

    def add_frame(self, frame) -> list:
        """Take one camera frame.

        Parameters
        ----------
        frame : galvo_driver.genicam_camera.CameraFrame
            Anything with ``frame_id`` and ``timestamp_ns`` (exposure start, camera clock).

        Returns
        -------
        list of PairedFrame and Drop
        """
        self.counters['frames_in'] += 1
        last = self._last_frame
        frame = _Frame(frame, self._unwrap(frame.frame_id), int(frame.timestamp_ns))
        if last is not None and frame.frame_id == last.frame_id:
            self._drop_frame('duplicate_frame', frame, None,
                             f'frame id {frame.raw.frame_id} again')
            return self._take()
        if last is not None and frame.frame_id < last.frame_id:
            self._on_camera_reset(frame)
        self._last_frame = frame
        if self._camera_lost or self._scan is None:
            why = 'camera restarted during the scan' if self._camera_lost else 'no scan'
            self._drop_frame('camera_reset' if self._camera_lost else 'outside_scan',
                             frame, None, why)
            return self._take()
        self._frames.append(frame)
        self._process_frames()
        return self._take()

    @property
    def pending(self) -> tuple[int, int]:
        """(frames waiting for events, pairs held for confirmation)."""
        return len(self._frames), len(self._held)

    def stats(self) -> dict:
        """Counters plus the clock estimate, for diagnostics.

        Returns
        -------
        dict
            :attr:`counters`, ``drift_ppm`` (camera clock vs board clock [ppm]) and
            ``fit_pairs``.
        """
        out = dict(self.counters)
        out.update(drift_ppm=self.fit.drift_ppm if len(self.fit) else float('nan'),
                   fit_pairs=len(self.fit))
        return out

    # ------------------------------------------------------------------ internals: state
    def _reset_scan_state(self) -> None:
        self._events: dict[int, Any] = {}
        self._conflict: set[int] = set()
        self._paired: set[int] = set()
        self._max_index = -1
        self._complete = False
        self._camera_lost = False
        self._k: int | None = None
        self._last_pair: tuple[Any, int] | None = None
        self._phase_from = 0  # first trigger index on the current board-clock segment
        self._earliest: list[tuple[int, float]] = []  # (index, earliest phase up to it)
        self._suspect = False  # an unexplained timing mismatch since the last pair
        self._suspect_schedule: tuple[float, float] | None = None
        self._unanchored = False  # the scan's anchor was refuted, nothing can re-anchor it
        self._finalized_below = 0
        self._last_emitted = -1
        self._held: list[PairedFrame] = []
        self._probation = 0
        self._snapshot: tuple | None = None
        self._board_shift_us = 0.0  # board clock steps since the scan began [us]

    def _take(self) -> list:
        out, self._out = self._out, []
        return out

    def _drop(self, kind: str, *, frame=None, event=None, index=None, detail='') -> None:
        self.counters[kind] += 1
        self._out.append(Drop(kind, frame, event, index, detail))

    def _drop_frame(self, kind, frame: _Frame, index, detail) -> None:
        event = self._events.get(index) if index is not None else None
        self._drop(kind, frame=frame.raw, event=event, index=index, detail=detail)

    def _unwrap(self, raw_id: int) -> int:
        """Frame id made monotonic across the camera's id wrap (``frame_id_wrap``)."""
        raw_id, last, wrap = int(raw_id), self._last_frame, self.frame_id_wrap
        if wrap is None or last is None:
            return raw_id
        span = wrap - 1  # ids run 1..wrap-1 (GigE Vision block ids skip 0)
        delta = (raw_id - last.raw.frame_id) % span
        return last.frame_id + (delta if delta <= span // 2 else delta - span)

    def _store_event(self, ev) -> None:
        i = ev.index
        if i in self._events or i < self._finalized_below:
            old = self._events.get(i)
            same = old is not None and (old.timestamp_us, tuple(old.codes), old.laser_on,
                                        old.status) == (ev.timestamp_us, tuple(ev.codes),
                                                        ev.laser_on, ev.status)
            if old is not None and not same:
                self._conflict.add(i)
            self._drop('duplicate_event', event=ev, index=i,
                       detail='identical copy' if same else 'copy with other content')
            return
        if i < self._max_index:
            self._drop('late_event', event=ev, index=i, detail='arrived after a later index')
            return
        self._events[i] = ev
        self._max_index = i
        if i >= self._phase_from:
            self._note_phase(i)

    def _on_board_reset(self, boot_id: int) -> None:
        if not self._complete:
            self.counters['board_resets'] += 1
            self._complete = True  # no event of this scan will follow

    def _on_camera_reset(self, frame) -> None:
        self.counters['camera_resets'] += 1
        if self._scan is not None and not self._camera_lost:
            self._process_frames(force=True)
            self._drop_held('the camera restarted before the pairing was confirmed')
            self._camera_lost = True
        self.fit.clear()
        self._fit_boot = None
        self._camera_shift_ns = 0.0

    # ------------------------------------------------------------------ internals: frames
    def _process_frames(self, force: bool = False) -> None:
        while self._frames:
            forced = force or len(self._frames) > self.max_pending_frames
            result = self._try_frame(self._frames[0], forced)
            if result is _WAIT:
                return
            if result is not _RETRY:
                self._frames.popleft()

    def _event_state(self, i: int, force: bool) -> str:
        scan = self._scan
        if i < 0 or (scan.n_rows is not None and i >= scan.n_rows):
            return 'outside'
        if i in self._events:
            return 'present'
        if i <= self._max_index or self._complete or force:
            return 'lost'
        return 'pending'

    def _residual_us(self, frame, i: int) -> float:
        return self.fit.board_us(frame.timestamp_ns) - self._exposure_us(i)

    def _exposure_us(self, i: int) -> float:
        """Board time the exposure of trigger ``i`` starts [us]."""
        return self._events[i].timestamp_us + self.trigger_delay_us

    def _tol(self) -> float:
        """Timing tolerance [us]: ``sigma_factor`` standard deviations of the fit's
        prediction at the newest event (scatter, and the slope's uncertainty over the time
        since the last pair), at least ``min_tolerance_us``, at most ``tolerance`` periods."""
        ceiling = self.tolerance * self._scan.period_us
        if len(self.fit) == 0 or self._max_index not in self._events:
            return ceiling
        sigma = self.fit.sigma_at_us(self._events[self._max_index].timestamp_us)
        return min(ceiling, max(self.min_tolerance_us, self.sigma_factor * sigma))

    def _try_frame(self, frame, force: bool):
        if self._k is None:
            first = self._scan.first_frame_id
            if first is not None and frame.frame_id < first:
                self._drop_frame('outside_scan', frame, None, 'frame before the scan')
                return _DONE
            self._k = frame.frame_id if first is None else first
        i = frame.frame_id - self._k
        if self._unanchored:
            self._drop_frame('timing_mismatch', frame, i, "the scan's anchor was refuted; "
                             'without camera_to_host nothing re-anchors the sequence')
            return _DONE
        state = self._event_state(i, force)
        if state == 'pending':
            return _WAIT
        if state == 'outside':
            self._drop_frame('frame_without_event', frame, None, f'index {i} outside the scan')
            return _DONE
        if state == 'lost':
            self._drop_frame('frame_without_event', frame, i, f'event {i} lost')
            return _DONE
        if i in self._conflict:
            self._drop_frame('ambiguous', frame, i, f'conflicting copies of event {i}')
            return _DONE
        if len(self.fit) == 0:
            return self._anchor(frame, i, force)
        if self.fit.span_us >= 1e6 and abs(self.fit.drift_ppm) > self.max_drift_ppm:
            self._drop_frame('timing_mismatch', frame, i, f'clock drift estimate '
                             f'{self.fit.drift_ppm:.0f} ppm out of range (an exposure delay '
                             'that keeps growing?)')
            return _DONE
        if abs(self._residual_us(frame, i)) <= self._tol():
            if self._suspect and not self._on_schedule(frame, i):
                self._drop_frame('timing_mismatch', frame, i, 'off the trigger schedule '
                                 'since an unexplained mismatch')
                return _DONE
            moved = self._schedule_moved(i, force)
            if moved is _WAIT:
                return _WAIT
            if moved:
                self._set_suspect()
                self._drop_frame('timing_mismatch', frame, i, f'trigger {i} and the next one '
                                 'off the trigger schedule: a board clock step, which missed '
                                 'triggers may hide')
                return _DONE
            result = self._accept(frame, i, force)
            if result is _DONE and self._last_pair is not None and self._last_pair[0] is frame:
                self._suspect = False
            return result
        return self._on_mismatch(frame, i, force)

    def _schedule_moved(self, i: int, force: bool):
        """True when event ``i`` is off the trigger schedule of the last verified pair
        (:meth:`_schedule`) and the next trigger is not back on it: the schedule moved, so
        the board clock stepped. False when ``i`` is on the schedule or only late (or no
        schedule is known); _WAIT for the next event."""
        if self._last_pair is None:
            return False
        schedule = self._schedule(self._last_pair[1])
        if schedule is None:
            return False
        phase, on_time = schedule
        period = self._scan.period_us

        def off(m: int) -> bool:
            return abs(self._events[m].timestamp_us - m * period - phase) > on_time

        if not off(i):
            return False
        state = self._event_state(i + 1, force)
        if state == 'pending':
            return _WAIT
        return state != 'present' or off(i + 1)

    def _on_schedule(self, frame, i: int) -> bool:
        """Both the frame and event ``i`` lie on the trigger schedule of before the last
        unexplained mismatch (:attr:`_suspect_schedule`)."""
        if self._suspect_schedule is None:
            return False
        phase, on_time = self._suspect_schedule
        slot = phase + i * self._scan.period_us
        frame_us = self.fit.board_us(frame.timestamp_ns) - self.trigger_delay_us
        return (abs(self._events[i].timestamp_us - slot) <= on_time
                and abs(frame_us - slot) <= on_time)

    def _neighbour_time(self, i: int, j: int, force: bool):
        """Board time of trigger ``j`` next to present trigger ``i``: float, None when it is
        outside the scan, _WAIT when not yet known, or nan when it cannot be bounded."""
        state = self._event_state(j, force)
        if state == 'outside':
            return None
        if state == 'present':
            return self._exposure_us(j)
        if state == 'pending':
            return _WAIT
        step = j - i
        for m in range(j + step, j + 8 * step, step):  # nearest present beyond the lost one
            st = self._event_state(m, force)
            if st == 'pending':
                return _WAIT
            if st == 'outside':
                return math.nan
            if st == 'present':
                ti, tm = self._exposure_us(i), self._exposure_us(m)
                span = (tm - ti) / (m - i)  # per index
                if abs(span - self._scan.period_us) > self._tol() / abs(m - i):
                    return math.nan
                return ti + span * (j - i)
        return math.nan

    def _separated(self, frame, i: int, force: bool):
        """True when no neighbouring trigger could also have exposed ``frame`` and the
        next trigger came after the exposure ended (else the voltages changed during it);
        _WAIT if that is not known yet."""
        start = self.fit.board_us(frame.timestamp_ns)  # exposure start, board clock [us]
        tol = self._tol()
        for j in (i - 1, i + 1):
            t = self._neighbour_time(i, j, force)
            if t is _WAIT:
                return _WAIT
            if t is None:
                continue
            if math.isnan(t) or abs(start - t) <= 3.0 * tol:
                return False
            if j > i and t - self.trigger_delay_us < start + self.exposure_ns / 1e3 + tol:
                return False
        return True

    def _accept(self, frame, i: int, force: bool, *, anchor: bool = False,
                probation: bool = False):
        """Pair ``frame`` with trigger ``i`` if no neighbour competes (skipped for an
        ``anchor``, which starts a new clock fit); hold it if a hypothesis is on probation."""
        if not anchor:
            sep = self._separated(frame, i, force)
            if sep is _WAIT:
                return _WAIT
            if not sep:
                self._drop_frame('ambiguous', frame, i,
                                 f'a neighbour of trigger {i} is as close in time, or '
                                 'came during the exposure')
                return _DONE
        latency = self._host_latency(frame, i) if anchor else None
        if latency is not None and abs(latency) > self._host_tolerance():
            self._drop_frame('timing_mismatch', frame, i, f'exposure {latency * 1e3:.3f} ms '
                             f'from trigger {i} on the host clock')
            return _DONE
        ev = self._events[i]
        self.fit.add(ev.timestamp_us + round(self.trigger_delay_us), frame.timestamp_ns)
        self._last_pair = (frame, i)
        self._paired.add(i)
        pair = self._make_pair(frame, ev)
        if anchor or probation:
            self._probation = self.lock_pairs
            self._held.append(pair)
        elif self._probation > 0:
            self._held.append(pair)
            self._probation -= 1
            if self._probation == 0:
                self._release_held()
        else:
            self._emit(pair)
        return _DONE

    def _anchor(self, frame, i: int, force: bool):
        """Start a clock fit with ``frame`` and trigger ``i`` (its index by sequence). With
        ``camera_to_host`` the pair must hold on the host clock; if it does not, the one
        later trigger it holds for is taken instead (the camera missed the ones between),
        found among the events received so far."""
        latency = self._host_latency(frame, i)
        if latency is None or abs(latency) <= self._host_tolerance():
            return self._accept(frame, i, force, anchor=True)
        tol = self._host_tolerance()
        found = [j for j in range(i + 1, self._max_index + 1) if j in self._events
                 and abs(self._host_latency(frame, j)) <= tol]
        last_host = self.board_to_host(self._exposure_us(self._max_index))
        if not found and not (force or self._complete) and \
                self.camera_to_host(frame.timestamp_ns) > last_host - tol:
            return _WAIT  # its trigger's event may still be on its way
        if len(found) != 1 or found[0] in self._conflict:
            self._drop_frame('timing_mismatch', frame, i, f'exposure {latency * 1e3:.3f} ms '
                             f'from trigger {i} on the host clock, and no one later '
                             'trigger matches')
            return _DONE
        j = found[0]
        self.counters['resyncs'] += 1
        self._k -= j - i
        return self._accept(frame, j, force, anchor=True)

    def _host_latency(self, frame, i: int) -> float | None:
        """Exposure start minus trigger ``i`` (plus the trigger delay) on the host clock [s],
        from the two coarse host mappings; None without ``camera_to_host``."""
        if self.camera_to_host is None:
            return None
        return (self.camera_to_host(frame.timestamp_ns - self._camera_shift_ns)
                - self.board_to_host(self._exposure_us(i) - self._board_shift_us))

    def _host_tolerance(self) -> float:
        if self.host_tolerance_s is not None:
            return self.host_tolerance_s
        return 0.5 * self._scan.period_us * 1e-6 - self._tol() * 1e-6

    def _make_pair(self, frame, ev) -> PairedFrame:
        mid_us = self.fit.board_us(frame.timestamp_ns + self.exposure_ns / 2)
        start_us = self.fit.board_us(frame.timestamp_ns)
        return PairedFrame(frame.raw, ev, self._scan.seq_base + ev.index, 0,
                           float(self.board_to_host(mid_us - self._board_shift_us)), mid_us,
                           start_us - ev.timestamp_us - self.trigger_delay_us)

    def _emit(self, pair: PairedFrame) -> None:
        i = pair.event.index
        self._finalize_events(i)
        gap = i - self._last_emitted - 1
        self._last_emitted = i
        self._finalized_below = i + 1
        self.counters['paired'] += 1
        self._out.append(PairedFrame(pair.frame, pair.event, pair.seq, gap, pair.stamp,
                                     pair.board_mid_us, pair.residual_us))

    def _release_held(self) -> None:
        held, self._held = self._held, []
        self._snapshot = None
        for pair in held:
            self._emit(pair)

    def _drop_held(self, why: str) -> None:
        held, self._held = self._held, []
        self._probation = 0
        for pair in held:
            self._paired.discard(pair.event.index)
            self.counters['refuted'] += 1
            self._drop('ambiguous', frame=pair.frame, event=pair.event,
                       index=pair.event.index, detail=why)

    def _finalize_events(self, below: int) -> None:
        for i in range(self._finalized_below, below):
            if i in self._paired:
                continue
            if i in self._events:
                self._drop('event_without_frame', event=self._events[i], index=i,
                           detail=f'no frame paired with trigger {i}')
            else:
                self._drop('event_lost', index=i, detail=f'event {i} never arrived')
        self._finalized_below = max(self._finalized_below, below)
        for old in [j for j in self._events if j < self._finalized_below - _KEEP_EVENTS]:
            del self._events[old]
            self._paired.discard(old)

    # ------------------------------------------------------------------ internals: changes
    def _save(self) -> tuple:
        """The pairing hypothesis, for :meth:`_restore`."""
        return (self._k, self.fit.state(), self._last_pair, self._phase_from,
                list(self._earliest), self._board_shift_us, self._camera_shift_ns)

    def _restore(self, state: tuple) -> None:
        (self._k, fit_state, self._last_pair, self._phase_from, self._earliest,
         self._board_shift_us, self._camera_shift_ns) = state
        self.fit.restore(fit_state)

    def _on_mismatch(self, frame, i: int, force: bool):
        if self._probation > 0:
            # the frame contradicts the hypothesis on probation: refute it, go back
            self._drop_held(f'frame {frame.raw.frame_id} contradicted the pairing on '
                            'probation')
            if self._snapshot is not None:
                # The old hypothesis was contradicted too (by the frame that proposed the
                # refuted change): two faults at once, which may cancel out on it (a board
                # clock step of n periods, then n missed triggers). Restored, it is suspect.
                self._restore(self._snapshot)
                self._snapshot = None
                self._set_suspect()
            else:
                self.fit.clear()
                self._last_pair = None
                # the scan's anchor, refuted: re-anchoring by sequence would trust the very
                # sequence just contradicted (a trigger the camera missed meanwhile)
                self._unanchored = self.camera_to_host is None
            return _RETRY
        change = self._classify(frame, i, force)
        if change is _WAIT:
            return _WAIT
        if change is None:
            # Something changed that no single fault explains (two at once, or a timing
            # outlier): until a pair is seen on the old trigger schedule again, agreeing
            # sequence and timing are not enough (a missed trigger and a board clock step
            # of the same number of periods cancel out).
            self._set_suspect()
            self._drop_frame('timing_mismatch', frame, i,
                             f'{self._residual_us(frame, i):.0f} us off trigger {i}')
            return _DONE
        kind, n = change
        state = self._save()
        if kind == 'camera_skip':
            j = i + n
            if self._event_state(j, force) != 'present' or j in self._conflict:
                self._drop_frame('ambiguous', frame, i, f'missed trigger(s), event {j} unknown')
                return _DONE
            self._k -= n
            result = self._accept(frame, j, force, probation=True)
        else:
            residual = self._residual_us(frame, i)  # on the old fit
            if kind == 'board_step':  # the board clock moved by -residual
                self._board_shift_us -= residual
                self._phase_from = i
                self._earliest = []
                for m in sorted(j for j in self._events if j >= i):
                    self._note_phase(m)
            else:  # the camera clock moved by +residual
                self._camera_shift_ns += residual * self.fit.slope
            self.fit.clear()
            result = self._accept(frame, i, force, anchor=True)
        if result is _DONE and self._last_pair is not None and self._last_pair[0] is frame:
            self.counters['resyncs' if kind == 'camera_skip' else 'clock_steps'] += 1
            self._snapshot = state
            self._suspect = False
        else:  # not taken (ambiguous, or not on the host clock), or not decidable yet
            self._restore(state)
        return result

    def _set_suspect(self) -> None:
        """Agreeing sequence and timing no longer suffice to pair (:meth:`_on_schedule`),
        against the trigger schedule of the last verified pair, until a pair is seen on it."""
        if not self._suspect:
            self._suspect = True
            self._suspect_schedule = self._schedule(self._last_pair[1]) \
                if self._last_pair is not None else None

    def _note_phase(self, m: int) -> None:
        """Extend the earliest phase of the board-clock segment with present event ``m``."""
        phase = self._events[m].timestamp_us - m * self._scan.period_us
        if self._earliest:
            phase = min(phase, self._earliest[-1][1])
        self._earliest.append((m, phase))

    def _schedule(self, before: int) -> tuple[float, float] | None:
        """The trigger schedule on the board clock before a change: its phase [us] (``t(m) -
        m * period`` of an on-time trigger) and how far from it a trigger still counts as on
        time [us]. None with fewer than 3 present events among the 32 indices up to
        ``before`` (from the last board clock step on).

        A trigger is never early on its own board's clock (the period counts the same
        crystal as the timestamps) but may be late, by any amount: a host that stalls fires
        the triggers it owes in a burst, and a burst can fill the whole 32-trigger window.
        The phase is therefore the earliest of every trigger of the segment up to
        ``before`` (from the last board clock step on), not a quantile of recent ones (a
        phase taken from late triggers would put on-time triggers whole periods off it,
        and a missed trigger would then pass for a board clock step). The trigger jitter
        (the upper quartile of the lateness of the window's triggers within a quarter
        period of the phase) widens the timing tolerance, up to a quarter period (a clock
        step of whole periods must never count as on time).
        """
        period = self._scan.period_us
        k = bisect.bisect_right(self._earliest, before, key=lambda e: e[0])
        first = max(before - _PHASE_WINDOW + 1, self._phase_from)
        present = [m for m in range(first, before + 1) if m in self._events]
        if k == 0 or len(present) < 3:
            return None
        phase = self._earliest[k - 1][1]
        late = [x for x in (self._events[m].timestamp_us - m * period - phase
                            for m in present) if x <= 0.25 * period]
        jitter = float(np.percentile(late, 75)) if late else 0.0
        return phase, min(self._tol() + jitter, 0.25 * period)

    def _classify(self, frame, i: int, force: bool):
        """What changed between the last verified pair and ``frame`` (index ``i`` by
        sequence): ('camera_skip', n), ('board_step', 0), ('camera_step', 0), None when
        nothing explains it, or _WAIT for events still to come.

        Shifts are measured against the trigger schedule before the change (its phase,
        :meth:`_schedule`): ``ev_shift`` of event ``i``, ``fr_shift`` of the frame; "on the
        schedule" is within the timing tolerance plus the trigger jitter.

        * The frame matches exactly one later trigger ``j = i + n`` in time (clock fit
          unchanged; all the events received up to the frame's time are searched) and ``j``
          is on the schedule: the camera missed ``n`` triggers. (A board
          clock step of whole periods also makes a later trigger match, but moves it off
          the schedule.)
        * The frame is on the schedule at ``i`` and event ``i`` is not: the board clock
          stepped (whether or not a stepped trigger happens to match the frame).
        * Event ``i`` is on the schedule, no trigger matches the frame, and the frame is
          early: the camera clock stepped back (a timestamp reset). A frame that comes late
          is never explained as a camera clock step: its exposure may really have started
          late, under the next trigger's voltages (a camera that delays its exposures), or
          it may be of a missed trigger whose event is lost.
        """
        if self._last_pair is None:
            return None
        schedule = self._schedule(self._last_pair[1])
        if schedule is None:
            return None
        phase, on_time = schedule
        tol, period = self._tol(), self._scan.period_us
        frame_us = self.fit.board_us(frame.timestamp_ns) - self.trigger_delay_us
        newest = self._events.get(self._max_index)
        last_row = self._scan.n_rows is not None and self._max_index >= self._scan.n_rows - 1
        if not (force or self._complete or last_row) and (
                newest is None or newest.timestamp_us < frame_us + tol):
            return _WAIT  # the trigger this frame may be of has not been reported yet
        matches = []
        for j in range(i + 1, self._max_index + 1):
            if j not in self._events:
                continue
            if self._events[j].timestamp_us > frame_us + tol + 10 * period:
                break
            if abs(self._residual_us(frame, j)) <= tol:
                matches.append(j)
        if len(matches) > 1:
            return None
        if matches and abs(self._events[matches[0]].timestamp_us - matches[0] * period
                           - phase) <= on_time:
            return 'camera_skip', matches[0] - i
        ev_shift = self._events[i].timestamp_us - i * period - phase
        fr_shift = (self.fit.board_us(frame.timestamp_ns) - self.trigger_delay_us
                    - i * period - phase)
        if abs(fr_shift) <= on_time < abs(ev_shift):
            return 'board_step', 0
        if abs(ev_shift) <= on_time and fr_shift < -on_time:
            return 'camera_step', 0
        return None
