"""Frames paired with the galvo board's trigger events, with drops injected on both sides.

The firmware emulator scans ``--frames`` rows at ``--fps``; the real serial host
(:class:`~galvo_driver.serial_link.backend.SerialBackend`) uploads the scan and reads the
trigger EVENTs over a pty, and :class:`~galvo_driver.trigger_pairing.TriggerPairer` pairs
frames with events as they arrive.

Cameras (``--camera``):

* ``fake`` (default): :class:`galvo_driver.fake_camera.FakeCamera` (Aravis' GigE Vision
  fake camera on loopback, real GVCP/GVSP; ``--width`` x ``--height`` Mono8) hardware-
  triggered on ``Line0``: the emulator's trigger hook is the wire, it sends each edge with
  the trigger's own instant (``pulse_line(edge_at(t))``). The camera is driven by the
  driver's own :class:`~galvo_driver.rig_backend.RigBackend` (``camera_clock='host'``,
  TriggerMode On, TriggerSource Line0), whose pairer's results are tapped for the checks.
* ``synthetic``: frames with ids and timestamps on a simulated camera clock with its own
  offset and rate (``--camera-drift-ppm``), a latency and a jitter; no pixels; paired by a
  TriggerPairer fed directly.

Injected faults, at seeded random trigger indices: lost EVENTs (the emulator loses a byte
of the EVENT frame), duplicated EVENTs, camera frames lost in transfer (the camera exposed,
its frame id advanced, the frame never reaches the pairer), missed camera triggers (no
edge reaches the camera: no exposure, no frame id), and the board clock drifting by
``--drift-ppm``.

The truth: every frame is traced to the trigger instant that exposed it (the synthetic
camera records it; the fake camera writes the instant of the line edge into the image's
first bytes, ``edge_of``, and the hook recorded which trigger sent that edge), and that
trigger's codes come from the emulator's own record (:meth:`FirmwareEmulator.triggers`),
never from an EVENT. With the fake camera, every frame the backend delivers is checked
(seq, voltages, laser), as test_rig_backend.py does.

    .venv/bin/python benchmarks/camera_trigger.py [--frames 10000] [--fps 500]
        [--camera fake|synthetic] [--seed 1]

Last line: one JSON object with frames, fps, mistagged, unaccounted, injected_drops,
injected_drops_detected, clock_offset_error_us_p99, the drift estimated and true, the
pairer's counters and (fake camera) why each trigger without a frame has none.
"""

from __future__ import annotations

import argparse
import gc
import heapq
import json
import math
import queue
import random
import sys
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np

from galvo_driver.fake_camera import edge_at, edge_of
from galvo_driver.rig_backend import RigBackend
from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link.backend import SerialBackend
from galvo_driver.serial_link.emulator import FirmwareEmulator
from galvo_driver.trigger_pairing import PairedFrame, TriggerPairer

#: Drop kinds that account for a trigger index without a pair.
EVENT_SIDE = ('event_lost', 'event_without_frame')


class TappedBackend(SerialBackend):
    """The real serial host, with every EVENT and BOOT it decodes copied to a queue through
    its public listener hook (:meth:`SerialBackend.add_listener`)."""

    def __init__(self, port: str, **kw):
        super().__init__(port, **kw)
        self.tap: queue.Queue = queue.Queue()
        self.add_listener(lambda msg: self.tap.put(msg)
                          if isinstance(msg, (p.Event, p.Boot)) else None)


@dataclass(frozen=True)
class SimFrame:
    """A synthetic camera frame (the fields of GenICamCamera's CameraFrame it needs), with
    its truth, which the pairer never reads: the instant of the trigger that exposed it
    (emulator ``time.monotonic()`` [s]) and the board clock at the exposure start [us]."""

    frame_id: int
    timestamp_ns: int
    trigger_t: float = field(default=math.nan, compare=False)
    exposure_board_us: float = field(default=math.nan, compare=False)
    image: None = None
    bit_depth: int = 8


