"""SIGKILL of `galvoscan run` takes every node with it, and the driver still goes safe."""

import os
import signal
import sys
import time

import pytest

pytestmark = pytest.mark.dds


def _children(pid):
    """PIDs of the direct children of ``pid`` (from /proc)."""
    out = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            stat = open(f'/proc/{entry}/stat').read()
        except OSError:
            continue
        if int(stat.rsplit(')', 1)[1].split()[1]) == pid:
            out.append(int(entry))
    return out


def _alive(pid):
    try:
        stat = open(f'/proc/{pid}/stat').read()
    except OSError:
        return False
    return stat.rsplit(')', 1)[1].split()[0] != 'Z'


def test_sigkill_of_the_supervisor_stops_every_node(spawn, tmp_path):
    logs = tmp_path / 'logs'
    proc = spawn([sys.executable, '-m', 'galvoscan.cli', 'run', '--log-dir', logs],
                 name='galvoscan')
    deadline = time.monotonic() + 60
    while True:
        nodes = _children(proc.pid)
        driver_log = logs / 'galvo_driver.log'
        if len(nodes) == 3 and driver_log.exists() and 'active' in driver_log.read_text():
            break
        assert time.monotonic() < deadline and proc.poll() is None, proc.log_path.read_text()
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)   # the supervisor only, not its process group
    proc.wait(10)
    deadline = time.monotonic() + 20
    while any(_alive(p) for p in nodes):
        assert time.monotonic() < deadline, f'nodes survived their supervisor: {nodes}'
        time.sleep(0.1)
    assert 'shutting down in the safe state: galvos at 0 V, laser off' in \
        driver_log.read_text(), driver_log.read_text()
