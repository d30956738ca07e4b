"""Recovery of killed and truncated bags keeps every complete chunk and exactly its messages.

The expected messages come from a small MCAP record walker written here from the MCAP spec
(opcodes, little-endian lengths), independent of the mcap and rosbags readers used by the code.
"""

import shutil
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.highlevel import AnyReader

from galvoscan_bag.reader import read_messages
from galvoscan_bag.recover import RecoveryError, default_output, main, recover_bag
from galvoscan_bag.typestore import default_typestore
from galvoscan_bag.writer import BagWriter

STORE = default_typestore()
Time = STORE.types['builtin_interfaces/msg/Time']
Header = STORE.types['std_msgs/msg/Header']
GalvoState = STORE.types['galvoscan_msgs/msg/GalvoState']
StripeCenters = STORE.types['galvoscan_msgs/msg/StripeCenters']
Image = STORE.types['sensor_msgs/msg/Image']
MAGIC = b'\x89MCAP0\r\n'


# -- independent MCAP walker ---------------------------------------------------------------


def _string(buf, pos):
    (n,) = struct.unpack_from('<I', buf, pos)
    return buf[pos + 4 : pos + 4 + n].decode(), pos + 4 + n


def walk_chunks(data):
    """Complete chunks of an MCAP byte string: list of (end offset, [(topic, log_time, bytes)]).

    Only our writer's layout is handled: channel records between chunks or inside them,
    messages inside uncompressed chunks.
    """
    assert data[:8] == MAGIC
    pos, topics, chunks = 8, {}, []
    while pos + 9 <= len(data):
        op, length = struct.unpack_from('<BQ', data, pos)
        body_start, end = pos + 9, pos + 9 + length
        if end > len(data):
            break
        if op == 0x04:  # channel between chunks: id, schema id, topic, ...
            cid, _ = struct.unpack_from('<HH', data, body_start)
            topics[cid], _ = _string(data, body_start + 4)
        if op == 0x06:  # chunk
            _, _, size, _ = struct.unpack_from('<QQQI', data, body_start)
            compression, p = _string(data, body_start + 28)
            assert compression == ''
            (records_len,) = struct.unpack_from('<Q', data, p)
            inner = data[p + 8 : p + 8 + records_len]
            assert len(inner) == size == records_len
            messages, q = [], 0
            while q < len(inner):
                iop, ilen = struct.unpack_from('<BQ', inner, q)
                body = inner[q + 9 : q + 9 + ilen]
                if iop == 0x04:  # channel: id, schema id, topic, ...
                    cid, _ = struct.unpack_from('<HH', body, 0)
                    topics[cid], _ = _string(body, 4)
                elif iop == 0x05:  # message: channel, sequence, log time, publish time, data
                    cid, _, log_time, _ = struct.unpack_from('<HIQQ', body, 0)
                    messages.append((topics[cid], log_time, bytes(body[22:])))
                q += 9 + ilen
            chunks.append((end, messages))
        pos = end
    return chunks


def expected_after_cut(chunks, cut):
    return [m for end, msgs in chunks if end <= cut for m in msgs]


def recovered_messages(path):
    return [(m.topic, m.log_time_ns, m.data) for m in read_messages(path)]


# -- killed bags -----------------------------------------------------------------------------


def cdr(msg):
    return bytes(STORE.serialize_cdr(msg, msg.__msgtype__))


def galvo_state(i):
    return GalvoState(
        header=Header(stamp=Time(sec=10, nanosec=i), frame_id='v0'), seq=i,
        g1_pan_voltage=0.01 * i, g1_tilt_voltage=-0.5, g2_pan_voltage=1.5,
        g2_tilt_voltage=0.02 * i, laser_on=True, status=0,
    )


def stripe_centers(i):
    u = np.arange(20, dtype=np.float32)
    return StripeCenters(
        header=Header(stamp=Time(sec=10, nanosec=i), frame_id='cam'), galvo=galvo_state(i),
        image_width=64, image_height=48, u=u, v=u * 0.5 + i, width=u * 0 + 4, strength=u + 9,
        method='steger', sigma=2.0, min_strength=5.0, roi_half_height=8, orientation=0,
        rejected_secondary=0, saturated_fraction=0.0, peak_level=28.0,
    )