@dataclass
class SyntheticCamera:
    """A triggered camera on its own clock: ``ns = offset_ns + t * 1e9 * (1 + drift)``.

    ``trigger(index, t)`` is the emulator's hook. A trigger index in ``miss`` is not seen
    (no exposure, the frame id does not advance); one in ``lose`` is exposed but the frame is
    lost in transfer (the id advances, nothing is delivered). Delivered frames become
    available after a random 0..``max_delay_s`` transfer delay.
    """

    emulator: FirmwareEmulator | None = None
    seed: int = 0
    offset_ns: int = 1_700_000_000_000_000_000
    drift_ppm: float = 0.0
    latency_us: float = 30.0
    jitter_us: float = 20.0
    max_delay_s: float = 0.003
    first_frame_id: int = 1
    miss: set = field(default_factory=set)
    lose: set = field(default_factory=set)

    def __post_init__(self):
        self._rng = random.Random(self.seed)
        self.next_id = self.first_frame_id
        self.missed: list[float] = []
        self.delivered: list[int] = []
        self.lost: list[float] = []
        self._heap: list = []
        self._release = 0.0
        self._sent = 0
        self._real_minus_mono = time.time() - time.monotonic()
        self._lock = threading.Lock()

    def camera_ns(self, t: float) -> int:
        return self.offset_ns + round(t * 1e9 * (1 + self.drift_ppm * 1e-6))

    def trigger(self, index: int, t: float) -> None:
        if index in self.miss:
            self.missed.append(t)
            return
        fid, self.next_id = self.next_id, self.next_id + 1
        t_exp = t + (self.latency_us + self._rng.uniform(0, self.jitter_us)) * 1e-6
        board_us = self.emulator.board_clock_us(t_exp) if self.emulator else float('nan')
        if index in self.lose:
            self.lost.append(t)
            return
        frame = SimFrame(fid, self.camera_ns(t_exp), t, board_us)
        self.delivered.append(fid)
        with self._lock:  # a camera delivers in order: never before the previous frame
            self._release = max(self._release,
                                time.monotonic() + self._rng.uniform(0, self.max_delay_s))
            self._sent += 1  # ties in release time keep the sending order
            heapq.heappush(self._heap, (self._release, self._sent, frame))

    def to_host(self, ns: int) -> float:
        """The coarse camera-to-host mapping a timestamp latch would give (time.time())."""
        mono = (ns - self.offset_ns) / (1e9 * (1 + self.drift_ppm * 1e-6))
        return mono + self._real_minus_mono

    def restart(self, clock_jump_ns: int = 10**12) -> None:
        """Unplugged and plugged in again: frame ids start over, the clock jumps."""
        with self._lock:
            self.next_id = self.first_frame_id
            self.offset_ns += int(clock_jump_ns)

    def poll(self) -> list[SimFrame]:
        """Frames whose transfer delay has passed, in the order the camera sent them (not
        sorted by frame id: after :meth:`restart` the ids start over)."""
        now, out = time.monotonic(), []
        with self._lock:
            while self._heap and self._heap[0][0] <= now:
                out.append(heapq.heappop(self._heap)[2])
        return out

    def pending(self) -> int:
        with self._lock:
            return len(self._heap)


@dataclass
class Faults:
    """Trigger indices of the injected faults (disjoint sets)."""

    lost_events: set = field(default_factory=set)
    dup_events: set = field(default_factory=set)
    lost_frames: set = field(default_factory=set)
    missed_triggers: set = field(default_factory=set)

    @classmethod
    def random(cls, n: int, rate: float, seed: int) -> Faults:
        """Each kind at about ``rate`` of the triggers, spaced >= 8 triggers apart."""
        rng = random.Random(seed)
        kinds = ('lost_events', 'dup_events', 'lost_frames', 'missed_triggers')
        out, used = cls(), set()
        for kind in kinds:
            for _ in range(max(1, round(rate * n))):
                for _attempt in range(100):
                    i = rng.randrange(8, n - 8)
                    if all(abs(i - j) >= 8 for j in used):
                        used.add(i)
                        getattr(out, kind).add(i)
                        break
        return out

    def arm(self, emulator: FirmwareEmulator) -> None:
        """Schedule the lost EVENTs on the emulator (call before the scan starts; the
        duplicates are armed from the trigger hook, :meth:`on_trigger`).

        drop_bytes(skip=s) counts EVENT frames: each duplicate is one more frame, and a
        fault queued behind another one does not count the frame that one consumed.
        """
        msg_no = {}
        extra = 0
        for i in range(max(self.lost_events | self.dup_events, default=0) + 1):
            msg_no[i] = i + extra
            extra += i in self.dup_events
        for k, i in enumerate(sorted(self.lost_events)):
            emulator.drop_bytes(1, 'event', skip=msg_no[i] - k)

    def on_trigger(self, emulator: FirmwareEmulator, index: int) -> None:
        """Arm the duplicate of the EVENT about to be sent (called from the hook)."""
        if index in self.dup_events:
            emulator.duplicate_events(1, skip=0)


