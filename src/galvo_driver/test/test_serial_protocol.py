"""Serial protocol: COBS, CRC, DAC codes, message codec and the streaming decoder."""

import binascii
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from galvo_driver.serial_link import protocol as p

SETTINGS = settings(max_examples=200, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------ independent references
def ref_cobs_encode(data: bytes) -> bytes:
    """Byte-by-byte COBS encoder after Cheshire & Baker (the well-known C loop)."""
    out = bytearray([0])
    code_pos, code = 0, 1
    n = len(data)
    for i, b in enumerate(data):
        if b:
            out.append(b)
            code += 1
        if not b or code == 0xFF:
            out[code_pos] = code
            code = 1
            code_pos = len(out)
            if not b or i < n - 1:
                out.append(0)
    if code_pos < len(out):
        out[code_pos] = code
    return bytes(out)


def ref_crc16_ccitt_false(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def ref_crc32(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


# ------------------------------------------------------------------ CRC and COBS
def test_crc32_check_value_and_reference():
    assert p.crc32(b'123456789') == 0xCBF43926
    data = bytes(range(256)) * 3
    assert p.crc32(data) == ref_crc32(data)
    # binascii.crc_hqx is CRC-16/CCITT-FALSE with init 0xFFFF (the brief's alternative)
    assert binascii.crc_hqx(b'123456789', 0xFFFF) == ref_crc16_ccitt_false(b'123456789')


@pytest.mark.parametrize('raw, enc', [
    (b'', b'\x01'),
    (b'\x00', b'\x01\x01'),
    (b'\x00\x00', b'\x01\x01\x01'),
    (b'\x00\x11\x00', b'\x01\x02\x11\x01'),
    (b'\x11\x22\x00\x33', b'\x03\x11\x22\x02\x33'),
    (b'\x11\x22\x33\x44', b'\x05\x11\x22\x33\x44'),
    (b'\x11\x00\x00\x00', b'\x02\x11\x01\x01\x01'),
    (bytes(range(1, 255)), b'\xff' + bytes(range(1, 255))),
    (bytes(range(0, 255)), b'\x01\xff' + bytes(range(1, 255))),
    (bytes(range(1, 256)), b'\xff' + bytes(range(1, 255)) + b'\x02\xff'),
])
def test_cobs_known_vectors(raw, enc):
    # vectors of the COBS article (Wikipedia "Consistent Overhead Byte Stuffing")
    assert p.cobs_encode(raw) == enc
    assert p.cobs_decode(enc) == raw


@SETTINGS
@given(st.binary(max_size=700))
def test_cobs_matches_reference_and_round_trips(data):
    enc = p.cobs_encode(data)
    assert enc == ref_cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + 1 + len(data) // 254
    assert p.cobs_decode(enc) == data


@pytest.mark.parametrize('bad', [b'\x05\x11\x22', b'\x02\x11\x00\x01', b'\x00'])
def test_cobs_decode_rejects_bad_input(bad):
    with pytest.raises(p.ProtocolError):
        p.cobs_decode(bad)


# ------------------------------------------------------------------ volts <-> codes
def test_codes_exact_points():
    codes = p.volts_to_codes([-10.0, 0.0, 10.0, -0.0])
    np.testing.assert_array_equal(codes, [1, 32768, 65535, 32768])
    np.testing.assert_array_equal(p.codes_to_volts(codes), [-10.0, 0.0, 10.0, 0.0])
    assert p.volts_to_codes(np.zeros((3, 4))).shape == (3, 4)


def test_codes_rounding_half_up():
    lsb = 10.0 / 32767
    # exactly halfway between two codes rounds up; just below rounds down
    np.testing.assert_array_equal(p.volts_to_codes([2.5 * lsb, -2.5 * lsb]),
                                  [32768 + 3, 32768 - 2])
    np.testing.assert_array_equal(p.volts_to_codes([2.4 * lsb, 2.6 * lsb]),
                                  [32768 + 2, 32768 + 3])


@pytest.mark.parametrize('bad', [[np.nan], [np.inf], [10.000001], [-10.5], [[0, 0, 0, 11]]])
def test_volts_to_codes_rejects(bad):
    with pytest.raises(ValueError, match='voltages'):
        p.volts_to_codes(bad)


@pytest.mark.parametrize('bad', [[0], [65536], [-1], [1.5]])
def test_codes_to_volts_rejects(bad):
    with pytest.raises(ValueError, match='codes'):
        p.codes_to_volts(bad)


@SETTINGS
@given(st.lists(st.floats(-10.0, 10.0, allow_nan=False), min_size=1, max_size=40))
def test_volts_codes_round_trip_error_below_half_lsb(volts):
    v = np.array(volts)
    codes = p.volts_to_codes(v)
    assert codes.dtype == np.uint16
    assert codes.min() >= 1
    lsb = 20.0 / 65534
    back = p.codes_to_volts(codes)
    assert np.all(np.abs(back - v) <= lsb / 2 * (1 + 1e-9))
    # idempotent on the code grid, and monotone
    np.testing.assert_array_equal(p.volts_to_codes(back), codes)
    order = np.argsort(v, kind='stable')
    assert np.all(np.diff(codes[order].astype(int)) >= 0)


# ------------------------------------------------------------------ message codec
codes4 = st.tuples(*[st.integers(1, 65535)] * 4)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
u64 = st.integers(0, 2**64 - 1)
info_st = st.builds(p.BoardInfo, u16, st.text('abcdefghijklmnopqrstuvwxyz-0123456789',
                                              max_size=16),
                    st.integers(0, 255), st.integers(0, 255), u32, u64, u32, u32)
status_st = st.builds(p.BoardStatus, u32, u64, st.sampled_from(sorted(p.STATE_NAMES)),
                      st.integers(0, 255), st.booleans(), codes4, u16, u32, u32)
messages = st.one_of(
    st.builds(p.Hello, u16),
    st.just(p.Heartbeat()),
    st.builds(p.SetVolts, codes4),
    st.builds(p.Laser, st.booleans()),
    st.builds(p.ScanBegin, u16, st.integers(1, 0xFFFFFFFF)),
    st.builds(p.ScanData, u16, u32,
              st.lists(codes4, min_size=1, max_size=p.ROWS_PER_CHUNK).map(tuple)),
    st.builds(p.ScanStart, u16, st.integers(1, 0xFFFFFFFF), st.integers(1, 0xFFFFFFFF),
              st.booleans(), u32),
    st.just(p.ScanStop()), st.just(p.Safe()), st.just(p.GetStatus()),
    st.builds(p.Ack, u16, st.binary(max_size=p.MAX_PAYLOAD - 2)),
    st.builds(p.Nak, u16, st.integers(0, 255)),
    st.builds(p.Event, u32, u16, u32, u64, codes4, st.booleans(), st.integers(0, 2)),
    st.builds(p.Boot, info_st),
    st.builds(p.Status, status_st),
    st.builds(p.Fault, st.integers(0, 255), u64, u32),
)


@SETTINGS
@given(u16, messages)
def test_message_round_trip(seq, msg):
    frame = p.encode_frame(seq, msg)
    assert frame.endswith(b'\x00') and frame.count(0) == 1
    assert len(frame) - 1 <= p.MAX_ENCODED_FRAME
    pkt = p.decode_frame(frame[:-1])
    assert pkt == p.Packet(seq, msg)
    # the packet layout: type byte, LE seq, payload, LE CRC-32 of everything before it
    raw = p.cobs_decode(frame[:-1])
    assert raw[0] == msg.TYPE
    assert struct.unpack_from('<H', raw, 1)[0] == seq
    assert struct.unpack_from('<I', raw, len(raw) - 4)[0] == ref_crc32(raw[:-4])


def test_event_byte_layout():
    ev = p.Event(0x01020304, 7, 9, 123456789, (1, 32768, 65535, 2), True, 0)
    raw = p.cobs_decode(p.encode_frame(5, ev)[:-1])
    expected = (bytes([0x82, 5, 0]) + (0x01020304).to_bytes(4, 'little')
                + (7).to_bytes(2, 'little') + (9).to_bytes(4, 'little')
                + (123456789).to_bytes(8, 'little')
                + b''.join(c.to_bytes(2, 'little') for c in (1, 32768, 65535, 2))
                + b'\x01\x00')
    assert raw[:-4] == expected


def _frame_with_body(body: bytes) -> bytes:
    return p.cobs_encode(body + struct.pack('<I', ref_crc32(body)))


@pytest.mark.parametrize('body, match', [
    (bytes([0x7E, 3, 0]), 'unknown message type'),
    (bytes([p.SET_VOLTS, 3, 0]) + bytes(6), 'expected 8'),
    (bytes([p.SET_VOLTS, 3, 0]) + bytes(8), 'reserved'),
    (bytes([p.LASER, 3, 0, 2]), 'laser'),
    (bytes([p.SCAN_DATA, 3, 0]) + struct.pack('<HIB', 1, 0, 0), 'count'),
    (bytes([p.SCAN_DATA, 3, 0]) + struct.pack('<HIB', 1, 0, 2) + bytes(8), 'expected'),
    (bytes([p.SAFE, 3, 0, 1]), 'empty payload'),
])
def test_malformed_payload_is_protocol_error_with_seq(body, match):
    with pytest.raises(p.ProtocolError, match=match) as info:
        p.decode_frame(_frame_with_body(body))
    assert info.value.seq == 3


def test_bad_crc_has_no_seq():
    frame = bytearray(p.encode_frame(3, p.Safe())[:-1])
    raw = bytearray(p.cobs_decode(bytes(frame)))
    raw[-1] ^= 0x01
    with pytest.raises(p.ProtocolError, match='CRC') as info:
        p.decode_frame(p.cobs_encode(bytes(raw)))
    assert info.value.seq is None


def test_encode_rejects_bad_seq_and_oversize():
    with pytest.raises(ValueError, match='seq'):
        p.encode_frame(70000, p.Safe())
    with pytest.raises(ValueError, match='payload'):
        p.encode_frame(1, p.Ack(1, bytes(p.MAX_PAYLOAD)))


# ------------------------------------------------------------------ streaming decoder
@SETTINGS
@given(st.lists(st.tuples(u16, messages), min_size=1, max_size=12), st.data())
def test_decoder_any_chunking(items, data):
    stream = b''.join(p.encode_frame(s, m) for s, m in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    dec = p.FrameDecoder()
    out = []
    prev = 0
    for c in cuts + [len(stream)]:
        out += dec.feed(stream[prev:c])
        prev = c
    assert out == [p.Packet(s, m) for s, m in items]
    assert dec.error_count == 0 and dec.buffered == 0


def test_decoder_resyncs_after_garbage():
    good = [p.encode_frame(i, p.SetVolts((i + 1, 2, 3, 4))) for i in range(5)]
    garbage = bytes(range(1, 200)) * 3  # no delimiter, longer than a frame
    stream = good[0] + garbage + b'\x00' + good[1] + b'\xff\x13\x00' + good[2] + good[3][:7] \
        + good[4]
    dec = p.FrameDecoder()
    out = dec.feed(stream)
    # good[3] was truncated and merged with good[4]: both are lost, nothing else
    assert [pkt.seq for pkt in out] == [0, 1, 2]
    assert dec.error_count >= 2
    assert dec.feed(good[4]) == [p.Packet(4, p.SetVolts((5, 2, 3, 4)))]


def test_decoder_buffer_is_bounded():
    dec = p.FrameDecoder()
    for _ in range(200):
        dec.feed(b'\x01' * 1000)
        assert dec.buffered <= p.MAX_ENCODED_FRAME
    assert dec.errors['oversize'] == 1
    # the tail of the over-long frame is skipped, then decoding resumes
    frame = p.encode_frame(9, p.Safe())
    assert dec.feed(b'\x02\x03' + frame) == []
    assert dec.feed(frame) == [p.Packet(9, p.Safe())]


def test_decoder_on_error_callback():
    seen = []
    dec = p.FrameDecoder(on_error=seen.append)
    dec.feed(_frame_with_body(bytes([p.LASER, 0x34, 0x12, 7])) + b'\x00')
    assert len(seen) == 1 and seen[0].seq == 0x1234 and seen[0].msg_type == p.LASER
    assert dec.errors['message'] == 1


# ------------------------------------------------------------------ fuzz
@st.composite
def mangled_frames(draw):
    seq = draw(u16)
    frame = bytearray(p.encode_frame(seq, draw(messages))[:-1])
    kind = draw(st.sampled_from(['random', 'truncate', 'flip', 'flips']))
    if kind == 'random':
        return draw(st.binary(max_size=400)), None
    if kind == 'truncate':
        cut = draw(st.integers(0, len(frame) - 1))
        return bytes(frame[:cut]), None
    n_flips = 1 if kind == 'flip' else draw(st.integers(2, 8))
    for _ in range(n_flips):
        pos = draw(st.integers(0, len(frame) - 1))
        frame[pos] ^= 1 << draw(st.integers(0, 7))
    return bytes(frame), n_flips


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mangled_frames())
def test_fuzz_only_protocol_errors(case):
    data, n_flips = case
    try:
        p.decode_frame(data)
    except p.ProtocolError:
        pass
    else:
        # Only an unmodified-in-effect frame could pass: never for one bit flip (CRC-32
        # detects every single-bit error; a flipped COBS code byte fails COBS or the CRC).
        assert n_flips != 1
    dec = p.FrameDecoder()
    out = dec.feed(data + b'\x00')
    assert len(out) <= 1 + data.count(0)
    assert dec.buffered == 0
    # whatever came before, the decoder is in sync for the next frame
    assert dec.feed(p.encode_frame(1, p.Safe())) == [p.Packet(1, p.Safe())]


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.integers(0, 255), st.sampled_from(sorted(p.MESSAGE_TYPES))), u16,
       st.binary(max_size=p.MAX_PAYLOAD))
def test_fuzz_payload_behind_valid_crc(msg_type, seq, payload):
    """A well-framed packet with any type and payload: a ProtocolError naming its seq, or
    a message that encodes back to exactly the same bytes."""
    frame = _frame_with_body(bytes([msg_type]) + struct.pack('<H', seq) + payload)
    try:
        pkt = p.decode_frame(frame)
    except p.ProtocolError as err:
        assert err.seq == seq and err.msg_type == msg_type
    else:
        assert pkt.seq == seq and pkt.msg.TYPE == msg_type
        assert p.encode_frame(pkt.seq, pkt.msg)[:-1] == frame
