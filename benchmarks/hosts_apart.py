"""Hosts apart: the image path across a network link, DDS over UDP only.

Two Linux network namespaces, each with its own loopback, joined by a veth pair (MTU 1500
unless ``--mtu``), stand for two hosts. In host ``a`` a player stands in for the driver:
it publishes recorded stair-block frames (``camera/image_raw`` and ``galvo/state``,
re-stamped, the driver's QoS) at a fixed rate and is the viewer-side reader of the clouds
(``points``) that come back. Host ``b`` runs ``galvoscan run --nodes
stripe_extractor,reconstructor``. Every process has ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``
and ``ROS_STATIC_PEERS`` set to the other host's address. (The simulator renders about 150
frames/s on one core here, so the driver itself cannot make 500 fps;
``tests/test_hosts_apart_dds.py`` runs the driver.) Both "hosts" share this machine's two
cores, so the CPU time of the receiving side competes with the sender's, which it would
not between real hosts.

Arrangements (Fast DDS profile of every process):
  multihost      ``GALVOSCAN_DDS=multihost``: galvoscan_common/fastdds_multihost.xml
  relay          the link alone: multihost, with a relay in host ``b`` in place of the
                 graph (``pipeline.Relay``: each image it takes answered at once with an
                 empty cloud), so that what is lost is lost on the way, not to a busy
                 extractor; its frame loss is its cloud loss
  udp_defaults   UDPv4 only with Fast DDS's default socket settings (the system's default
                 socket buffers, 4 peers tried per address)
  local          galvoscan's default profile (shared memory + UDP)
  same_host      no link: the graph runs in host ``a`` beside the player, default profile;
                 what this machine gives without the link in the same run (the shared
                 machine's speed varies with the load of other tenants)

Figures per arrangement: ``frame_loss_pct``, the images published in ``a`` that the
extractor in ``b`` never took (its ``images_received`` counter, from its diagnostics);
``cloud_loss_pct``, frames whose cloud never came back to ``a``; ``discovery_s``, from the
player's participant creation (the graph in ``b`` already up) to the first cloud of a
frame it published (``match_s``: to seeing the extractor's image reader); the p50/p99
frame-to-cloud latency; the bytes the veth of ``b`` received per published image (389 kB
when images cross the link), and the kernel's counts in ``b``: UDP datagrams dropped for
a full receive buffer (``udp_rcvbuf_errors``) and IP datagrams not reassembled
(``ip_reasm_fails``); CPU time per published image of the player (sender) and of the
processes in ``b`` (receiver), and the steal time (the share of the machine's CPU time the
hypervisor gave to other guests) and load average while the arrangement ran. (The
player's CPU time is that of its 500 fps run; that of ``b`` is over the player's whole
run, warm-up included, per image published.) Needs root
(``ip netns``). The last stdout line is one JSON object.

    sudo .venv/bin/python benchmarks/hosts_apart.py [--frames 5000] [--rate 500]
                                                    [--mtu 1500] [--only multihost ...]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from galvoscan_common.runtime import private_domain

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pipeline import (  # noqa: E402 - benchmarks/ is no package
    Bench,
    Relay,
    _cpu_ticks,
    load_frames,
    make_bag,
)

#: UDPv4 only, Fast DDS's own transport settings: what the multi-host profile improves on
UDP_DEFAULTS_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors><transport_descriptor>
    <transport_id>udp_defaults</transport_id><type>UDPv4</type>
  </transport_descriptor></transport_descriptors>
  <participant profile_name="udp_defaults" is_default_profile="true"><rtps>
    <userTransports><transport_id>udp_defaults</transport_id></userTransports>
    <useBuiltinTransports>false</useBuiltinTransports>
  </rtps></participant>
</profiles>
"""
ARRANGEMENTS = ('multihost', 'relay', 'udp_defaults', 'local', 'same_host')
#: bytes of one 720x540 mono8 image's pixels
IMAGE_BYTES = 720 * 540


