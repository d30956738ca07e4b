"""Bags written by galvoscan_bag read back identically with our reader, mcap and rosbags."""

import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from galvoscan_bag.reader import BagReadError, deserialize, read_messages, read_topics
from galvoscan_bag.recover import recover_bag
from galvoscan_bag.typestore import default_typestore
from galvoscan_bag.writer import BagWriter, serialize, write_bag

STORE = default_typestore()
Time = STORE.types['builtin_interfaces/msg/Time']
Header = STORE.types['std_msgs/msg/Header']
GalvoState = STORE.types['galvoscan_msgs/msg/GalvoState']
StripeCenters = STORE.types['galvoscan_msgs/msg/StripeCenters']
Image = STORE.types['sensor_msgs/msg/Image']
INSTALLED_MSG_DIR = Path(sys.prefix) / 'share' / 'galvoscan_msgs' / 'msg'
T0 = 1_700_000_000_000_000_000  # ns


def header(i, frame_id='v0'):
    stamp = T0 + i * 2_000_000
    return Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame_id)


def galvo_state(i, volts=(0.1, -0.2, 0.3, -0.4)):
    return GalvoState(
        header=header(i), seq=i, g1_pan_voltage=volts[0] * i, g1_tilt_voltage=volts[1],
        g2_pan_voltage=volts[2], g2_tilt_voltage=volts[3] * i, laser_on=i % 2 == 0,
        status=GalvoState.STATUS_SETTLED,
    )


def stripe_centers(i, n=37):
    rng = np.random.default_rng(i)
    return StripeCenters(
        header=header(i, 'camera_optical'), galvo=galvo_state(i), image_width=720,
        image_height=540, u=np.arange(n, dtype=np.float32),
        v=rng.uniform(0, 539, n).astype(np.float32),
        width=rng.uniform(3, 6, n).astype(np.float32),
        strength=rng.uniform(10, 200, n).astype(np.float32), method='steger', sigma=2.0,
        min_strength=5.0, roi_half_height=12, orientation=StripeCenters.ORIENTATION_HORIZONTAL,
        rejected_secondary=i % 3, saturated_fraction=0.125 * (i % 4), peak_level=180.0 + i,
    )


def image(i, width=720, height=540):
    pixels = np.random.default_rng(100 + i).integers(0, 256, (height, width), dtype=np.uint8)
    return Image(
        header=header(i, 'camera_optical'), height=height, width=width, encoding='mono8',
        is_bigendian=0, step=width, data=pixels.ravel(),
    )


def sample_messages():
    """(topic, None, rosbags message, log time) for 2 full images and 12 small messages."""
    items = []
    for i in range(6):
        items.append(('/galvo/state', None, galvo_state(i), T0 + i * 2_000_000 + 100))
        items.append(('/stripe/centers', None, stripe_centers(i), T0 + i * 2_000_000 + 200))
    for i in range(2):
        items.append(('/camera/image_raw', None, image(i), T0 + i * 2_000_000 + 50))
    return sorted(items, key=lambda item: item[3])


def assert_same_message(decoded, original):
    """Field-by-field equality of two rosbags messages (arrays compared elementwise)."""
    assert type(decoded).__name__ == type(original).__name__
    for name in original.__dataclass_fields__:
        a, b = getattr(decoded, name), getattr(original, name)
        if hasattr(b, '__dataclass_fields__'):
            assert_same_message(a, b)
        elif isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b, name


@pytest.fixture
def sample_bag(tmp_path):
    items = sample_messages()
    path = tmp_path / 'sample'
    counts = write_bag(path, items)
    return path, items, counts


def test_write_then_read_back_identical(sample_bag):
    path, items, counts = sample_bag
    assert counts == {'/galvo/state': 6, '/stripe/centers': 6, '/camera/image_raw': 2}
    read = list(read_messages(path))
    assert [(m.topic, m.log_time_ns) for m in read] == [(t, ts) for t, _, _, ts in items]
    for message, (_, _, original, _) in zip(read, items, strict=True):
        assert message.msgtype == original.__msgtype__
        assert message.data == bytes(STORE.serialize_cdr(original, original.__msgtype__))
        assert_same_message(deserialize(message), original)


