"""Write rosbag2 directories (metadata.yaml version 9 + one MCAP file) with rosbags.

Messages are stored as CDR bytes with a receive ("log") time in nanoseconds. Every connection
carries its full ``ros2msg`` definition (dependencies included) and its RIHS01 type hash, so
``ros2 bag``, rosbags' ``AnyReader`` and the ``mcap`` tools can decode galvoscan_msgs without
our sources.

Crash safety: messages are buffered in an in-memory chunk, written when it exceeds 1 MiB.
:class:`BagWriter` additionally closes the pending chunk and flushes the file to the OS when it
reaches ``chunk_size`` bytes or when ``flush_interval`` seconds have passed, so a killed writer
(SIGKILL) loses at most the messages of the last, unflushed chunk. Such a bag has no MCAP
summary and no metadata.yaml; :mod:`.recover` turns it into a valid bag again.

Speed: rosbags' own MCAP storage copies each message about four times through ``BytesIO``
buffers (measured here: 1.1-1.6 ms per 720x540 mono8 image, too slow for 500 fps).
:class:`_ZeroCopyMcapStorage` subclasses it and keeps a chunk as a list of references to the
message bytes, written to the file once when the chunk closes (0.18-0.28 ms per image);
schemas, channels, summary and metadata.yaml are still rosbags' code. It relies on rosbags'
``McapWriter`` internals (``chunk``, ``chunks``, ``bio``, ``close_chunk``), which is why rosbags
is pinned in constraints.txt; the tests read every bag back with rosbags, ``mcap`` and an
independent record walker. No rclpy here.
"""

from __future__ import annotations

import os
import shutil
import struct
import time
import zlib
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Sequence
from io import BytesIO
from pathlib import Path
from typing import Any

from rosbags.interfaces import Connection, MessageDefinitionFormat, Qos
from rosbags.rosbag2 import CompressionMode, StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import (
    Channel,
    McapWriter,
    PendingChunk,
    Schema,
    write_channel,
    write_schema,
    write_string,
)
from rosbags.typesys.store import Typestore

from .sections import write_section_crcs
from .typestore import default_typestore

#: A chunk is always closed above this many bytes (rosbags' value); chunk_size may only be lower.
ROSBAGS_CHUNK_LIMIT = 2**20


class BagWriteError(RuntimeError):
    """A bag cannot be written as asked; the message says why."""


_MESSAGE_HEADER = struct.Struct('<BQHIQQ')  # opcode, record length, channel, seq, log, publish
_CHUNK_HEADER = struct.Struct('<BQQQQIIQ')  # opcode, length, start, end, size, crc, '', size


#: The ROS distribution the bags are written for (metadata.yaml ``ros_distro``).
ROS_DISTRO = 'jazzy'


class _CrcFile:
    """A binary file that keeps the CRC-32 of every byte written, with recent checkpoints.

    ``checkpoints`` maps the offset at the start of each of the last writes to the CRC of all
    bytes before it: the data-section CRC is the one at the DataEnd record's offset.
    """

    def __init__(self, raw, crc: int, offset: int) -> None:
        self.raw = raw
        self.crc = crc
        self.offset = offset
        self.checkpoints: deque[tuple[int, int]] = deque(maxlen=4096)

    def write(self, data) -> int:
        self.checkpoints.append((self.offset, self.crc))
        self.crc = zlib.crc32(data, self.crc)
        self.offset += len(data)
        return self.raw.write(data)

    def crc_before(self, offset: int) -> int | None:
        for at, crc in reversed(self.checkpoints):
            if at == offset:
                return crc
        return None

    def tell(self) -> int:
        return self.offset

    def flush(self) -> None:
        self.raw.flush()

    def fileno(self) -> int:
        return self.raw.fileno()

    def close(self) -> None:
        self.raw.close()