class HostsApart:
    """Two network namespaces ("hosts" ``a`` and ``b``) joined by a veth pair.

    Each has its loopback up and one address on the pair: ``ips[0]`` in ``a``, ``ips[1]``
    in ``b``. Leaving the ``with`` block (also on an error) stops every process still in
    either namespace and removes both (the veth pair goes with them).
    """

    def __init__(self, tag: str | None = None, subnet: str = '10.231.7', mtu: int = 1500):
        tag = tag or str(os.getpid() % 1_000_000)
        self.mtu = int(mtu)
        self.names = (f'gs{tag}a', f'gs{tag}b')          # interface names: <= 15 chars
        self.devs = (f'gs{tag}va', f'gs{tag}vb')
        self.ips = (f'{subnet}.1', f'{subnet}.2')

    @staticmethod
    def unavailable() -> str:
        """Why two namespaces cannot be made here ('' when they can)."""
        if os.geteuid() != 0:
            return 'network namespaces need root'
        if shutil.which('ip') is None:
            return "no 'ip' command (Debian: apt-get install iproute2)"
        probe = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True)
        return '' if probe.returncode == 0 else f'ip netns: {probe.stderr.strip()}'

    def __enter__(self):
        try:
            for name in self.names:
                _ip('netns', 'add', name)
            _ip('link', 'add', self.devs[0], 'type', 'veth', 'peer', 'name', self.devs[1])
            for name, dev, ip in zip(self.names, self.devs, self.ips, strict=True):
                _ip('link', 'set', dev, 'netns', name)
                _ip('-n', name, 'addr', 'add', f'{ip}/24', 'dev', dev)
                _ip('-n', name, 'link', 'set', 'lo', 'up')
                _ip('-n', name, 'link', 'set', dev, 'mtu', str(self.mtu), 'up')
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()

    def exec(self, host: int) -> list[str]:
        """Command prefix that runs a program in host 0 (``a``) or 1 (``b``)."""
        return ['ip', 'netns', 'exec', self.names[host]]

    def close(self) -> None:
        for name in self.names:
            pids = subprocess.run(['ip', 'netns', 'pids', name], capture_output=True,
                                  text=True).stdout.split()
            for sig in (signal.SIGTERM, signal.SIGKILL):
                for pid in pids:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(int(pid), sig)
                deadline = time.monotonic() + 5
                while any(Path(f'/proc/{p}').exists() for p in pids) and \
                        time.monotonic() < deadline:
                    time.sleep(0.05)
            subprocess.run(['ip', 'netns', 'del', name], capture_output=True)
        subprocess.run(['ip', 'link', 'del', self.devs[0]], capture_output=True)

    def link_stats(self, host: int) -> dict:
        """Counters of the host's veth end (``rx_bytes``, ``rx_packets``, ``rx_dropped``...)."""
        out = json.loads(_ip('-n', self.names[host], '-s', '-j', 'link', 'show', 'dev',
                             self.devs[host]))[0]['stats64']
        return {f'{d}_{k}': v for d in ('rx', 'tx') for k, v in out[d].items()}

    def cpu_seconds(self, host: int) -> float:
        """User + system CPU time [s] of the processes now in the host."""
        pids = subprocess.run(['ip', 'netns', 'pids', self.names[host]], capture_output=True,
                              text=True).stdout.split()
        total = 0.0
        for pid in pids:
            try:
                fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
            except OSError:
                continue
            total += (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
        return total

    def snmp(self, host: int) -> dict:
        """The host's ``/proc/net/snmp`` as ``{'Udp.RcvbufErrors': n, ...}``."""
        text = subprocess.run([*self.exec(host), 'cat', '/proc/net/snmp'], check=True,
                              capture_output=True, text=True).stdout.splitlines()
        out = {}
        for head, values in zip(text[::2], text[1::2], strict=True):
            proto, keys = head.split(':')
            out.update({f'{proto}.{k}': int(v) for k, v in zip(
                keys.split(), values.split(':')[1].split(), strict=True)})
        return out


def _ip(*args) -> str:
    proc = subprocess.run(['ip', *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")
    return proc.stdout


def dds_env(arrangement: str, peer: str, domain: int, tmp: Path) -> dict:
    """Environment of every process of an arrangement (``peer``: the other host's address)."""
    from galvoscan_common.runtime import PROFILE_VARS, child_env

    env = {k: v for k, v in os.environ.items()
           if k not in (*PROFILE_VARS, 'GALVOSCAN_DDS', 'ROS_LOCALHOST_ONLY')}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET',
               ROS_STATIC_PEERS=peer, PYTHONUNBUFFERED='1')
    if arrangement == 'multihost':
        env['GALVOSCAN_DDS'] = 'multihost'
    elif arrangement == 'udp_defaults':
        profile = tmp / 'udp_defaults.xml'
        profile.write_text(UDP_DEFAULTS_PROFILE)
        env.update(dict.fromkeys(PROFILE_VARS, str(profile)))
    return child_env(env)


def play(args) -> dict:
    """The player in host ``a``: discovery, then ``args.frames`` frames at ``args.rate``."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node

    from galvoscan_common.runtime import freeze_startup_heap, tune_this_process

    tune_this_process()
    frames = load_frames(args.bag)
    t0 = time.monotonic()
    rclpy.init()
    node = Node('hosts_apart_player')
    ex = EventsExecutor()
    ex.add_node(node)
    try:
        bench = Bench(node, frames, 50.0, 10 ** 9)
        match_s = None
        deadline = t0 + args.timeout
        while not bench.received:        # one frame at a time until a cloud comes back
            if time.monotonic() > deadline:
                raise RuntimeError(f'no cloud came back within {args.timeout} s')
            if match_s is None and node.count_subscribers('camera/image_raw'):
                match_s = time.monotonic() - t0
            bench.publish_due()
            ex.spin_once(timeout_sec=0.005)
        discovery_s = time.monotonic() - t0
        while bench.received < 50 and time.monotonic() < deadline:    # warm-up, 50 fps
            bench.publish_due()
            ex.spin_once(timeout_sec=0.005)
        t_end = time.monotonic() + 1.5                  # drain; a diagnostics message
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        counts0, start_sent = dict(bench.extractor_counts), bench.sent
        bench.rate, bench.total, bench.t0 = args.rate, bench.sent + args.frames, None
        bench.received = 0
        bench.latency.clear()
        freeze_startup_heap()
        cpu0 = time.process_time()
        while bench.sent < bench.total:
            bench.publish_due()
            ex.spin_once(timeout_sec=max(bench.t0 + bench.sent / bench.rate
                                         - time.monotonic(), 0.0))
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and bench.received < args.frames:
            ex.spin_once(timeout_sec=0.01)
        cpu_s = time.process_time() - cpu0
        t_end = time.monotonic() + 1.5                  # the extractor's next diagnostics
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        sent = bench.sent - start_sent
        ext = {k: int(bench.extractor_counts.get(k, 0)) - int(counts0.get(k, 0))
               for k in ('images_received', 'dropped_busy', 'centers_published')}
        lat = np.array(bench.latency) * 1e3
        return {'sent': sent, 'clouds': bench.received, 'extractor': ext,
                'published_total': bench.sent,
                'player_cpu_ms_per_frame': 1e3 * cpu_s / sent,
                'frame_loss_pct': 100.0 * max(sent - ext['images_received'], 0) / sent,
                'cloud_loss_pct': 100.0 * max(sent - bench.received, 0) / sent,
                'discovery_s': discovery_s, 'match_s': match_s,
                'p50_ms': float(np.percentile(lat, 50)) if lat.size else None,
                'p99_ms': float(np.percentile(lat, 99)) if lat.size else None}
    finally:
        node.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown()


def relay() -> None:
    """The relay in host ``b`` (arrangement ``relay``): until SIGINT or SIGTERM."""
    import rclpy
    from rclpy.node import Node

    from galvoscan_common.executor import spin_nodes
    from galvoscan_common.runtime import tune_this_process

    tune_this_process()
    rclpy.init()
    node = Node('relay')
    Relay(node)
    print('ready: relay', flush=True)
    try:
        spin_nodes([node])
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _wait_for_log(path: Path, text: str, proc, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and text in path.read_text(errors='replace')):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f'{path.name}: no {text!r}: '
                               + (path.read_text() if path.exists() else 'no log'))
        time.sleep(0.1)


def run_arrangement(arrangement: str, args, tmp: Path, cal: Path) -> dict:
    """One arrangement in a fresh pair of namespaces."""
    # same_host: the graph beside the player, in host a (the machine's own figures)
    far, profile = (0, 'local') if arrangement == 'same_host' else (1, arrangement)
    profile = 'multihost' if arrangement == 'relay' else profile
    domain = private_domain()
    work = tmp / arrangement
    work.mkdir()
    params = work / 'params.yaml'
    params.write_text(json.dumps({'reconstructor': {'ros__parameters': {
        'calibration_file': str(cal), 'marker_period': 0.0}}}))
    logs = work / 'logs'
    logs.mkdir()
    if arrangement == 'relay':
        far_side = [sys.executable, __file__, '--relay']
        ready = {'far_side.log': 'ready: relay'}
    else:
        far_side = [sys.executable, '-m', 'galvoscan.cli', 'run', '--nodes',
                    'stripe_extractor,reconstructor', '--params', str(params), '--log-dir',
                    str(logs)]
        ready = {'stripe_extractor.log': 'ready:', 'reconstructor.log': 'calibration loaded'}
    with HostsApart(mtu=args.mtu) as hosts, open(logs / 'far_side.log', 'wb') as log:
        graph = subprocess.Popen([*hosts.exec(far), *far_side],
                                 env=dds_env(profile, hosts.ips[0], domain, tmp), stdout=log,
                                 stderr=subprocess.STDOUT)
        try:
            for name, text in ready.items():
                _wait_for_log(logs / name, text, graph, 120)
            link0, snmp0, cpu0 = hosts.link_stats(1), hosts.snmp(far), hosts.cpu_seconds(far)
            ticks0 = _cpu_ticks()
            player = subprocess.run(
                [*hosts.exec(0), sys.executable, __file__, '--player', '--bag', str(args.bag),
                 '--frames', str(args.frames), '--rate', str(args.rate)],
                env=dds_env(profile, hosts.ips[far], domain, tmp), capture_output=True,
                text=True, timeout=args.frames / args.rate + 300)
            if player.returncode != 0:
                raise RuntimeError(f'player failed: {player.stderr[-3000:]}')
            out = json.loads(player.stdout.strip().splitlines()[-1])
            link, snmp, cpu = hosts.link_stats(1), hosts.snmp(far), hosts.cpu_seconds(far)
            ticks = _cpu_ticks() - ticks0
        finally:
            graph.send_signal(signal.SIGINT)
            try:
                graph.wait(timeout=20)
            except subprocess.TimeoutExpired:
                graph.kill()
                graph.wait()
    if arrangement == 'relay':      # each image the relay took came back as a cloud
        out['frame_loss_pct'] = out['cloud_loss_pct']
        out.pop('extractor')
    total = out.pop('published_total')     # warm-up frames included
    out['graph_cpu_ms_per_frame'] = 1e3 * (cpu - cpu0) / total
    out['link_rx_bytes_per_image'] = (link['rx_bytes'] - link0['rx_bytes']) / total
    out['link_rx_dropped'] = link['rx_dropped'] - link0['rx_dropped']
    out['udp_rcvbuf_errors'] = snmp['Udp.RcvbufErrors'] - snmp0['Udp.RcvbufErrors']
    out['ip_reasm_fails'] = snmp['Ip.ReasmFails'] - snmp0['Ip.ReasmFails']
    # the share of the machine's CPU time the hypervisor gave to other guests, and the load
    out['steal_pct'] = 100.0 * ticks[7] / max(ticks.sum(), 1)
    out['load_average_1min'] = os.getloadavg()[0]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=5000, help='frames per arrangement')
    parser.add_argument('--rate', type=float, default=500.0, help='frame rate [1/s]')
    parser.add_argument('--distinct', type=int, default=100, help='distinct recorded frames')
    parser.add_argument('--mtu', type=int, default=1500, help='MTU of the veth pair [bytes]')
    parser.add_argument('--only', choices=ARRANGEMENTS, action='append',
                        help='run only this arrangement (repeatable)')
    parser.add_argument('--player', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--bag', type=Path, help=argparse.SUPPRESS)
    parser.add_argument('--timeout', type=float, default=120.0, help=argparse.SUPPRESS)
    parser.add_argument('--relay', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.relay:
        relay()
        return 0
    if args.player:
        print(json.dumps(play(args)))
        return 0
    why = HostsApart.unavailable()
    if why:
        print(f'hosts_apart: {why}', file=sys.stderr)
        return 2
    from galvoscan.simulated_rig import truth_calibration
    from reconstructor import calibration_file

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        args.bag = tmp / 'frames'
        rig = make_bag(args.bag, args.distinct)
        cal = tmp / 'simulator_truth_for_benchmark.yaml'
        calibration_file.save(truth_calibration(rig), cal)
        print(f'{args.distinct} recorded frames; {args.frames} at {args.rate:g} fps per '
              'arrangement', flush=True)
        for arrangement in args.only or ARRANGEMENTS:
            results[arrangement] = run_arrangement(arrangement, args, tmp, cal)
            print(f'{arrangement}: {results[arrangement]}', flush=True)
    best = results.get('multihost') or next(iter(results.values()))
    print(json.dumps({
        'frames': args.frames, 'fps': args.rate,
        'frame_loss_pct': best['frame_loss_pct'], 'cloud_loss_pct': best['cloud_loss_pct'],
        **{f'{k}_frame_loss_pct': results[k]['frame_loss_pct']
           for k in ('relay', 'udp_defaults', 'local', 'same_host') if k in results},
        'discovery_s': best['discovery_s'], 'match_s': best['match_s'],
        'p99_ms': best['p99_ms'], 'link_rx_bytes_per_image': best['link_rx_bytes_per_image'],
        'udp_rcvbuf_errors': best['udp_rcvbuf_errors'],
        'net_core_rmem_max': int(Path('/proc/sys/net/core/rmem_max').read_text()),
        'mtu': args.mtu,
        'load_average_1min': os.getloadavg()[0],
        'arrangements': results}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