def image(i, width=64, height=48):
    pixels = np.full((height, width), i % 256, dtype=np.uint8)
    return Image(
        header=Header(stamp=Time(sec=10, nanosec=i), frame_id='cam'), height=height,
        width=width, encoding='mono8', is_bigendian=0, step=width, data=pixels.ravel(),
    )


def make_killed_bag(directory, n=40, chunk_size=1500, unflushed=3, big_image=False):
    """A bag left as by SIGKILL: flushed chunks on disk, ``unflushed`` messages lost.

    Returns (bag directory, every message written as (topic, log_time, bytes)).
    """
    bag = BagWriter(directory, chunk_size=chunk_size, flush_interval=None).open()
    bag.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    bag.add_topic('/stripe/centers', 'galvoscan_msgs/msg/StripeCenters')
    bag.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
    written = []
    for i in range(n):
        topic, msg = [
            ('/galvo/state', galvo_state(i)),
            ('/stripe/centers', stripe_centers(i)),
            ('/camera/image_raw', image(i, *((720, 540) if big_image and i == 7 else (64, 48)))),
        ][i % 3]
        written.append((topic, 1000 + i, cdr(msg)))
        bag.write(topic, written[-1][2], 1000 + i)
    bag.flush()
    for i in range(n, n + unflushed):
        bag.write('/galvo/state', cdr(galvo_state(i)), 1000 + i)
    bag.abort()
    return directory, written


@pytest.fixture(scope='module')
def killed(tmp_path_factory):
    directory, written = make_killed_bag(tmp_path_factory.mktemp('k') / 'killed', big_image=True)
    data = (directory / 'killed.mcap').read_bytes()
    return directory, written, data, walk_chunks(data)


def test_walker_agrees_with_what_was_written(killed):
    _, written, data, chunks = killed
    assert len(chunks) > 10
    # Everything flushed is on disk in complete chunks; the unflushed tail is not.
    assert expected_after_cut(chunks, len(data)) == written


def test_killed_bag_is_fully_recovered(killed, tmp_path):
    directory, written, data, chunks = killed
    assert not (directory / 'metadata.yaml').exists()
    report = recover_bag(directory, tmp_path / 'out')
    assert report.chunks == len(chunks)
    assert report.messages == len(written)
    assert report.per_topic == {
        t: sum(1 for w in written if w[0] == t) for t in {w[0] for w in written}
    }
    assert not report.complete and report.bytes_dropped == 0
    assert recovered_messages(tmp_path / 'out') == written


def cut_points(chunks, size):
    points = {0, 4, 8, 9, 20, size, size - 1}
    for end, _ in chunks[::3]:  # hypothesis below samples the rest at random
        points.update({end - 1, end, end + 12, end - 200})
    return sorted(p for p in points if 0 <= p <= size)


def test_every_cut_keeps_exactly_the_complete_chunks(killed, tmp_path):
    _, _, data, chunks = killed
    for index, cut in enumerate(cut_points(chunks, len(data))):
        source = tmp_path / f'cut{index}.mcap'
        source.write_bytes(data[:cut])
        if cut < 8:
            with pytest.raises(RecoveryError, match='magic'):
                recover_bag(source, tmp_path / f'out{index}')
            continue
        report = recover_bag(source, tmp_path / f'out{index}')
        expected = expected_after_cut(chunks, cut)
        assert recovered_messages(tmp_path / f'out{index}') == expected, f'cut at {cut}'
        assert report.chunks == sum(1 for end, _ in chunks if end <= cut)
        assert report.messages == len(expected)


@settings(max_examples=30, deadline=None)
@given(fraction=st.floats(0.0, 1.0))
def test_random_cut_property(killed, fraction):
    _, _, data, chunks = killed
    cut = 8 + int(fraction * (len(data) - 8))
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / 'cut.mcap'
        source.write_bytes(data[:cut])
        recover_bag(source, Path(tmp) / 'out')
        got = recovered_messages(Path(tmp) / 'out')
    assert got == expected_after_cut(chunks, cut)


