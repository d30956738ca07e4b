"""The sim backend's exposure: fixed, limited by the frame period, and set by a pre-scan."""

from __future__ import annotations

import time

import numpy as np
import pytest

from galvo_driver.sim_backend import SimBackend, exposure_limits, pre_scan_exposure
from stripe_extractor.exposure import frame_levels


def _sweep(n=5):
    v = np.zeros((n, 4))
    v[:, 3] = np.linspace(-0.2, 0.1, n)
    return v


def _frames(backend, n):
    out = []
    t_end = time.monotonic() + 30
    while len(out) < n and time.monotonic() < t_end:
        out += backend.poll()
    return out


def test_auto_exposure_brings_a_black_part_to_the_target():
    dark = SimBackend(scene='stair_block_black_anodised', seed=1)
    dark.open()
    dark.start(_sweep(), 500.0)
    base = [frame_levels(f.image)[1] for f in _frames(dark, 5)]
    auto = SimBackend(scene='stair_block_black_anodised', seed=1, auto_exposure=True)
    auto.open()
    auto.start(_sweep(), 500.0)
    lo, hi = exposure_limits(500.0)
    assert auto.scan_exposure > 2 * auto.sim.rig.image.exposure
    assert lo <= auto.scan_exposure <= hi
    frames = _frames(auto, 5)
    peaks = [frame_levels(f.image)[1] for f in frames]
    # at the rig's exposure the stripe is dim; the pre-scan's exposure (here capped by the
    # 2 ms frame period) raises it in proportion
    assert np.median(peaks) > 2.0 * np.median(base), (base, peaks)
    ratio = auto.scan_exposure / auto.sim.rig.image.exposure
    assert np.median(peaks) == pytest.approx(np.median(base) * ratio, rel=0.25)
    assert auto.scan_exposure == pytest.approx(hi) or 0.5 < np.median(peaks) < 0.95
    assert len(auto.pre_scan_levels) == 5


def test_auto_exposure_shortens_a_clipping_exposure():
    b = SimBackend(scene='stair_block', seed=1, exposure=1.5e-3, auto_exposure=True)
    b.open()
    clipped = [frame_levels(b.sim.render(v, exposure=1.5e-3).image)[0] for v in _sweep(3)]
    t, levels = pre_scan_exposure(b.sim, _sweep(), 500.0, 3, 1.5e-3)
    assert min(clipped) > 0.2 and t <= 0.75e-3
    after = [frame_levels(b.sim.render(v, exposure=t).image)[0] for v in _sweep(3)]
    assert max(after) <= 0.1, after


def test_exposure_outside_the_frame_period_is_refused():
    b = SimBackend(exposure=3e-3)
    b.open()
    with pytest.raises(ValueError, match='exposure'):
        b.start(_sweep(), 500.0)
    assert not b.running
    with pytest.raises(ValueError):
        SimBackend(exposure=-1.0)


def test_auto_exposure_raises_the_laser_power_when_the_frame_period_caps_the_exposure():
    b = SimBackend(scene='stair_block_black_anodised', seed=1, auto_exposure=True,
                   max_laser_power=3.0)
    b.open()
    b.start(_sweep(), 500.0)
    assert b.scan_exposure == pytest.approx(exposure_limits(500.0)[1])
    assert 1.0 < b.scan_laser_power <= 3.0
    plain = SimBackend(scene='stair_block_black_anodised', seed=1, auto_exposure=True)
    plain.open()
    plain.start(_sweep(), 500.0)
    assert plain.scan_laser_power == 1.0
    peaks = [frame_levels(f.image)[1] for f in _frames(b, 5)]
    peaks_plain = [frame_levels(f.image)[1] for f in _frames(plain, 5)]
    assert np.median(peaks) > 1.3 * np.median(peaks_plain)


def test_hdr_takes_every_position_twice_long_then_short():
    b = SimBackend(scene='stair_block', seed=1, hdr_ratio=4.0)
    b.open()
    assert b.start(_sweep(3), 500.0) == 6
    frames = _frames(b, 6)
    assert len(frames) == 6
    for long, short in zip(frames[0::2], frames[1::2], strict=True):
        assert np.array_equal(long.voltages, short.voltages)
        assert short.seq == long.seq + 1
        a, c = (float(np.percentile(f.image.max(axis=0), 50)) - 8 for f in (long, short))
        assert a / c == pytest.approx(4.0, rel=0.35)
    with pytest.raises(ValueError, match='hdr_ratio'):
        SimBackend(hdr_ratio=0.5)