class _ZeroCopyMcapStorage(McapWriter):
    """rosbags' MCAP storage, with chunks kept as a list of byte strings (uncompressed only).

    Schema and channel records still go through ``self.chunk.bio`` as in rosbags; they are moved
    into the part list before each message, so chunk offsets stay exact.
    """

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        if compression != CompressionMode.NONE:
            raise BagWriteError('the zero-copy MCAP storage writes uncompressed chunks only')
        super().__init__(path, compression)
        self._parts: list[bytes] = []
        self.pending_size = 0  # bytes in the pending chunk [B]
        # From here on every byte goes through the CRC tracker (magic and header first).
        self.bio.flush()
        head = self.path.read_bytes()
        self.bio = _CrcFile(self.bio, zlib.crc32(head), len(head))

    def add_msgtype(self, connection: Connection) -> None:
        """rosbags' schema record, written straight to the file (see :meth:`add_connection`)."""
        self.schemas.append(Schema(
            len(self.schemas) + 1, connection.msgtype,
            'ros2msg' if connection.msgdef.format == MessageDefinitionFormat.MSG else 'ros2idl',
            connection.msgdef.data))
        write_schema(self.bio, self.schemas[-1])

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        """rosbags' channel record, plus the ``topic_type_hash`` rosbag2 Jazzy writes.

        Schema and channel records go to the file between chunks, not into the pending
        chunk: a damaged chunk then never takes the types of later chunks with it.
        """
        metadata = BytesIO()
        write_string(metadata, 'offered_qos_profiles')
        write_string(metadata, offered_qos_profiles)
        if connection.digest:
            write_string(metadata, 'topic_type_hash')
            write_string(metadata, connection.digest)
        self.channels.append(Channel(
            connection.id, connection.msgtype, connection.topic,
            connection.ext.serialization_format, metadata.getvalue()))
        self.channel_stats[connection.id] = 0
        write_channel(self.bio, self.channels[-1], self.schemas)

    def _absorb_bio(self) -> None:
        bio = self.chunk.bio
        if bio.tell():
            data = bio.getvalue()
            self._parts.append(data)
            self.pending_size += len(data)
            self.chunk.bio = BytesIO()

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        self._absorb_bio()
        if not isinstance(data, bytes):
            data = bytes(data)
        chunk = self.chunk
        self.message_start_time = min(timestamp, self.message_start_time)
        self.message_end_time = max(timestamp, self.message_end_time)
        self.channel_stats[connection.id] += 1
        chunk.message_start_time = min(timestamp, chunk.message_start_time)
        chunk.message_end_time = max(timestamp, chunk.message_end_time)
        chunk.msgs[connection.id].append((timestamp, self.pending_size))
        header = _MESSAGE_HEADER.pack(0x05, 22 + len(data), connection.id, 0, timestamp, timestamp)
        self._parts.append(header)
        self._parts.append(data)
        self.pending_size += len(header) + len(data)
        if self.pending_size > ROSBAGS_CHUNK_LIMIT:
            self.close_chunk()

    def close_chunk(self) -> None:
        self._absorb_bio()
        chunk, size = self.chunk, self.pending_size
        chunk_start = self.bio.tell()
        crc = 0
        for part in self._parts:
            crc = zlib.crc32(part, crc)
        # Chunk record: start, end, uncompressed size, crc, compression '', data size.
        self.bio.write(
            _CHUNK_HEADER.pack(
                0x06, 8 + 8 + 8 + 4 + 4 + 8 + size, chunk.message_start_time,
                chunk.message_end_time, size, crc, 0, size,
            )
        )
        for part in self._parts:
            self.bio.write(part)
        chunk_end = self.bio.tell()

        offsets: list[tuple[int, int]] = []
        for cid, msgs in chunk.msgs.items():
            offsets.append((cid, self.bio.tell()))
            body = bytearray(struct.pack('<HI', cid, len(msgs) * 16))
            for ts, offset in msgs:
                body += struct.pack('<QQ', ts, offset)
            self.bio.write(struct.pack('<BQ', 0x07, len(body)))
            self.bio.write(body)

        index = BytesIO()  # chunk index record body, kept for the summary (as rosbags does)
        index.write(struct.pack('<QQQQI', chunk.message_start_time, chunk.message_end_time,
                                chunk_start, chunk_end - chunk_start, len(offsets) * 10))
        for cid, offset in offsets:
            index.write(struct.pack('<HQ', cid, offset))
        index.write(struct.pack('<QI', self.bio.tell() - chunk_end, 0))  # index length, ''
        index.write(struct.pack('<QQ', size, size))
        self.chunks.append(index)

        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        self._parts = []
        self.pending_size = 0

    def close(self, version: int, metadata: str) -> None:
        self._absorb_bio()
        if self.pending_size:
            self.close_chunk()
        tracker = self.bio
        metadata = metadata.replace('ros_distro: rosbags', f'ros_distro: {ROS_DISTRO}')
        super().close(version, metadata)
        write_section_crcs(self.path, tracker.crc_before)


class _Writer(Writer):
    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _ZeroCopyMcapStorage}



