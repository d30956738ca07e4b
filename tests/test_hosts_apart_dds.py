"""Hosts apart: the graph split over two "hosts", DDS over UDP only.

Two Linux network namespaces, each with its own loopback, joined by a veth pair: the
driver (``galvoscan run --nodes galvo_driver``) and a recorder of ``points`` (the viewer's
side) in host ``a``; extractor and reconstructor (``galvoscan run --nodes
stripe_extractor,reconstructor``) and the scan command in host ``b``. Every process has
``GALVOSCAN_DDS=multihost``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` and the other host in
``ROS_STATIC_PEERS``, what a user sets on each host. Clouds must come back to ``a``, the
images must have crossed the link (the veth counters), no process may map a Fast DDS
shared-memory file, and the UDP sockets must have the profile's buffers. Needs root and
``ip netns`` (skipped otherwise, with the reason). Figures: ``benchmarks/hosts_apart.py``.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from galvoscan_bag.reader import read_messages
from galvoscan_common import cdr
from galvoscan_common.runtime import (
    FASTDDS_MULTIHOST_PROFILE,
    FASTDDS_PROFILE,
    PROFILE_VARS,
    child_env,
    fastdds_profile,
)

ROOT = Path(__file__).resolve().parents[1]
SEED = 11
#: clouds the recorder in host a waits for
CLOUDS = 8
#: the multi-host profile's socket buffers [bytes] (fastdds_multihost.xml)
PROFILE_BUFFER_BYTES = 4 * 1024 * 1024


def _hosts_apart_class():
    """``HostsApart`` of benchmarks/hosts_apart.py: the benchmark and this test share it."""
    spec = importlib.util.spec_from_file_location(
        'hosts_apart_benchmark', ROOT / 'benchmarks' / 'hosts_apart.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.HostsApart, module.IMAGE_BYTES


@pytest.fixture
def hosts():
    """Two namespaces joined by a veth pair; removed (processes in them stopped) always."""
    hosts_apart, _ = _hosts_apart_class()
    why = hosts_apart.unavailable()
    if why:
        pytest.skip(f'hosts apart: {why}')
    with hosts_apart() as pair:
        yield pair


# ---- selecting the profile (no namespaces needed) ---------------------------------------

def test_galvoscan_dds_selects_the_profile():
    assert fastdds_profile({}) == FASTDDS_PROFILE
    assert fastdds_profile({'GALVOSCAN_DDS': 'local'}) == FASTDDS_PROFILE
    multihost = {'GALVOSCAN_DDS': 'multihost', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}
    assert fastdds_profile(multihost) == FASTDDS_MULTIHOST_PROFILE
    env = child_env(multihost)
    assert all(env[k] == str(FASTDDS_MULTIHOST_PROFILE) for k in PROFILE_VARS)
    assert FASTDDS_MULTIHOST_PROFILE.is_file()
    # a profile file of the user's own wins
    own = child_env({**multihost, 'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/my.xml'})
    assert own['FASTRTPS_DEFAULT_PROFILES_FILE'] == '/etc/my.xml'


@pytest.mark.parametrize('env, complaint', [
    ({'GALVOSCAN_DDS': 'multi'}, "GALVOSCAN_DDS='multi'"),
    ({'GALVOSCAN_DDS': 'multihost', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
     'needs ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET'),
    ({'GALVOSCAN_DDS': 'multihost', 'ROS_LOCALHOST_ONLY': '1'}, 'SUBNET'),
])
def test_a_bad_galvoscan_dds_is_refused(env, complaint):
    with pytest.raises(ValueError, match=re.escape(complaint)):
        child_env(env)


def test_galvoscan_run_refuses_a_bad_galvoscan_dds_and_starts_nothing(ros_env, tmp_path):
    env = {**ros_env, 'GALVOSCAN_DDS': 'multi', **dict.fromkeys(PROFILE_VARS, '')}
    proc = subprocess.run(
        [sys.executable, '-m', 'galvoscan.cli', 'run', '--duration', '5', '--log-dir',
         str(tmp_path / 'logs')], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "galvoscan run: GALVOSCAN_DDS='multi'" in proc.stderr
    assert not (tmp_path / 'logs').exists()


# ---- the graph across two namespaces ----------------------------------------------------

def _env(hosts, here: int) -> dict:
    """What a user sets on host ``here``: the multi-host profile, the other host as peer."""
    return {'GALVOSCAN_DDS': 'multihost', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET',
            'ROS_STATIC_PEERS': hosts.ips[1 - here], **dict.fromkeys(PROFILE_VARS, '')}


def _wait_for(path: Path, text: str, proc, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and text in path.read_text(errors='replace')):
        assert proc.poll() is None, proc.log_path.read_text()
        assert time.monotonic() < deadline, \
            f'{path.name} never said {text!r}:\n' + (path.read_text() if path.exists() else '')
        time.sleep(0.2)


def _shm_mappings(hosts) -> dict:
    """``{pid: [Fast DDS shared-memory files it maps]}`` of the processes in both hosts."""
    out = {}
    for name in hosts.names:
        for pid in subprocess.run(['ip', 'netns', 'pids', name], capture_output=True,
                                  text=True).stdout.split():
            try:
                maps = Path(f'/proc/{pid}/maps').read_text()
            except OSError:
                continue
            out[int(pid)] = sorted({line.split()[-1] for line in maps.splitlines()
                                    if '/dev/shm/fast' in line})
    return out


def _udp_receive_buffers(hosts, host: int, pids) -> list[int]:
    """Receive buffer sizes [bytes] (``ss`` skmem ``rb``) of the UDP sockets of ``pids``."""
    out = subprocess.run([*hosts.exec(host), 'ss', '-uanmp'], capture_output=True,
                         text=True, check=True).stdout
    sizes = []
    for block in re.split(r'\n(?=UNCONN|ESTAB)', out):
        owners = {int(p) for p in re.findall(r'pid=(\d+)', block)}
        size = re.search(r'\brb(\d+)', block)
        if size and owners & set(pids):
            sizes.append(int(size.group(1)))
    return sizes


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir('/proc'):
        if entry.isdigit():
            try:
                stat = Path(f'/proc/{entry}/stat').read_text()
            except OSError:
                continue
            if int(stat.rsplit(')', 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return out


@pytest.mark.dds
def test_clouds_cross_between_two_hosts_over_udp(hosts, spawn, tmp_path, sim_graph_params):
    _, image_bytes = _hosts_apart_class()
    params = sim_graph_params(seed=SEED, extractor={'line_width_px': 4.0},
                              reconstructor={'scan_end_timeout': 1.0})
    run = [sys.executable, '-m', 'galvoscan.cli', 'run', '--params', params]
    driver = spawn([*hosts.exec(0), *run, '--nodes', 'galvo_driver', '--log-dir',
                    tmp_path / 'a'], name='host_a_driver', env=_env(hosts, 0))
    graph = spawn([*hosts.exec(1), *run, '--nodes', 'stripe_extractor,reconstructor',
                   '--log-dir', tmp_path / 'b'], name='host_b_graph', env=_env(hosts, 1))
    bag = tmp_path / 'clouds'
    recorder = spawn([*hosts.exec(0), sys.executable, '-m', 'galvoscan.cli', 'record', '-o',
                      bag, '-n', CLOUDS, 'points:sensor_msgs/msg/PointCloud2'],
                     name='host_a_record', env=_env(hosts, 0))
    _wait_for(tmp_path / 'a' / 'galvo_driver.log', 'active', driver)
    _wait_for(tmp_path / 'b' / 'stripe_extractor.log', 'ready:', graph)
    _wait_for(tmp_path / 'b' / 'reconstructor.log', 'calibration loaded', graph)

    # the scan command in host b calls the driver in host a; discovery across the link is
    # not instantaneous, so short scans until the recorder has its clouds
    scan = [*hosts.exec(1), sys.executable, '-m', 'galvoscan.cli', 'scan', '--pattern',
            'raster', '--g1-pan', '0', '0', '--g1-tilt', '0', '0', '--g2-tilt', '-0.3', '0.3',
            '--steps-tilt', '10', '--rate', '50', '--timeout', '30']
    scan_env = {**os.environ, **_env(hosts, 1)}
    deadline = time.monotonic() + 120
    scans = []
    while recorder.poll() is None:
        assert time.monotonic() < deadline, (scans, recorder.log_path.read_text(),
                                             graph.log_path.read_text())
        scans.append(subprocess.run(scan, env=scan_env, capture_output=True, text=True,
                                    timeout=90))
        assert scans[-1].returncode == 0, scans[-1].stdout + scans[-1].stderr
        t_end = time.monotonic() + 3
        while recorder.poll() is None and time.monotonic() < t_end:
            time.sleep(0.1)
    assert recorder.returncode == 0, recorder.log_path.read_text()

    clouds = [cdr.parse_point_cloud(m.data) for m in read_messages(bag, ['/points'])]
    assert len(clouds) == CLOUDS
    for header, points in clouds:
        assert header.frame_id == 'v0'
        assert len(points) > 100
        xyz = np.column_stack([points[c] for c in ('x', 'y', 'z')])
        assert np.isfinite(xyz).all()
    # every image a cloud came from crossed the veth (389 kB each), not shared memory
    assert hosts.link_stats(1)['rx_bytes'] >= CLOUDS * image_bytes
    mapped = _shm_mappings(hosts)
    assert len(mapped) >= 4 and not any(mapped.values()), mapped
    # the extractor's sockets got the profile's buffers (Linux: twice what is asked for,
    # at most twice net.core.rmem_max, which a namespace takes from the host)
    rmem_max = int(Path('/proc/sys/net/core/rmem_max').read_text())
    nodes_b = [p for c in _children(graph.pid) for p in (c, *_children(c))]
    buffers = _udp_receive_buffers(hosts, 1, nodes_b)
    assert buffers and max(buffers) >= 2 * min(PROFILE_BUFFER_BYTES, rmem_max), buffers
    assert driver.poll() is None and graph.poll() is None
