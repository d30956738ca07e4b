"""In-process hand-off (galvoscan_common.intra) between real nodes, with DDS beside it.

A player and the stripe_extractor (``intra_process`` true) share one context and one
EventsExecutor, as in ``galvoscan run --one-process``. The extractor gets each frame once,
handed over; the player publishes over DDS only while a DDS subscriber exists, here the
``galvoscan record`` recorder in another process, which gets every frame published while it
listens. A DDS publisher is not heard by the extractor in that mode.
"""

import signal
import sys
import time

import numpy as np
import pytest
import rclpy
from galvoscan_msgs.msg import GalvoState, StripeCenters
from rclpy.experimental import EventsExecutor
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from galvoscan_bag.reader import read_messages
from galvoscan_common import cdr, intra
from galvoscan_common.cdr import image_to_array, parse_image_cdr
from stripe_extractor.extractor_node import StripeExtractorNode
from stripe_extractor.synthetic import StripeSpec, render, score

pytestmark = pytest.mark.dds

H, W = 120, 160
QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def ctx(ros_env):
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    executor = EventsExecutor(context=context)
    nodes = []
    try:
        yield context, executor, nodes
    finally:
        for n in reversed(nodes):
            n.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)


def spin_until(executor, cond, timeout, what, proc=None):
    deadline = time.monotonic() + timeout
    while not cond():
        if proc is not None:
            assert proc.poll() is None, f'{what}: child died\n{proc.log_path.read_text()}'
        assert time.monotonic() < deadline, f'timeout waiting for {what}' + (
            f'\n{proc.log_path.read_text()}' if proc is not None else '')
        executor.spin_once(timeout_sec=0.02)


def frame(i, rng):
    """(state CDR, image CDR, stripe spec) of frame i, stamped 50 + i s."""
    spec = StripeSpec(v0=rng.uniform(40, 80), slope=rng.uniform(-0.1, 0.1), amplitude=170.0)
    img = render((H, W), spec, noise_dn=3.0, rng=rng)
    header = cdr.Header(50 + i, 1000 + i, 'camera_optical')
    state = cdr.GalvoState(cdr.Header(50 + i, 1000 + i, 'v0'), 700 + i, 0.1 * i, -0.2 * i,
                           0.3, 0.01 * i, True, 0)
    return cdr.serialize_galvo_state(state), cdr.serialize_image(img, header), spec, img