class BagWriter:
    """Record CDR messages into a new rosbag2 directory.

    Parameters
    ----------
    path : path
        Bag directory to create; it must not exist. The MCAP file is ``<path>/<name>.mcap``.
    typestore : Typestore, optional
        Where message definitions and hashes come from; default Jazzy + galvoscan_msgs.
    chunk_size : int
        Close a chunk once it holds at least this many bytes (1 .. 1 MiB) [bytes].
    flush_interval : float or None
        Close the pending chunk and flush the file at most this long after its first message
        [s]; ``None`` flushes only by size and at close.
    fsync : bool
        Also ``os.fsync`` after each flush (survives power loss, not just a killed process).
    clock : callable
        Monotonic time source [s]; replaceable for tests.
    custom_data : dict of str to str, optional
        Extra ``custom_data`` entries of metadata.yaml.

    Use as a context manager, or call :meth:`open` and :meth:`close` (in a ``finally``).
    """

    def __init__(
        self,
        path: Path | str,
        *,
        typestore: Typestore | None = None,
        chunk_size: int = ROSBAGS_CHUNK_LIMIT,
        flush_interval: float | None = 1.0,
        fsync: bool = False,
        clock: Callable[[], float] = time.monotonic,
        custom_data: dict[str, str] | None = None,
    ) -> None:
        if not isinstance(chunk_size, int) or not 1 <= chunk_size <= ROSBAGS_CHUNK_LIMIT:
            raise ValueError(
                f'chunk_size must be an int in 1..{ROSBAGS_CHUNK_LIMIT}, got {chunk_size!r}'
            )
        if flush_interval is not None and not flush_interval > 0:
            raise ValueError(f'flush_interval must be > 0 s or None, got {flush_interval!r}')
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f'path {self.path} exists already; a bag is never overwritten')
        self.typestore = default_typestore() if typestore is None else typestore
        self.chunk_size = chunk_size
        self.flush_interval = flush_interval
        self.fsync = fsync
        self._clock = clock
        self.custom_data = {'galvoscan.writer': 'galvoscan_bag', **(custom_data or {})}
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self._counts: dict[str, int] = {}
        self._pending_since: float | None = None
        self.chunks_flushed = 0

    # -- life cycle -----------------------------------------------------------------------------

    def open(self) -> BagWriter:
        """Create the bag directory and the MCAP file. Returns self."""
        if self._writer is not None:
            raise BagWriteError(f'bag {self.path} is already open')
        writer = _Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        for key, value in self.custom_data.items():
            writer.set_custom_data(key, value)
        writer.open()
        self._writer = writer
        return self

    @property
    def is_open(self) -> bool:
        """Whether the bag is open for writing."""
        return self._writer is not None

    def close(self) -> None:
        """Write the last chunk, the MCAP summary and metadata.yaml. Idempotent."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            _set_ros_distro(self.path / 'metadata.yaml')

    def abort(self) -> None:
        """Close the file without summary or metadata.yaml (what a crash leaves). Idempotent."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.abort()

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        # Close even after an exception: everything written so far stays readable.
        self.close()

    # -- topics and messages --------------------------------------------------------------------

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """Declare ``topic`` of ``msgtype`` (e.g. ``'galvoscan_msgs/msg/GalvoState'``).

        ``qos`` is the publishers' offered QoS, stored so that a player can offer the same.
        """
        writer = self._require_open()
        if not isinstance(topic, str) or not topic:
            raise ValueError(f'topic must be a non-empty string, got {topic!r}')
        if topic in self._connections:
            if self._connections[topic].msgtype != msgtype:
                raise ValueError(
                    f'topic {topic} already has type {self._connections[topic].msgtype}, '
                    f'not {msgtype}'
                )
            return
        if msgtype not in self.typestore.fielddefs:
            raise ValueError(f'msgtype {msgtype!r} is unknown to the type store')
        self._connections[topic] = writer.add_connection(
            topic, msgtype, typestore=self.typestore, offered_qos_profiles=list(qos)
        )
        self._counts[topic] = 0

    def has_topic(self, topic: str) -> bool:
        """Whether ``topic`` has been declared."""
        return topic in self._connections

    def write(self, topic: str, data: bytes | bytearray | memoryview, log_time_ns: int) -> None:
        """Append one CDR-serialised message of a declared topic.

        Parameters
        ----------
        topic : str
            A topic declared with :meth:`add_topic`.
        data : bytes
            The CDR serialisation (with its 4-byte encapsulation header).
        log_time_ns : int
            Receive time, nanoseconds since the epoch [ns].
        """
        writer = self._require_open()
        connection = self._connections.get(topic)
        if connection is None:
            raise ValueError(f'topic {topic!r} was not declared with add_topic')
        if not isinstance(log_time_ns, int) or not 0 <= log_time_ns < 2**63:
            raise ValueError(f'log_time_ns must be an int in [0, 2**63), got {log_time_ns!r}')
        if len(data) < 4:
            raise ValueError(f'data must be a CDR message (>= 4 bytes), got {len(data)} bytes')
        storage = writer.storage
        chunk_before = storage.chunk
        writer.write(connection, log_time_ns, data)
        self._counts[topic] += 1
        now = self._clock()
        if storage.chunk is not chunk_before:
            # The storage closed a full chunk by itself: push it to the OS now.
            self._flush_file()
            self._pending_since = None
        if self._pending_since is None and storage.chunk.msgs:
            self._pending_since = now
        if storage.pending_size >= self.chunk_size:
            self.flush()
        else:
            self.flush_if_due(now)

    def flush_if_due(self, now: float | None = None) -> bool:
        """:meth:`flush` if the pending chunk is older than ``flush_interval``.

        Call it periodically (e.g. from a timer) so that a quiet recording is flushed too.
        """
        if self.flush_interval is None or self._pending_since is None:
            return False
        now = self._clock() if now is None else now
        if now - self._pending_since >= self.flush_interval:
            return self.flush()
        return False

    def flush(self) -> bool:
        """Close the pending chunk (if it holds messages) and hand the file to the OS.

        Returns whether a chunk was written.
        """
        writer = self._require_open()
        storage = writer.storage
        wrote = False
        if storage.chunk.msgs:
            storage.close_chunk()
            self.chunks_flushed += 1
            wrote = True
        self._flush_file()
        self._pending_since = None
        return wrote

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return dict(self._counts)

    @property
    def mcap_path(self) -> Path:
        """Path of the MCAP file inside the bag directory."""
        return self.path / f'{self.path.name}.mcap'

    def _flush_file(self) -> None:
        bio = self._require_open().storage.bio
        bio.flush()
        if self.fsync:
            os.fsync(bio.fileno())

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise BagWriteError(f'bag {self.path} is not open')
        return self._writer


