"""rclpy side of the bag library: message classes, CDR with rclpy, QoS conversion.

:func:`write_ros_bag` is the sample-bag maker: it writes rclpy messages (or CDR bytes, or rosbags
messages) into a rosbag2 directory.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.serialization import serialize_message
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.typesys.store import Typestore

from .writer import ROSBAGS_CHUNK_LIMIT, write_bag


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split ``argv`` into (our arguments, ROS arguments).

    ROS arguments are every ``--ros-args ...`` section up to a ``--`` terminator. Unlike
    ``rclpy.utilities.remove_ros_args`` this leaves ``FROM:=TO`` outside ``--ros-args`` to us.
    """
    ours: list[str] = []
    ros: list[str] = []
    in_ros = False
    for arg in argv:
        if arg == '--ros-args':
            in_ros = True
            ros.append(arg)
        elif in_ros and arg == '--':
            in_ros = False
        elif in_ros:
            ros.append(arg)
        else:
            ours.append(arg)
    return ours, ros


def import_message_class(msgtype: str) -> type:
    """The rclpy message class of ``msgtype`` ('pkg/msg/Name' or 'pkg/Name')."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts) or parts[1] != 'msg':
        raise ValueError(f"msgtype must look like 'pkg/msg/Name', got {msgtype!r}")
    try:
        module = importlib.import_module(f'{parts[0]}.msg')
        return getattr(module, parts[2])
    except (ImportError, AttributeError) as err:
        raise ValueError(f'message type {msgtype} is not installed: {err}') from err


def message_type_name(msg: Any) -> str:
    """'pkg/msg/Name' of an rclpy message (instance or class)."""
    cls = msg if isinstance(msg, type) else type(msg)
    package = cls.__module__.split('.')[0]
    if not hasattr(cls, '_TYPE_SUPPORT') and not hasattr(cls, 'get_fields_and_field_types'):
        raise ValueError(f'{cls.__name__} is not an rclpy message class')
    return f'{package}/msg/{cls.__name__}'


def to_cdr(msg: Any, msgtype: str | None = None) -> tuple[Any, str | None]:
    """rclpy messages become (CDR bytes, type); CDR bytes and rosbags messages pass through."""
    if isinstance(msg, (bytes, bytearray, memoryview)) or hasattr(msg, '__msgtype__'):
        return msg, msgtype
    own_type = message_type_name(msg)
    if msgtype is not None and msgtype != own_type:
        raise ValueError(f'msgtype {msgtype!r} does not match the message type {own_type!r}')
    return serialize_message(msg), own_type


def write_ros_bag(
    path: Path | str,
    messages: Iterable[tuple[str, str | None, Any, int]],
    *,
    typestore: Typestore | None = None,
    chunk_size: int = ROSBAGS_CHUNK_LIMIT,
) -> dict[str, int]:
    """Write ``(topic, msgtype, message, log_time_ns)`` tuples into a new rosbag2 directory.

    ``message`` is an rclpy message (``msgtype`` may then be None), CDR bytes (``msgtype``
    required) or a rosbags message. ``log_time_ns`` is the receive time [ns since the epoch].
    Returns the message count per topic.
    """

    def converted():
        for index, item in enumerate(messages):
            if len(item) != 4:
                raise ValueError(
                    f'messages[{index}] must be (topic, msgtype, message, log_time_ns)'
                )
            topic, msgtype, msg, log_time_ns = item
            data, resolved = to_cdr(msg, msgtype)
            yield topic, resolved, data, log_time_ns

    return write_bag(path, converted(), typestore=typestore, chunk_size=chunk_size)


def _qos_time(duration: Duration) -> QosTime:
    sec, nsec = divmod(int(duration.nanoseconds), 10**9)
    return QosTime(sec, nsec)


def qos_to_rosbags(profile: QoSProfile) -> Qos:
    """A rosbags :class:`Qos` (for metadata.yaml) from an rclpy QoS profile."""

    def enum(cls, value, unknown):
        try:
            return cls(int(value))
        except ValueError:
            return unknown

    return Qos(
        history=enum(QosHistory, profile.history, QosHistory.UNKNOWN),
        depth=int(profile.depth),
        reliability=enum(QosReliability, profile.reliability, QosReliability.UNKNOWN),
        durability=enum(QosDurability, profile.durability, QosDurability.UNKNOWN),
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=enum(QosLiveliness, profile.liveliness, QosLiveliness.UNKNOWN),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def qos_from_rosbags(recorded: Qos | None, depth: int) -> QoSProfile:
    """A KEEP_LAST(``depth``) rclpy profile with a recorded profile's reliability/durability.

    Without a recorded profile (or with an unknown policy) the result is reliable, volatile.
    """
    if depth < 1:
        raise ValueError(f'depth must be >= 1, got {depth}')
    reliability = ReliabilityPolicy.RELIABLE
    durability = DurabilityPolicy.VOLATILE
    if recorded is not None:
        if recorded.reliability == QosReliability.BEST_EFFORT:
            reliability = ReliabilityPolicy.BEST_EFFORT
        if recorded.durability == QosDurability.TRANSIENT_LOCAL:
            durability = DurabilityPolicy.TRANSIENT_LOCAL
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=reliability,
        durability=durability,
        liveliness=LivelinessPolicy.AUTOMATIC,
    )