def test_frames_are_handed_over_once_and_published_only_to_dds_listeners(ctx, spawn, tmp_path):
    context, executor, nodes = ctx
    player = Node('player', context=context)
    sink = Node('sink', context=context)
    extractor = StripeExtractorNode(context=context, intra_process_default=True,
                                    extraction_thread_default=False)
    nodes += [player, sink, extractor]
    for n in nodes:
        executor.add_node(n)
    bus = intra.bus_for(context)
    img_pub = intra.HandOffPublisher(player.create_publisher(Image, 'camera/image_raw', QOS),
                                     bus)
    state_pub = intra.HandOffPublisher(
        player.create_publisher(GalvoState, 'galvo/state', QOS), bus)
    centers = []
    sink.create_subscription(StripeCenters, 'stripe/centers', centers.append, 50)
    rng = np.random.default_rng(3)
    sent = {}

    def send(i, image_first=False):
        state, image, spec, img = frame(i, rng)
        sent[50 + i] = (spec, img)
        for pub, data in ((img_pub, image), (state_pub, state))[::1 if image_first else -1]:
            pub.publish(data)

    # 1. Nobody listens over DDS: the extractor has no DDS subscription, frames are handed over.
    assert img_pub.publisher.get_subscription_count() == 0
    assert state_pub.publisher.get_subscription_count() == 0
    for i in range(3):
        send(i, image_first=bool(i % 2))
    spin_until(executor, lambda: len(centers) >= 3, 20, '3 StripeCenters')
    assert (img_pub.handed_off, img_pub.published, state_pub.published) == (3, 0, 0)

    # 2. A recorder in another process subscribes: frames now also go out over DDS.
    bag = tmp_path / 'handoff_bag'
    rec = spawn([sys.executable, '-m', 'galvoscan_bag.record_node', '-o', bag,
                 'camera/image_raw', 'galvo/state'], name='recorder')
    spin_until(executor, lambda: img_pub.publisher.get_subscription_count() >= 1 and
               state_pub.publisher.get_subscription_count() >= 1, 30,
               'the recorder to subscribe', rec)
    time.sleep(0.5)             # writer-side matching can precede the reader side
    for i in range(3, 6):
        send(i)
    spin_until(executor, lambda: len(centers) >= 6, 20, '6 StripeCenters')
    assert (img_pub.handed_off, img_pub.published, state_pub.published) == (6, 3, 3)
    end = time.monotonic() + 1.0            # let the recorder take them, then stop it
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0, rec.log_path.read_text()
    recorded = {}
    for m in read_messages(bag):
        recorded.setdefault(m.topic, []).append(m.data)
    images = [parse_image_cdr(d) for d in recorded['/camera/image_raw']]
    assert [im.stamp_sec for im in images] == [53, 54, 55]
    for im in images:
        np.testing.assert_array_equal(image_to_array(im), sent[im.stamp_sec][1])
    assert [cdr.parse_galvo_state(d).seq for d in recorded['/galvo/state']] == [703, 704, 705]

    # 3. Each frame reached the extractor once, with its state; centres near the truth.
    assert sorted(m.header.stamp.sec for m in centers) == list(range(50, 56))
    for m in centers:
        i = m.header.stamp.sec - 50
        assert (m.header.stamp.nanosec, m.galvo.seq, m.galvo.g1_pan_voltage) == (
            1000 + i, 700 + i, pytest.approx(0.1 * i))
        rms, cov, _ = score(np.asarray(m.u), np.asarray(m.v), sent[50 + i][0], W)
        assert cov >= 0.95 and rms <= 0.05
    c = extractor.counters()
    assert (c['images_received'], c['states_received'], c['duplicate_stamps']) == (6, 6, 0)

    # 4. A plain DDS publisher is not heard by an extractor that takes frames in-process.
    dds_img = player.create_publisher(Image, 'camera/image_raw', QOS)
    dds_state = player.create_publisher(GalvoState, 'galvo/state', QOS)
    state, image, _, _ = frame(9, rng)
    dds_state.publish(state)
    dds_img.publish(image)
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    assert extractor.counters()['images_received'] == 6 and len(centers) == 6


def test_a_failing_subscriber_is_counted_and_the_others_still_served(ctx):
    context, executor, nodes = ctx
    node = Node('handoff_errors', context=context)
    nodes.append(node)
    bus = intra.bus_for(context)
    topic = node.resolve_topic_name('errors_topic')
    got, errors = [], []

    def bad(data):
        raise ValueError('subscriber bug')

    bus.subscribe(topic, bad)
    bus.subscribe(topic, got.append)
    pub = intra.HandOffPublisher(node.create_publisher(GalvoState, 'errors_topic', QOS), bus,
                                 errors.append)
    state = cdr.serialize_galvo_state(cdr.GalvoState(cdr.Header(), 1, 0, 0, 0, 0, False, 0))
    pub.publish(state)
    assert got == [state] and pub.errors == 1 and isinstance(errors[0], ValueError)
    with pytest.raises(TypeError, match='bytes'):
        pub.publish(bytearray(state))
    assert got == [state] and pub.handed_off == 2


def test_an_inactive_lifecycle_publisher_hands_nothing_over(ctx):
    context, executor, nodes = ctx
    node = LifecycleNode('handoff_lifecycle', context=context)
    nodes.append(node)
    bus = intra.bus_for(context)
    got = []
    bus.subscribe(node.resolve_topic_name('lc_topic'), got.append)
    pub = intra.HandOffPublisher(node.create_lifecycle_publisher(GalvoState, 'lc_topic', QOS),
                                 bus)
    data = cdr.serialize_galvo_state(cdr.GalvoState(cdr.Header(), 1, 0, 0, 0, 0, False, 0))
    pub.publish(data)
    assert got == [] and pub.handed_off == 0
    node.trigger_configure()
    node.trigger_activate()
    pub.publish(data)
    assert got == [data] and pub.handed_off == 1