@dataclass
class Outcome:
    """Everything the pairer said, and the checks against the truth."""

    pairs: list = field(default_factory=list)
    drops: list = field(default_factory=list)

    def add(self, results) -> None:
        for r in results:
            (self.pairs if isinstance(r, PairedFrame) else self.drops).append(r)


def feed(pairer: TriggerPairer, backend: TappedBackend, camera, out: Outcome) -> int:
    """Give the pairer what has arrived on both sides; return how many items."""
    n = 0
    while True:
        try:
            msg = backend.tap.get_nowait()
        except queue.Empty:
            break
        n += 1
        if isinstance(msg, p.Event):
            out.add(pairer.add_event(msg))
        else:
            out.add(pairer.board_reset(msg.info.boot_id))
    for frame in camera.poll():
        n += 1
        out.add(pairer.add_frame(frame))
    return n


def run_scan(emulator: FirmwareEmulator, backend: TappedBackend, camera, pairer: TriggerPairer,
             codes: np.ndarray, fps: float, *, during=None, timeout: float = 60.0,
             first_frame_id: int | None = None) -> Outcome:
    """Run one scan of ``codes`` rows at ``fps`` and pair everything until it is over.

    ``during(emulator, camera)`` is called once the scan is running (mid-scan faults).
    """
    out = Outcome()
    volts = p.codes_to_volts(codes)
    n = backend.start(volts, fps, laser_on=True)
    st = emulator.snapshot()
    pairer.begin_scan(st['boot_id'], st['scan_id'], round(1e6 / fps), n_rows=n,
                      first_frame_id=first_frame_id)
    if during is not None:
        during(emulator, camera)
    deadline = time.monotonic() + timeout
    quiet_since = None
    while time.monotonic() < deadline:
        if feed(pairer, backend, camera, out):
            quiet_since = None
        elif not backend.running and camera.pending() == 0:
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 0.05:
                break
        time.sleep(0.0005)
    out.add(pairer.end_scan())
    return out


def check(outcome: Outcome, emulator: FirmwareEmulator, truth_of, n_rows: int,
          frames_in: int) -> dict:
    """Compare every pair with the emulator's record of the trigger that exposed it.

    ``truth_of(frame) -> trigger t or None`` (the trigger instant that exposed the frame).
    """
    records = {r.t: r for r in emulator.triggers()}
    mistagged = unknown = 0
    for pair in outcome.pairs:
        t = truth_of(pair.frame)
        rec = records.get(t) if t is not None else None
        if rec is None:
            unknown += 1
            continue
        ev = pair.event
        if ((rec.boot_id, rec.scan_id, rec.index) != (ev.boot_id, ev.scan_id, ev.index)
                or rec.codes != tuple(ev.codes) or rec.laser_on != ev.laser_on):
            mistagged += 1
    frame_drops = sum(d.frame is not None for d in outcome.drops)
    indices = {pair.index for pair in outcome.pairs}
    indices |= {d.index for d in outcome.drops if d.kind in EVENT_SIDE}
    return {'mistagged': mistagged, 'truth_unknown': unknown,
            'unaccounted_frames': frames_in - len(outcome.pairs) - frame_drops,
            'unaccounted_triggers': len(set(range(n_rows)) - indices)}


def detected(outcome: Outcome, indices) -> int:
    """Injected drops at these trigger indices that the pairer reported (not paired, and
    named in an event-side drop)."""
    paired = {pair.index for pair in outcome.pairs}
    named = {d.index for d in outcome.drops if d.kind in EVENT_SIDE}
    return sum(1 for i in indices if i in named and i not in paired)


