"""The set-up's apt step waits for a busy package manager, then says what to do.

apt-get itself is never run here: a stand-in ``apt-get`` first on PATH records the command
line it was given and, like apt, waits for the lock for ``DPkg::Lock::Timeout`` seconds. The
lock is a real ``flock`` this test holds, as another package manager would hold dpkg's.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SETUP = ROOT / 'tools' / 'setup_venv.sh'

FAKE_APT = r'''#!/usr/bin/env bash
# stands in for apt-get: records its arguments, waits for the lock as apt would
printf '%s\n' "$*" >> "$FAKE_APT_LOG"
timeout=0
while [ $# -gt 0 ]; do
  case "$1" in -o) shift; case "$1" in DPkg::Lock::Timeout=*) timeout=${1#*=};; esac;; esac
  shift
done
if ! flock -w "$timeout" "$FAKE_LOCK" true; then
  lock=/var/lib/dpkg/lock-frontend
  echo "E: Could not get lock $lock. It is held by process 4242 (unattended-upgr)" >&2
  echo "E: Unable to acquire the dpkg frontend lock ($lock), is another process using it?" >&2
  exit 100
fi
'''
NOTHING_INSTALLED = '#!/usr/bin/env bash\nexit 1\n'
PASS_THROUGH = '#!/usr/bin/env bash\nexec "$@"\n'


@pytest.fixture
def fake_apt(tmp_path):
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    for name, text in (('apt-get', FAKE_APT), ('dpkg-query', NOTHING_INSTALLED),
                       ('sudo', PASS_THROUGH)):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    lock = tmp_path / 'lock-frontend'
    lock.touch()
    log = tmp_path / 'apt.log'
    env = dict(os.environ, PATH=f'{bin_dir}:{os.environ["PATH"]}', FAKE_APT_LOG=str(log),
               FAKE_LOCK=str(lock))

    def run(timeout_s, hold_s=0.0):
        env['APT_LOCK_TIMEOUT'] = str(timeout_s)
        with open(lock) as held:
            if hold_s:
                fcntl.flock(held, fcntl.LOCK_EX)
            proc = subprocess.Popen(['bash', str(SETUP), 'apt'], env=env, text=True,
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            if hold_s:
                time.sleep(hold_s)
                fcntl.flock(held, fcntl.LOCK_UN)
            out, _ = proc.communicate(timeout=60)
        calls = log.read_text().splitlines() if log.exists() else []
        return proc.returncode, out, calls

    return run


def wanted_packages():
    lines = (ROOT / 'tools' / 'apt-packages.txt').read_text().splitlines()
    return [p.strip() for p in lines if p.strip() and not p.strip().startswith('#')]


def test_apt_waits_for_the_lock_with_the_stated_timeout(fake_apt):
    rc, out, calls = fake_apt(timeout_s=20, hold_s=0.5)
    assert rc == 0, out
    assert 'waiting up to 20 s' in out
    assert len(calls) == 2, calls
    update, install = calls
    assert update.split() == ['-o', 'DPkg::Lock::Timeout=20', 'update', '-qq']
    assert install.split()[:2] == ['-o', 'DPkg::Lock::Timeout=20']
    assert install.split()[2:6] == ['install', '-y', '-qq', '--no-install-recommends']
    assert install.split()[6:] == wanted_packages()


def test_a_lock_held_too_long_fails_with_what_to_do(fake_apt):
    t0 = time.monotonic()
    rc, out, calls = fake_apt(timeout_s=1, hold_s=2.5)
    assert rc == 1
    assert time.monotonic() - t0 >= 1.0           # it waited before giving up
    assert len(calls) == 1 and 'DPkg::Lock::Timeout=1' in calls[0]   # no install tried
    assert 'the dpkg lock is still held by another process after waiting 1 s' in out
    assert 'held by process 4242 (unattended-upgr)' in out
    assert 'APT_LOCK_TIMEOUT=' in out and 'run the same make command again' in out
