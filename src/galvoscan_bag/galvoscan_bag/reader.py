"""Read rosbag2 directories (or a lone, complete MCAP file) as CDR bytes with rosbags.

A bag whose writer was killed has no metadata.yaml and no MCAP summary; rosbags cannot read it.
Such a bag raises :class:`BagReadError` naming ``galvoscan bag-recover`` (:mod:`.recover`).
No rclpy here.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from rosbags.interfaces import ConnectionExtRosbag2, Qos
from rosbags.rosbag2 import Reader
from rosbags.typesys.store import Typestore

from .typestore import default_typestore


class BagReadError(RuntimeError):
    """A bag cannot be read; the message says why and what to do."""


class BagMessage(NamedTuple):
    """One stored message."""

    topic: str
    msgtype: str
    log_time_ns: int  # receive time, ns since the epoch [ns]
    data: bytes  # CDR serialisation, encapsulation header included


class TopicInfo(NamedTuple):
    """One topic of a bag."""

    topic: str
    msgtype: str
    count: int  # messages stored [1]
    msgdef: str  # ros2msg definition text, dependencies included ('' when absent)
    rihs01: str  # type hash 'RIHS01_...' ('' when absent)
    qos: list[Qos]  # publishers' offered QoS as recorded (may be empty)


def _open(path: Path | str) -> Reader:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'bag path {path} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        raise BagReadError(
            f'{path} has no metadata.yaml (was its writer killed?); '
            f'run `galvoscan bag-recover {path}` to make a readable copy'
        )
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:  # rosbags raises several unrelated types for a damaged file
        raise BagReadError(
            f'cannot read bag {path}: {err}; if its writer was killed, run '
            f'`galvoscan bag-recover {path}`'
        ) from err
    return reader


def read_topics(path: Path | str) -> list[TopicInfo]:
    """Topics of the bag at ``path`` (a rosbag2 directory or a complete ``.mcap`` file)."""
    reader = _open(path)
    try:
        infos = []
        for connection in reader.connections:
            ext = connection.ext
            qos = list(ext.offered_qos_profiles) if isinstance(ext, ConnectionExtRosbag2) else []
            infos.append(
                TopicInfo(
                    topic=connection.topic,
                    msgtype=connection.msgtype,
                    count=connection.msgcount,
                    msgdef=connection.msgdef.data or '',
                    rihs01=connection.digest or '',
                    qos=qos,
                )
            )
        return infos
    finally:
        reader.close()


def read_messages(
    path: Path | str, topics: Collection[str] | None = None
) -> Iterator[BagMessage]:
    """Yield the bag's messages in log-time order, optionally only those of ``topics``.

    Topic names are compared as stored (fully qualified, e.g. ``/galvo/state``).
    """
    reader = _open(path)
    try:
        if topics is not None:
            wanted = set(topics)
            unknown = wanted - {c.topic for c in reader.connections}
            if unknown:
                raise ValueError(f'topics {sorted(unknown)} are not in bag {path}')
            connections = [c for c in reader.connections if c.topic in wanted]
        else:
            connections = list(reader.connections)
        if not connections:
            return
        for connection, timestamp, rawdata in reader.messages(connections=connections):
            yield BagMessage(connection.topic, connection.msgtype, timestamp, bytes(rawdata))
    finally:
        reader.close()


def deserialize(message: BagMessage, typestore: Typestore | None = None) -> Any:
    """Decode a :class:`BagMessage` into a rosbags message object."""
    store = default_typestore() if typestore is None else typestore
    return store.deserialize_cdr(message.data, message.msgtype)
