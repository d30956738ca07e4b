"""Reading sensor_msgs/Image straight from CDR: same fields as rclpy, clear errors otherwise."""

import struct
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from galvoscan_common.cdr import BadImageError, image_to_array, parse_image_cdr


def _image(h, w, encoding, frame_id, big, pad, seed):
    bpp = 2 if '16' in encoding else 1
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=int(big),
                step=w * bpp + pad)
    msg.header.stamp.sec, msg.header.stamp.nanosec = -5 + seed, 999_999_999 - seed
    msg.header.frame_id = frame_id
    msg.data = np.random.default_rng(seed).integers(0, 256, msg.step * h, np.uint8).tobytes()
    return msg


@settings(max_examples=80, deadline=None)
@given(h=st.integers(0, 9), w=st.integers(0, 9), enc=st.sampled_from(
    ['mono8', 'mono16', '8UC1', '16UC1', 'rgb8']),
    # ROS strings are C strings: no NUL inside
    frame_id=st.text(st.characters(blacklist_characters='\x00', blacklist_categories=('Cs',)),
                     max_size=12),
    big=st.booleans(), pad=st.integers(0, 3), seed=st.integers(0, 1000))
def test_fields_equal_rclpy_deserialisation(h, w, enc, frame_id, big, pad, seed):
    msg = _image(h, w, enc, frame_id, big, pad, seed)
    raw = parse_image_cdr(serialize_message(msg))
    assert (raw.stamp_sec, raw.stamp_nanosec) == (msg.header.stamp.sec,
                                                  msg.header.stamp.nanosec)
    assert raw.stamp_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    assert raw.frame_id == frame_id
    assert (raw.height, raw.width, raw.encoding, raw.is_bigendian, raw.step) == (
        h, w, enc, int(big), msg.step)
    assert bytes(raw.data) == bytes(msg.data)
    try:
        expected = image_to_array(msg)
    except BadImageError as exc:
        with pytest.raises(BadImageError) as got:
            image_to_array(raw)
        assert got.value.cause == exc.cause
    else:
        np.testing.assert_array_equal(image_to_array(raw), expected)


def test_big_endian_encapsulation_reads_the_same():
    """A big-endian CDR writer (encapsulation 0x0000) gives the same image."""
    w, h = 4, 3
    pixels = bytes(range(w * h))

    def s(text):
        b = text.encode() + b'\0'
        return struct.pack('>I', len(b)) + b

    body = struct.pack('>iI', 7, 8) + s('cam')
    body += b'\0' * (-len(body) % 4) + struct.pack('>II', h, w) + s('mono8')
    body += b'\x00'
    body += b'\0' * (-len(body) % 4) + struct.pack('>I', w) + struct.pack('>I', len(pixels))
    raw = parse_image_cdr(b'\x00\x00\x00\x00' + body + pixels)
    assert (raw.stamp_sec, raw.stamp_nanosec, raw.frame_id) == (7, 8, 'cam')
    np.testing.assert_array_equal(image_to_array(raw),
                                  np.arange(w * h, dtype=np.uint8).reshape(h, w))


def test_pixels_are_a_view_not_a_copy():
    data = bytearray(serialize_message(_image(3, 4, 'mono8', 'c', False, 0, 1)))
    arr = image_to_array(parse_image_cdr(data))
    data[-1] ^= 0xFF
    assert arr[-1, -1] == data[-1]


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 10**6), cut=st.integers(0, 400), flips=st.lists(
    st.tuples(st.integers(0, 10**6), st.integers(0, 7)), max_size=4),
    junk=st.binary(max_size=64))
def test_truncated_flipped_or_random_bytes_give_only_bad_image_errors(seed, cut, flips, junk):
    data = bytearray(serialize_message(_image(5, 6, 'mono8', 'camera', False, 1, seed)))
    data = data[:cut] if cut < len(data) else data
    for pos, bit in flips:
        if data:
            data[pos % len(data)] ^= 1 << bit
    for candidate in (bytes(data), junk, b'\x00\x01\x00\x00' + junk):
        try:
            image_to_array(parse_image_cdr(candidate))
        except BadImageError as exc:
            assert exc.cause in ('malformed_cdr', 'unsupported_encoding', 'zero_size',
                                 'step_too_small', 'data_length', 'too_small')


@pytest.mark.parametrize('data, match', [
    (b'', 'encapsulation'),
    (b'\x00\x07\x00\x00' + b'\0' * 64, 'encapsulation'),
    (b'\x00\x01\x00\x00\x01\x00\x00\x00', 'header.stamp: needs 8 bytes'),
    (b'\x00\x01\x00\x00' + struct.pack('<iI', 0, 1_000_000_000) + b'\0' * 32, '>= 1e9'),
    (b'\x00\x01\x00\x00' + struct.pack('<iII', 0, 0, 0) + b'\0' * 32, 'string length 0'),
    (b'\x00\x01\x00\x00' + struct.pack('<iII', 0, 0, 2) + b'ab\0\0' + b'\0' * 32,
     'not NUL-terminated'),
    (b'\x00\x01\x00\x00' + struct.pack('<iII', 0, 0, 2) + b'\xff\0\0\0' + b'\0' * 32,
     'not UTF-8'),
])
def test_malformed_cdr_is_named(data, match):
    with pytest.raises(BadImageError, match=match) as exc:
        parse_image_cdr(data)
    assert exc.value.cause == 'malformed_cdr'


def _msg(**kw):
    base = dict(height=4, width=5, encoding='mono8', is_bigendian=0, step=5,
                data=bytes(range(20)))
    base.update(kw)
    return SimpleNamespace(**base)


def test_image_decoding_respects_step_and_endianness():
    a = np.arange(4 * 5, dtype=np.uint16).reshape(4, 5) * 300
    padded = np.zeros((4, 7), np.uint16)
    padded[:, :5] = a
    for big in (0, 1):
        raw = padded.astype('>u2' if big else '<u2').tobytes()
        out = image_to_array(_msg(encoding='mono16', step=14, data=raw, is_bigendian=big))
        np.testing.assert_array_equal(out, a)
    out = image_to_array(_msg())
    np.testing.assert_array_equal(out, np.arange(20, dtype=np.uint8).reshape(4, 5))


@pytest.mark.parametrize(('kw', 'cause'), [
    ({'encoding': 'rgb8'}, 'unsupported_encoding'),
    ({'encoding': 'bgr8', 'data': b''}, 'unsupported_encoding'),
    ({'height': 0, 'width': 0, 'step': 0, 'data': b''}, 'zero_size'),
    ({'width': 0}, 'zero_size'),
    ({'step': 4}, 'step_too_small'),
    ({'encoding': 'mono16', 'step': 9, 'data': bytes(36)}, 'step_too_small'),
    ({'data': bytes(19)}, 'data_length'),
    ({'data': bytes(21)}, 'data_length'),
    ({'height': 2, 'data': bytes(10)}, 'too_small'),
])
def test_bad_images_name_their_cause(kw, cause):
    with pytest.raises(BadImageError) as exc:
        image_to_array(_msg(**kw))
    assert exc.value.cause == cause
