"""Recorder and player as real processes over DDS: record, replay, SIGINT/SIGTERM, SIGKILL.

Messages are published from the test as CDR bytes (``publish(bytes)`` is rclpy's raw publish)
and received with raw subscriptions. Fast DDS delivers a payload zero-padded to a multiple of
4 bytes, so what any subscriber (the recorder included) receives is :func:`padded` of what was
sent; from the bag on, replayed bytes are identical to recorded bytes. Each test uses its own
random ROS_DOMAIN_ID, passed to the children.
"""

import os
import random
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from galvoscan_msgs.msg import GalvoState, StripeCenters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from galvoscan_bag.reader import BagReadError, read_messages, read_topics
from galvoscan_bag.recover import recover_bag
from galvoscan_bag.ros_messages import write_ros_bag

pytestmark = pytest.mark.dds

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


# -- independent MCAP walker (see the MCAP spec): messages of complete chunks ---------------


def complete_chunk_messages(path):
    """[(topic, log_time, bytes)] of the complete chunks of a possibly truncated MCAP file."""
    data = Path(path).read_bytes() if Path(path).exists() else b''
    if len(data) < 8:
        return []
    pos, topics, out = 8, {}, []
    while pos + 9 <= len(data):
        op, length = struct.unpack_from('<BQ', data, pos)
        if pos + 9 + length > len(data):
            break
        if op == 0x04:  # channel record between chunks
            cid, _, tlen = struct.unpack_from('<HHI', data, pos + 9)
            topics[cid] = data[pos + 9 + 8 : pos + 9 + 8 + tlen].decode()
        if op == 0x06:
            (n,) = struct.unpack_from('<I', data, pos + 9 + 28)
            start = pos + 9 + 28 + 4 + n + 8
            inner = data[start : pos + 9 + length]
            q = 0
            while q < len(inner):
                iop, ilen = struct.unpack_from('<BQ', inner, q)
                body = inner[q + 9 : q + 9 + ilen]
                if iop == 0x04:
                    cid, _, tlen = struct.unpack_from('<HHI', body, 0)
                    topics[cid] = body[8 : 8 + tlen].decode()
                elif iop == 0x05:
                    cid, _, log_time, _ = struct.unpack_from('<HIQQ', body, 0)
                    out.append((topics[cid], log_time, bytes(body[22:])))
                q += 9 + ilen
        pos += 9 + length
    return out


def padded(data):
    """``data`` as a DDS subscriber receives it: zero-padded to a multiple of 4 bytes."""
    return data + bytes(-len(data) % 4)


# -- messages --------------------------------------------------------------------------------


def galvo_state(i):
    msg = GalvoState()
    msg.header = Header(stamp=Time(sec=1_700_000_000, nanosec=i * 2_000_000), frame_id='v0')
    msg.seq = i
    msg.g1_pan_voltage, msg.g1_tilt_voltage = 0.01 * i, -2.0 + 0.001 * i
    msg.g2_pan_voltage, msg.g2_tilt_voltage = 1.25, -0.02 * i
    msg.laser_on = True
    msg.status = GalvoState.STATUS_SETTLED
    return serialize_message(msg)


def stripe_centers(i):
    msg = StripeCenters()
    msg.header = Header(stamp=Time(sec=1_700_000_000, nanosec=i), frame_id='camera_optical')
    msg.image_width, msg.image_height = 720, 540
    rng = np.random.default_rng(i)
    n = 100 + i
    msg.u = np.arange(n, dtype=np.float32).tolist()
    msg.v = rng.uniform(0, 539, n).astype(np.float32).tolist()
    msg.width = rng.uniform(3, 6, n).astype(np.float32).tolist()
    msg.strength = rng.uniform(5, 250, n).astype(np.float32).tolist()
    msg.method = 'steger'
    msg.sigma = 2.0
    return serialize_message(msg)


def image(i):
    msg = Image()
    msg.header = Header(stamp=Time(sec=1_700_000_000, nanosec=i), frame_id='camera_optical')
    msg.height, msg.width, msg.encoding, msg.step = 540, 720, 'mono8', 720
    msg.data = np.random.default_rng(i).integers(0, 256, 540 * 720, np.uint8).tobytes()
    return serialize_message(msg)


# -- processes ---------------------------------------------------------------------------------