def test_read_one_topic(sample_bag):
    path, items, _ = sample_bag
    seqs = [deserialize(m).seq for m in read_messages(path, ['/galvo/state'])]
    assert seqs == list(range(6))
    with pytest.raises(ValueError, match='not in bag'):
        list(read_messages(path, ['/nope']))


def test_metadata_yaml_parses_and_counts(sample_bag):
    path, _, counts = sample_bag
    info = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['version'] == 9
    assert info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == ['sample.mcap']
    assert info['message_count'] == 14
    assert info['starting_time']['nanoseconds_since_epoch'] == T0 + 50
    assert info['duration']['nanoseconds'] == 5 * 2_000_000 + 200 - 50
    topics = {t['topic_metadata']['name']: t for t in info['topics_with_message_count']}
    assert {name: t['message_count'] for name, t in topics.items()} == counts
    assert topics['/galvo/state']['topic_metadata']['type'] == 'galvoscan_msgs/msg/GalvoState'
    assert topics['/galvo/state']['topic_metadata']['serialization_format'] == 'cdr'
    if INSTALLED_MSG_DIR.is_dir():
        rosidl = json.loads((INSTALLED_MSG_DIR / 'StripeCenters.json').read_text())
        expected = {h['type_name']: h['hash_string'] for h in rosidl['type_hashes']}
        got = topics['/stripe/centers']['topic_metadata']['type_description_hash']
        assert got == expected['galvoscan_msgs/msg/StripeCenters']


def test_mcap_library_reads_it_with_definitions(sample_bag):
    path, items, _ = sample_bag
    with (path / 'sample.mcap').open('rb') as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary.statistics.message_count == 14
        schemas = {s.name: s for s in summary.schemas.values()}
        centers = schemas['galvoscan_msgs/msg/StripeCenters']
        assert centers.encoding == 'ros2msg'
        text = centers.data.decode()
        # The definition embeds its dependencies, ours included, as ros2 bag does.
        assert 'uint32 rejected_secondary' in text
        assert 'float32 peak_level' in text
        assert 'MSG: galvoscan_msgs/GalvoState' in text
        assert 'float64 g2_tilt_voltage' in text
        assert 'MSG: std_msgs/Header' in text
        got = [(c.topic, m.log_time, bytes(m.data)) for _, c, m in reader.iter_messages()]
    expected = [
        (t, ts, bytes(STORE.serialize_cdr(msg, msg.__msgtype__))) for t, _, msg, ts in items
    ]
    assert got == expected


def test_rosbags_anyreader_decodes_from_embedded_definitions_only(sample_bag):
    path, items, _ = sample_bag
    # No default typestore: AnyReader must build galvoscan_msgs from the bag's definitions
    # (and it checks them against the stored type hashes).
    with AnyReader([path]) as reader:
        assert 'galvoscan_msgs/msg/StripeCenters' in reader.typestore.fielddefs
        decoded = [
            (c.topic, ts, reader.deserialize(raw, c.msgtype))
            for c, ts, raw in reader.messages(connections=reader.connections)
        ]
    assert [(t, ts) for t, ts, _ in decoded] == [(t, ts) for t, _, _, ts in items]
    for (_, _, got), (_, _, original, _) in zip(decoded, items, strict=True):
        assert_same_message(got, original)


@settings(max_examples=25, deadline=None)
@given(
    seq=st.integers(0, 2**64 - 1),
    volts=st.tuples(*[st.floats(-10, 10, allow_nan=False)] * 4),
    laser=st.booleans(),
    status=st.sampled_from([0, 1, 2]),
    frame_id=st.text(st.characters(codec='utf-8', exclude_categories=['Cs']), max_size=20),
    stamp=st.integers(0, 2**63 - 1),
)
def test_galvo_state_round_trip(seq, volts, laser, status, frame_id, stamp):
    sec, nanosec = divmod(stamp, 10**9)
    msg = GalvoState(
        header=Header(stamp=Time(sec=sec % 2**31, nanosec=nanosec), frame_id=frame_id), seq=seq,
        g1_pan_voltage=volts[0], g1_tilt_voltage=volts[1], g2_pan_voltage=volts[2],
        g2_tilt_voltage=volts[3], laser_on=laser, status=status,
    )
    with tempfile.TemporaryDirectory() as tmp:
        write_bag(Path(tmp) / 'b', [('/galvo/state', None, msg, stamp)])
        (message,) = read_messages(Path(tmp) / 'b')
    assert message.log_time_ns == stamp
    assert_same_message(deserialize(message), msg)


