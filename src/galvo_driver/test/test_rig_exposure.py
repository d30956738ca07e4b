"""Auto exposure and HDR on the ``rig`` backend, through the real GenICam stack: the firmware
emulator on a pty fires Aravis' fake GigE Vision camera through its ``Line0`` input, and the
backend sets ``ExposureTime`` over GVCP.

The fake camera's image brightness is proportional to ``(1 + Gain) * ExposureTime``
(``fake_camera._RampFill``: a ramp through every grey level 0..254 at 10 ms and gain 0, so
with 256 rows every column's brightest pixel is ``254 * (1 + Gain) * ExposureTime / 10 ms``
clipped at 255). The exposure the backend chooses therefore shows in the frames the camera
sends afterwards, measured here from those frames alone; a backend that wrote the wrong
exposure, or none, fails.

The machine may be loaded (the fake camera then misses triggers): the assertions hold for
whatever frames came, and need only a few.
"""

from __future__ import annotations

import gc
import time

import numpy as np
import pytest

from galvo_driver.fake_camera import FakeCamera, edge_at, edge_of
from galvo_driver.rig_backend import RigBackend
from galvo_driver.serial_link.emulator import FirmwareEmulator
from galvoscan_common import cdr
from stripe_extractor.exposure import TARGET_PEAK, frame_levels

SERIAL = 'GSEXPOSURE'
WIDTH, HEIGHT = 96, 256  # 256 rows: every column holds the ramp's whole range


@pytest.fixture(scope='module')
def fake():
    gc.collect()
    gc.freeze()  # see test_rig_backend.py: a full collection would stall the emulator
    try:
        with FakeCamera(SERIAL, width=WIDTH, height=HEIGHT) as cam:
            yield cam
    finally:
        gc.unfreeze()


class Rig:
    def __init__(self, fake: FakeCamera, features: dict, **backend_kw):
        self.fake = fake
        self.edges: dict[int, float] = {}
        self.emu = FirmwareEmulator('pty', seed=0, on_trigger=self._hook, watchdog=1.0)
        self.emu.start()
        self.backend = RigBackend(self.emu.port, camera_serial=SERIAL,
                                  features={'PixelFormat': 'Mono8', **features},
                                  camera_clock='host', frame_timeout=0.3, **backend_kw)
        self.backend.open()
        self.backend.arm()

    def _hook(self, index: int, t: float) -> None:
        edge = edge_at(t)
        self.edges[edge] = t
        self.fake.pulse_line(edge)

    def scan(self, rows: int, rate: float, laser_on: bool = True) -> list:
        volts = np.zeros((rows, 4))
        volts[:, 0] = np.linspace(-2.0, 2.0, rows)
        n = self.backend.start(volts, rate, laser_on)
        frames, deadline = [], time.monotonic() + n / rate + 15.0
        while self.backend.running and time.monotonic() < deadline:
            frames += self.backend.poll(0.02)
        frames += self.backend.poll(0.0)
        assert not self.backend.running, 'the scan did not end'
        return frames

    def close(self) -> None:
        self.backend.close()
        self.emu.stop()


@pytest.fixture
def rig(fake):
    made = []

    def make(features, **kw) -> Rig:
        if not fake.running:
            fake.replug()
        made.append(Rig(fake, features, **kw))
        return made[-1]

    yield make
    for r in made:
        r.close()


def _peaks(frames) -> list[float]:
    """The median column's brightest pixel of each frame, share of 255; the first row is
    left out (it carries the trigger's instant, see fake_camera.edge_of)."""
    return [frame_levels(np.ascontiguousarray(f.image[1:]), 255)[1] for f in frames]


def test_auto_exposure_puts_the_peak_at_the_target(rig):
    r = rig({'ExposureTime': 1000.0, 'Gain': 0.0}, auto_exposure=True, auto_exposure_frames=8)
    frames = r.scan(30, 50.0)
    # the pre-scan saw the dim frames of 1 ms: 254 * 0.1 of 255
    assert r.backend.pre_scan_levels
    assert max(p for _, p in r.backend.pre_scan_levels) == pytest.approx(25 / 255, abs=0.01)
    expected_us = 1000.0 * TARGET_PEAK / (25 / 255)
    assert r.backend.camera.get('ExposureTime') == pytest.approx(expected_us, rel=0.02)
    assert r.backend.scan_exposure == pytest.approx(expected_us * 1e-6, rel=0.02)
    assert r.backend.stats['pre_scans'] >= 1 and r.backend.stats['pre_scan_frames'] >= 1
    assert frames, 'no frame of the scan came'
    assert np.allclose(_peaks(frames), TARGET_PEAK, atol=0.015), _peaks(frames)
    # the pre-scan's triggers are not handed out: the scan's frames number from 0
    assert min(f.seq for f in frames) < 30 and max(f.seq for f in frames) < 30


