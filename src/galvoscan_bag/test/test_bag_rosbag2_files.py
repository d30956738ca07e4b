"""rosbag2's own test bags (tests/data/rosbag2): every message read and recovered.

The expected messages come from the ``mcap`` package's stream reader (CRCs validated),
walking every file of a bag record by record, independent of the bag's metadata.yaml, of
its summary and of our reader.
"""

import collections
from pathlib import Path

import pytest
import yaml
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer as McapFileWriter

from galvoscan_bag.reader import BagReadError, read_messages, read_topics
from galvoscan_bag.recover import recover_bag

DATA = Path(__file__).resolve().parents[3] / 'tests' / 'data' / 'rosbag2'
BAGS = sorted(p.name for p in DATA.iterdir() if p.is_dir())


def independent_messages(bag: Path):
    """(topic, log time, bytes) of every message of every .mcap file, sorted."""
    out = []
    for file in sorted(bag.glob('*.mcap')):
        topics = {}
        with open(file, 'rb') as stream:
            for record in StreamReader(stream, skip_magic=False, validate_crcs=True).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    out.append((topics[record.channel_id], record.log_time, bytes(record.data)))
    return sorted(out)


def ours(bag: Path):
    return sorted((m.topic, m.log_time_ns, m.data) for m in read_messages(bag))


def test_the_bags_are_here():
    assert len(BAGS) == 9 and all(independent_messages(DATA / b) for b in BAGS)


@pytest.mark.parametrize('name', BAGS)
def test_every_message_is_read_with_the_right_counts(name):
    bag = DATA / name
    expected = independent_messages(bag)
    assert ours(bag) == expected
    counts = collections.Counter(t for t, _, _ in expected)
    listed = {t.topic: t.count for t in read_topics(bag)}
    assert {t: c for t, c in listed.items() if c} == dict(counts)


@pytest.mark.parametrize('name', BAGS)
def test_every_message_is_recovered(name, tmp_path):
    bag = DATA / name
    report = recover_bag(bag, tmp_path / 'out')
    assert report.complete and not report.damaged
    assert ours(tmp_path / 'out') == independent_messages(bag)
    assert report.messages == len(independent_messages(bag))


def test_schema_names_without_msg_read_as_full_type_names(tmp_path):
    (info,) = read_topics(DATA / 'test_bag_for_seek')
    assert info.msgtype == 'test_msgs/msg/BasicTypes' and info.count == 5
    recover_bag(DATA / 'test_bag_for_seek', tmp_path / 'out')
    (info,) = read_topics(tmp_path / 'out')
    assert info.msgtype == 'test_msgs/msg/BasicTypes' and info.rihs01.startswith('RIHS01_')


def test_metadata_qos_that_differs_from_the_channels_loses_nothing():
    """talker's metadata.yaml and its MCAP channels record different QoS (depth 0 vs 10...)."""
    meta = yaml.safe_load((DATA / 'talker' / 'metadata.yaml').read_text())
    topics = meta['rosbag2_bagfile_information']['topics_with_message_count']
    in_meta = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
               for t in topics}
    with open(DATA / 'talker' / 'talker.mcap', 'rb') as stream:
        in_file = {r.topic: r.metadata['offered_qos_profiles']
                   for r in StreamReader(stream).records if isinstance(r, Channel)}
    assert any(in_meta[t] != q for t, q in in_file.items())
    by_topic = collections.Counter(m.topic for m in read_messages(DATA / 'talker'))
    assert by_topic == {'/topic': 10, '/rosout': 10}
    qos = {t.topic: t.qos for t in read_topics(DATA / 'talker')}
    assert qos['/topic'] and qos['/rosout']


def test_a_bag_without_metadata_reads_all_its_files_in_time_order():
    bag = DATA / 'multiple_files'
    assert not (bag / 'metadata.yaml').exists() and len(list(bag.glob('*.mcap'))) == 3
    times = [m.log_time_ns for m in read_messages(bag)]
    assert len(times) == 3177 and times == sorted(times)


