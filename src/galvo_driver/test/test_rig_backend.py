"""The ``rig`` backend with both sides real: the firmware emulator on a pty and the fake
GigE Vision camera, the emulator's trigger wired to the camera's ``Line0`` input.

Every frame the backend delivers is traced to the trigger that exposed it through the
camera (the fake camera writes the edge instant into the image), independently of the
pairing, and its voltages are compared with the emulator's own record of that trigger
(:meth:`FirmwareEmulator.triggers`): a wrong tag fails the test, whatever the fault.
The pairing rules themselves are tested in test_trigger_pairing.py; here each fault is
injected at the backend level and the outcome is checked: recovered (the scan completes, the
frames concerned are counted as dropped) or stopped in the safe state with an ERROR log.

The machine may be loaded (the fake camera then misses triggers, as a busy camera does):
the assertions are about tags and accounting, not about how many frames came.
"""

from __future__ import annotations

import gc
import logging
import time

import numpy as np
import pytest

from galvo_driver.backend import BackendError
from galvo_driver.fake_camera import FakeCamera, edge_at, edge_of
from galvo_driver.rig_backend import RigBackend
from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link.emulator import FirmwareEmulator

SERIAL = 'GSRIGTEST'
RATE = 200.0  # [Hz]
ROWS = 300
EXPOSURE_US = 300.0


@pytest.fixture(scope='module')
def fake():
    # The emulator runs in this process, a board does not: a full garbage collection of a
    # long test session's heap holds the GIL for up to a second and would stall it (its
    # ACKs, its triggers). Freezing what exists keeps collections to the tests' new objects.
    gc.collect()
    gc.freeze()
    try:
        with FakeCamera(SERIAL, width=64, height=32) as cam:
            yield cam
    finally:
        gc.unfreeze()


class Rig:
    """The emulator, the fake camera's trigger line and the rig backend, with the truth."""

    def __init__(self, fake: FakeCamera, *, seed: int = 0, drift_ppm: float = 0.0,
                 miss: set = frozenset(), dup: set = frozenset(), **backend_kw):
        self.fake = fake
        self.miss, self.dup = set(miss), set(dup)
        self.edges: dict[int, float] = {}  # edge instant [ns] -> emulator trigger time t
        self.rng = np.random.default_rng(seed)
        self.emu = FirmwareEmulator('pty', seed=seed, on_trigger=self._hook,
                                    clock_drift_ppm=drift_ppm, watchdog=1.0)
        self.emu.start()
        self.backend = RigBackend(self.emu.port, camera_serial=SERIAL,
                                  features={'ExposureTime': EXPOSURE_US, 'PixelFormat': 'Mono8'},
                                  camera_clock='host', frame_timeout=0.3, **backend_kw)
        self.backend.open()
        self.backend.arm()

    def _hook(self, index: int, t: float) -> None:
        """The board's trigger output: the wire to the camera's Line0."""
        if index in self.dup:
            self.emu.duplicate_events(1, skip=0)
        if index in self.miss:
            return  # the camera does not see this edge: it does not expose
        edge = edge_at(t)
        self.edges[edge] = t
        self.fake.pulse_line(edge)

    def scan(self, rows: int = ROWS, rate: float = RATE, during=None) -> list:
        """Run one scan of random rows; every frame the backend delivered, in order."""
        volts = self.rng.uniform(-9.0, 9.0, (rows, 4))
        self.backend.start(volts, rate)
        frames, deadline = [], time.monotonic() + rows / rate + 10.0
        while self.backend.running and time.monotonic() < deadline:
            frames += self.backend.poll(0.02)
            if during is not None:
                during(self, frames)
        frames += self.backend.poll(0.0)
        assert not self.backend.running, 'the scan did not end'
        return frames

    def check(self, frames, seq_base: int = 0) -> set:
        """Every frame against the emulator's record of the trigger that exposed it; the
        trigger indices delivered."""
        records = {r.t: r for r in self.emu.triggers()}
        delivered = set()
        for f in frames:
            rec = records[self.edges[edge_of(f.image)]]
            assert f.seq == seq_base + rec.index, (f.seq, rec.index)
            np.testing.assert_array_equal(f.voltages, p.codes_to_volts(np.array(rec.codes)))
            assert f.laser_on == rec.laser_on
            assert f.image.dtype == np.uint8 and f.image.shape == (32, 64)
            delivered.add(rec.index)
        assert len(delivered) == len(frames), 'a trigger was delivered twice'
        return delivered

    def pairing(self) -> dict:
        return self.backend.stats['pairing']

    def close(self) -> None:
        self.backend.close()
        self.emu.stop()


