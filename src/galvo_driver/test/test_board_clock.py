"""BoardClock (galvo_driver.serial_link.clock): the board clock in host time, drift included,
from arrivals that are late by a random latency, never early."""

import math

import numpy as np
import pytest

from galvo_driver.serial_link.clock import BoardClock


def feed(clock, rng, *, ppm, seconds, rate=500.0, offset=1.7e9, start_s=10.0,
         stalls=(), step=None):
    """Triggers on the board clock; the host reads each 80 us to a few ms later. Returns the
    true host time of board time b [s] as a function."""
    def host_of(b):  # board b [s] -> host [s]: the board runs (1 + ppm) fast
        h = offset + (b - start_s) / (1.0 + ppm * 1e-6)
        if step is not None and b >= step[0]:
            h -= step[1]  # the board clock jumped forward by step[1]: same host, later b
        return h

    for b in np.arange(start_s, start_s + seconds, 1.0 / rate):
        latency = 80e-6 + rng.exponential(400e-6)
        for t0, t1, extra in stalls:
            if t0 <= b < t1:
                latency += extra
        clock.arrival(host_of(b) + latency, b * 1e6)
    return host_of


@pytest.mark.parametrize('ppm', [200.0, -200.0, 0.0, 800.0])
def test_the_drift_is_found_and_the_stamps_follow_it(ppm):
    rng = np.random.default_rng(3)
    clock = BoardClock()
    clock.sync(1.7e9 - 10.0, 10.0e6)  # an exact sync at the start (feed's offset, start)
    host_of = feed(clock, rng, ppm=ppm, seconds=20.0)
    expected = (1.0 / (1.0 + ppm * 1e-6) - 1.0) * 1e6
    assert abs(clock.drift_ppm - expected) < 3.0, clock.drift_ppm
    # 20 s after the sync the stamp is still on the host's clock (uncorrected: ppm * 20 us)
    assert abs(clock.to_host(30.0e6) - host_of(30.0)) < 60e-6


def test_no_drift_before_a_few_seconds_of_events():
    clock = BoardClock()
    feed(clock, np.random.default_rng(1), ppm=500.0, seconds=1.0)
    assert clock.drift_ppm == 0.0


def test_a_host_stall_of_one_bin_is_ignored():
    rng = np.random.default_rng(2)
    clock = BoardClock()
    feed(clock, rng, ppm=200.0, seconds=20.0, stalls=[(15.0, 15.6, 0.02)])
    assert abs(clock.drift_ppm + 200.0) < 3.0 and clock.restarts == 0


def test_a_board_clock_step_restarts_the_envelope():
    rng = np.random.default_rng(4)
    clock = BoardClock()
    feed(clock, rng, ppm=200.0, seconds=30.0, step=(15.0, 0.010))
    assert clock.restarts == 1
    assert abs(clock.drift_ppm + 200.0) < 5.0, clock.drift_ppm  # from after the step only


def test_a_reset_forgets_the_drift_and_bad_input_changes_nothing():
    clock = BoardClock()
    feed(clock, np.random.default_rng(5), ppm=300.0, seconds=10.0)
    before = (clock.drift_ppm, clock.to_host(12e6))
    for host, board in ((math.nan, 1e6), (1.0, math.inf), (math.inf, 2e6)):
        clock.arrival(host, board)
    clock.sync(math.nan, 1e6)
    assert (clock.drift_ppm, clock.to_host(12e6)) == before
    clock.reset()
    assert clock.drift_ppm == 0.0