class Child:
    """A child process whose output goes to a log file."""

    def __init__(self, module, args, env, log_path):
        self.log_path = log_path
        self._log = open(log_path, 'w')  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [sys.executable, '-m', module, *args], env=env, stdout=self._log,
            stderr=subprocess.STDOUT,
        )

    def log(self):
        self._log.flush()
        return self.log_path.read_text()

    def send(self, sig):
        self.proc.send_signal(sig)

    def wait(self, timeout):
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f'child did not exit within {timeout} s; log:\n{self.log()}')

    def stop(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self._log.close()


@pytest.fixture
def ros(monkeypatch):
    """rclpy in the test process on a fresh random domain; yields (node, executor, env)."""
    domain = random.randint(100, 200)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['PYTHONUNBUFFERED'] = '1'
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node('bag_dds_test')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    children = []
    try:
        yield node, executor, env, children
    finally:
        for child in children:
            child.stop()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


def wait_until(condition, timeout, what, executor=None, children=(), watch=()):
    """Poll ``condition``; fail early if a child of ``children`` exits or one of ``watch``
    fails (exits non-zero)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return
        for child in (*children, *watch):
            code = child.proc.poll()
            if code is not None and (child in children or code != 0):
                pytest.fail(f'child exited ({code}) while waiting for {what}:\n{child.log()}')
        if executor is not None:
            executor.spin_once(timeout_sec=0.02)
        else:
            time.sleep(0.02)
    logs = '\n'.join(child.log() for child in (*children, *watch))
    pytest.fail(f'timed out after {timeout} s waiting for {what}\n{logs}')


def start_recorder(tmp_path, env, children, bag, *args):
    child = Child(
        'galvoscan_bag.record_node', ['-o', str(bag), *args], env, tmp_path / 'rec.log'
    )
    children.append(child)
    return child


def publish_all(node, batches):
    """Create one publisher per topic; return them (callers wait for subscribers)."""
    return {topic: node.create_publisher(msgtype, topic, QOS) for topic, msgtype in batches}


# -- tests -----------------------------------------------------------------------------------


def test_record_then_replay_identical_bytes(ros, tmp_path):
    node, executor, env, children = ros
    bag = tmp_path / 'bag'
    recorder = start_recorder(
        tmp_path, env, children, bag, 'galvo/state', 'stripe/centers', 'camera/image_raw',
        '--flush-interval', '0.2',
    )
    originals = {
        '/galvo/state': [galvo_state(i) for i in range(30)],
        '/stripe/centers': [stripe_centers(i) for i in range(30)],
        '/camera/image_raw': [image(i) for i in range(3)],
    }
    types = {'/galvo/state': GalvoState, '/stripe/centers': StripeCenters,
             '/camera/image_raw': Image}
    pubs = publish_all(node, types.items())
    wait_until(
        lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 30,
        'the recorder to subscribe', children=children,
    )
    before = time.time_ns()
    for i in range(30):
        pubs['/galvo/state'].publish(originals['/galvo/state'][i])
        pubs['/stripe/centers'].publish(originals['/stripe/centers'][i])
        if i % 10 == 0:
            pubs['/camera/image_raw'].publish(originals['/camera/image_raw'][i // 10])
        time.sleep(0.003)
    # Wait until every message is in a flushed chunk on disk, then stop with SIGINT.
    wait_until(
        lambda: len(complete_chunk_messages(bag / 'bag.mcap')) == 63, 20,
        'all 63 messages flushed', children=children,
    )
    after = time.time_ns()
    recorder.send(signal.SIGINT)
    assert recorder.wait(20) == 0, recorder.log()
    assert (bag / 'metadata.yaml').exists()
    assert 'recorded 63 messages' in recorder.log()

    recorded = list(read_messages(bag))
    for topic, expected in originals.items():
        assert [m.data for m in recorded if m.topic == topic] == [padded(d) for d in expected]
    assert all(before <= m.log_time_ns <= after for m in recorded)
    assert {t.topic: t.msgtype for t in read_topics(bag)} == {
        '/galvo/state': 'galvoscan_msgs/msg/GalvoState',
        '/stripe/centers': 'galvoscan_msgs/msg/StripeCenters',
        '/camera/image_raw': 'sensor_msgs/msg/Image',
    }

    # Replay (remapping one topic) into raw subscriptions of the test.
    for pub in pubs.values():
        node.destroy_publisher(pub)
    received = {topic: [] for topic in originals}
    out_names = {'/galvo/state': '/replayed/galvo_state'}
    for topic, msgtype in types.items():
        node.create_subscription(
            msgtype, out_names.get(topic, topic),
            lambda data, topic=topic: received[topic].append(data), QOS, raw=True,
        )
    player = Child(
        'galvoscan_bag.replay_node',
        [str(bag), '--rate', '2', '--wait-subscribers', '1',
         '--remap', 'galvo/state:=/replayed/galvo_state'],
        env, tmp_path / 'play.log',
    )
    children.append(player)
    wait_until(
        lambda: all(len(received[t]) == len(originals[t]) for t in originals), 30,
        'the replayed messages', executor=executor, watch=[player],
    )
    assert player.wait(20) == 0, player.log()
    assert 'published 63 messages' in player.log()
    for topic in originals:  # byte-identical to the bag
        assert received[topic] == [m.data for m in recorded if m.topic == topic], topic


def test_sigkill_then_recover_keeps_complete_chunks(ros, tmp_path):
    node, executor, env, children = ros
    bag = tmp_path / 'killed'
    recorder = start_recorder(tmp_path, env, children, bag, 'galvo/state', '--flush-interval',
                              '0.2')
    pub = node.create_publisher(GalvoState, 'galvo/state', QOS)
    wait_until(lambda: pub.get_subscription_count() >= 1, 30, 'the recorder to subscribe',
               children=children)
    sent = [galvo_state(i) for i in range(60)]
    for data in sent[:30]:
        pub.publish(data)
    wait_until(
        lambda: len(complete_chunk_messages(bag / 'killed.mcap')) >= 30, 20,
        'the first batch flushed', children=children,
    )
    for data in sent[30:]:
        pub.publish(data)
    recorder.send(signal.SIGKILL)
    recorder.wait(10)

    assert not (bag / 'metadata.yaml').exists()
    with pytest.raises(BagReadError, match='bag-recover'):
        list(read_messages(bag))
    on_disk = [data for _, _, data in complete_chunk_messages(bag / 'killed.mcap')]
    # Every complete chunk holds messages in the order sent, starting with the whole first batch.
    assert 30 <= len(on_disk) <= 60
    assert on_disk == [padded(d) for d in sent[: len(on_disk)]]

    report = recover_bag(bag, tmp_path / 'recovered')
    assert report.messages == len(on_disk)
    assert [m.data for m in read_messages(tmp_path / 'recovered')] == on_disk


def test_sigterm_stops_a_looping_player_and_a_recorder_cleanly(ros, tmp_path):
    node, executor, env, children = ros
    source = tmp_path / 'source'
    sent = [galvo_state(i) for i in range(5)]
    write_ros_bag(
        source,
        [('/galvo/state', 'galvoscan_msgs/msg/GalvoState', d, 10**9 + i * 20_000_000)
         for i, d in enumerate(sent)],
    )
    bag = tmp_path / 'rerecorded'
    recorder = start_recorder(
        tmp_path, env, children, bag, '/galvo/state', '--qos', 'reliable', '--flush-interval',
        '0.2',
    )
    received = []
    node.create_subscription(GalvoState, '/galvo/state', received.append, QOS, raw=True)
    player = Child(
        'galvoscan_bag.replay_node', [str(source), '--loop', '--wait-subscribers', '2'],
        env, tmp_path / 'play.log',
    )
    children.append(player)
    # Writer-side matching can precede reader-side matching, so the recorder may get the first
    # messages late (reliable repair); wait until it has flushed at least two loops, too.
    mcap = bag / 'rerecorded.mcap'
    wait_until(
        lambda: len(received) >= 12 and len(complete_chunk_messages(mcap)) >= 10,
        30, 'two loops of the bag', executor=executor, children=children,
    )
    player.send(signal.SIGTERM)
    assert player.wait(20) == 0, player.log()
    recorder.send(signal.SIGTERM)
    assert recorder.wait(20) == 0, recorder.log()
    # The loop repeats the bag's messages in order.
    expected = [padded(d) for d in sent]
    assert received[:12] == (expected * 3)[:12]
    recorded = [m.data for m in read_messages(bag)]
    assert len(recorded) >= 10
    start = expected.index(recorded[0])
    assert recorded == (expected * (len(recorded) // 5 + 2))[start : start + len(recorded)]


def test_record_names_an_unusable_folder_and_a_silent_topic(tmp_path):
    """``record -o /proc/x`` is an error without a "recorded 0 messages" summary; a named
    topic that never publishes ends with a warning naming it."""
    env = {**os.environ, 'ROS_DOMAIN_ID': str(random.randint(100, 200))}
    cmd = [sys.executable, '-m', 'galvoscan_bag.record_node']
    bad = subprocess.run([*cmd, '-o', '/proc/galvoscan_bag', '/galvo/state'], env=env,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and '/proc/galvoscan_bag' in bad.stderr
    assert 'recorded' not in bad.stdout and 'Traceback' not in bad.stderr
    quiet = subprocess.run([*cmd, '-o', str(tmp_path / 'q'), '--duration', '1.0',
                            '/never/published'], env=env, capture_output=True, text=True,
                           timeout=60)
    assert quiet.returncode == 0 and 'recorded 0 messages' in quiet.stdout
    assert 'warning: no message on /never/published' in quiet.stderr