def test_a_clipped_pre_scan_halves_the_exposure_and_measures_again(rig):
    """At gain 10 the 1 ms frames clip in every column: the exposure halves, the second
    pre-scan measures the stripe and sets it at the target."""
    r = rig({'ExposureTime': 1000.0, 'Gain': 10.0}, auto_exposure=True, auto_exposure_frames=8)
    frames = r.scan(20, 50.0)
    assert r.backend.stats['pre_scans'] >= 2
    # 1000 us clipped -> 500 us, where the peak is 140 of 255 -> 500 * 0.7 / (140 / 255)
    assert r.backend.camera.get('ExposureTime') == pytest.approx(500 * TARGET_PEAK * 255 / 140,
                                                                 rel=0.02)
    assert frames
    assert np.allclose(_peaks(frames), TARGET_PEAK, atol=0.02), _peaks(frames)


def test_the_frame_period_and_the_camera_bounds_limit_the_exposure(rig):
    """1 ms at gain 0 asks for 7 ms; at 200 Hz the frame period allows 0.9 x 5 ms."""
    r = rig({'ExposureTime': 1000.0, 'Gain': 0.0}, auto_exposure=True, auto_exposure_frames=8)
    frames = r.scan(20, 200.0)
    assert r.backend.camera.get('ExposureTime') == pytest.approx(4500.0, abs=1.0)
    lo, hi = r.backend._exposure_limits(200.0)
    assert lo == pytest.approx(10e-6) and hi == pytest.approx(4.5e-3)
    assert all(p == pytest.approx(254 * 0.45 / 255, abs=0.01) for p in _peaks(frames))
    with pytest.raises(ValueError, match='shortest exposure'):
        r.backend._exposure_limits(1e6 / 55.0)


def test_hdr_hands_out_each_row_long_then_short(rig):
    """hdr_ratio 4: every row's two frames, consecutive in sequence, same voltages, the
    second exposed later (in the short pass) and a quarter as bright; the extractor's
    pairing rule takes them as one HDR pair. The long exposure is back afterwards."""
    r = rig({'ExposureTime': 4000.0, 'Gain': 0.0}, hdr_ratio=4.0)
    # the pairer locks on the two clocks in a first scan (laser off: no HDR), as after
    # any arming; the fake camera also sends few frames in its first 100 ms
    assert len(r.scan(30, 50.0, laser_on=False)) > 0
    rows, base = 30, r.backend._seq_base
    frames = r.scan(rows, 50.0)
    assert r.backend.camera.get('ExposureTime') == pytest.approx(4000.0)
    by_seq = {f.seq - base: f for f in frames}
    assert all(0 <= s < 2 * rows for s in by_seq)
    assert r.backend._seq_base == base + 2 * rows
    pairs = [(by_seq[s], by_seq[s + 1]) for s in by_seq if s % 2 == 0 and s + 1 in by_seq]
    assert pairs, f'no pair among {sorted(by_seq)}'
    assert r.backend.stats['hdr_pairs'] == len(pairs)
    from stripe_extractor.extractor_node import _same_position

    for long, short in pairs:
        np.testing.assert_array_equal(long.voltages, short.voltages)
        assert edge_of(long.image) < edge_of(short.image) and long.stamp < short.stamp
        states = [cdr.GalvoState(cdr.Header(), f.seq, *map(float, f.voltages), True, 0)
                  for f in (long, short)]
        assert _same_position(*states)
        pl, ps = _peaks([long, short])
        assert pl == pytest.approx(254 * 0.4 / 255, abs=0.01)
        assert ps == pytest.approx(254 * 0.1 / 255, abs=0.01)
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs)


def test_an_hdr_scan_too_long_to_hold_is_refused(rig):
    r = rig({'ExposureTime': 1000.0}, hdr_ratio=2.0)
    with pytest.raises(ValueError, match='HDR'):
        r.backend.start(np.zeros((60_000, 4)), 50.0)
    assert not r.backend.running
