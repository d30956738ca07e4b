"""galvoscan_common.cdr: the bytes rclpy reads, the fields rclpy wrote, CdrError otherwise."""

import struct

import numpy as np
import pytest
from galvoscan_msgs.msg import GalvoState, StripeCenters
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, PointCloud2, PointField

from galvoscan_common import cdr

# ROS strings are UTF-8 C strings: no NUL inside, no lone surrogates
TEXT = st.text(st.characters(blacklist_characters='\x00', blacklist_categories=('Cs',)),
               max_size=12)
F64 = st.floats(allow_nan=False, width=64)


@st.composite
def galvo_states(draw):
    return cdr.GalvoState(
        cdr.Header(draw(st.integers(-2**31, 2**31 - 1)), draw(st.integers(0, 999_999_999)),
                   draw(TEXT)),
        draw(st.integers(0, 2**64 - 1)), *(draw(F64) for _ in range(4)), draw(st.booleans()),
        draw(st.integers(0, 255)))


@st.composite
def stripe_centers(draw):
    n = draw(st.integers(0, 40))
    rng = np.random.default_rng(draw(st.integers(0, 10**6)))
    arrays = [rng.normal(0, 300, n).astype(np.float32) for _ in range(4)]
    return cdr.StripeCenters(
        cdr.Header(draw(st.integers(-2**31, 2**31 - 1)), draw(st.integers(0, 999_999_999)),
                   draw(TEXT)),
        draw(galvo_states()), draw(st.integers(0, 2**32 - 1)), draw(st.integers(0, 2**32 - 1)),
        *arrays, draw(TEXT), float(np.float32(draw(F64.filter(lambda x: abs(x) < 1e30)))),
        float(np.float32(draw(st.floats(0, 1e6)))), draw(st.integers(0, 2**32 - 1)),
        draw(st.integers(0, 1)), draw(st.integers(0, 2**32 - 1)),
        float(np.float32(draw(st.floats(0, 1)))), float(np.float32(draw(st.floats(0, 65535)))))


def _assert_state_equal(ours: cdr.GalvoState, ros: GalvoState):
    assert (ours.header.sec, ours.header.nanosec, ours.header.frame_id) == (
        ros.header.stamp.sec, ros.header.stamp.nanosec, ros.header.frame_id)
    assert (ours.seq, ours.g1_pan_voltage, ours.g1_tilt_voltage, ours.g2_pan_voltage,
            ours.g2_tilt_voltage, ours.laser_on, ours.status) == (
        ros.seq, ros.g1_pan_voltage, ros.g1_tilt_voltage, ros.g2_pan_voltage,
        ros.g2_tilt_voltage, ros.laser_on, ros.status)


def _assert_centers_equal(ours: cdr.StripeCenters, ros: StripeCenters):
    assert (ours.header.sec, ours.header.nanosec, ours.header.frame_id) == (
        ros.header.stamp.sec, ros.header.stamp.nanosec, ros.header.frame_id)
    _assert_state_equal(ours.galvo, ros.galvo)
    for name in ('u', 'v', 'width', 'strength'):
        np.testing.assert_array_equal(getattr(ours, name),
                                      np.asarray(getattr(ros, name), np.float32))
    assert (ours.image_width, ours.image_height, ours.method, ours.sigma, ours.min_strength,
            ours.roi_half_height, ours.orientation, ours.rejected_secondary,
            ours.saturated_fraction, ours.peak_level) == (
        ros.image_width, ros.image_height, ros.method, ros.sigma, ros.min_strength,
        ros.roi_half_height, ros.orientation, ros.rejected_secondary, ros.saturated_fraction,
        ros.peak_level)


@settings(max_examples=60, deadline=None)
@given(m=stripe_centers())
def test_stripe_centers_written_are_what_rclpy_reads(m):
    _assert_centers_equal(m, deserialize_message(cdr.serialize_stripe_centers(m), StripeCenters))