def _schemaless(path: Path, n: int = 4) -> None:
    with open(path, 'wb') as stream:
        writer = McapFileWriter(stream)
        writer.start(profile='ros2', library='test')
        channel = writer.register_channel(topic='/raw', message_encoding='cdr', schema_id=0)
        for i in range(n):
            writer.add_message(channel, log_time=100 + i, data=bytes([0, 1, 0, 0, i, 0, 0, 0]),
                               publish_time=100 + i)
        writer.finish()


def test_a_schemaless_file_reads_and_recovers_with_the_type_from_metadata(tmp_path):
    bag = tmp_path / 'schemaless'
    bag.mkdir()
    _schemaless(bag / 'schemaless_0.mcap')
    assert [m.log_time_ns for m in read_messages(bag / 'schemaless_0.mcap')] == [100, 101, 102,
                                                                                 103]
    (bag / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': {
        'version': 5, 'storage_identifier': 'mcap', 'relative_file_paths': ['schemaless_0.mcap'],
        'topics_with_message_count': [{'message_count': 4, 'topic_metadata': {
            'name': '/raw', 'type': 'std_msgs/UInt32', 'serialization_format': 'cdr',
            'offered_qos_profiles': ''}}]}}))
    (info,) = read_topics(bag)
    assert info.msgtype == 'std_msgs/msg/UInt32' and info.count == 4
    report = recover_bag(bag, tmp_path / 'out')
    assert report.messages == 4 and report.complete
    assert [m.data for m in read_messages(tmp_path / 'out')] == \
        [bytes([0, 1, 0, 0, i, 0, 0, 0]) for i in range(4)]


def test_a_file_whose_messages_do_not_come_out_is_an_error(tmp_path):
    """Statistics that count messages the file does not yield: an error, never silence."""
    bag = tmp_path / 'short'
    with open(bag.with_suffix('.mcap'), 'wb') as stream:
        writer = McapFileWriter(stream)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('std_msgs/msg/UInt32', 'ros2msg', b'uint32 data')
        channel = writer.register_channel('/a', 'cdr', schema)
        writer.add_message(channel, log_time=1, data=bytes([0, 1, 0, 0, 1, 0, 0, 0]),
                           publish_time=1)
        writer._Writer__statistics.channel_message_counts[channel] = 5  # claims 5
        writer._Writer__statistics.message_count = 5
        writer.finish()
    with pytest.raises(BagReadError, match='read 1 messages'):
        list(read_messages(bag.with_suffix('.mcap')))


def test_a_file_without_statistics_is_counted_by_reading_it(tmp_path):
    """The Statistics record is optional in MCAP: without it, counts come from the messages."""
    path = tmp_path / 'nostats.mcap'
    with open(path, 'wb') as stream:
        writer = McapFileWriter(stream, use_statistics=False)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('std_msgs/msg/UInt32', 'ros2msg', b'uint32 data')
        channel = writer.register_channel('/a', 'cdr', schema)
        for i in range(7):
            writer.add_message(channel, log_time=i, data=bytes([0, 1, 0, 0, i, 0, 0, 0]),
                               publish_time=i)
        writer.finish()
    (info,) = read_topics(path)
    assert info.count == 7
    assert [m.log_time_ns for m in read_messages(path)] == list(range(7))


def test_our_summary_crc_agrees_with_the_mcap_cpp_writer_of_rosbag2():
    """rosbag2's files store summary CRCs (no data-section CRC): ours must compute the same."""
    from galvoscan_bag.sections import read_tail, section_crc_errors, summary_crc

    files = sorted(DATA.rglob('*.mcap'))
    assert len(files) >= 10
    for file in files:
        with open(file, 'rb') as fh:
            tail = read_tail(fh)
            assert tail.summary_crc != 0, file
            assert summary_crc(fh, tail) == tail.summary_crc, file
        assert section_crc_errors(file) == [], file