def test_bytes_and_objects_mix(tmp_path):
    msg = galvo_state(3)
    data = bytes(STORE.serialize_cdr(msg, msg.__msgtype__))
    write_bag(
        tmp_path / 'b',
        [
            ('/a', 'galvoscan_msgs/msg/GalvoState', data, 10),
            ('/a', None, msg, 20),
        ],
    )
    assert [m.data for m in read_messages(tmp_path / 'b')] == [data, data]


def test_bad_input_is_rejected_and_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match='msgtype is required'):
        write_bag(tmp_path / 'b1', [('/a', None, b'\x00\x01\x00\x00', 1)])
    assert not (tmp_path / 'b1').exists()
    with pytest.raises(ValueError, match='unknown to the type store'):
        write_bag(tmp_path / 'b2', [('/a', 'nope/msg/Nope', b'\x00\x01\x00\x00', 1)])
    assert not (tmp_path / 'b2').exists()
    with pytest.raises(ValueError, match='log_time_ns'):
        write_bag(tmp_path / 'b3', [('/a', None, galvo_state(0), -1)])
    with pytest.raises(ValueError, match=r'messages\[0\]'):
        write_bag(tmp_path / 'b4', [('/a', galvo_state(0), 1)])
    with pytest.raises(ValueError, match='does not match'):
        serialize(galvo_state(0), 'sensor_msgs/msg/Image')
    with pytest.raises(ValueError, match='chunk_size'):
        BagWriter(tmp_path / 'b5', chunk_size=0)
    with pytest.raises(ValueError, match='flush_interval'):
        BagWriter(tmp_path / 'b5', flush_interval=0)
    (tmp_path / 'exists').mkdir()
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / 'exists')


def test_writer_topic_rules(tmp_path):
    with BagWriter(tmp_path / 'b') as bag:
        bag.add_topic('/a', 'galvoscan_msgs/msg/GalvoState')
        bag.add_topic('/a', 'galvoscan_msgs/msg/GalvoState')  # same again: no-op
        with pytest.raises(ValueError, match='already has type'):
            bag.add_topic('/a', 'sensor_msgs/msg/Image')
        with pytest.raises(ValueError, match='not declared'):
            bag.write('/b', b'\x00\x01\x00\x00', 1)
        with pytest.raises(ValueError, match='CDR'):
            bag.write('/a', b'\x00', 1)
    assert read_topics(tmp_path / 'b')[0].count == 0


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_flush_interval_makes_a_killed_bag_recoverable(tmp_path):
    clock = FakeClock()
    bag = BagWriter(tmp_path / 'live', flush_interval=1.0, clock=clock).open()
    bag.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    written = []
    for i in range(10):
        clock.now = 0.25 * i  # 0 .. 2.25 s
        msg = galvo_state(i)
        written.append(bytes(STORE.serialize_cdr(msg, msg.__msgtype__)))
        bag.write('/galvo/state', written[-1], T0 + i)
    # Pending since t=0: flushed at t=1.0 (5 messages), pending since 1.25: flushed at 2.25.
    assert bag.chunks_flushed == 2
    clock.now = 2.4
    assert bag.flush_if_due() is False  # nothing pending
    clock.now = 2.5  # one more message, which a kill now loses
    bag.write('/galvo/state', written[0], T0 + 99)
    # Copy the file as a SIGKILL would leave it (no summary, no metadata.yaml).
    killed = tmp_path / 'killed'
    killed.mkdir()
    shutil.copy(bag.mcap_path, killed / 'killed.mcap')
    bag.abort()
    report = recover_bag(killed, tmp_path / 'recovered')
    assert report.chunks == 2 and not report.complete
    assert [m.data for m in read_messages(tmp_path / 'recovered')] == written


def test_idle_flush_writes_the_pending_chunk(tmp_path):
    clock = FakeClock()
    bag = BagWriter(tmp_path / 'b', flush_interval=0.5, clock=clock).open()
    bag.add_topic('/a', 'galvoscan_msgs/msg/GalvoState')
    bag.write('/a', bytes(STORE.serialize_cdr(galvo_state(0), GalvoState.__msgtype__)), 5)
    size = bag.mcap_path.stat().st_size
    clock.now = 0.4
    assert bag.flush_if_due() is False
    clock.now = 0.6
    assert bag.flush_if_due() is True
    assert bag.mcap_path.stat().st_size > size
    bag.close()


