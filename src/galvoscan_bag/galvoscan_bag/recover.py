"""Recover a bag whose writer was killed: keep every complete MCAP chunk.

A killed writer leaves an MCAP file without summary and footer (and, with rosbags, no
metadata.yaml), possibly cut inside a record. :func:`recover_bag` reads the file front to back
with ``mcap``'s :class:`~mcap.stream_reader.StreamReader` (the only reader that does not need the
summary), keeps the schema, channel and message records of every *complete* chunk (and of
complete records outside chunks), stops at the first incomplete or damaged record, and writes
the messages into a new, valid rosbag2 directory with rosbags.

Type hashes come from the damaged bag's metadata.yaml when it exists, else they are computed
from the message definitions stored in the MCAP schemas (as rosbags' AnyReader does), so the
recovered bag carries exactly the definitions the recorder wrote. No rclpy here.
"""

from __future__ import annotations

import argparse
import mmap
import os
import shutil
import struct
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.rosbag2 import StoragePlugin
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from .bagdir import BagLayoutError, bag_files, message_type, metadata_topics, offered_qos
from .sections import section_crc_errors
from .writer import _Writer


class RecoveryError(RuntimeError):
    """Nothing can be recovered from the given path; the message says why."""


@dataclass
class RecoveryReport:
    """What :func:`recover_bag` found and wrote."""

    source_files: list[Path]
    output: Path
    chunks: int = 0  # complete chunks read [1]
    messages: int = 0  # messages written to the output [1]
    per_topic: dict[str, int] = field(default_factory=dict)
    complete: bool = False  # every source file ended with a valid footer
    chunks_damaged: int = 0  # chunks skipped: CRC or layout wrong [1]
    damaged: list[str] = field(default_factory=list)  # what was skipped, where and why
    stop_reason: str = ''  # why reading stopped early ('' when complete)
    bytes_dropped: int = 0  # bytes after the last complete record, all files [B]

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = [
            f'recovered {self.messages} messages from {self.chunks} complete chunks '
            f'into {self.output}',
        ]
        for topic, count in sorted(self.per_topic.items()):
            lines.append(f'  {topic}: {count}')
        for line in self.damaged:
            lines.append(f'  LOST: {line}')
        if self.complete:
            lines.append('  source was complete (footer present)')
        else:
            lines.append(f'  source truncated or damaged: {self.stop_reason.rstrip("; ")}')
        return '\n'.join(lines)


def _source_files(source: Path) -> tuple[list[Path], dict]:
    """MCAP files of ``source`` in order, and the parsed metadata.yaml (or {})."""
    try:
        files, metadata = bag_files(source)
    except BagLayoutError as err:
        if source.is_file():  # not an MCAP file: a wrong argument rather than a lost bag
            raise ValueError(str(err)) from None
        raise RecoveryError(str(err)) from None
    return files, metadata


def _hashes_from_metadata(metadata: dict) -> dict[str, str]:
    """RIHS01 hash per message type recorded in metadata.yaml."""
    return {message_type(str(meta['type'])): meta['type_description_hash']
            for meta in metadata_topics(metadata).values()
            if meta.get('type') and meta.get('type_description_hash')}


def _schemaless_types(metadata: dict) -> dict[str, Schema]:
    """Stand-in schemas (no definition) for topics whose metadata.yaml names their type."""
    return {topic: Schema(id=0, data=b'', encoding='ros2msg', name=message_type(str(meta['type'])))
            for topic, meta in metadata_topics(metadata).items() if meta.get('type')}


def _hash_from_definition(schema: Schema) -> str:
    """RIHS01 hash of ``schema``'s type computed from its own stored definition."""
    store = get_typestore(Stores.EMPTY)
    text = schema.data.decode('utf8')
    name = message_type(schema.name)
    if schema.id == 0:  # a schemaless channel's stand-in: the Jazzy store may know the type
        try:
            return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(name)
        except KeyError:
            raise RecoveryError(f'type {name} has neither a definition nor a hash') from None
    if schema.encoding == 'ros2msg':
        store.register(get_types_from_msg(text, name))
    elif schema.encoding == 'ros2idl':
        sep = '=' * 80 + '\n'
        parts = text.split(sep)[1:] if text.startswith(sep + 'IDL: ') else ['\n' + text]
        for part in parts:
            store.register(get_types_from_idl(part.split('\n', 1)[1]))
    else:
        raise RecoveryError(f'schema {schema.name} has unsupported encoding {schema.encoding!r}')
    return store.hash_rihs01(name)


def _chunk_is_complete(chunk: Chunk) -> bool:
    """Check that a chunk was read whole and its records tile it exactly.

    The stream reader trusts the length fields: a short read or a damaged inner length would
    otherwise give truncated messages instead of an error. Compressed chunks are checked by
    their decompressor instead; the CRC, where stored, by ``breakup_chunk``.
    """
    if chunk.compression != '':
        return True
    data = chunk.data
    if len(data) != chunk.uncompressed_size:
        return False
    pos = 0
    while pos + 9 <= len(data):
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        pos += 9 + length
    return pos == len(data)


