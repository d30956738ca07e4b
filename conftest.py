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

# The machine is shared and noisy: no per-example deadlines. Under CI, the examples are
# derived from a fixed seed so that a run is repeatable.
settings.register_profile('galvoscan', deadline=None,
                          derandomize=bool(os.environ.get('CI')))
settings.load_profile('galvoscan')


@pytest.fixture
def ros_env(monkeypatch):
    """Environment for this test and its child processes: a private DDS domain on localhost."""
    domain = str(random.Random(os.getpid() * 7919 + time.monotonic_ns()).randint(101, 230))
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