def offset_errors_us(outcome: Outcome, exposure_s: float, truth_board_us) -> np.ndarray:
    """Estimated minus true board time of each paired frame's exposure start [us]."""
    errs = []
    for pair in outcome.pairs:
        truth = truth_board_us(pair.frame)
        if truth is not None and np.isfinite(truth):
            errs.append(pair.board_mid_us - exposure_s * 0.5e6 - truth)
    return np.asarray(errs)


@dataclass
class RigRun:
    """One scan of the emulator + camera + pairer, and what came out of it."""

    outcome: Outcome
    pairer: TriggerPairer
    emulator: FirmwareEmulator
    camera: SyntheticCamera
    faults: Faults
    backend_stats: dict
    wall_s: float
    n_rows: int

    def check(self) -> dict:
        """:func:`check` against the emulator's trigger records."""
        return check(self.outcome, self.emulator, lambda f: f.trigger_t, self.n_rows,
                     self.pairer.counters['frames_in'])


def run_rig(n: int, fps: float, *, faults: Faults | None = None, seed: int = 0,
            drift_ppm: float = 0.0, camera_kw: dict | None = None, exposure: float = 0.001,
            during=None, host_check: bool = True, watchdog: float = 0.15) -> RigRun:
    """Scan ``n`` random rows at ``fps`` on the emulator with a synthetic camera, pairing
    frames and events with a :class:`TriggerPairer`; ``during(emulator, camera)`` runs once
    the scan has started (mid-scan faults). ``watchdog`` is the board's heartbeat timeout
    [s] (the firmware's 0.15 s by default)."""
    faults = faults or Faults()
    rng = np.random.default_rng(seed)
    codes = rng.integers(1, 65536, (n, 4)).astype(np.uint16)
    camera = SyntheticCamera(seed=seed, miss=faults.missed_triggers, lose=faults.lost_frames,
                             **(camera_kw or {}))

    def hook(index, t):
        faults.on_trigger(emu, index)
        camera.trigger(index, t)

    emu = FirmwareEmulator('pty', seed=seed, on_trigger=hook, clock_drift_ppm=drift_ppm,
                           watchdog=watchdog)
    camera.emulator = emu
    with emu:
        backend = TappedBackend(emu.port, exposure=exposure)
        backend.open()
        try:
            pairer = TriggerPairer(exposure_s=exposure, trigger_delay_us=camera.latency_us,
                                   board_to_host=backend.board_to_host,
                                   camera_to_host=camera.to_host if host_check else None)
            faults.arm(emu)
            t0 = time.monotonic()
            outcome = run_scan(emu, backend, camera, pairer, codes, fps, during=during,
                               timeout=n / fps * 3 + 10, first_frame_id=camera.first_frame_id)
            wall = time.monotonic() - t0
            stats = backend.stats
        finally:
            backend.close()
    return RigRun(outcome, pairer, emu, camera, faults, stats, wall, n)


def run_synthetic(args) -> dict:
    n = args.frames
    faults = Faults.random(n, args.drop_rate, args.seed)
    run = run_rig(n, args.fps, faults=faults, seed=args.seed, drift_ppm=args.drift_ppm,
                  camera_kw={'drift_ppm': args.camera_drift_ppm}, exposure=args.exposure)
    errs = offset_errors_us(run.outcome, args.exposure, lambda f: f.exposure_board_us)
    injected = faults.lost_events | faults.lost_frames | faults.missed_triggers
    return summary(args, n, run.wall_s, len(run.emulator.triggers()), run.outcome,
                   run.check(), errs, injected, run.pairer, run.emulator, run.backend_stats,
                   camera_ppm=args.camera_drift_ppm)