#: MCAP record opcodes (spec): header .. data end.
_OPCODES = frozenset(range(0x01, 0x10))


def _record_at(data, pos: int):
    """The record at ``pos`` as (record, end, '') or (None, None, why) if it cannot be read."""
    if pos + 9 > len(data):
        return None, None, f'{len(data) - pos} bytes, shorter than a record header'
    opcode = data[pos]
    (length,) = struct.unpack_from('<Q', data, pos + 1)
    end = pos + 9 + length
    if opcode not in _OPCODES:
        return None, None, f'opcode 0x{opcode:02x} is not an MCAP record'
    if end > len(data):
        return None, None, f'record 0x{opcode:02x} claims {length} bytes, past the end'
    try:
        reader = StreamReader(BytesIO(data[pos:end]), skip_magic=True, emit_chunks=True,
                              record_size_limit=None)
        record = next(iter(reader.records))
    except (McapError, ValueError, EOFError, struct.error, StopIteration,
            UnicodeDecodeError) as err:
        return None, None, f'record 0x{opcode:02x}: {err or type(err).__name__}'
    return record, end, ''


def _chunk_records(chunk: Chunk) -> list:
    """The records of a chunk whose layout and CRC check out (else ValueError/McapError)."""
    if not _chunk_is_complete(chunk):
        raise ValueError('its records do not fill it exactly (a damaged length)')
    return breakup_chunk(chunk, validate_crc=True)


def _next_chunk(data, start: int) -> int | None:
    """Offset of the next chunk record at or after ``start`` whose records check out."""
    pos = data.find(b'\x06', start)
    while pos != -1:
        record, _, _ = _record_at(data, pos)
        if isinstance(record, Chunk):
            try:
                _chunk_records(record)
                return pos
            except (McapError, ValueError, EOFError, struct.error):
                pass
        pos = data.find(b'\x06', pos + 1)
    return None


class _Recovery:
    """Copies records from one or more damaged MCAP files into one rosbags Writer."""

    def __init__(self, writer: _Writer, report: RecoveryReport, metadata: dict) -> None:
        self.writer = writer
        self.report = report
        self.hashes = _hashes_from_metadata(metadata)
        self.connections: dict[tuple[str, str], object] = {}
        #: Schemas standing in for schemaless channels: type and definition from metadata.yaml.
        self.schemaless: dict[str, Schema] = _schemaless_types(metadata)

    def read_file(self, path: Path) -> bool:
        """Copy the messages of every intact chunk of ``path``; return whether it had a footer.

        A chunk whose CRC (or record layout) does not check out is skipped and named in the
        report; so is any stretch of unreadable bytes, after which reading resumes at the
        next intact chunk. Reading ends at the footer or at the end of the file.
        """
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        self._seed_from_summary(path, schemas, channels)
        with path.open('rb') as stream:
            size = os.fstat(stream.fileno()).st_size
            if size <= 8:
                self.report.stop_reason += f'{path.name}: no record after the magic; '
                return False
            data = mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ)
            try:
                return self._walk(path, data, schemas, channels)
            finally:
                data.close()

    def _walk(self, path: Path, data, schemas: dict, channels: dict) -> bool:
        size, pos, chunk_no = len(data), 8, 0
        while pos < size:
            record, end, why = _record_at(data, pos)
            if record is None:
                if not any(data[pos:]):  # a zero-filled (preallocated) tail
                    self.report.stop_reason += f'{path.name}: zero-filled tail, no footer; '
                    return False
                resume = _next_chunk(data, pos + 1)
                lost = (resume if resume is not None else size) - pos
                self.report.bytes_dropped += lost
                if resume is None:
                    self.report.stop_reason += (f'{path.name}: dropped the last {lost} bytes '
                                                f'(incomplete or damaged record: {why}); ')
                    return False
                self.report.damaged.append(f'{path.name}: {lost} unreadable bytes at offset '
                                           f'{pos} ({why}); resumed at the next intact chunk')
                pos = resume
                continue
            if isinstance(record, Chunk):
                chunk_no += 1
                try:
                    self._take(_chunk_records(record), schemas, channels)
                    self.report.chunks += 1
                except (McapError, ValueError, EOFError, struct.error) as err:
                    self.report.damaged.append(
                        f'{path.name}: chunk {chunk_no} at offset {pos} ({end - pos} bytes, '
                        f'log time {record.message_start_time}..{record.message_end_time} ns) '
                        f'skipped: {err or type(err).__name__}')
                    self.report.chunks_damaged += 1
            elif isinstance(record, Footer):
                return True
            elif isinstance(record, (Schema, Channel, Message)):
                self._take([record], schemas, channels)
            pos = end
        self.report.stop_reason += f'{path.name}: ends after a complete record, no footer; '
        return False

    def _seed_from_summary(self, path: Path, schemas: dict, channels: dict) -> None:
        """Schemas and channels of an intact summary: chunks after a lost one still resolve."""
        try:
            with path.open('rb') as stream:
                summary = SeekingReader(stream).get_summary()
        except Exception:  # noqa: BLE001 - a killed or damaged file has no usable summary
            return
        if summary is not None:
            schemas.update(summary.schemas)
            channels.update(summary.channels)

    def _take(
        self,
        records: list,
        schemas: dict[int, Schema],
        channels: dict[int, Channel],
    ) -> None:
        """Write the messages of ``records`` once every one of them resolves to a type."""
        new_schemas = dict(schemas)
        new_channels = dict(channels)
        resolved: list[tuple[Channel, Schema, Message]] = []
        for record in records:
            if isinstance(record, Schema):
                new_schemas[record.id] = record
            elif isinstance(record, Channel):
                new_channels[record.id] = record
            elif isinstance(record, Message):
                channel = new_channels.get(record.channel_id)
                if channel is None:
                    raise ValueError(f'message on unknown channel {record.channel_id}')
                schema = new_schemas.get(channel.schema_id)
                if schema is None and channel.schema_id == 0:  # schemaless: type from metadata
                    schema = self.schemaless.get(channel.topic)
                if schema is None:
                    raise ValueError(f'channel {channel.topic} has unknown schema')
                resolved.append((channel, schema, record))
        schemas.update(new_schemas)
        channels.update(new_channels)
        for channel, schema, message in resolved:
            connection = self._connection(channel, schema)
            self.writer.write(connection, message.log_time, message.data)
            self.report.messages += 1
            self.report.per_topic[channel.topic] = self.report.per_topic.get(channel.topic, 0) + 1

    def _connection(self, channel: Channel, schema: Schema) -> object:
        msgtype = message_type(schema.name)
        key = (channel.topic, msgtype)
        connection = self.connections.get(key)
        if connection is None:
            digest = (self.hashes.get(msgtype) or channel.metadata.get('topic_type_hash')
                      or _hash_from_definition(schema))
            connection = self.writer.add_connection(
                channel.topic,
                msgtype,
                msgdef=schema.data.decode('utf8'),
                rihs01=digest,
                serialization_format=channel.message_encoding or 'cdr',
                offered_qos_profiles=offered_qos(channel.metadata.get('offered_qos_profiles')),
            )
            self.connections[key] = connection
            self.report.per_topic.setdefault(channel.topic, 0)
        return connection


