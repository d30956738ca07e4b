"""rclpy side of the bag library (no DDS): CDR interoperability, QoS and argument parsing."""

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from galvoscan_msgs.msg import GalvoState, StripeCenters
from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import QosDurability, QosReliability
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from galvoscan_bag.reader import read_messages
from galvoscan_bag.record_node import DEFAULT_TOPICS, parse_topic_specs
from galvoscan_bag.replay_node import parse_remaps
from galvoscan_bag.ros_messages import (
    import_message_class,
    message_type_name,
    qos_from_rosbags,
    qos_to_rosbags,
    to_cdr,
    write_ros_bag,
)
from galvoscan_bag.typestore import default_typestore

STORE = default_typestore()


def ros_galvo_state(i):
    msg = GalvoState()
    msg.header = Header(stamp=Time(sec=1_700_000_000, nanosec=i * 1000), frame_id='v0')
    msg.seq = i
    msg.g1_pan_voltage = 0.125 * i
    msg.g1_tilt_voltage = -3.5
    msg.g2_pan_voltage = 9.75
    msg.g2_tilt_voltage = -0.001 * i
    msg.laser_on = bool(i % 2)
    msg.status = GalvoState.STATUS_MOVING
    return msg


def ros_stripe_centers(i):
    msg = StripeCenters()
    msg.header = Header(stamp=Time(sec=5, nanosec=i), frame_id='camera_optical')
    msg.galvo = ros_galvo_state(i)
    msg.image_width, msg.image_height = 720, 540
    n = 50 + i
    msg.u = np.arange(n, dtype=np.float32).tolist()
    msg.v = (np.arange(n, dtype=np.float32) * 0.25 + 100).tolist()
    msg.width = [4.5] * n
    msg.strength = [120.0] * n
    msg.method = 'center_of_gravity'
    msg.sigma, msg.min_strength = 1.5, 8.0
    msg.roi_half_height = 10
    msg.orientation = StripeCenters.ORIENTATION_VERTICAL
    msg.rejected_secondary = 2
    msg.saturated_fraction, msg.peak_level = 0.25, 255.0
    return msg


def ros_image(i, width=720, height=540):
    msg = Image()
    msg.header = Header(stamp=Time(sec=5, nanosec=i), frame_id='camera_optical')
    msg.height, msg.width, msg.encoding, msg.step = height, width, 'mono8', width
    msg.data = np.random.default_rng(i).integers(0, 256, height * width, np.uint8).tobytes()
    return msg


@pytest.mark.parametrize(
    'msg', [ros_galvo_state(3), ros_stripe_centers(2), ros_image(1)], ids=type
)
def test_rclpy_and_rosbags_cdr_interoperate(msg):
    msgtype = message_type_name(msg)
    data = serialize_message(msg)
    decoded = STORE.deserialize_cdr(data, msgtype)  # rclpy bytes -> rosbags
    again = bytes(STORE.serialize_cdr(decoded, msgtype))
    # Same length and layout; only alignment padding may differ (rclpy leaves it
    # uninitialised, rosbags writes zeros), so compare the decoded values both ways.
    assert len(again) == len(data)
    assert deserialize_message(again, type(msg)) == msg  # rosbags bytes -> rclpy
    assert decoded.header.frame_id == msg.header.frame_id
    assert decoded.header.stamp.nanosec == msg.header.stamp.nanosec


def test_write_ros_bag_round_trip(tmp_path):
    messages = [ros_galvo_state(i) for i in range(5)] + [ros_stripe_centers(i) for i in range(3)]
    items = [
        ('/galvo/state' if isinstance(m, GalvoState) else '/stripe/centers', None, m, 100 + k)
        for k, m in enumerate(messages)
    ]
    items.append(('/raw', 'galvoscan_msgs/msg/GalvoState', serialize_message(messages[0]), 999))
    counts = write_ros_bag(tmp_path / 'b', items)
    assert counts == {'/galvo/state': 5, '/stripe/centers': 3, '/raw': 1}
    read = list(read_messages(tmp_path / 'b'))
    assert [m.log_time_ns for m in read] == [100 + k for k in range(8)] + [999]
    for message, original in zip(read, messages + [messages[0]], strict=True):
        assert deserialize_message(message.data, type(original)) == original


def test_write_ros_bag_rejects_wrong_type(tmp_path):
    with pytest.raises(ValueError, match='does not match'):
        write_ros_bag(tmp_path / 'b', [('/a', 'sensor_msgs/msg/Image', ros_galvo_state(0), 1)])
    assert not (tmp_path / 'b').exists()
    with pytest.raises(ValueError, match='not an rclpy message'):
        to_cdr(object())


def test_message_type_names():
    assert message_type_name(GalvoState) == 'galvoscan_msgs/msg/GalvoState'
    assert message_type_name(Image()) == 'sensor_msgs/msg/Image'
    assert import_message_class('galvoscan_msgs/msg/StripeCenters') is StripeCenters
    assert import_message_class('sensor_msgs/Image') is Image
    with pytest.raises(ValueError, match='not installed'):
        import_message_class('no_such_pkg/msg/Thing')
    with pytest.raises(ValueError, match='pkg/msg/Name'):
        import_message_class('Image')


def test_qos_conversion():
    reliable_latched = QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL, deadline=Duration(seconds=1.5),
    )
    stored = qos_to_rosbags(reliable_latched)
    assert stored.reliability == QosReliability.RELIABLE
    assert stored.durability == QosDurability.TRANSIENT_LOCAL
    assert (stored.deadline.sec, stored.deadline.nsec) == (1, 500_000_000)
    assert stored.depth == 1
    back = qos_from_rosbags(stored, depth=7)
    assert back.reliability == ReliabilityPolicy.RELIABLE
    assert back.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert back.history == HistoryPolicy.KEEP_LAST and back.depth == 7
    sensor = qos_from_rosbags(qos_to_rosbags(qos_profile_sensor_data), depth=3)
    assert sensor.reliability == ReliabilityPolicy.BEST_EFFORT
    assert sensor.durability == DurabilityPolicy.VOLATILE
    default = qos_from_rosbags(None, depth=2)
    assert default.reliability == ReliabilityPolicy.RELIABLE
    with pytest.raises(ValueError, match='depth'):
        qos_from_rosbags(None, depth=0)


def test_topic_specs_and_remaps():
    assert parse_topic_specs(['galvo/state', '/points', 'x:std_msgs/msg/String', 'y']) == {
        'galvo/state': DEFAULT_TOPICS['galvo/state'],
        '/points': 'sensor_msgs/msg/PointCloud2',
        'x': 'std_msgs/msg/String',
        'y': None,
    }
    with pytest.raises(ValueError, match='bad topic'):
        parse_topic_specs([':std_msgs/msg/String'])
    assert parse_remaps(['galvo/state:=/replayed/state', '/a:=b']) == {
        '/galvo/state': '/replayed/state',
        '/a': '/b',
    }
    with pytest.raises(ValueError, match='FROM:=TO'):
        parse_remaps(['a=b'])