@settings(max_examples=60, deadline=None)
@given(m=stripe_centers())
def test_stripe_centers_read_are_what_rclpy_wrote(m):
    ros = deserialize_message(cdr.serialize_stripe_centers(m), StripeCenters)
    ours = cdr.parse_stripe_centers(serialize_message(ros))
    _assert_centers_equal(ours, ros)
    assert not ours.u.flags.writeable      # a view of the received bytes, not a copy


@settings(max_examples=60, deadline=None)
@given(g=galvo_states())
def test_galvo_state_round_trips_through_rclpy(g):
    ros = deserialize_message(cdr.serialize_galvo_state(g), GalvoState)
    _assert_state_equal(g, ros)
    _assert_state_equal(cdr.parse_galvo_state(serialize_message(ros)), ros)


def test_big_endian_galvo_state_reads_the_same():
    """A big-endian CDR writer (encapsulation 0x0000) gives the same state."""
    body = struct.pack('>iI', -3, 17) + struct.pack('>I', 3) + b'v0\0'
    body += b'\0' * (-len(body) % 8) + struct.pack('>Qdddd', 42, 1.5, -2.25, 3.0, -9.75)
    body += b'\x01\x02'
    g = cdr.parse_galvo_state(b'\x00\x00\x00\x00' + body)
    assert (g.header.sec, g.header.nanosec, g.header.frame_id, g.seq) == (-3, 17, 'v0', 42)
    assert (g.g1_pan_voltage, g.g1_tilt_voltage, g.g2_pan_voltage, g.g2_tilt_voltage) == (
        1.5, -2.25, 3.0, -9.75)
    assert (g.laser_on, g.status) == (True, 2)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(0, 50), seed=st.integers(0, 10**6), frame_id=TEXT)
def test_point_cloud_is_what_rclpy_reads(n, seed, frame_id):
    dtype = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('i', '<f8'), ('n', '<u2')])
    pts = np.zeros(n, dtype)
    rng = np.random.default_rng(seed)
    for name in dtype.names:
        pts[name] = rng.uniform(0, 100, n)
    ros = deserialize_message(cdr.serialize_point_cloud(pts, cdr.Header(5, 6, frame_id)),
                              PointCloud2)
    assert (ros.header.stamp.sec, ros.header.stamp.nanosec, ros.header.frame_id) == (
        5, 6, frame_id)
    assert (ros.height, ros.width, ros.point_step, ros.row_step) == (
        1, n, dtype.itemsize, n * dtype.itemsize)
    assert (ros.is_bigendian, ros.is_dense) == (False, True)
    assert [(f.name, f.offset, f.datatype, f.count) for f in ros.fields] == [
        ('x', 0, PointField.FLOAT32, 1), ('y', 4, PointField.FLOAT32, 1),
        ('z', 8, PointField.FLOAT32, 1), ('i', 12, PointField.FLOAT64, 1),
        ('n', 20, PointField.UINT16, 1)]
    assert bytes(ros.data) == pts.tobytes()
    # the same points in parts (an accumulated scan): the same message
    cuts = np.sort(rng.integers(0, n + 1, 3))
    parts = np.split(pts, cuts)
    assert cdr.serialize_point_cloud(parts, cdr.Header(5, 6, frame_id)) == \
        cdr.serialize_point_cloud(pts, cdr.Header(5, 6, frame_id))


@settings(max_examples=40, deadline=None)
@given(h=st.integers(0, 9), w=st.integers(0, 9), dtype=st.sampled_from(['u1', '<u2', '>u2']),
       seed=st.integers(0, 10**6), frame_id=TEXT)
def test_image_is_what_rclpy_reads(h, w, dtype, seed, frame_id):
    img = np.random.default_rng(seed).integers(0, 2**16, (h, w)).astype(dtype)
    ros = deserialize_message(cdr.serialize_image(img, cdr.Header(-7, 8, frame_id)), Image)
    assert (ros.header.stamp.sec, ros.header.stamp.nanosec, ros.header.frame_id) == (
        -7, 8, frame_id)
    assert (ros.height, ros.width, ros.step) == (h, w, w * img.itemsize)
    assert (ros.encoding, ros.is_bigendian) == (
        'mono8' if img.itemsize == 1 else 'mono16', dtype == '>u2')
    assert bytes(ros.data) == img.tobytes()


