"""Read rosbag2 MCAP bags (a directory, one or several files, or a lone file) as CDR bytes.

Built on the ``mcap`` package's indexed reader, independent of the bag's metadata.yaml: a
bag recorded by rosbag2 (Jazzy or older: schema names with or without ``/msg/``, any
metadata version, several files, or no metadata.yaml at all) reads the same as our own,
whatever QoS its metadata and its channels record. Chunk, data-section and summary CRCs
are checked where the writer stored them (:mod:`.sections`); a mismatch raises
:class:`BagReadError` naming ``galvoscan bag-recover``,
which keeps every intact chunk (:mod:`.recover`). So does a file without its summary (a
killed writer). A bag whose summary counts messages that the reader does not yield is an
error, never a silently short result. No rclpy here.
"""

from __future__ import annotations

import heapq
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from rosbags.interfaces import Qos
from rosbags.typesys.store import Typestore

from .bagdir import BagLayoutError, bag_files, message_type, metadata_topics, offered_qos
from .sections import section_crc_errors
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


def _recover_hint(path) -> str:
    return f'run `galvoscan bag-recover {path}` to make a readable copy of every intact chunk'


def _summary(file: Path, fh):
    """The file's summary section (schemas, channels, statistics, chunk index)."""
    try:
        reader = SeekingReader(fh, validate_crcs=True)
        summary = reader.get_summary()
    except (McapError, EOFError, OSError, ValueError, StopIteration) as err:
        raise BagReadError(f'{file} has no readable summary ({err or type(err).__name__}); '
                           f'was its writer killed? {_recover_hint(file.parent)}') from None
    if summary is None:
        raise BagReadError(f'{file} has no summary section; {_recover_hint(file.parent)}')
    return reader, summary


def _channel_counts(file: Path, reader, summary) -> dict[int, int]:
    """Messages per channel id: the statistics record, or counted where a file has none."""
    if summary.statistics is not None:
        return dict(summary.statistics.channel_message_counts)
    counts: dict[int, int] = {}
    try:
        for _, channel, _ in reader.iter_messages(log_time_order=False):
            counts[channel.id] = counts.get(channel.id, 0) + 1
    except (McapError, EOFError, ValueError) as err:
        raise BagReadError(f'{file}: {err}; {_recover_hint(file.parent)}') from None
    return counts


def _topic_type(channel, summary, meta: dict) -> str:
    schema = summary.schemas.get(channel.schema_id)
    if schema is not None and schema.name:
        return message_type(schema.name)
    # schemaless channel: the type recorded in metadata.yaml, if any
    return message_type(str(meta.get(channel.topic, {}).get('type', '')))


def read_topics(path: Path | str) -> list[TopicInfo]:
    """Topics of the bag at ``path`` (a rosbag2 directory or a complete ``.mcap`` file).

    Counts come from the files' statistics; a topic that metadata.yaml lists with no
    channel in any file is listed with count 0.
    """
    files, metadata = _files(path)
    meta = metadata_topics(metadata)
    infos: dict[str, TopicInfo] = {}
    for file in files:
        with open(file, 'rb') as fh:
            reader, summary = _summary(file, fh)
            counts = _channel_counts(file, reader, summary)
            for cid, channel in summary.channels.items():
                known = infos.get(channel.topic)
                count = int(counts.get(cid, 0)) + (known.count if known else 0)
                if known is not None:
                    infos[channel.topic] = known._replace(count=count)
                    continue
                schema = summary.schemas.get(channel.schema_id)
                tmeta = meta.get(channel.topic, {})
                infos[channel.topic] = TopicInfo(
                    topic=channel.topic,
                    msgtype=_topic_type(channel, summary, meta),
                    count=count,
                    msgdef=schema.data.decode('utf8', 'replace') if schema else '',
                    rihs01=channel.metadata.get('topic_type_hash', '')
                    or str(tmeta.get('type_description_hash', '') or ''),
                    qos=offered_qos(channel.metadata.get('offered_qos_profiles')
                                    or tmeta.get('offered_qos_profiles')),
                )
    for topic, tmeta in meta.items():
        if topic not in infos:
            infos[topic] = TopicInfo(topic, message_type(str(tmeta.get('type', ''))), 0, '',
                                     str(tmeta.get('type_description_hash', '') or ''),
                                     offered_qos(tmeta.get('offered_qos_profiles')))
    return list(infos.values())


def _files(path) -> tuple[list[Path], dict]:
    try:
        return bag_files(path)
    except BagLayoutError as err:
        raise BagReadError(str(err)) from None


def read_messages(
    path: Path | str, topics: Collection[str] | None = None
) -> Iterator[BagMessage]:
    """Yield the bag's messages in log-time order, optionally only those of ``topics``.

    Topic names are compared as stored (fully qualified, e.g. ``/galvo/state``). Files of a
    multi-file bag are merged by log time.

    Raises
    ------
    FileNotFoundError
        No such path.
    ValueError
        A requested topic is not in the bag.
    BagReadError
        Not an MCAP bag, a file without summary, a chunk, data-section or summary CRC that
        does not match, or fewer messages than the files' statistics count.
    """
    infos = read_topics(path)
    if topics is not None:
        wanted = set(topics)
        unknown = wanted - {t.topic for t in infos}
        if unknown:
            raise ValueError(f'topics {sorted(unknown)} are not in bag {path}')
    else:
        wanted = {t.topic for t in infos}
    expected = sum(t.count for t in infos if t.topic in wanted)
    if not wanted:
        return
    files, _ = _files(path)
    types = {t.topic: t.msgtype for t in infos}
    streams = [_file_messages(file, wanted, types) for file in files]
    n = 0
    for message in heapq.merge(*streams, key=lambda m: m.log_time_ns):
        n += 1
        yield message
    if n != expected:
        raise BagReadError(f'bag {path}: read {n} messages of {sorted(wanted)} but its '
                           f'files count {expected}; {_recover_hint(path)}')


def _check_sections(file: Path) -> None:
    """The data-section and summary CRCs, where the writer stored them."""
    try:
        errors = section_crc_errors(file)
    except ValueError as err:
        raise BagReadError(f'{file}: {err}; {_recover_hint(file.parent)}') from None
    if errors:
        raise BagReadError(f'{file}: {"; ".join(errors)}; {_recover_hint(file.parent)}')


def _file_messages(file: Path, wanted: set, types: dict) -> Iterator[BagMessage]:
    _check_sections(file)
    with open(file, 'rb') as fh:
        reader, _ = _summary(file, fh)
        try:
            for _, channel, message in reader.iter_messages(topics=sorted(wanted),
                                                            log_time_order=True):
                yield BagMessage(channel.topic, types[channel.topic], message.log_time,
                                 bytes(message.data))
        except (McapError, EOFError, ValueError) as err:
            raise BagReadError(f'{file}: {err}; {_recover_hint(file.parent)}') from None


def deserialize(message: BagMessage, typestore: Typestore | None = None) -> Any:
    """Decode a :class:`BagMessage` into a rosbags message object."""
    store = default_typestore() if typestore is None else typestore
    return store.deserialize_cdr(message.data, message.msgtype)