def summary(args, n, wall, n_triggers, outcome, res, errs, injected, pairer, emu,
            backend_stats, camera_ppm: float) -> dict:
    """The figures of a run; ``camera_ppm``: the camera clock's true rate error against the
    emulator's ``time.monotonic()`` [ppm] (the drift the pairer's fit should find is that of
    the camera clock against the board clock)."""
    abs_err = np.abs(errs)
    drift_true = ((1 + camera_ppm * 1e-6) / (1 + args.drift_ppm * 1e-6) - 1) * 1e6
    times = [r.t for r in emu.triggers()]
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
    return {
        'camera': args.camera, 'frames': n, 'triggers': n_triggers,
        'fps': round(rate, 1), 'fps_set': args.fps, 'wall_s': round(wall, 2),
        'paired': len(outcome.pairs), 'mistagged': res['mistagged'],
        'truth_unknown': res['truth_unknown'],
        'unaccounted': res['unaccounted_frames'] + res['unaccounted_triggers'],
        'injected_drops': len(injected),
        'injected_drops_detected': detected(outcome, injected),
        'clock_offset_error_us_p99': round(float(np.percentile(abs_err, 99)), 2)
        if len(abs_err) else None,
        'clock_offset_error_us_max': round(float(abs_err.max()), 2) if len(abs_err) else None,
        'drift_ppm_set': args.drift_ppm,
        'drift_ppm_true': round(drift_true, 2),  # camera clock vs board clock
        'drift_ppm_estimated': round(pairer.fit.drift_ppm, 2),
        'late_triggers': emu.stats['late_triggers'],
        'backend_lost_events': backend_stats['lost_events'],
        'pairer': {k: v for k, v in pairer.counters.items() if v},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=10_000)
    parser.add_argument('--fps', type=float, default=500.0)
    parser.add_argument('--camera', choices=('fake', 'synthetic'), default='fake')
    parser.add_argument('--drop-rate', type=float, default=0.002,
                        help='fraction of triggers per injected fault kind')
    parser.add_argument('--drift-ppm', type=float, default=200.0,
                        help='board clock rate error [ppm]')
    parser.add_argument('--camera-drift-ppm', type=float, default=-50.0,
                        help='synthetic camera clock rate error [ppm]')
    parser.add_argument('--exposure', type=float, default=0.0005, help='exposure [s]')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--width', type=int, default=128, help='fake camera ROI width [px]')
    parser.add_argument('--height', type=int, default=64, help='fake camera ROI height [px]')
    args = parser.parse_args(argv)
    if args.camera == 'fake':
        result = run_fake(args)
    else:
        result = run_synthetic(args)
    print(json.dumps(result))
    return 0


@dataclass(frozen=True)
class FakeFrame:
    """A fake-camera frame as the checks keep it: without its pixels (the pairer's results
    for 10,000 images need not stay in memory), with its truth from the line edge that
    exposed it (the instant the image carries, ``edge_of``): that trigger's emulator
    instant and index, and the board clock at it [us] (the exposure start: the fake camera
    latches the edge instant, no trigger delay)."""

    frame_id: int
    timestamp_ns: int
    trigger_t: float | None
    index: int | None
    exposure_board_us: float


class LineWire:
    """The board's trigger output wired to the fake camera's ``Line0``: the emulator's hook.

    At each trigger it arms the injected duplicate EVENT, then sends the line edge with the
    trigger's own instant (``edge_at(t)``: the hook may run late, a wire does not), except
    for the injected missed camera triggers. It records which trigger each edge came from:
    the truth of every frame, read back from the instant the image carries.
    """

    def __init__(self, fake, faults: Faults):
        self.fake, self.faults = fake, faults
        self.emulator: FirmwareEmulator | None = None
        self.edges: dict[int, tuple[float, int]] = {}  # edge [ns] -> (trigger t [s], index)

    def hook(self, index: int, t: float) -> None:
        self.faults.on_trigger(self.emulator, index)
        if index in self.faults.missed_triggers:
            return  # the camera does not see this edge: no exposure, no frame id
        edge = edge_at(t)
        self.edges[edge] = (t, index)
        self.fake.pulse_line(edge)

    def truth(self, image) -> tuple[float | None, int | None]:
        """(trigger t, index) of the edge that exposed ``image``; (None, None) if unknown."""
        return self.edges.get(edge_of(image), (None, None))


