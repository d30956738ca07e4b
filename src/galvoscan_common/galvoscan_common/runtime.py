"""Process settings for the 500 fps image path: glibc malloc, BLAS threads, Fast DDS.

No rclpy here. Measured on this 2-core machine (``benchmarks/pipeline.py``):

- Every 720x540 image is copied several times per hop (rmw take, Python ``bytes``). glibc
  serves blocks this large with fresh ``mmap`` pages and unmaps them on free, so each copy
  page-faults on all its ~95 pages: publishing and taking one image cost about 0.6 ms of
  the executor thread, about half of it in the kernel. With the mmap threshold raised (and
  the heap no longer trimmed back after each frame) the same hop costs about 0.3 ms.
- OpenBLAS threads spin after each call and take the second core from the extraction
  thread; the nodes' matrices are 3x3/4x4, which one thread does faster anyway.
- Fast DDS's default shared-memory segment (0.5 MB) holds one 389 kB image, so a frame
  published while a reader still holds the previous one is lost for it
  (``fastdds_profile.xml`` beside this file: a 32 MB segment; its comment has the figures).
  Fast DDS 2.x reads the profile's path from ``FASTRTPS_DEFAULT_PROFILES_FILE`` only;
  ``tests`` check that a participant really gets the large segment.

:func:`child_env` adds all three as environment variables for processes the supervisor
starts (glibc, OpenBLAS and Fast DDS read them at start-up); :func:`tune_this_process`
applies the malloc part to the running process with ``mallopt`` and sets the Fast DDS
profile for participants it creates later (call it before ``rclpy.init``). Both leave
settings the user already made alone, and the profile is only used with Fast DDS.
``GALVOSCAN_DDS=multihost`` selects ``fastdds_multihost.xml`` instead, for a graph spread
over hosts (UDP only; see that file).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import fcntl
import gc
import os
import re
import signal
from pathlib import Path

#: Private DDS domains of throwaway graphs on one host (with
#: ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``): the test suite draws from the first range,
#: evaluations and benchmarks from the second, so a benchmark running beside ``make test``
#: never joins a test's domain (a shared domain once made a test count the benchmark's
#: extractor as a subscriber).
TEST_DOMAINS = (101, 165)
RUN_DOMAINS = (166, 230)


def private_domain(rng=None, *, test: bool = False) -> int:
    """A random private ROS domain id from :data:`RUN_DOMAINS` (or :data:`TEST_DOMAINS`)."""
    import random

    lo, hi = TEST_DOMAINS if test else RUN_DOMAINS
    return (rng or random).randint(lo, hi)


#: Blocks at least this large come from mmap [bytes]: above any image we handle.
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: Free memory at the top of the heap kept for reuse rather than returned [bytes].
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024

#: Environment for child processes (glibc reads the MALLOC_* variables at start-up).
ENV = {
    'MALLOC_MMAP_THRESHOLD_': str(MMAP_THRESHOLD_BYTES),
    'MALLOC_TRIM_THRESHOLD_': str(TRIM_THRESHOLD_BYTES),
    'OPENBLAS_NUM_THREADS': '1',
}

#: Fast DDS participant profile with a shared-memory segment that holds many images.
FASTDDS_PROFILE = Path(__file__).with_name('fastdds_profile.xml')
#: Profile for a graph spread over hosts: UDPv4 only, socket buffers for images (its comments).
FASTDDS_MULTIHOST_PROFILE = Path(__file__).with_name('fastdds_multihost.xml')
#: ``GALVOSCAN_DDS`` value -> the profile it selects; unset or empty is ``local``.
FASTDDS_PROFILES = {'local': FASTDDS_PROFILE, 'multihost': FASTDDS_MULTIHOST_PROFILE}
#: Where Fast DDS looks for a default profile: 2.x (ROS 2 Jazzy ships 2.14) reads only
#: ``FASTRTPS_DEFAULT_PROFILES_FILE``, 3.x only ``FASTDDS_DEFAULT_PROFILES_FILE``.
PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')

#: Where Fast DDS keeps its shared-memory files on Linux.
SHM_DIR = Path('/dev/shm')
#: A participant's segment ``fastrtps_<16 hex digits>`` has this lock file beside it, which the
#: owner holds (flock) while it is alive.
SEGMENT_LOCK = re.compile(r'^fastrtps_[0-9a-f]{16}_el$')

# mallopt parameter numbers from glibc's <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def child_env(env: dict | None = None) -> dict:
    """``env`` (default: ``os.environ``) plus :data:`ENV`, without overriding what is set."""
    out = dict(os.environ if env is None else env)
    for key, value in ENV.items():
        out.setdefault(key, value)
    _add_fastdds_profile(out)
    return out


def fastdds_profile(env) -> Path:
    """The galvoscan Fast DDS profile that ``env``'s ``GALVOSCAN_DDS`` selects.

    ``local`` (the default) is :data:`FASTDDS_PROFILE`; ``multihost`` is
    :data:`FASTDDS_MULTIHOST_PROFILE`, which needs discovery beyond this host.

    Parameters
    ----------
    env : mapping
        Environment variables (``os.environ`` or a child's environment).

    Returns
    -------
    Path
        The profile file.

    Raises
    ------
    ValueError
        An unknown ``GALVOSCAN_DDS``, or ``multihost`` with discovery kept on localhost.
    """
    choice = env.get('GALVOSCAN_DDS') or 'local'
    if choice not in FASTDDS_PROFILES:
        raise ValueError(f'GALVOSCAN_DDS={choice!r}: expected one of '
                         f"{', '.join(FASTDDS_PROFILES)}")
    if choice == 'multihost' and (env.get('ROS_AUTOMATIC_DISCOVERY_RANGE') == 'LOCALHOST'
                                  or env.get('ROS_LOCALHOST_ONLY') == '1'):
        raise ValueError('GALVOSCAN_DDS=multihost needs ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET '
                         '(discovery is kept on localhost, and shared memory added back)')
    return FASTDDS_PROFILES[choice]


def _add_fastdds_profile(env) -> None:
    """Point Fast DDS at :func:`fastdds_profile` unless a profile or another RMW is chosen."""
    rmw = env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    if rmw.startswith('rmw_fastrtps') and not any(env.get(k) for k in PROFILE_VARS):
        profile = fastdds_profile(env)
        for key in PROFILE_VARS:
            env[key] = str(profile)


def tune_this_process() -> bool:
    """Apply the malloc thresholds to this process; False where there is no glibc mallopt.

    Also sets the Fast DDS profile (see :func:`child_env`) for participants created after
    this call. The malloc part is skipped (True returned) when the process already got
    ``MALLOC_MMAP_THRESHOLD_`` from its environment, so a user's own setting wins.
    """
    _add_fastdds_profile(os.environ)
    if 'MALLOC_MMAP_THRESHOLD_' in os.environ:
        return True
    name = ctypes.util.find_library('c')
    if not name:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    return mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 and ok


#: prctl option: the signal a process gets when its parent dies (linux/prctl.h).
_PR_SET_PDEATHSIG = 1


def die_with_parent(signum: int = signal.SIGTERM):
    """A ``preexec_fn`` for ``subprocess.Popen``: the child gets ``signum`` when its parent dies.

    A supervisor killed with SIGKILL cannot stop its children; with this, Linux sends them
    ``signum`` (SIGTERM: a node's normal shutdown, which runs its safe-state ``finally``).
    Linux only (``prctl(PR_SET_PDEATHSIG)``); elsewhere the function does nothing.
    If the parent died before the child got there, the child signals itself at once.
    """
    parent = os.getpid()
    name = ctypes.util.find_library('c')

    def preexec() -> None:
        if not name:
            return
        libc = ctypes.CDLL(name, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0) == 0 and os.getppid() != parent:
            os.kill(os.getpid(), signum)

    return preexec


def freeze_startup_heap() -> int:
    """Collect garbage, then exempt every object alive now from later collections.

    Call once the nodes are built, before the first frame. A node process holds about
    160,000 Python objects after start-up (rclpy, numpy, numba, the message types), nearly
    all of them alive until it exits, and every full (generation 2) collection walked them
    all: up to 50 ms in ``benchmarks/pipeline.py`` (one process, 5,000 frames at 500 fps:
    two of them, 74 ms in all), during which no frame moves: 25 frames late at 500 fps, and
    more than the 30-frame queues hold at 1000 fps. After ``gc.freeze()`` a collection walks
    only the objects made since. Returns how many objects are frozen.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def remove_zombie_shm_segments(shm_dir: Path = SHM_DIR) -> list[Path]:
    """Remove the Fast DDS shared-memory segments whose owner process is gone.

    A process that dies without destroying its participant (SIGKILL, a crash) leaves its
    segment in ``shm_dir``; with :data:`FASTDDS_PROFILE` each can hold up to 32 MB of memory
    until the machine restarts. A segment is a zombie when its ``_el`` lock file can be
    locked, which a live owner prevents (Fast DDS's own ``fastdds shm clean`` uses the same
    test). The lock is held while the two files are removed. Files of other users, and
    segments in use, are left alone. Returns the segments removed.
    """
    removed = []
    try:
        names = sorted(os.listdir(shm_dir))
    except OSError:
        return removed
    for name in names:
        if not SEGMENT_LOCK.match(name):
            continue
        lock = Path(shm_dir) / name
        segment = lock.with_name(name[:-3])
        try:
            with open(lock, 'rb') as fd:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                with contextlib.suppress(FileNotFoundError):
                    segment.unlink()
                lock.unlink()
        except OSError:             # in use, another user's, or gone meanwhile
            continue
        removed.append(segment)
    return removed
