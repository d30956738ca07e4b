"""What a rosbag2 bag is made of, for the reader and the recovery (no rclpy).

- :func:`bag_files`: the MCAP files of a bag (a directory with or without ``metadata.yaml``,
  or one ``.mcap`` file) and its parsed metadata, any metadata version;
- :func:`message_type`: the ROS type name of an MCAP schema, ``pkg/msg/Name`` even where an
  older rosbag2 wrote ``pkg/Name``;
- :func:`offered_qos`: the QoS profiles a channel (or metadata entry) recorded.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import parse_qos


class BagLayoutError(ValueError):
    """The path is not a bag: the message says why."""


def bag_files(path: Path | str) -> tuple[list[Path], dict]:
    """The MCAP files of a bag, in recording order, and its metadata (``{}`` when none).

    ``metadata.yaml``'s ``relative_file_paths`` order the files when it lists existing
    ``.mcap`` files; otherwise every ``*.mcap`` of the directory is taken, by name (a bag
    whose writer was killed before writing metadata, or a copied set of files).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    BagLayoutError
        A file that is not ``.mcap``, a directory without ``.mcap`` files, or a
        ``metadata.yaml`` of another storage (e.g. sqlite3).
    """
    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f'bag path {source} does not exist')
    if source.is_file():
        if source.suffix != '.mcap':
            raise BagLayoutError(f'{source} is not a .mcap file or a bag directory')
        return [source], {}
    metadata = _metadata(source / 'metadata.yaml')
    storage = metadata.get('storage_identifier')
    if storage not in (None, '', 'mcap'):
        raise BagLayoutError(f'{source} is a {storage} bag; galvoscan reads MCAP bags only')
    files = []
    for name in metadata.get('relative_file_paths', []) or []:
        candidate = source / str(name)
        if candidate.suffix == '.mcap' and candidate.is_file():
            files.append(candidate)
    if not files:
        files = sorted(p for p in source.glob('*.mcap') if p.is_file())
    if not files:
        raise BagLayoutError(f'{source} holds no .mcap file')
    return files, metadata


def _metadata(path: Path) -> dict:
    """``rosbag2_bagfile_information`` of a metadata.yaml, ``{}`` when absent or unreadable."""
    if not path.is_file():
        return {}
    try:
        loaded = yaml.safe_load(path.read_text(encoding='utf8'))
    except (yaml.YAMLError, UnicodeDecodeError, OSError):
        return {}
    info = loaded.get('rosbag2_bagfile_information') if isinstance(loaded, dict) else None
    return info if isinstance(info, dict) else {}


def metadata_topics(metadata: dict) -> dict[str, dict]:
    """``topic_metadata`` of every topic in a bag's metadata, by topic name."""
    out = {}
    for entry in metadata.get('topics_with_message_count', []) or []:
        meta = (entry or {}).get('topic_metadata') if isinstance(entry, dict) else None
        if isinstance(meta, dict) and isinstance(meta.get('name'), str):
            out[meta['name']] = meta
    return out


def message_type(schema_name: str) -> str:
    """``pkg/msg/Name`` for an MCAP schema name; ``pkg/Name`` (older rosbag2) gains ``/msg/``."""
    parts = schema_name.split('/')
    if len(parts) == 2 and all(parts):
        return f'{parts[0]}/msg/{parts[1]}'
    return schema_name


def offered_qos(profiles) -> list[Qos]:
    """QoS profiles from a channel's ``offered_qos_profiles`` (YAML text or list); [] if none.

    A damaged or foreign QoS text gives [] (the profiles are advice for replay, never a
    reason to lose messages).
    """
    if not profiles:
        return []
    try:
        return parse_qos(profiles)
    except Exception:  # noqa: BLE001 - rosbags raises several types for foreign QoS text
        return []