def test_image_of_a_view_is_written_contiguous():
    img = np.arange(60, dtype=np.uint8).reshape(6, 10)[1:5, 2:9]
    ros = deserialize_message(cdr.serialize_image(img, cdr.Header()), Image)
    assert (ros.height, ros.width, ros.step, bytes(ros.data)) == (4, 7, 7, img.tobytes())


def test_image_rejects_what_mono_encodings_cannot_describe():
    for bad in (np.zeros((2, 2), np.float32), np.zeros((2, 2, 3), np.uint8),
                np.zeros(4, np.uint8), [[1, 2], [3, 4]]):
        with pytest.raises(ValueError, match='image'):
            cdr.serialize_image(bad, cdr.Header())


def test_point_cloud_rejects_what_point_field_cannot_describe():
    with pytest.raises(ValueError, match='structured'):
        cdr.serialize_point_cloud(np.zeros(3), cdr.Header())
    with pytest.raises(ValueError, match='PointField'):
        cdr.serialize_point_cloud(np.zeros(3, [('x', '>f4')]), cdr.Header())
    xyz = np.zeros(3, [('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    with pytest.raises(ValueError, match='same dtype'):
        cdr.serialize_point_cloud([xyz, np.zeros(2, [('x', '<f4')])], cdr.Header())
    with pytest.raises(ValueError, match='same dtype'):
        cdr.serialize_point_cloud([xyz.reshape(3, 1)], cdr.Header())
    with pytest.raises(ValueError, match='empty sequence'):
        cdr.serialize_point_cloud([], cdr.Header())


@settings(max_examples=300, deadline=None)
@given(m=stripe_centers(), cut=st.integers(0, 1000), flips=st.lists(
    st.tuples(st.integers(0, 10**6), st.integers(0, 7)), max_size=4),
    junk=st.binary(max_size=64))
def test_damaged_messages_raise_only_cdr_error(m, cut, flips, junk):
    """Truncated, bit-flipped, extended or random bytes: a parse result or CdrError."""
    good = bytearray(cdr.serialize_stripe_centers(m))
    for data in (good[:cut], good + junk, junk, bytes(good[:2]) + junk):
        for parse in (cdr.parse_stripe_centers, cdr.parse_galvo_state):
            try:
                parse(bytes(data))
            except cdr.CdrError:
                pass
    for pos, bit in flips:
        good[pos % len(good)] ^= 1 << bit
    for parse in (cdr.parse_stripe_centers, cdr.parse_galvo_state):
        try:
            parse(bytes(good))
        except cdr.CdrError:
            pass


def test_clear_errors():
    good = cdr.serialize_stripe_centers(cdr.StripeCenters(
        cdr.Header(1, 2, 'cam'), cdr.GalvoState(cdr.Header(), 0, 0.0, 0.0, 0.0, 0.0, True, 0),
        720, 540, *(np.zeros(3, np.float32) for _ in range(4)), 'steger', 1.0, 20.0, 12, 0, 0))
    cases = [(b'', 'encapsulation'), (b'\x07\x01\x00\x00' + good[4:], 'encapsulation'),
             (good[:-6], 'needs'), (good + b'\0' * 8, 'after the last field'),
             (None, 'bytes-like')]
    for data, words in cases:
        with pytest.raises(cdr.CdrError, match=words):
            cdr.parse_stripe_centers(data)
    bad_nsec = bytearray(good)
    bad_nsec[8:12] = struct.pack('<I', 10**9)
    with pytest.raises(cdr.CdrError, match='nanosec'):
        cdr.parse_stripe_centers(bytes(bad_nsec))