@pytest.fixture
def rig_factory(fake):
    made = []

    def make(**kw) -> Rig:
        if not fake.running:
            fake.replug()
        rig = Rig(fake, **kw)
        made.append(rig)
        return rig

    yield make
    for rig in made:
        rig.close()


def assert_safe(emu: FirmwareEmulator) -> None:
    last = emu.last_applied()
    assert last.codes == tuple(p.volts_to_codes(np.zeros(4))) and not last.laser_on, last


def recovered(rig: Rig, caplog) -> bool:
    """True if the scan ran to its end without a fault; else it must have stopped in the
    safe state with an ERROR log (the only other acceptable outcome of a fault)."""
    if rig.backend.fault is None:
        return True
    assert any(r.levelno == logging.ERROR for r in caplog.records), rig.backend.fault
    assert_safe(rig.emu)
    return False


def test_clean_scans_tag_every_frame_right_and_stamp_mid_exposure(rig_factory):
    rig = rig_factory(seed=1)
    t0 = time.time()
    frames = rig.scan()
    delivered = rig.check(frames)
    assert len(delivered) >= 20, rig.pairing()  # frames really come through (a loaded
    # machine makes the fake camera miss triggers: how many is not the point here)
    assert rig.backend.fault is None
    # the stamp is the middle of the exposure, in host time: edge + exposure / 2
    records = {r.t: r for r in rig.emu.triggers()}
    errs = [f.stamp - (edge_of(f.image) * 1e-9 + EXPOSURE_US * 0.5e-6) for f in frames]
    assert np.median(np.abs(errs)) < 2e-3 and t0 < frames[0].stamp < time.time()
    assert records  # the emulator recorded the triggers
    # the next scan's sequence continues after this one's triggers
    frames2 = rig.scan(rows=50)
    rig.check(frames2, seq_base=ROWS)
    stats = rig.backend.stats
    unpaired = ROWS + 50 - stats['frames']
    assert stats['pairing']['event_without_frame'] + stats['pairing']['event_lost'] == unpaired


def test_lost_trigger_events_are_dropped_and_counted(rig_factory, caplog):
    rig = rig_factory(seed=2)
    lost = [60, 140, 220]
    for k, i in enumerate(lost):
        rig.emu.drop_bytes(1, 'event', skip=i - k)
    with caplog.at_level(logging.ERROR):
        frames = rig.scan()
    delivered = rig.check(frames)
    assert not delivered & set(lost)
    if recovered(rig, caplog):
        assert rig.pairing()['event_lost'] >= len(lost)
        assert rig.backend.stats['board']['lost_events'] == len(lost)


def test_lost_and_missed_camera_frames_leave_gaps_and_no_wrong_tag(rig_factory, caplog):
    rig = rig_factory(seed=3, miss={50, 51, 170})
    lost = {100, 230}  # exposed (the frame id advances) but lost in transfer
    grab = rig.backend.camera.grab

    def lossy_grab(timeout):
        frame = grab(timeout)
        if frame is not None and edge_of(frame.image) in rig.edges:
            t = rig.edges[edge_of(frame.image)]
            if any(r.t == t and r.index in lost for r in rig.emu.triggers()[-20:]):
                return None
        return frame

    rig.backend.camera.grab = lossy_grab
    with caplog.at_level(logging.ERROR):
        frames = rig.scan()
    delivered = rig.check(frames)
    assert not delivered & (lost | {50, 51, 170})
    gaps = np.diff([f.seq for f in frames])
    assert (gaps >= 1).all()
    if recovered(rig, caplog):
        assert gaps.max() > 1  # the missing triggers are gaps in seq


def test_duplicated_events_are_ignored(rig_factory, caplog):
    rig = rig_factory(seed=4, dup={30, 31, 200})
    with caplog.at_level(logging.ERROR):
        frames = rig.scan()
    rig.check(frames)
    if recovered(rig, caplog):
        assert rig.pairing()['duplicate_event'] == 3


