"""The galvo board firmware in simavr: triggers, timing, watchdog and interlock, measured in
simulated CPU cycles (16 MHz) from the harness log.

A scripted host (simulated time, free-running) uploads scans of up to 768 rows (the
board's table) back to back until ``--triggers`` triggers at ``--rate`` Hz have fired,
sending HEARTBEAT every 50 ms; then it stops the heartbeats during a lasing SET_VOLTS
(watchdog), and opens the interlock during a scan. Reported:

* ``event_dac_mismatches``: triggers whose EVENT codes differ from the DAC outputs at the
  rising edge or from the uploaded row (must be 0);
* ``period_cycles_min/max``, ``period_jitter_us_pp``: spread of the edge-to-edge period
  within a scan (the nominal period is ``period_cycles_nominal``);
* ``watchdog_ms``: last host byte to all channels at 0 V and the laser off (<= 300 ms);
* ``interlock_laser_off_us``: interlock opened to laser off; ``interlock_park_us`` to the
  galvos at 0 V; ``trigger_period_us`` for comparison;
* ``sim_seconds``, ``wall_seconds``, ``speed_vs_real_time``: simulated time over the wall
  time of the harness runs (the reference of the ratio is real time).

Usage::

    python benchmarks/firmware_simavr.py [--triggers 10000] [--rate 500]

The last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link import simavr_board as sb

F = sb.F_CPU
ZERO = (p.CODE_ZERO,) * 4


def triggers_run(n_triggers: int, rate: float, seed: int) -> tuple[dict, float]:
    rng = np.random.default_rng(seed)
    period_us = round(1e6 / rate)
    script = sb.Script()
    script.send(1000.0, p.Hello(p.PROTOCOL_VERSION))
    t = 5000.0
    scans = []
    total = 0
    while total < n_triggers:
        n = min(768, n_triggers - total)
        codes = rng.integers(1, 65536, (n, 4)).astype(np.uint16)
        t_start = script.upload_scan(t, len(scans) + 1, codes, period_us)
        scans.append(codes)
        total += n
        t = t_start + n * period_us + 100_000
    script.heartbeats(1000.0, t)
    t0 = time.perf_counter()
    log = sb.run_script(script, t + 5000)
    wall = time.perf_counter() - t0
    edges = log.rising_edges()
    events = log.events()
    mismatches = 0
    for edge, (_, ev) in zip(edges, events, strict=False):
        row = tuple(int(c) for c in scans[ev.scan_id - 1][ev.index])
        mismatches += (log.codes_at(int(edge)) != ev.codes) or (ev.codes != row)
    periods = []
    start = 0
    for codes in scans:
        periods.append(np.diff(edges[start:start + len(codes)]))
        start += len(codes)
    per = np.concatenate(periods)
    return {
        'triggers': int(len(edges)),
        'events': len(events),
        'event_dac_mismatches': int(mismatches + abs(len(edges) - len(events))),
        'period_cycles_nominal': period_us * 16,
        'period_cycles_min': int(per.min()),
        'period_cycles_max': int(per.max()),
        'period_jitter_us_pp': float(np.ptp(per) / 16),
        'sim_seconds': log.end / F,
    }, wall


def watchdog_run() -> tuple[dict, float]:
    script = sb.Script()
    script.send(1000.0, p.Hello(p.PROTOCOL_VERSION))
    script.send(3000.0, p.SetVolts((40000, 20000, 50000, 1000)))
    script.send(5000.0, p.Laser(True))
    script.heartbeats(10_000.0, 400_000.0)
    t0 = time.perf_counter()
    log = sb.run_script(script, 1_000_000.0)
    wall = time.perf_counter() - t0
    last_rx = log.rx[-1][0]
    safe = next(c for c, codes, *_ in log.outputs if c > last_rx and codes == ZERO)
    laser_off = next(c for c, v in log.laser if c > last_rx and v == 0)
    return {'watchdog_ms': (max(safe, laser_off) - last_rx) / F * 1e3,
            'sim_seconds': log.end / F}, wall


def interlock_run(rate: float) -> tuple[dict, float]:
    period_us = round(1e6 / rate)
    script = sb.Script()
    script.send(1000.0, p.Hello(p.PROTOCOL_VERSION))
    codes = np.full((500, 4), 50000, np.uint16)
    t0_us = script.upload_scan(3000.0, 1, codes, period_us)
    t_open = t0_us + 100_000.0 + 333.0
    script.at(t_open, 'interlock open')
    script.heartbeats(10_000.0, t_open + 50_000)
    t0 = time.perf_counter()
    log = sb.run_script(script, t_open + 50_000)
    wall = time.perf_counter() - t0
    opened = next(c for c, is_open in log.interlock if is_open)
    laser_off = next(c for c, v in log.laser if c >= opened and v == 0)
    parked = next(c for c, cd, *_ in log.outputs if c > opened and cd == ZERO)
    edges_after = int(np.sum(log.rising_edges() > opened))
    return {'interlock_laser_off_us': (laser_off - opened) / F * 1e6,
            'interlock_park_us': (parked - opened) / F * 1e6,
            'interlock_edges_after': edges_after, 'trigger_period_us': period_us,
            'sim_seconds': log.end / F}, wall


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--triggers', type=int, default=10_000)
    ap.add_argument('--rate', type=float, default=500.0, help='trigger rate [Hz]')
    ap.add_argument('--seed', type=int, default=1)
    args = ap.parse_args(argv)
    sb.build()
    out = {}
    sim = wall = 0.0
    for res, w in (triggers_run(args.triggers, args.rate, args.seed), watchdog_run(),
                   interlock_run(args.rate)):
        sim += res.pop('sim_seconds')
        wall += w
        out.update(res)
    out['sim_seconds'] = round(sim, 3)
    out['wall_seconds'] = round(wall, 3)
    out['speed_vs_real_time'] = round(sim / wall, 2)
    for k, v in out.items():
        if isinstance(v, float):
            out[k] = round(v, 3)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
