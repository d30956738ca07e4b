"""The MCAP file's tail: where the DataEnd and Footer records sit, and their two CRCs (no rclpy).

An MCAP file ends ``... DataEnd [summary section] Footer magic``. The DataEnd record holds
the CRC-32 of every byte before it (leading magic included, so every chunk, schema, channel
and message index); the Footer holds the CRC-32 of the summary section and of the footer
itself up to that CRC. A stored 0 means "not computed" (the MCAP specification), which
writers other than ours often leave. Chunk CRCs are checked by the ``mcap`` reader; this
module checks the other two: the writer fills them in (:mod:`.writer`) and the reader
verifies them (:mod:`.reader`).
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import NamedTuple

MAGIC = b'\x89MCAP0\r\n'
FOOTER_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary start, summary offset start, crc
DATA_END_SIZE = 1 + 8 + 4  # opcode, length, data section crc
_OP_FOOTER, _OP_DATA_END = 0x02, 0x0F
_BLOCK = 8 << 20  # bytes read at a time while checking [bytes]


class Tail(NamedTuple):
    """Offsets [bytes] and stored CRCs of a file's DataEnd and Footer records."""

    data_end: int          # offset of the DataEnd record: the data-section CRC covers [0, this)
    data_crc: int          # stored data-section CRC (0: none)
    summary_start: int     # offset of the summary section (0: the file has none)
    footer_start: int      # offset of the Footer record
    summary_crc: int       # stored summary CRC (0: none)


def read_tail(fh) -> Tail:
    """The DataEnd and Footer of the open MCAP file ``fh`` (binary, seekable).

    Raises
    ------
    ValueError
        The file does not end in a Footer and magic, or no DataEnd record sits where the
        footer says the data section ends.
    """
    size = fh.seek(0, os.SEEK_END)
    if size < len(MAGIC) * 2 + FOOTER_SIZE + DATA_END_SIZE:
        raise ValueError(f'{size} bytes: too short for an MCAP file with a footer')
    footer_start = size - len(MAGIC) - FOOTER_SIZE
    fh.seek(footer_start)
    tail = fh.read(FOOTER_SIZE + len(MAGIC))
    opcode, length, summary_start, _, summary_crc = struct.unpack_from('<BQQQI', tail)
    if opcode != _OP_FOOTER or length != FOOTER_SIZE - 9 or tail[FOOTER_SIZE:] != MAGIC:
        raise ValueError('no footer record and magic at the end of the file')
    data_end = (summary_start or footer_start) - DATA_END_SIZE
    if not len(MAGIC) <= data_end < footer_start:
        raise ValueError(f'footer names summary start {summary_start}, outside the file')
    fh.seek(data_end)
    opcode, length, data_crc = struct.unpack('<BQI', fh.read(DATA_END_SIZE))
    if opcode != _OP_DATA_END or length != 4:
        raise ValueError(f'no DataEnd record at offset {data_end}, where the data section ends')
    return Tail(data_end, data_crc, summary_start, footer_start, summary_crc)


def _crc(fh, start: int, stop: int, crc: int = 0) -> int:
    fh.seek(start)
    left = stop - start
    while left > 0:
        block = fh.read(min(_BLOCK, left))
        if not block:
            raise ValueError(f'file ends before offset {stop}')
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc


def summary_crc(fh, tail: Tail) -> int:
    """CRC-32 of the summary section and the footer up to its CRC field."""
    start = tail.summary_start or tail.footer_start
    return _crc(fh, start, tail.footer_start + FOOTER_SIZE - 4)


def section_crc_errors(path: Path | str) -> list[str]:
    """What does not match in the file's data-section and summary CRCs ([] when all do).

    A CRC stored as 0 (not computed by its writer) is not checked. Reads the whole data
    section once (about 0.3 s per GB of CRC on this project's reference machine).

    Raises
    ------
    ValueError
        The file's tail is not an MCAP footer and DataEnd (see :func:`read_tail`).
    OSError
        The file cannot be read.
    """
    errors = []
    with open(path, 'rb') as fh:
        tail = read_tail(fh)
        if tail.data_crc:
            got = _crc(fh, 0, tail.data_end)
            if got != tail.data_crc:
                errors.append(f'data-section CRC {got:08x} does not match the stored '
                              f'{tail.data_crc:08x}: bytes before offset {tail.data_end} changed')
        if tail.summary_crc:
            got = summary_crc(fh, tail)
            if got != tail.summary_crc:
                errors.append(f'summary CRC {got:08x} does not match the stored '
                              f'{tail.summary_crc:08x}: the summary section changed')
    return errors


def write_section_crcs(path: Path, crc_before) -> bool:
    """Fill in the DataEnd and Footer CRCs of a closed MCAP file.

    ``crc_before(offset)`` gives the CRC-32 of every byte before ``offset`` as the writer
    tracked it, or None when it did not track that offset; then both CRCs stay 0 (none).
    Returns whether they were written.
    """
    with path.open('r+b') as f:
        tail = read_tail(f)
        data_crc = crc_before(tail.data_end)
        if data_crc is None:
            return False
        f.seek(tail.data_end + 9)
        f.write(struct.pack('<I', data_crc))
        crc = summary_crc(f, tail)
        f.seek(tail.footer_start + FOOTER_SIZE - 4)
        f.write(struct.pack('<I', crc))
    return True
