"""Shared pytest fixtures for tests that start real ROS 2 processes.

Every DDS test gets its own ROS_DOMAIN_ID so that concurrent runs on one machine do not
see each other, and discovery stays on this host.
"""

import os
import random
import signal
import subprocess
import sys
import time

import pytest
from hypothesis import settings

from galvoscan_common.runtime import private_domain

# The machine is shared and noisy: no per-example deadlines. Every `make test` derives its
# examples from a fixed seed, so that a user's run is as repeatable as CI's. The random
# exploration is a separate command, `make explore` (profile 'explore': fresh random
# examples, ten times as many), whose finds become fixed test cases.
settings.register_profile('galvoscan', deadline=None, derandomize=True)
settings.register_profile('explore', deadline=None, derandomize=False, max_examples=1000)
settings.load_profile(os.environ.get('HYPOTHESIS_PROFILE', 'galvoscan'))


@pytest.fixture(scope='session', autouse=True)
def _private_state_dir(tmp_path_factory):
    """The suite's own state directory: a calibration that a test's demo or calibrate records
    must neither reach the user's ``galvoscan run`` nor another test's."""
    previous = os.environ.get('GALVOSCAN_STATE_DIR')
    os.environ['GALVOSCAN_STATE_DIR'] = str(tmp_path_factory.mktemp('galvoscan-state'))
    yield
    if previous is None:
        os.environ.pop('GALVOSCAN_STATE_DIR', None)
    else:
        os.environ['GALVOSCAN_STATE_DIR'] = previous


@pytest.fixture(scope='session', autouse=True)
def _no_zombie_shm_segments():
    """Tests SIGKILL DDS processes on purpose; remove the shared-memory segments they leave."""
    yield
    from galvoscan_common.runtime import remove_zombie_shm_segments

    remove_zombie_shm_segments()


@pytest.fixture
def ros_env(monkeypatch):
    """Environment for this test and its child processes: a private DDS domain on localhost."""
    domain = str(private_domain(random.Random(os.getpid() * 7919 + time.monotonic_ns()),
                                test=True))
    monkeypatch.setenv('ROS_DOMAIN_ID', domain)
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.setenv('PYTHONUNBUFFERED', '1')
    return dict(os.environ)


@pytest.fixture
def spawn(ros_env, tmp_path):
    """Start child processes (stdout+stderr to a log file); all are stopped at teardown.

    ``spawn(args)`` returns the Popen; ``proc.log_path`` holds its output.
    """
    procs = []

    def _spawn(args, name=None, env=None):
        name = name or os.path.basename(str(args[0]))
        log_path = tmp_path / f'{name}-{len(procs)}.log'
        log = open(log_path, 'wb')  # noqa: SIM115 - closed at teardown
        proc = subprocess.Popen(
            [str(a) for a in args], stdout=log, stderr=subprocess.STDOUT,
            env={**ros_env, **(env or {})}, start_new_session=True)
        proc.log_path = log_path
        proc.log_file = log
        procs.append(proc)
        return proc

    yield _spawn
    for proc in procs:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.log_file.close()


@pytest.fixture
def venv_python():
    return sys.executable


def _owned_shm_segments(pid):
    """The Fast DDS segments whose ``_el`` lock file process ``pid`` holds exclusively: the
    ones it owns (a participant holds shared locks on the segments of peers it maps)."""
    from galvoscan_common.runtime import SEGMENT_LOCK, SHM_DIR

    inodes = set()
    with open('/proc/locks') as locks:
        for line in locks:
            f = line.split()
            if f[1] == 'FLOCK' and f[3] == 'WRITE' and f[4] == str(pid):
                inodes.add(int(f[5].split(':')[2]))
    return [SHM_DIR / n[:-3] for n in sorted(os.listdir(SHM_DIR))
            if SEGMENT_LOCK.match(n) and (SHM_DIR / n).stat().st_ino in inodes]


@pytest.fixture
def shm_segment_owner(ros_env):
    """``start()`` runs a process holding a DDS participant; returns (Popen, its segments).

    Each process gets a domain of its own, so that they do not map each other's segments.
    With ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` rmw_fastrtps adds a shared-memory
    transport of its own (0.5 MB segment) beside the one of galvoscan's profile.
    """
    from galvoscan_common.runtime import child_env

    procs = []
    code = ('import rclpy, time; rclpy.init(); n = rclpy.create_node("segment_owner"); '
            'print("up", flush=True); time.sleep(60)')

    def _start():
        domain = str(int(ros_env['ROS_DOMAIN_ID']) + len(procs))
        proc = subprocess.Popen([sys.executable, '-c', code],
                                env=child_env({**ros_env, 'ROS_DOMAIN_ID': domain}),
                                stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert proc.stdout.readline().strip() == 'up'
        segments = _owned_shm_segments(proc.pid)
        assert segments
        return proc, segments

    yield _start
    for proc in procs:
        proc.kill()
        proc.wait(10)
        proc.stdout.close()


@pytest.fixture
def sim_graph_params(tmp_path):
    """``make(...)`` writes the parameters YAML of the simulated graph; returns its path.

    The driver runs the sim backend on the reference rig with ``scene`` and ``seed``; the
    reconstructor loads ``calibration`` (default: the reference rig's true calibration,
    written to ``simulator_truth_for_tests.yaml``). ``driver``, ``extractor`` and
    ``reconstructor`` add or replace that node's parameters (an ``extractor`` of None
    leaves the node out of the file).
    """
    import yaml

    def make(*, scene='stair_block', seed=7, calibration=None, driver=None, extractor=None,
             reconstructor=None):
        if calibration is None:
            from galvoscan.simulated_rig import truth_calibration
            from galvoscan_sim import load_rig
            from reconstructor import calibration_file

            calibration = tmp_path / 'simulator_truth_for_tests.yaml'
            calibration_file.save(truth_calibration(load_rig('reference')), calibration)
        params = {'galvo_driver': {'ros__parameters': {
            'backend': 'sim', 'rig': 'reference', 'scene': scene, 'seed': seed,
            **(driver or {})}}}
        if extractor is not None:
            params['stripe_extractor'] = {'ros__parameters': dict(extractor)}
        params['reconstructor'] = {'ros__parameters': {
            'calibration_file': str(calibration), **(reconstructor or {})}}
        path = tmp_path / 'params.yaml'
        path.write_text(yaml.safe_dump(params))
        return path

    return make


@pytest.fixture
def logged_port():
    """``wait(proc, what)``: the port a process logs as ``<what> on <scheme>://host:PORT``."""
    import re

    def wait(proc, what: str, timeout: float = 60.0) -> int:
        deadline = time.monotonic() + timeout
        pattern = re.compile(re.escape(what) + r' on \w+://[^\s]+:(\d+)')
        while time.monotonic() < deadline:
            assert proc.poll() is None, proc.log_path.read_text()
            found = pattern.search(proc.log_path.read_text())
            if found:
                return int(found.group(1))
            time.sleep(0.2)
        raise AssertionError(f'no "{what}" port in the log:\n{proc.log_path.read_text()}')

    return wait