@pytest.mark.parametrize('drift_ppm', [200.0, -200.0])
def test_board_clock_drift_is_tracked(rig_factory, caplog, drift_ppm):
    rig = rig_factory(seed=5, drift_ppm=drift_ppm)
    with caplog.at_level(logging.ERROR):
        frames = rig.scan(rows=400)
    rig.check(frames)
    if recovered(rig, caplog) and rig.pairing()['fit_pairs'] >= 100:
        # the camera stamps host time, so the fit sees the board's drift, reversed
        assert abs(rig.pairing()['drift_ppm'] + drift_ppm) < 60, rig.pairing()


@pytest.mark.parametrize('step_us', [3333, -1500])
def test_board_clock_step_is_recovered_or_stops_safe(rig_factory, caplog, step_us):
    """The pairer restarts its clock fit after a step; if the camera misses triggers
    around it too (a loaded machine), it may not find the new schedule: the backend then
    stops the scan rather than drop frames forever."""
    rig = rig_factory(seed=6, max_unpaired_frames=40)
    rig.emu.step_clock(step_us, at_trigger=150)
    with caplog.at_level(logging.ERROR):
        frames = rig.scan()
    delivered = rig.check(frames)
    counts = {k: v for k, v in rig.pairing().items() if v}
    if rig.backend.fault is None:
        assert any(i > 160 for i in delivered), counts  # recovered after the step
        assert counts.get('clock_steps', 0) >= 1, counts
    else:
        assert rig.backend.fault.startswith('pairing lost'), rig.backend.fault
        assert any(r.levelno == logging.ERROR and 'pairing lost' in r.getMessage()
                   for r in caplog.records)
        assert_safe(rig.emu)


def test_board_reset_mid_scan_stops_safe_with_an_error(rig_factory, caplog):
    rig = rig_factory(seed=7)
    rig.emu.reset(at_trigger=120)
    with caplog.at_level(logging.ERROR):
        frames = rig.scan()
    delivered = rig.check(frames)
    assert max(delivered, default=0) <= 120
    assert rig.backend.fault and 'reset' in rig.backend.fault
    assert any(r.levelno == logging.ERROR and 'reset' in r.getMessage()
               for r in caplog.records)
    assert_safe(rig.emu)
    with pytest.raises(BackendError, match='FAULT'):
        rig.backend.start(np.zeros((10, 4)), RATE)
    rig.backend.arm()  # activate again: a new session, and scans work
    rig.check(rig.scan(rows=60), seq_base=ROWS)


def test_camera_unplug_mid_scan_stops_safe_then_reconnects(rig_factory, fake, caplog):
    rig = rig_factory(seed=8)

    def unplug_after_80(rig, frames):
        if fake.running and rig.emu.snapshot()['triggers'] >= 80:
            fake.unplug()

    with caplog.at_level(logging.ERROR):
        frames = rig.scan(rows=600, during=unplug_after_80)
    rig.check(frames)
    assert rig.backend.fault and rig.backend.fault.startswith('camera')
    assert any(r.levelno == logging.ERROR and 'camera' in r.getMessage()
               for r in caplog.records)
    assert rig.emu.snapshot()['triggers'] < 600  # the board was stopped
    assert_safe(rig.emu)
    fake.replug()
    rig.backend.arm()  # reopens the same camera, clears the fault
    assert rig.backend.fault is None
    rig.check(rig.scan(rows=60), seq_base=600)


def test_bad_arguments_change_nothing(rig_factory):
    rig = rig_factory(seed=9)
    with pytest.raises(ValueError, match='exposure'):
        rig.backend.start(np.zeros((10, 4)), 4000.0)  # 250 us per frame < exposure + 50
    with pytest.raises(ValueError):
        rig.backend.start(np.full((10, 4), 11.0), RATE)
    with pytest.raises(ValueError, match='not a camera parameter'):
        rig.backend.set_feature('TriggerMode', 'Off')
    from galvo_driver.genicam_camera import CameraError
    with pytest.raises(CameraError, match='outside'):
        rig.backend.set_feature('ExposureTime', 5.0)
    assert rig.backend.camera.get('ExposureTime') == EXPOSURE_US
    assert rig.backend.set_feature('ExposureTime', 400.0) == 400.0
    assert rig.backend.exposure == pytest.approx(400e-6)
    with pytest.raises(ValueError, match='trigger_source'):
        RigBackend(rig.emu.port, trigger_source='Line9')
    assert rig.emu.snapshot()['triggers'] == 0
