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
import shutil
import struct
import sys
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import Qos
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore


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
        if self.complete:
            lines.append('  source was complete (footer present)')
        else:
            lines.append(f'  source truncated or damaged: {self.stop_reason.rstrip("; ")}')
        return '\n'.join(lines)


def _source_files(source: Path) -> tuple[list[Path], dict]:
    """MCAP files of ``source`` in order, and the parsed metadata.yaml (or {})."""
    if source.is_file():
        if source.suffix != '.mcap':
            raise ValueError(f'source {source} is not a .mcap file or a bag directory')
        return [source], {}
    if not source.is_dir():
        raise FileNotFoundError(f'source {source} does not exist')
    metadata: dict = {}
    files: list[Path] = []
    metapath = source / 'metadata.yaml'
    if metapath.exists():
        try:
            loaded = yaml.safe_load(metapath.read_text(encoding='utf8'))
            metadata = (loaded or {}).get('rosbag2_bagfile_information', {}) or {}
        except yaml.YAMLError:
            metadata = {}
        for name in metadata.get('relative_file_paths', []) or []:
            candidate = source / name
            if candidate.suffix == '.mcap' and candidate.exists():
                files.append(candidate)
    if not files:
        files = sorted(source.glob('*.mcap'))
    if not files:
        raise RecoveryError(f'source {source} holds no .mcap file')
    return files, metadata


def _hashes_from_metadata(metadata: dict) -> dict[str, str]:
    hashes = {}
    for entry in metadata.get('topics_with_message_count', []) or []:
        topic_meta = (entry or {}).get('topic_metadata', {}) or {}
        if topic_meta.get('type') and topic_meta.get('type_description_hash'):
            hashes[topic_meta['type']] = topic_meta['type_description_hash']
    return hashes


def _hash_from_definition(schema: Schema) -> str:
    """RIHS01 hash of ``schema``'s type computed from its own stored definition."""
    store = get_typestore(Stores.EMPTY)
    text = schema.data.decode('utf8')
    if schema.encoding == 'ros2msg':
        store.register(get_types_from_msg(text, schema.name))
    elif schema.encoding == 'ros2idl':
        sep = '=' * 80 + '\n'
        parts = text.split(sep)[1:] if text.startswith(sep + 'IDL: ') else ['\n' + text]
        for part in parts:
            store.register(get_types_from_idl(part.split('\n', 1)[1]))
    else:
        raise RecoveryError(f'schema {schema.name} has unsupported encoding {schema.encoding!r}')
    return store.hash_rihs01(schema.name)


def _qos_of(channel: Channel) -> list[Qos]:
    text = channel.metadata.get('offered_qos_profiles', '')
    if not text:
        return []
    try:
        return parse_qos(text)
    except Exception:  # a damaged or foreign QoS string must not stop a recovery
        return []


def _chunk_is_complete(chunk: Chunk) -> bool:
    """Check that a chunk was read whole and its records tile it exactly.

    The stream reader trusts the length fields: a short read or a damaged inner length would
    otherwise give truncated messages instead of an error. Compressed chunks are checked by
    their decompressor (and CRC) instead.
    """
    if chunk.compression != '':
        return True
    data = chunk.data
    if len(data) != chunk.uncompressed_size:
        return False
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        return False
    pos = 0
    while pos + 9 <= len(data):
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        pos += 9 + length
    return pos == len(data)


class _Recovery:
    """Copies records from one or more damaged MCAP files into one rosbags Writer."""

    def __init__(self, writer: Writer, report: RecoveryReport, hashes: dict[str, str]) -> None:
        self.writer = writer
        self.report = report
        self.hashes = hashes
        self.connections: dict[tuple[str, str], object] = {}

    def read_file(self, path: Path) -> bool:
        """Copy the complete records of ``path``; return whether it ended with a footer."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        size = path.stat().st_size
        used = 0
        with path.open('rb') as stream:
            reader = StreamReader(stream, emit_chunks=True, record_size_limit=2**32)
            try:
                for record in reader.records:
                    if isinstance(record, Chunk):
                        if not _chunk_is_complete(record):
                            raise ValueError('chunk is incomplete or its records do not fit it')
                        inner = breakup_chunk(record, validate_crc=True)
                    else:
                        inner = [record]
                    # Resolve the whole record (chunk) before writing any of it.
                    self._take(inner, schemas, channels)
                    self.report.chunks += isinstance(record, Chunk)
                    used = stream.tell()
                    if isinstance(record, Footer):
                        used = size  # the closing magic follows
                        return True
                reason = 'no footer'
            except (McapError, ValueError, EOFError, OverflowError, struct.error) as err:
                reason = f'{type(err).__name__}: {err}' if str(err) else type(err).__name__
            finally:
                self.report.bytes_dropped += size - used
        if used == size:
            self.report.stop_reason += f'{path.name}: ends after a complete record, no footer; '
        else:
            self.report.stop_reason += (
                f'{path.name}: dropped the last {size - used} bytes (incomplete or damaged '
                f'record: {reason}); '
            )
        return False

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
        key = (channel.topic, schema.name)
        connection = self.connections.get(key)
        if connection is None:
            digest = self.hashes.get(schema.name) or _hash_from_definition(schema)
            connection = self.writer.add_connection(
                channel.topic,
                schema.name,
                msgdef=schema.data.decode('utf8'),
                rihs01=digest,
                serialization_format=channel.message_encoding or 'cdr',
                offered_qos_profiles=_qos_of(channel),
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
    writer = Writer(output, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_custom_data('galvoscan.recovered_from', str(source))
    writer.open()
    try:
        recovery = _Recovery(writer, report, _hashes_from_metadata(metadata))
        complete = True
        for path in files:
            complete = recovery.read_file(path) and complete
        report.complete = complete
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