def test_zero_filled_tail_is_ignored(killed, tmp_path):
    _, written, data, _ = killed
    source = tmp_path / 'padded.mcap'
    source.write_bytes(data + bytes(4096))  # a preallocated, never written tail
    recover_bag(source, tmp_path / 'out')
    assert recovered_messages(tmp_path / 'out') == written


def expected_without(chunks, lost):
    """Messages of every chunk but those whose end offsets are in ``lost``."""
    return [m for end, msgs in chunks if end not in lost for m in msgs]


def _chunk_starts(data, chunks):
    """Start offset of each walked chunk (the chunk record's opcode)."""
    starts, pos = [], 8
    for end, _ in chunks:
        while data[pos] != 0x06:  # header, message index records
            pos += 9 + struct.unpack_from('<Q', data, pos + 1)[0]
        starts.append(pos)
        pos = end
    return starts


def test_garbage_record_header_loses_only_that_record(killed, tmp_path):
    _, _, data, chunks = killed
    # The 4th chunk's record header claims a 1 TiB chunk: reading resumes at the 5th.
    start = _chunk_starts(data, chunks)[3]
    damaged = bytearray(data)
    damaged[start : start + 9] = struct.pack('<BQ', 0x06, 2**40)
    source = tmp_path / 'damaged.mcap'
    source.write_bytes(bytes(damaged))
    report = recover_bag(source, tmp_path / 'out')
    assert recovered_messages(tmp_path / 'out') == expected_without(chunks, {chunks[3][0]})
    assert report.chunks == len(chunks) - 1 and not report.complete
    assert len(report.damaged) == 1 and f'offset {start}' in report.damaged[0]
    assert 'LOST' in report.summary()


def test_damaged_chunk_content_is_not_kept(killed, tmp_path):
    _, _, data, chunks = killed
    # Inside the 4th chunk, make the first inner record claim more bytes than the chunk has.
    start = _chunk_starts(data, chunks)[3]
    _, p = _string(data, start + 9 + 28)
    inner = p + 8
    damaged = bytearray(data)
    damaged[inner + 1 : inner + 9] = struct.pack('<Q', 10**6)
    source = tmp_path / 'damaged.mcap'
    source.write_bytes(bytes(damaged))
    report = recover_bag(source, tmp_path / 'out')
    assert recovered_messages(tmp_path / 'out') == expected_without(chunks, {chunks[3][0]})
    assert report.chunks_damaged == 1 and 'chunk 4' in report.damaged[0]


@pytest.mark.parametrize('k', [0, 2, 5])
def test_one_flipped_byte_loses_its_chunk_only(killed, tmp_path, k):
    """A flipped byte inside chunk k's messages: its CRC catches it, every other chunk stays."""
    directory, written, data, chunks = killed
    starts = _chunk_starts(data, chunks)
    target = (starts[k] + chunks[k][0]) // 2  # the middle of chunk k, inside its records
    damaged = bytearray(data)
    damaged[target] ^= 0x10
    source = tmp_path / 'flipped.mcap'
    source.write_bytes(bytes(damaged))
    report = recover_bag(source, tmp_path / 'out')
    got = recovered_messages(tmp_path / 'out')
    assert got == expected_without(chunks, {chunks[k][0]})  # channels are outside chunks
    assert report.chunks_damaged == 1
    assert f'chunk {k + 1} at offset {starts[k]}' in report.damaged[0]
    assert 'crc' in report.damaged[0].lower()


def test_complete_bag_recovers_everything(tmp_path):
    _, written = _complete_bag(tmp_path)
    report = recover_bag(tmp_path / 'whole')
    assert report.output == tmp_path / 'whole_recovered' == default_output(tmp_path / 'whole')
    assert report.complete and report.bytes_dropped == 0 and report.stop_reason == ''
    assert recovered_messages(report.output) == written