def test_chunk_size_closes_chunks(tmp_path):
    bag = BagWriter(tmp_path / 'b', chunk_size=500, flush_interval=None).open()
    bag.add_topic('/c', 'galvoscan_msgs/msg/StripeCenters')
    for i in range(6):  # each StripeCenters here is > 500 bytes
        data = bytes(STORE.serialize_cdr(stripe_centers(i), StripeCenters.__msgtype__))
        bag.write('/c', data, i)
    assert bag.chunks_flushed == 6
    bag.close()
    with (tmp_path / 'b' / 'b.mcap').open('rb') as stream:
        assert len(make_reader(stream).get_summary().chunk_indexes) == 6


def test_reading_a_killed_bag_names_the_fix(tmp_path):
    bag = BagWriter(tmp_path / 'k').open()
    bag.add_topic('/a', 'galvoscan_msgs/msg/GalvoState')
    bag.abort()
    with pytest.raises(BagReadError, match='bag-recover'):
        list(read_messages(tmp_path / 'k'))
    with pytest.raises(BagReadError, match='bag-recover'):
        read_topics(tmp_path / 'k' / 'k.mcap')
    with pytest.raises(FileNotFoundError):
        read_topics(tmp_path / 'missing')


def _images_bag(path, n=12):
    Image = STORE.types['sensor_msgs/msg/Image']
    written = []
    with BagWriter(path, chunk_size=20000, flush_interval=None) as bag:
        bag.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        for i in range(n):
            pixels = np.full((60, 80), i, dtype=np.uint8)
            msg = Image(header=header(i, 'cam'), height=60, width=80, encoding='mono8',
                        is_bigendian=0, step=80, data=pixels.ravel())
            written.append(bytes(STORE.serialize_cdr(msg, msg.__msgtype__)))
            bag.write('/camera/image_raw', written[-1], T0 + i)
    return written


def test_bags_carry_crcs_type_hashes_and_the_ros_distro(tmp_path):
    """As rosbag2 Jazzy's MCAP plugin writes them: chunk, data and summary CRCs, the type
    hash in each channel's metadata, and ``ros_distro: jazzy``."""
    from mcap.records import Channel, Chunk, DataEnd, Footer
    from mcap.stream_reader import StreamReader

    _images_bag(tmp_path / 'b')
    with open(tmp_path / 'b' / 'b.mcap', 'rb') as stream:
        records = list(StreamReader(stream, skip_magic=False, emit_chunks=True,
                                    validate_crcs=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) >= 3 and all(c.uncompressed_crc != 0 for c in chunks)
    (data_end,) = [r for r in records if isinstance(r, DataEnd)]
    (footer,) = [r for r in records if isinstance(r, Footer)]
    assert data_end.data_section_crc != 0 and footer.summary_crc != 0
    info = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())
    info = info['rosbag2_bagfile_information']
    assert info['ros_distro'] == 'jazzy'
    (topic,) = info['topics_with_message_count']
    hashes = {r.metadata['topic_type_hash'] for r in records if isinstance(r, Channel)}
    assert hashes == {topic['topic_metadata']['type_description_hash']}
    assert next(iter(hashes)).startswith('RIHS01_')


def test_a_flipped_byte_in_an_image_is_caught_on_read_and_loses_one_chunk(tmp_path):
    written = _images_bag(tmp_path / 'b')
    data = bytearray((tmp_path / 'b' / 'b.mcap').read_bytes())
    at = data.index(bytes([7]) * 80)  # inside the pixels of image 7
    data[at + 40] ^= 0x01
    (tmp_path / 'b' / 'b.mcap').write_bytes(bytes(data))
    with pytest.raises(BagReadError, match='bag-recover'):
        list(read_messages(tmp_path / 'b'))
    report = recover_bag(tmp_path / 'b', tmp_path / 'r')
    kept = [m.data for m in read_messages(tmp_path / 'r')]
    assert report.chunks_damaged == 1 and 'crc' in report.damaged[0].lower()
    assert written[7] not in kept and 0 < len(kept) < len(written)
    assert all(k in written for k in kept)