class BenchRig(RigBackend):
    """The driver's ``rig`` backend, unchanged, with two taps for the benchmark.

    * Every result of its pairer (:meth:`RigBackend._take`) is copied, pixels left out,
      into :attr:`outcome`: the pairs and drops the checks need, with their indices.
    * Its camera's ``grab`` discards the frames exposed by the injected "lost in transfer"
      triggers (the camera exposed them and its frame id advanced; the host never gets
      them), as test_rig_backend.py does, and records which trigger each grabbed frame
      came from.
    """

    def __init__(self, port: str, wire: LineWire, **kw):
        super().__init__(port, **kw)
        self.wire = wire
        self.outcome = Outcome()
        self.grabbed: set[int] = set()  # trigger indices of the frames the host received
        self.lost_in_transfer: list[int] = []
        self.not_from_an_edge = 0
        self.frame_ids: list[int] = []  # of every frame the host received
        grab = self.camera.grab

        def lossy_grab(timeout_s):
            frame = grab(timeout_s)
            if frame is None:
                return None
            self.frame_ids.append(frame.frame_id)
            _, index = wire.truth(frame.image)
            if index is None:
                self.not_from_an_edge += 1
                return frame
            self.grabbed.add(index)
            if index in wire.faults.lost_frames:
                self.lost_in_transfer.append(index)
                return None
            return frame

        self.camera.grab = lossy_grab

    def _light(self, frame) -> FakeFrame:
        t, index = self.wire.truth(frame.image)
        board_us = self.wire.emulator.board_clock_us(t) if t is not None else math.nan
        return FakeFrame(frame.frame_id, frame.timestamp_ns, t, index, board_us)

    def _take(self, results) -> None:
        results = list(results)
        self.outcome.add(replace(r, frame=self._light(r.frame)) if r.frame is not None else r
                         for r in results)
        super()._take(results)


def run_fake(args) -> dict:
    """Scan ``--frames`` rows on the emulator through :class:`RigBackend` with the fake
    camera hardware-triggered on ``Line0``; check every frame it delivers against the
    emulator's record of the trigger whose edge exposed it."""
    n = args.frames
    faults = Faults.random(n, args.drop_rate, args.seed)
    codes = np.random.default_rng(args.seed).integers(1, 65536, (n, 4)).astype(np.uint16)
    # The emulator runs in this process, a board does not: a full garbage collection of
    # the heap holds the GIL and would stall its triggers (see test_rig_backend.fake).
    gc.collect()
    gc.freeze()
    try:
        return _run_fake(args, n, faults, codes)
    finally:
        gc.unfreeze()


def _run_fake(args, n: int, faults: Faults, codes: np.ndarray) -> dict:
    from galvo_driver.fake_camera import FakeCamera

    exposure_us = args.exposure * 1e6
    with FakeCamera('GSBENCH', width=args.width, height=args.height,
                    wake_on_edge=True) as fake:
        wire = LineWire(fake, faults)
        emu = FirmwareEmulator('pty', seed=args.seed, on_trigger=wire.hook,
                               clock_drift_ppm=args.drift_ppm)
        wire.emulator = emu
        with emu:
            backend = BenchRig(emu.port, wire, camera_serial=fake.serial, camera_clock='host',
                               features={'PixelFormat': 'Mono8', 'ExposureTime': exposure_us})
            backend.open()
            try:
                backend.arm()
                faults.arm(emu)
                delivered = DeliveredCheck(emu, wire, args.exposure)
                t0 = time.monotonic()
                backend.start(p.codes_to_volts(codes), args.fps, laser_on=True)
                deadline = t0 + n / args.fps * 3 + 10
                while backend.running and time.monotonic() < deadline:
                    delivered.add(backend.poll(0.02))
                delivered.add(backend.poll(0.0))
                wall = time.monotonic() - t0
                timed_out = backend.running
                stats = backend.stats
                fault = backend.fault
            finally:
                backend.close()
    delivered.finish()
    outcome, pairer = backend.outcome, backend.pairer
    res = check(outcome, emu, lambda f: f.trigger_t, n, pairer.counters['frames_in'])
    errs = offset_errors_us(outcome, args.exposure, lambda f: f.exposure_board_us)
    injected = faults.lost_events | faults.lost_frames | faults.missed_triggers
    # The camera stamps CLOCK_REALTIME, the emulator's board clock counts CLOCK_MONOTONIC
    # (times 1 + drift): NTP slews both alike, so the camera clock's own rate error is 0.
    out = summary(args, n, wall, len(emu.triggers()), outcome, res, errs, injected, pairer,
                  emu, stats['board'], camera_ppm=0.0)
    # what the driver outputs: each delivered frame against the truth of its edge
    out['delivered'] = delivered.n
    out['delivered_mistagged'] = delivered.mistagged
    out['delivered_truth_unknown'] = delivered.unknown
    # the same frames, tagged by the pairer and as the backend delivers them
    out['mistagged'] = max(out['mistagged'], delivered.mistagged)
    abs_stamp = np.abs(np.asarray(delivered.stamp_err_us))
    out['stamp_error_us_p99'] = (round(float(np.percentile(abs_stamp, 99)), 2)
                                 if len(abs_stamp) else None)
    out['triggers_without_frame'] = causes(outcome, faults, backend)
    out['injected'] = {'lost_events': len(faults.lost_events),
                       'duplicated_events': len(faults.dup_events),
                       'lost_in_transfer': len(faults.lost_frames),
                       'missed_triggers': len(faults.missed_triggers)}
    # frames of an injected "lost in transfer" trigger the camera did send (a camera that
    # missed that edge made none to lose)
    out['lost_in_transfer_discarded'] = len(backend.lost_in_transfer)
    out['camera_frames_received'] = len(backend.frame_ids)
    # frames the camera made (its ids, which skip 0 and wrap after 65535) that never
    # reached the host: lost packets or no free buffer (camera_statistics says which)
    ids = backend.frame_ids
    out['camera_frame_id_gaps'] = sum((b - a) % 65535 - 1
                                        for a, b in zip(ids, ids[1:], strict=False))
    out['camera_frames_not_from_an_edge'] = backend.not_from_an_edge
    out['camera_statistics'] = stats['camera']
    out['mismatched_codes'] = stats['mismatched_codes']
    out['backend_fault'] = fault
    out['timed_out'] = timed_out
    out['hook_errors'] = emu.stats['hook_errors']
    out['hook_error'] = emu.hook_error
    out['watchdog_trips'] = len(emu.watchdog_trips)
    return out