def test_recovered_bag_is_valid_for_other_readers(killed, tmp_path):
    directory, written, _, _ = killed
    recover_bag(directory, tmp_path / 'out')
    info = yaml.safe_load((tmp_path / 'out' / 'metadata.yaml').read_text())
    info = info['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['message_count'] == len(written)
    hashes = {
        t['topic_metadata']['type']: t['topic_metadata']['type_description_hash']
        for t in info['topics_with_message_count']
    }
    # Hashes computed from the stored definitions equal the type store's (rclpy-compatible) ones.
    for msgtype, digest in hashes.items():
        assert digest == STORE.hash_rihs01(msgtype)
    with AnyReader([tmp_path / 'out']) as reader:  # no default typestore: definitions inside
        seqs = [
            reader.deserialize(raw, c.msgtype).seq
            for c, _, raw in reader.messages(connections=reader.connections)
            if c.topic == '/galvo/state'
        ]
    assert seqs == [i for i in range(40) if i % 3 == 0]


def test_metadata_hashes_are_used_when_present(killed, tmp_path):
    directory, written, _, _ = killed
    source = tmp_path / 'withmeta'
    shutil.copytree(directory, source)
    (source / 'metadata.yaml').write_text(
        yaml.safe_dump(
            {
                'rosbag2_bagfile_information': {
                    'relative_file_paths': ['killed.mcap'],
                    'topics_with_message_count': [
                        {
                            'topic_metadata': {
                                'name': '/galvo/state',
                                'type': 'galvoscan_msgs/msg/GalvoState',
                                'type_description_hash': 'RIHS01_' + 'ab' * 32,
                            }
                        }
                    ],
                }
            }
        )
    )
    recover_bag(source, tmp_path / 'out')
    info = yaml.safe_load((tmp_path / 'out' / 'metadata.yaml').read_text())
    topics = info['rosbag2_bagfile_information']['topics_with_message_count']
    by_type = {t['topic_metadata']['type']: t['topic_metadata'] for t in topics}
    stored = by_type['galvoscan_msgs/msg/GalvoState']['type_description_hash']
    assert stored == 'RIHS01_' + 'ab' * 32
    assert recovered_messages(tmp_path / 'out') == written


def test_bad_sources(tmp_path):
    with pytest.raises(FileNotFoundError):
        recover_bag(tmp_path / 'missing')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(RecoveryError, match='no .mcap'):
        recover_bag(tmp_path / 'empty')
    (tmp_path / 'x.db3').write_bytes(b'')
    with pytest.raises(ValueError, match='.mcap'):
        recover_bag(tmp_path / 'x.db3')
    (tmp_path / 'notmcap.mcap').write_bytes(b'hello world')
    with pytest.raises(RecoveryError, match='magic'):
        recover_bag(tmp_path / 'notmcap.mcap', tmp_path / 'o')
    assert not (tmp_path / 'o').exists()


def test_cli(killed, tmp_path, capsys):
    directory, written, _, _ = killed
    assert main([str(directory), '-o', str(tmp_path / 'out')]) == 0
    out = capsys.readouterr().out
    assert f'recovered {len(written)} messages' in out
    assert '/galvo/state: 14' in out
    assert main([str(directory), '-o', str(tmp_path / 'out')]) == 1  # output exists
    assert 'exists' in capsys.readouterr().err


def test_message_indexes_point_at_their_messages(tmp_path):
    """Each chunk's message index records (opcode 0x07) give (log time, offset) of its messages;
    check them against the chunk's records, parsed here from the MCAP layout."""
    bag = BagWriter(tmp_path / 'ix', chunk_size=3000, flush_interval=None).open()
    bag.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    for i in range(12):
        if i == 5:  # a channel record in the middle of a chunk
            bag.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        if i >= 5 and i % 2:
            bag.write('/camera/image_raw', bytearray(cdr(image(i))), 100 + i)
        bag.write('/galvo/state', memoryview(cdr(galvo_state(i))), 100 + i)
    bag.close()
    data = (tmp_path / 'ix' / 'ix.mcap').read_bytes()
    pos, checked, chunk_records = 8, 0, None
    while pos + 9 <= len(data):
        op, length = struct.unpack_from('<BQ', data, pos)
        body = data[pos + 9 : pos + 9 + length]
        if op == 0x06:
            (n,) = struct.unpack_from('<I', body, 28)
            chunk_records = body[28 + 4 + n + 8 :]
        elif op == 0x07:
            cid, nbytes = struct.unpack_from('<HI', body, 0)
            for k in range(nbytes // 16):
                log_time, offset = struct.unpack_from('<QQ', body, 6 + 16 * k)
                rop, _, rcid, _, rlog = struct.unpack_from('<BQHIQ', chunk_records, offset)
                assert (rop, rcid, rlog) == (0x05, cid, log_time)
                checked += 1
        elif op == 0x02:  # footer
            break
        pos += 9 + length
    assert checked == 12 + 4  # every message is indexed (images at i = 5, 7, 9, 11)
    got = [(m.topic, m.log_time_ns) for m in read_messages(tmp_path / 'ix')]
    assert len(got) == 16 and got[-1] == ('/galvo/state', 111)


def _complete_bag(tmp_path, name='whole'):
    bag = BagWriter(tmp_path / name, chunk_size=800, flush_interval=None).open()
    bag.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    written = []
    for i in range(25):
        written.append(('/galvo/state', 5000 + i, cdr(galvo_state(i))))
        bag.write('/galvo/state', written[-1][2], 5000 + i)
    bag.close()
    return next((tmp_path / name).glob('*.mcap')), written


def test_section_crcs_catch_a_flip_outside_every_chunk(tmp_path):
    """A flipped byte in the schema text (no chunk CRC covers it) fails the data-section CRC:
    the reader refuses the file, recovery keeps every message and names the mismatch."""
    from galvoscan_bag.reader import BagReadError
    from galvoscan_bag.sections import read_tail, section_crc_errors

    mcap, written = _complete_bag(tmp_path)
    data = bytearray(mcap.read_bytes())
    with open(mcap, 'rb') as fh:
        tail = read_tail(fh)
    assert tail.data_crc and tail.summary_crc  # our writer stores both
    assert section_crc_errors(mcap) == []
    at = data.index(b'float64 g1_pan_voltage')  # the first copy: the Schema record in data
    assert at < tail.data_end
    data[at + 2] ^= 0x01  # 'float64' -> 'flnat64'
    mcap.write_bytes(bytes(data))
    (errors,) = section_crc_errors(mcap)
    assert 'data-section CRC' in errors and f'before offset {tail.data_end}' in errors
    with pytest.raises(BagReadError, match='data-section CRC.*bag-recover'):
        list(read_messages(mcap.parent))
    report = recover_bag(mcap.parent, tmp_path / 'out')
    assert report.messages == len(written) and report.chunks_damaged == 0
    assert not report.complete and len(report.damaged) == 1
    assert 'data-section CRC' in report.damaged[0] and 'outside every chunk' in report.damaged[0]


def test_summary_crc_catches_a_flip_in_the_summary(tmp_path):
    from galvoscan_bag.reader import BagReadError
    from galvoscan_bag.sections import read_tail, section_crc_errors

    mcap, _ = _complete_bag(tmp_path)
    data = bytearray(mcap.read_bytes())
    with open(mcap, 'rb') as fh:
        tail = read_tail(fh)
    at = data.index(b'float64 g1_pan_voltage', tail.summary_start)  # the summary's copy
    data[at + 2] ^= 0x01
    mcap.write_bytes(bytes(data))
    assert [e.split(' ')[0] for e in section_crc_errors(mcap)] == ['summary']
    with pytest.raises(BagReadError, match='summary CRC'):
        list(read_messages(mcap.parent))


def test_a_file_without_section_crcs_is_read(tmp_path):
    """0 stored means 'not computed' (as many writers leave it): nothing to check."""
    from galvoscan_bag.sections import read_tail, section_crc_errors

    mcap, written = _complete_bag(tmp_path)
    data = bytearray(mcap.read_bytes())
    with open(mcap, 'rb') as fh:
        tail = read_tail(fh)
    data[tail.data_end + 9:tail.data_end + 13] = bytes(4)
    data[-12:-8] = bytes(4)  # the footer's summary CRC, before the closing magic
    mcap.write_bytes(bytes(data))
    with open(mcap, 'rb') as fh:
        assert read_tail(fh)[1::3] == (0, 0)
    assert section_crc_errors(mcap) == []
    assert [(m.topic, m.log_time_ns, m.data) for m in read_messages(mcap.parent)] == written