def default_output(source: Path | str) -> Path:
    """``<bag>_recovered`` next to the source directory (or ``<stem>_recovered`` for a file)."""
    source = Path(source)
    name = source.stem if source.is_file() else source.name
    return source.parent / f'{name}_recovered'


def recover_bag(source: Path | str, output: Path | str | None = None) -> RecoveryReport:
    """Write every message of every complete chunk of ``source`` into a new bag ``output``.

    Parameters
    ----------
    source : path
        A rosbag2 directory (metadata.yaml optional) or a lone ``.mcap`` file.
    output : path, optional
        New rosbag2 directory; must not exist. Default :func:`default_output`.

    Returns
    -------
    RecoveryReport
        Counts of chunks and messages (per topic), and why reading stopped.

    Raises
    ------
    RecoveryError
        If the source has no MCAP file or is not an MCAP file at all.
    """
    source = Path(source)
    files, metadata = _source_files(source)
    output = default_output(source) if output is None else Path(output)
    if output.exists():
        raise FileExistsError(f'output {output} exists already; choose another path')
    for path in files:
        with path.open('rb') as stream:
            if stream.read(8) != b'\x89MCAP0\r\n':
                raise RecoveryError(f'{path} does not start with the MCAP magic')
    report = RecoveryReport(source_files=files, output=output)
    writer = _Writer(output, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_custom_data('galvoscan.recovered_from', str(source))
    writer.open()
    try:
        recovery = _Recovery(writer, report, metadata)
        complete = True
        for path in files:
            damaged_before = len(report.damaged)
            whole = recovery.read_file(path)
            if whole and len(report.damaged) == damaged_before:
                # every chunk intact: a mismatch is outside them (schema, channel, index)
                report.damaged += [f'{path.name}: {err} (outside every chunk; the chunks '
                                   'recovered are intact)' for err in section_crc_errors(path)]
            complete = whole and complete
        report.complete = complete and not report.damaged
    except BaseException:
        writer.abort()
        shutil.rmtree(output, ignore_errors=True)
        raise
    writer.close()
    return report


def main(argv: Sequence[str] | None = None) -> int:
    """``galvoscan bag-recover SOURCE [-o OUTPUT]``: recover a killed recording."""
    parser = argparse.ArgumentParser(
        prog='galvoscan bag-recover',
        description='Recover a bag whose writer was killed: keep every complete MCAP chunk and '
        'write a new, valid rosbag2 directory.',
    )
    parser.add_argument('source', type=Path, help='bag directory or lone .mcap file')
    parser.add_argument(
        '-o', '--output', type=Path, default=None,
        help='new bag directory (default: <source>_recovered)',
    )
    args = parser.parse_args(argv)
    try:
        report = recover_bag(args.source, args.output)
    except (RecoveryError, FileNotFoundError, FileExistsError, ValueError) as err:
        print(f'bag-recover: error: {err}', file=sys.stderr)
        return 1
    print(report.summary())
    return 0


if __name__ == '__main__':
    sys.exit(main())