class DeliveredCheck:
    """The frames :meth:`RigBackend.poll` delivers, each compared with the emulator's record
    of the trigger whose edge exposed its image (seq, voltages, laser), as
    test_rig_backend.py's ``Rig.check`` does. During the scan only what the check needs is
    kept (not the pixels); :meth:`finish` checks after it."""

    def __init__(self, emu: FirmwareEmulator, wire: LineWire, exposure_s: float):
        self.emu, self.wire, self.exposure_s = emu, wire, exposure_s
        self._kept: list = []
        self.n = self.mistagged = self.unknown = 0
        self.stamp_err_us: list[float] = []

    def add(self, frames) -> None:
        for f in frames:
            edge = edge_of(f.image)
            self._kept.append((edge, self.wire.edges.get(edge, (None, None))[0], f.seq,
                               f.voltages, f.laser_on, f.stamp))

    def finish(self) -> None:
        records = {r.t: r for r in self.emu.triggers()}
        for edge, t, seq, volts, laser_on, stamp in self._kept:
            self.n += 1
            rec = records.get(t)
            if rec is None:
                self.unknown += 1
                continue
            if (seq != rec.index or laser_on != rec.laser_on
                    or not np.array_equal(volts, p.codes_to_volts(np.array(rec.codes)))):
                self.mistagged += 1
            # the stamp is the middle of the exposure in host time: edge + exposure / 2
            self.stamp_err_us.append((stamp - (edge * 1e-9 + self.exposure_s / 2)) * 1e6)


def causes(outcome: Outcome, faults: Faults, backend: BenchRig) -> dict:
    """Why each trigger index the pairer reported without a frame has none."""
    paired = {pair.index for pair in outcome.pairs}
    dropped = {d.frame.index: d.kind for d in outcome.drops
               if d.frame is not None and d.frame.index is not None}
    out: dict[str, int] = {}
    for d in outcome.drops:
        if d.kind not in EVENT_SIDE or d.index in paired:
            continue
        i = d.index
        if i in faults.lost_events:
            why = 'injected_lost_event'
        elif i in faults.missed_triggers:
            why = 'injected_missed_trigger'
        elif i in faults.lost_frames:
            why = 'injected_lost_in_transfer'
        elif i in dropped:
            why = f'frame_dropped_{dropped[i]}'
        elif i not in backend.grabbed:
            why = 'camera_sent_no_frame'  # the edge came while the camera was busy, or the
            # frame's packets were lost (camera_statistics)
        else:
            why = 'other'
        out[why] = out.get(why, 0) + 1
    return out


if __name__ == '__main__':
    sys.exit(main())
