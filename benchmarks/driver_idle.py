"""CPU time of an idle galvo driver (sim backend, active, no scan), against a bare rclpy node.

Starts ``galvo_driver`` in its own process, waits until it is active, lets it sit for
``--seconds`` and reads its CPU time (user + system) from ``/proc/PID/stat`` before and after.
The same is measured in the same run for a bare rclpy node that only spins (the floor any
node pays), and the ratio is printed. Goal: the idle driver under 2 % of a core.

    .venv/bin/python benchmarks/driver_idle.py [--seconds 20]

Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from galvoscan_common.runtime import private_domain

BARE_NODE = ('import rclpy, rclpy.executors; rclpy.init(); n = rclpy.create_node("bare"); '
             'print("active", flush=True); ex = rclpy.executors.SingleThreadedExecutor(); '
             'ex.add_node(n); ex.spin()')


def cpu_seconds(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def measure(argv, env, seconds: float) -> float:
    """Percent of one core a process uses once it says 'active'."""
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60
            while True:
                log.seek(0)
                if b'active' in log.read():
                    break
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    raise RuntimeError(f'{argv[0]} did not start:\n{log.read().decode()}')
                time.sleep(0.1)
            time.sleep(1.0)  # start-up work (JIT, discovery bursts) is not idle time
            c0, t0 = cpu_seconds(proc.pid), time.monotonic()
            time.sleep(seconds)
            c1, t1 = cpu_seconds(proc.pid), time.monotonic()
        finally:
            proc.terminate()
            proc.wait(10)
    return 100.0 * (c1 - c0) / (t1 - t0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    args = parser.parse_args(argv)
    env = {**os.environ, 'ROS_DOMAIN_ID': str(private_domain()),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    driver = measure([sys.executable, '-m', 'galvo_driver.driver_node', '--ros-args',
                      '-p', 'backend:=sim'], env, args.seconds)
    bare = measure([sys.executable, '-c', BARE_NODE], env, args.seconds)
    print(f'idle driver: {driver:.2f} % of a core; bare rclpy node: {bare:.2f} % '
          f'({args.seconds:g} s each)')
    print(json.dumps({'driver_idle_cpu_pct': round(driver, 3),
                      'bare_node_idle_cpu_pct': round(bare, 3),
                      'ratio_to_bare_node': round(driver / bare, 2) if bare > 0 else None,
                      'goal_pct': 2.0, 'seconds': args.seconds}))


if __name__ == '__main__':
    main()