def serialize(msg: Any, msgtype: str | None, typestore: Typestore | None = None) -> tuple[
    bytes, str
]:
    """CDR bytes and type name of ``msg``.

    ``msg`` is either CDR ``bytes`` (then ``msgtype`` is required) or a rosbags message object of
    ``typestore`` (its ``__msgtype__`` is used when ``msgtype`` is None). rclpy messages are
    handled by :func:`galvoscan_bag.ros_messages.write_ros_bag`.
    """
    if isinstance(msg, (bytes, bytearray, memoryview)):
        if not msgtype:
            raise ValueError('msgtype is required when msg is CDR bytes')
        return bytes(msg), msgtype
    store = default_typestore() if typestore is None else typestore
    own_type = getattr(msg, '__msgtype__', None)
    if own_type is None:
        raise ValueError(
            f'msg of type {type(msg).__name__} is neither CDR bytes nor a rosbags message'
        )
    if msgtype is not None and msgtype != own_type:
        raise ValueError(f'msgtype {msgtype!r} does not match the message type {own_type!r}')
    return bytes(store.serialize_cdr(msg, own_type)), own_type


def write_bag(
    path: Path | str,
    messages: Iterable[tuple[str, str | None, Any, int]],
    *,
    typestore: Typestore | None = None,
    chunk_size: int = ROSBAGS_CHUNK_LIMIT,
) -> dict[str, int]:
    """Write ``(topic, msgtype, message, log_time_ns)`` tuples into a new rosbag2 directory.

    ``message`` is CDR bytes or a rosbags message object (see :func:`serialize`); ``msgtype``
    may be None for the latter. Returns the message count per topic. On error the partial
    directory is removed.
    """
    store = default_typestore() if typestore is None else typestore
    bag = BagWriter(path, typestore=store, chunk_size=chunk_size, flush_interval=None)
    bag.open()
    try:
        for index, item in enumerate(messages):
            if len(item) != 4:
                raise ValueError(
                    f'messages[{index}] must be (topic, msgtype, message, log_time_ns)'
                )
            topic, msgtype, msg, log_time_ns = item
            data, resolved_type = serialize(msg, msgtype, store)
            bag.add_topic(topic, resolved_type)
            bag.write(topic, data, log_time_ns)
    except BaseException:
        bag.abort()
        _remove_tree(bag.path)
        raise
    bag.close()
    return bag.counts


def _set_ros_distro(metapath: Path) -> None:
    """rosbags writes ``ros_distro: rosbags``; the bag is a ROS 2 Jazzy bag."""
    text = metapath.read_text(encoding='utf8')
    fixed = text.replace('ros_distro: rosbags', f'ros_distro: {ROS_DISTRO}')
    if fixed != text:
        tmp = metapath.with_suffix('.yaml.tmp')
        tmp.write_text(fixed, encoding='utf8')
        tmp.replace(metapath)


def _remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
