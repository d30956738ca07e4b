"""Pipeline benchmark: recorded frames replayed through stripe_extractor and reconstructor.

Frames of the stair block are rendered by the simulator, recorded into a rosbag2 directory
and read back; a player publishes them (cycling, re-stamped with the publish time) at a
fixed rate and a sink receives the PointCloud2 on ``points``.

Arrangements:
  one process, 500 fps   player, extractor, reconstructor and sink on one EventsExecutor;
      the player hands images and states to the extractor in-process, as the driver does
      under ``galvoscan run --one-process`` (``--intra-process false``: over DDS instead)
  one process, 1000 fps
  separate processes, 500 fps   extractor and reconstructor each in its own process

What the machine gives in the same run (this shared machine's speed varies with the load
other tenants put on it, so the targets are read against these):
  floor, 500 fps and 1000 fps   the one-process arrangement with a relay in place of the
      extractor and reconstructor: it takes each image and its state (the same way) and
      answers with an empty PointCloud2 carrying the image's stamp. What the player, the
      executor, rclpy and DDS alone cost per frame and lose on this machine now; no
      pipeline can do better.
  extract_ms_median   single-thread time of ``stripe_extractor.extract`` on the recorded
      frames, before the arrangements.

Figures: dropped frames [%] (frames published whose cloud never arrived), the p99
frame-to-cloud latency [ms] (cloud receipt time minus the image's publish time) and the CPU
time per frame [ms]: of the executor thread and of the whole process (one process), or of
all processes (separate), where frames were lost (the extractor's counters from its
``diagnostics``), and the steal time [%]: the share of the machine's CPU time that the
hypervisor gave to other guests while the arrangement ran. The processes get the malloc,
BLAS and Fast DDS settings of ``galvoscan_common.runtime``, as ``galvoscan run`` gives them.
The last stdout line is one JSON object.

    .venv/bin/python benchmarks/pipeline.py [--frames 10000] [--distinct 100]
                                            [--extraction-thread {default,true,false,auto}]
                                            [--intra-process {true,false}]
                                            [--only ARRANGEMENT ...]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from galvoscan_common.runtime import child_env, freeze_startup_heap, private_domain


def make_bag(path, n, seed=0):
    """Render n stair-block frames and record image + state messages into a bag."""
    from galvoscan_msgs.msg import GalvoState
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    from galvoscan_bag.writer import BagWriter
    from galvoscan_sim import Simulator, load_rig, load_scene, patterns

    rig = load_rig('reference')
    sim = Simulator(rig, load_scene('stair_block'), seed=seed)
    volts = patterns.synchronised(rig, [0.0], -0.3, steps=n, tilt_step=0.6 / n)
    writer = BagWriter(path)
    writer.open()
    writer.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
    writer.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    for i, frame in enumerate(sim.scan(volts)):
        t_ns = 1_000_000_000 + i * 2_000_000
        img = Image(height=frame.image.shape[0], width=frame.image.shape[1],
                    encoding='mono8', step=frame.image.shape[1])
        img.header.stamp.sec, img.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        img.header.frame_id = 'camera_optical'
        img.data = frame.image.tobytes()
        st = GalvoState(seq=i, laser_on=True)
        st.header = img.header
        (st.g1_pan_voltage, st.g1_tilt_voltage, st.g2_pan_voltage,
         st.g2_tilt_voltage) = (float(v) for v in volts[i])
        writer.write('/camera/image_raw', serialize_message(img), t_ns)
        writer.write('/galvo/state', serialize_message(st), t_ns)
    writer.close()
    return rig


def load_frames(path):
    """(image CDR, state CDR) pairs from the bag, in order."""
    from galvoscan_bag.reader import read_messages

    images, states = [], []
    for m in read_messages(path):
        (images if m.topic == '/camera/image_raw' else states).append(bytearray(m.data))
    return list(zip(images, states, strict=True))


class Bench:
    """Player + sink node: publishes re-stamped CDR frames, measures clouds."""

    def __init__(self, node, frames, rate, total, hand_off=False):
        from diagnostic_msgs.msg import DiagnosticArray
        from galvoscan_msgs.msg import GalvoState
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image, PointCloud2

        self.node, self.frames, self.rate, self.total = node, frames, rate, total
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_img = node.create_publisher(Image, 'camera/image_raw', qos)
        self.pub_state = node.create_publisher(GalvoState, 'galvo/state', qos)
        if hand_off:    # as the driver publishes: handed over in-process, DDS if heard there
            from galvoscan_common import intra

            bus = intra.bus_for(node.context)
            self.pub_img = intra.HandOffPublisher(self.pub_img, bus)
            self.pub_state = intra.HandOffPublisher(self.pub_state, bus)
        # raw: the sink reads only the stamp, so its own cost stays out of the figures
        node.create_subscription(PointCloud2, 'points', self._on_cloud,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE),
                                 raw=True)
        node.create_subscription(DiagnosticArray, 'diagnostics', self._on_diagnostics, 10)
        self.extractor_counts = {}
        self.sent = 0
        self.latency = []
        self.received = 0
        self.t0 = None

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if 'stripe extraction' in status.name:
                self.extractor_counts = {kv.key: kv.value for kv in status.values}

    def _on_cloud(self, data):
        now = time.time()
        sec, nsec = struct.unpack_from('<iI', data, 4)   # little-endian CDR: header.stamp
        self.latency.append(now - (sec + nsec * 1e-9))
        self.received += 1

    def publish_due(self):
        if self.t0 is None:
            self.t0 = time.monotonic()
        due = min(int((time.monotonic() - self.t0) * self.rate) + 1, self.total)
        while self.sent < due:
            img, state = self.frames[self.sent % len(self.frames)]
            sec, nsec = divmod(time.time_ns(), 1_000_000_000)
            struct.pack_into('<iI', img, 4, sec, nsec)
            struct.pack_into('<iI', state, 4, sec, nsec)
            self.pub_state.publish(bytes(state))
            self.pub_img.publish(bytes(img))
            self.sent += 1


class Relay:
    """The floor's stand-in for extractor + reconstructor: image and state in, empty cloud out."""

    def __init__(self, node, hand_off=False):
        from galvoscan_msgs.msg import GalvoState
        from rclpy.qos import (
            HistoryPolicy,
            QoSProfile,
            ReliabilityPolicy,
            qos_profile_sensor_data,
        )
        from sensor_msgs.msg import Image, PointCloud2

        from stripe_extractor.extractor_node import IMAGE_QUEUE_DEPTH

        self.empty = np.zeros(0, np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4')]))
        self.pub = node.create_publisher(
            PointCloud2, 'points', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        if hand_off:
            from galvoscan_common import intra

            bus = intra.bus_for(node.context)
            bus.subscribe(node.resolve_topic_name('camera/image_raw'), self._on_image)
            bus.subscribe(node.resolve_topic_name('galvo/state'), lambda data: None)
            return
        node.create_subscription(Image, 'camera/image_raw', self._on_image, QoSProfile(
            depth=IMAGE_QUEUE_DEPTH, reliability=qos_profile_sensor_data.reliability,
            history=HistoryPolicy.KEEP_LAST), raw=True)
        node.create_subscription(GalvoState, 'galvo/state', lambda data: None, QoSProfile(
            depth=50, reliability=ReliabilityPolicy.BEST_EFFORT), raw=True)

    def _on_image(self, data):
        from galvoscan_common import cdr

        sec, nsec = struct.unpack_from('<iI', data, 4)
        self.pub.publish(cdr.serialize_point_cloud(self.empty, cdr.Header(sec, nsec, 'v0')))


#: name: (frame rate [1/s], arrangement: 'one' process, 'separate' processes or the 'floor')
ARRANGEMENTS = {'one_process_500': (500.0, 'one'), 'one_process_1000': (1000.0, 'one'),
                'separate_500': (500.0, 'separate'), 'floor_500': (500.0, 'floor'),
                'floor_1000': (1000.0, 'floor')}


def _children_cpu(procs) -> np.ndarray:
    """User + system CPU time [s] of each running child process (from /proc)."""
    out = np.zeros(len(procs))
    for i, p in enumerate(procs):
        try:
            fields = Path(f'/proc/{p.pid}/stat').read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        out[i] = (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    return out


def _cpu_ticks() -> np.ndarray:
    """The machine's CPU time by state since boot (the ``cpu`` line of /proc/stat)."""
    with open('/proc/stat') as f:
        return np.array(f.readline().split()[1:], dtype=np.int64)


def run(frames, rate, total, arrangement, cal_path, warmup=50, extraction_thread=None,
        intra_process=True):
    """One arrangement; ``extraction_thread`` None keeps the node's default for it.

    ``intra_process``: in the one-process arrangements and the floor, images and states
    are handed over in-process (as ``galvoscan run --one-process`` does), else sent over DDS.
    """
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node

    hand_off = intra_process and arrangement != 'separate'

    domain = private_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('pipeline_bench', context=ctx)
    ex = EventsExecutor(context=ctx)
    ex.add_node(node)
    procs, nodes = [], []
    try:
        if arrangement == 'floor':
            relay = Node('relay', context=ctx)
            Relay(relay, hand_off)
            nodes = [relay]
            ex.add_node(relay)
        elif arrangement == 'one':
            from reconstructor.reconstructor_node import ReconstructorNode
            from stripe_extractor.extractor_node import StripeExtractorNode

            ext = StripeExtractorNode(context=ctx, intra_process_default=hand_off, **(
                {} if extraction_thread is None
                else {'extraction_thread_default': extraction_thread}))
            rec = ReconstructorNode(context=ctx, parameter_overrides=[
                rclpy.parameter.Parameter('calibration_file', value=str(cal_path)),
                rclpy.parameter.Parameter('marker_period', value=0.0)])
            nodes = [ext, rec]
            for n in nodes:
                ex.add_node(n)
        else:
            bin_dir = Path(sys.executable).parent
            env = child_env()
            ext_args = [] if extraction_thread is None else [
                '--ros-args', '-p', f'extraction_thread:={str(extraction_thread).lower()}']
            procs.append(subprocess.Popen([bin_dir / 'stripe_extractor', *ext_args], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            procs.append(subprocess.Popen(
                [bin_dir / 'reconstructor', '--ros-args', '-p',
                 f'calibration_file:={cal_path}', '-p', 'marker_period:=0.0'], env=env,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        # warm-up: until clouds come back (discovery, JIT)
        bench = Bench(node, frames, 50.0, 10 ** 9, hand_off)
        t_end = time.monotonic() + 60
        while bench.received < warmup and time.monotonic() < t_end:
            bench.publish_due()
            ex.spin_once(timeout_sec=0.005)
        if bench.received < warmup:
            raise RuntimeError('warm-up failed: no clouds from the pipeline')
        bench.rate, bench.total = rate, total + bench.sent
        bench.t0 = None
        bench.latency.clear()
        start_sent, bench.received = bench.sent, 0
        # drain clouds of the warm-up still in flight
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        bench.received = 0
        bench.latency.clear()
        bench.t0 = None
        freeze_startup_heap()     # as spin_nodes does for galvoscan run
        cpu0 = (time.thread_time(), time.process_time(), _children_cpu(procs))
        ticks0 = _cpu_ticks()
        counts0 = dict(bench.extractor_counts)
        while bench.sent < bench.total:
            bench.publish_due()
            # wait for events until the next frame is due (an idle spin_once costs CPU)
            ex.spin_once(timeout_sec=max(bench.t0 + bench.sent / bench.rate
                                         - time.monotonic(), 0.0))
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and bench.received < total:
            ex.spin_once(timeout_sec=0.01)
        ticks = _cpu_ticks() - ticks0
        thread_s, process_s, children_s = (b - a for a, b in zip(
            cpu0, (time.thread_time(), time.process_time(), _children_cpu(procs)),
            strict=True))
        t_end = time.monotonic() + 1.5     # one more diagnostics message (1 s period)
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        sent = bench.sent - start_sent
        lat = np.array(bench.latency) * 1e3
        out = {'sent': sent, 'received': bench.received,
               'drop_pct': 100.0 * max(sent - bench.received, 0) / sent,
               'p50_ms': float(np.percentile(lat, 50)) if lat.size else float('nan'),
               'p99_ms': float(np.percentile(lat, 99)) if lat.size else float('nan'),
               'executor_thread_cpu_ms_per_frame': 1e3 * thread_s / sent,
               'cpu_ms_per_frame': 1e3 * (process_s + children_s.sum()) / sent,
               # the share of the machine's CPU time the hypervisor gave to other guests
               'steal_pct': 100.0 * ticks[7] / max(ticks.sum(), 1)}
        if procs:
            out['cpu_ms_per_frame_by_process'] = dict(zip(
                ('player_and_sink', 'stripe_extractor', 'reconstructor'),
                (1e3 * x / sent for x in (process_s, *children_s)), strict=True))
        if arrangement == 'floor':
            return out
        # where frames were lost: not taken by the extractor, dropped at its queue, or later
        out['extractor'] = {k: int(bench.extractor_counts.get(k, 0)) - int(counts0.get(k, 0))
                            for k in ('images_received', 'dropped_busy', 'centers_published',
                                      'frames_offloaded')}
        return out
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        for n in nodes:
            n.destroy_node()
        node.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)


def extract_reference(frames, repeats=3) -> float:
    """Median single-thread time [ms] of ``extract()`` over the recorded frames."""
    from galvoscan_common.cdr import image_to_array, parse_image_cdr
    from stripe_extractor.extractor import extract, warm_up

    warm_up()
    images = [image_to_array(parse_image_cdr(bytes(img))) for img, _ in frames]
    times = []
    for _ in range(repeats):
        for img in images:
            t0 = time.perf_counter()
            extract(img)
            times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=10000, help='frames per arrangement')
    parser.add_argument('--distinct', type=int, default=100, help='distinct recorded frames')
    parser.add_argument('--extraction-thread', choices=('default', 'true', 'false', 'auto'),
                        default='default',
                        help="the extractor's extraction_thread parameter (default: the "
                             "node's own default, auto)")
    parser.add_argument('--intra-process', choices=('true', 'false'), default='true',
                        help='one process and floor: hand images and states over in-process '
                             '(as galvoscan run --one-process does; default) or send them over '
                             'DDS')
    parser.add_argument('--only', choices=ARRANGEMENTS, action='append',
                        help='run only this arrangement (repeatable); the JSON then holds '
                             'null for the others')
    args = parser.parse_args()
    from galvoscan.simulated_rig import truth_calibration
    from galvoscan_common.runtime import tune_this_process
    from reconstructor import calibration_file

    tune_this_process()

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'frames'
        rig = make_bag(bag, args.distinct)
        frames = load_frames(bag)
        cal = Path(tmp) / 'simulator_truth_for_benchmark.yaml'
        calibration_file.save(truth_calibration(rig), cal)
        print(f'{len(frames)} recorded frames in {bag}; {args.frames} per arrangement',
              flush=True)
        skipped = dict.fromkeys(('drop_pct', 'p50_ms', 'p99_ms', 'cpu_ms_per_frame',
                                 'executor_thread_cpu_ms_per_frame'))
        results = dict.fromkeys(ARRANGEMENTS, skipped)
        extract_ms = extract_reference(frames)
        print(f'extract() median {extract_ms:.3f} ms per frame (single thread)', flush=True)
        for key, (rate, arrangement) in ARRANGEMENTS.items():
            if args.only and key not in args.only:
                continue
            r = run(frames, rate, args.frames, arrangement, cal, extraction_thread={
                'default': None, 'true': True, 'false': False, 'auto': 'auto'}[
                    args.extraction_thread], intra_process=args.intra_process == 'true')
            results[key] = r
            print(f'{key}: {r}', flush=True)
        load = os.getloadavg()[0]
    out = {
        'one_process_500_drop_pct': results['one_process_500']['drop_pct'],
        'one_process_500_p99_ms': results['one_process_500']['p99_ms'],
        'one_process_1000_drop_pct': results['one_process_1000']['drop_pct'],
        'separate_500_drop_pct': results['separate_500']['drop_pct'],
        'one_process_500_p50_ms': results['one_process_500']['p50_ms'],
        'separate_500_p99_ms': results['separate_500']['p99_ms'],
        'one_process_500_executor_cpu_ms_per_frame':
            results['one_process_500']['executor_thread_cpu_ms_per_frame'],
        'one_process_500_cpu_ms_per_frame': results['one_process_500']['cpu_ms_per_frame'],
        'separate_500_cpu_ms_per_frame': results['separate_500']['cpu_ms_per_frame'],
        'floor_500_p99_ms': results['floor_500']['p99_ms'],
        'floor_1000_drop_pct': results['floor_1000']['drop_pct'],
        'floor_1000_cpu_ms_per_frame': results['floor_1000']['cpu_ms_per_frame'],
        'extract_ms_median': extract_ms,
        'frames_per_arrangement': args.frames,
        'extraction_thread': args.extraction_thread,
        'intra_process': args.intra_process == 'true',
        'load_average_1min': load,
        'steal_pct': {k: r.get('steal_pct') for k, r in results.items()},
    }
    print(json.dumps(out))


if __name__ == '__main__':
    main()
