"""tf2_msgs as built into the venv (msgs_vendor/tf2_msgs) has the type hashes of apt Jazzy's.

A tf2 listener on another host compares the RIHS01 hash that our publisher advertises with
its own; a different hash means "incompatible type" and no transforms. The reference values
are the ones an apt Jazzy install computes, as recorded by a third party:

    carla-simulator/carla, LibCarla/source/test/server/test_type_hash.cpp, commit 0fe520998
    (pull request #9787, "Pin golden hashes", 2026-07): golden hashes "from the REP-2011
    metadata that osrf/ros:jazzy-desktop installs", i.e.
    /opt/ros/jazzy/share/tf2_msgs/msg/TFMessage.json of the apt packages.

The same TFMessage hash appears in `ros2 topic info --verbose /tf` output of Jazzy robots and in
Jazzy rosbag2 metadata.yaml files (type_description_hash) quoted in public notes. The
interface files themselves are upstream's, byte for byte: ros2/geometry2 branch jazzy, commit
646342c6164e837d69460e3d28e7a025396544f6 (release 0.36.4), pinned below by git blob id.
"""

import hashlib
import json
import re
import sys
import time
from pathlib import Path

import pytest
import rclpy
from catkin_pkg.package import parse_package
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from tf2_msgs.msg import TF2Error, TFMessage

from galvoscan_bag.typestore import default_typestore

#: apt Jazzy's hashes (source: the module docstring).
JAZZY = {
    'tf2_msgs/msg/TFMessage':
        'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087',
    'tf2_msgs/msg/TF2Error':
        'RIHS01_db2485e7d6a0ec75bf087e058ee45df682acc3a621ca7780503d10aac141809a',
    'geometry_msgs/msg/TransformStamped':
        'RIHS01_0a241f87d04668d94099cbb5ba11691d5ad32c2f29682e4eb5653424bd275206',
}
#: git blob ids of the upstream files at ros2/geometry2@646342c6 (tf2_msgs/<path>).
UPSTREAM_BLOBS = {
    'msg/TFMessage.msg': 'fda1e4d0985406667d26b7b36cbbedc9bb497074',
    'msg/TF2Error.msg': 'e737b64698facba33e32f9cb934d336c207b20bc',
    'srv/FrameGraph.srv': '568d1965fbcb5c24aeba1006958fb7499f1e37fc',
    'action/LookupTransform.action': '27d35d4bbb602ab614a87c6be3e90bcd035363c4',
}
VENDOR = Path(__file__).resolve().parents[3] / 'msgs_vendor' / 'tf2_msgs'
SHARE = Path(sys.prefix) / 'share'


def rosidl_hashes(package: str, relpath: str) -> dict[str, str]:
    """The hashes rosidl computed at build time (<prefix>/share/<pkg>/<relpath>.json)."""
    path = SHARE / package / f'{relpath}.json'
    if not path.is_file():
        pytest.skip(f'{path} not found: no rosidl build output in this prefix')
    return {h['type_name']: h['hash_string']
            for h in json.loads(path.read_text())['type_hashes']}


def git_blob_id(data: bytes) -> str:
    return hashlib.sha1(b'blob %d\0' % len(data) + data).hexdigest()


@pytest.mark.parametrize('relpath', sorted(UPSTREAM_BLOBS))
def test_interface_files_are_upstreams(relpath):
    assert git_blob_id((VENDOR / relpath).read_bytes()) == UPSTREAM_BLOBS[relpath]


def test_the_package_builds_every_interface_file_it_holds():
    pkg = parse_package(VENDOR / 'package.xml')
    pkg.validate()
    assert pkg.name == 'tf2_msgs' and pkg.version == '0.36.4'
    listed = set(re.findall(r'"((?:msg|srv|action)/\w+\.\w+)"',
                            (VENDOR / 'CMakeLists.txt').read_text()))
    assert listed == set(UPSTREAM_BLOBS)
    on_disk = {str(p.relative_to(VENDOR)) for p in VENDOR.glob('*/*.*')}
    assert on_disk == set(UPSTREAM_BLOBS)


def test_built_hashes_equal_apt_jazzys():
    built = rosidl_hashes('tf2_msgs', 'msg/TFMessage')
    # TFMessage.json lists the message and every type it refers to, each with its hash
    for name in ('tf2_msgs/msg/TFMessage', 'geometry_msgs/msg/TransformStamped'):
        assert built[name] == JAZZY[name], name
    assert rosidl_hashes('tf2_msgs', 'msg/TF2Error')['tf2_msgs/msg/TF2Error'] == \
        JAZZY['tf2_msgs/msg/TF2Error']


def test_referenced_types_agree_with_the_installed_wheels():
    """Every type TFMessage refers to has, in our build, the hash its own wheel installed."""
    built = rosidl_hashes('tf2_msgs', 'msg/TFMessage')
    for name, digest in built.items():
        package, kind, msg = name.split('/')
        if package == 'tf2_msgs':
            continue
        assert rosidl_hashes(package, f'{kind}/{msg}')[name] == digest, name


def test_bag_writer_hash_is_the_same():
    """galvoscan record writes topic_type_hash from this type store (rosbags' own RIHS01)."""
    store = default_typestore()
    for name in ('tf2_msgs/msg/TFMessage', 'geometry_msgs/msg/TransformStamped'):
        assert store.hash_rihs01(name) == JAZZY[name], name


def test_the_hash_a_publisher_advertises(ros_env):
    """What DDS discovery carries to another host: the type hash of the /tf endpoint."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('tf2_msgs_hash_test', context=ctx)
    try:
        node.create_publisher(TFMessage, 'tf', 10)
        node.create_publisher(TransformStamped, 'one_transform', 10)
        node.create_publisher(TF2Error, 'tf_error', 10)
        advertised = {}
        deadline = time.monotonic() + 10
        while len(advertised) < 3 and time.monotonic() < deadline:
            for topic in ('/tf', '/one_transform', '/tf_error'):
                for info in node.get_publishers_info_by_topic(topic):
                    advertised[info.topic_type] = str(info.topic_type_hash)
            time.sleep(0.05)
        assert advertised == JAZZY
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
