"""The galvo board firmware in simavr, against a scripted host in simulated time.

Everything here is measured in the simulated CPU's cycles (16 MHz) from the harness log, so
the results do not depend on the load of the machine running the tests.
"""

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest

from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link import simavr_board as sb

F = sb.F_CPU
ZERO = (p.CODE_ZERO,) * 4


@pytest.fixture(scope='module', autouse=True)
def firmware_built():
    sb.build()


def session(script: sb.Script, t_us: float = 1000.0) -> None:
    script.send(t_us, p.Hello(p.PROTOCOL_VERSION))


def acked(log: sb.HarnessLog, script: sb.Script) -> None:
    """Every command of the script was answered with an ACK, exactly once."""
    ans = sb.answers(log)
    for seq, msg in script.sent.items():
        if seq == 0:
            continue
        got = ans.get(seq, [])
        assert len(got) == 1 and isinstance(got[0], p.Ack), (seq, msg, got)


def test_ten_thousand_triggers_fire_on_the_codes_their_events_report():
    """>= 10,000 triggers at 500 Hz (13 scans of up to 768 rows, the board's table size):
    at every rising edge the DAC outputs hold exactly the codes of that trigger's EVENT,
    which are the row the host uploaded; the edges come every 32,000 cycles exactly."""
    rng = np.random.default_rng(5)
    script = sb.Script()
    session(script)
    period_us = 2000
    t = 5000.0
    scans = []
    total = 0
    while total < 10_000:
        n = min(768, 10_000 - total)
        codes = rng.integers(1, 65536, (n, 4)).astype(np.uint16)
        scan_id = len(scans) + 1
        t_start = script.upload_scan(t, scan_id, codes, period_us)
        scans.append((scan_id, codes))
        total += n
        t = t_start + n * period_us + 100_000
    script.heartbeats(1000.0, t)
    log = sb.run_script(script, t + 5000)
    assert not log.crashed and log.frame_errors == 0
    acked(log, script)
    events = log.events()
    assert log.decode_errors == 0
    assert len(events) == 10_000
    edges = log.rising_edges()
    assert len(edges) == 10_000
    by_scan = {sid: codes for sid, codes in scans}
    mismatches = 0
    for edge, (_, ev) in zip(edges, events, strict=True):
        expected = tuple(int(c) for c in by_scan[ev.scan_id][ev.index])
        mismatches += (log.codes_at(int(edge)) != ev.codes) + (ev.codes != expected)
        assert ev.laser_on and ev.status == p.EVENT_SETTLED
    assert mismatches == 0
    # the outputs reached the row half a period before its edge (the galvos' settling time)
    for edge in edges[:50]:
        cycles = [o[0] for o in log.outputs if o[0] <= edge]
        assert edge - cycles[-1] >= 0.45 * period_us * 16
    # trigger period within each scan: 2 ms = 32,000 cycles. The compare unit sets the pin
    # on the exact cycle; simavr shows it at the end of the instruction running then, up
    # to 4 cycles (0.25 us) later, which is all the spread there may be.
    start = 0
    for sid, codes in scans:
        per = np.diff(edges[start:start + len(codes)])
        assert np.abs(per - period_us * 16).max() <= 4, (sid, per.min(), per.max())
        ts = np.array([ev.timestamp_us for _, ev in events[start:start + len(codes)]])
        assert np.all(np.diff(ts) == period_us)
        start += len(codes)
    # the EVENT stamps are the board clock at the edges: one offset for the whole run
    ts_all = np.array([ev.timestamp_us for _, ev in events], dtype=np.int64)
    offset = edges - ts_all * 16
    assert np.ptp(offset) <= 16 + 4  # the microsecond the stamp truncates to, and the above


def test_watchdog_makes_the_board_safe_within_300_ms():
    script = sb.Script()
    session(script)
    script.send(3000.0, p.SetVolts((40000, 20000, 50000, 1000)))
    script.send(5000.0, p.Laser(True))
    script.heartbeats(10_000.0, 400_000.0)  # the last heartbeat at 360 ms
    log = sb.run_script(script, 1_000_000.0)
    acked(log, script)
    last_rx = log.rx[-1][0]
    assert log.codes_at(last_rx) == (40000, 20000, 50000, 1000)
    assert log.level_at(log.laser, last_rx) == 1
    safe_at = next(c for c, codes, *_ in log.outputs if c > last_rx and codes == ZERO)
    laser_off = next(c for c, v in log.laser if c > last_rx and v == 0)
    watchdog_s = (max(safe_at, laser_off) - last_rx) / F
    assert 0.150 <= watchdog_s <= 0.300, watchdog_s
    faults = [m for _, pk in log.packets() if isinstance((m := pk.msg), p.Fault)]
    assert [f.code for f in faults] == [p.FAULT_WATCHDOG]
    status = [m.status for _, pk in log.packets() if isinstance((m := pk.msg), p.Status)]
    assert status[-1].flags & p.FLAG_WATCHDOG and status[-1].codes == ZERO


def test_watchdog_stops_a_scan():
    script = sb.Script()
    session(script)
    codes = np.full((700, 4), 40000, np.uint16)
    t0 = script.upload_scan(3000.0, 1, codes, 1000)
    script.heartbeats(10_000.0, t0 + 100_000.0)
    log = sb.run_script(script, t0 + 700_000.0)
    last_rx = log.rx[-1][0]
    edges = log.rising_edges()
    assert 0 < len(edges) < 700
    assert (edges[-1] - last_rx) / F <= 0.300
    safe_at = next(c for c, codes, *_ in log.outputs if c > last_rx and codes == ZERO)
    assert (safe_at - last_rx) / F <= 0.300
    assert log.level_at(log.laser, log.end) == 0 and log.level_at(log.trigger, log.end) == 0


def test_interlock_drops_the_laser_within_a_trigger_period_and_parks_the_galvos():
    script = sb.Script()
    session(script)
    codes = np.full((500, 4), 50000, np.uint16)
    period_us = 2000
    t0 = script.upload_scan(3000.0, 1, codes, period_us)
    t_open = t0 + 100_000.0 + 333.0
    script.at(t_open, 'interlock open')
    script.send(t_open + 20_000, p.Laser(True))
    script.send(t_open + 24_000, p.SetVolts((1000, 1000, 1000, 1000)))
    script.send(t_open + 28_000, p.ScanStart(1, 500, period_us, True, p.table_crc(codes)))
    script.at(t_open + 40_000, 'interlock closed')
    script.send(t_open + 50_000, p.Laser(True))
    script.heartbeats(10_000.0, t_open + 80_000)
    log = sb.run_script(script, t_open + 60_000)
    open_cycle = next(c for c, is_open in log.interlock if is_open)
    laser_off = next(c for c, v in log.laser if c >= open_cycle and v == 0)
    assert (laser_off - open_cycle) / F < period_us * 1e-6
    assert (laser_off - open_cycle) / F < 20e-6  # in the interrupt, not the main loop
    edges = log.rising_edges()
    assert len(edges) > 10 and edges[-1] < open_cycle  # no trigger after it opened
    parked = next(c for c, codes, *_ in log.outputs if c > open_cycle and codes == ZERO)
    assert (parked - open_cycle) / F < period_us * 1e-6
    pkts = [pk.msg for _, pk in log.packets()]
    faults = [m for m in pkts if isinstance(m, p.Fault)]
    assert [f.code for f in faults] == [p.FAULT_INTERLOCK]
    ans = sb.answers(log)
    seqs = sorted(ans)
    # while open: LASER on, SET_VOLTS and SCAN_START with the laser are refused
    refused = [ans[s][0] for s in seqs[-4:-1]]
    assert all(isinstance(a, p.Nak) and a.reason == p.NAK_INTERLOCK for a in refused)
    assert isinstance(ans[seqs[-1]][0], p.Ack)  # closed again: the laser may go on
    assert log.level_at(log.laser, log.end) == 1
    assert log.level_at(log.laser, open_cycle + 30_000 * 16) == 0


def test_laser_enable_is_off_from_reset():
    script = sb.Script()
    session(script)
    script.send(3000.0, p.Laser(True))
    script.at(20_000.0, 'reset')
    script.heartbeats(1000.0, 40_000.0)
    log = sb.run_script(script, 50_000.0)
    assert log.laser[0][1] == 1  # the command switched it on
    reset = log.resets[0]
    assert log.level_at(log.laser, reset + 1) == 0
    assert all(v == 0 for c, v in log.laser if c > reset)
    boots = [(c, pk.msg) for c, pk in log.packets() if isinstance(pk.msg, p.Boot)]
    assert len(boots) == 2 and boots[0][1].info.boot_id != boots[1][1].info.boot_id
    # the DAC is set to 0 V before its outputs are powered, on every boot
    first = log.outputs[0]
    assert first[1] == ZERO and first[2] == 0 and first[3] == 4


def malformed_frames() -> list[tuple[str, bytes, bool]]:
    """(name, frame, answered with NAK BAD_MESSAGE) for every way a host frame can be bad."""
    def packet(msg_type: int, seq: int, payload: bytes) -> bytes:
        body = bytes([msg_type]) + seq.to_bytes(2, 'little') + payload
        return p.cobs_encode(body + p.crc32(body).to_bytes(4, 'little')) + b'\x00'

    codes = (30000, 30000, 30000, 30000)
    good = {
        p.HELLO: p.Hello(1).payload(),
        p.SET_VOLTS: p.SetVolts(codes).payload(),
        p.LASER: p.Laser(False).payload(),
        p.SCAN_BEGIN: p.ScanBegin(9, 4).payload(),
        p.SCAN_DATA: p.ScanData(9, 0, (codes,)).payload(),
        p.SCAN_START: p.ScanStart(9, 4, 2000, False, 0).payload(),
    }
    out = []
    seq = 100
    for t, pl in good.items():  # one byte short, one byte long
        out.append((f'type {t:#x} short', packet(t, seq, pl[:-1]), True))
        out.append((f'type {t:#x} long', packet(t, seq + 1, pl + b'\x01'), True))
        seq += 2
    for t in (p.HEARTBEAT, p.SCAN_STOP, p.SAFE, p.GET_STATUS):
        out.append((f'type {t:#x} with a payload', packet(t, seq, b'\x00'), True))
        seq += 1
    out += [
        ('code 0 in SET_VOLTS', packet(p.SET_VOLTS, 120, bytes(2) + bytes(6 * [1])), True),
        ('laser 2', packet(p.LASER, 121, b'\x02'), True),
        ('SCAN_BEGIN 0 rows', packet(p.SCAN_BEGIN, 122, p.ScanBegin(9, 1).payload()[:2]
                                     + bytes(4)), True),
        ('SCAN_DATA count 0', packet(p.SCAN_DATA, 123, bytes(6) + b'\x00'), True),
        ('SCAN_DATA count 30', packet(p.SCAN_DATA, 124, bytes(6) + bytes([30])
                                      + bytes(30 * 8 * [1])), False),  # > 247 bytes
        ('SCAN_DATA count 2, one row', packet(p.SCAN_DATA, 125, bytes(6) + b'\x02'
                                              + bytes(8 * [1])), True),
        ('SCAN_DATA code 0', packet(p.SCAN_DATA, 126, bytes(6) + b'\x01' + bytes(8)), True),
        ('SCAN_START period 0', packet(p.SCAN_START, 127, bytes(2) + b'\x04\0\0\0'
                                       + bytes(9)), True),
        ('SCAN_START 0 rows', packet(p.SCAN_START, 128, bytes(6) + b'\xd0\x07\0\0'
                                     + bytes(5)), True),
        ('SCAN_START laser 2', packet(p.SCAN_START, 129, bytes(2) + b'\x04\0\0\0'
                                      + b'\xd0\x07\0\0\x02' + bytes(4)), True),
        ('unknown type 0x0b', packet(0x0B, 130, b''), True),
        ('unknown type 0x7f', packet(0x7F, 131, b'\x01\x02'), True),
        ('bad CRC', p.encode_frame(132, p.Laser(True))[:-2] + b'\x55\x00', False),
        ('truncated COBS block', bytes([0x09, 1, 2, 3]) + b'\x00', False),
        ('shorter than header + CRC', p.cobs_encode(b'\x09\x01\x00\x00') + b'\x00', False),
        ('oversize frame', bytes(300 * [0x11]) + b'\x00', False),
        ('oversize packet', p.cobs_encode(bytes([p.SET_VOLTS]) + bytes(250 * [1]))
         + b'\x00', False),
    ]
    return out


def test_every_malformed_frame_is_refused_and_changes_nothing():
    frames = malformed_frames()
    script = sb.Script()
    session(script)
    script.send(3000.0, p.SetVolts((40000, 41000, 42000, 43000)))
    t = 6000.0
    for _, frame, _ in frames:
        script.raw(t, frame)
        t += 3000.0
    status_seq = script.send(t + 3000, p.GetStatus())
    script.heartbeats(1000.0, t + 10_000)
    log = sb.run_script(script, t + 10_000)
    ans = sb.answers(log)
    naks = {s: a for s, a in ans.items() if s >= 100 and s < 200}
    for name, frame, answered in frames:
        body = p.cobs_decode(frame[:-1]) if answered else None
        if answered:
            seq = int.from_bytes(body[1:3], 'little')
            got = naks.get(seq, [])
            assert len(got) == 1 and isinstance(got[0], p.Nak), name
            assert got[0].reason == p.NAK_BAD_MESSAGE, name
    assert len(naks) == sum(a for *_, a in frames)
    # nothing executed: the outputs stayed, the laser off, no scan; every frame counted
    status = p.BoardStatus.unpack(ans[status_seq][0].data)
    assert status.codes == (40000, 41000, 42000, 43000) and not status.laser_on
    assert status.state == p.STATE_IDLE and status.rx_errors == len(frames)
    assert not log.trigger and all(v == 0 for _, v in log.laser)


def test_protocol_fuzz_against_the_firmware():
    """benchmarks/protocol_fuzz.py's firmware fuzz, shortened: random, truncated,
    bit-flipped and payload-mangled frames; the firmware neither crashes nor resets,
    answers every canary, sends only frames the host decodes, and drops exactly the frames
    the host-side decoder rejects."""
    path = Path(__file__).resolve().parents[3] / 'benchmarks' / 'protocol_fuzz.py'
    spec = importlib.util.spec_from_file_location('protocol_fuzz_bench', path)
    fuzz = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fuzz)
    res = fuzz.fuzz_firmware(1500, seed=3)
    assert res['fw_rx_errors_expected'] > 1000
    for key in ('fw_crashes', 'fw_resets', 'fw_canaries_unanswered', 'fw_undecodable_output',
                'fw_rx_error_mismatch'):
        assert res[key] == 0, res


def test_the_emulator_refuses_the_same_malformed_frames():
    """The Python emulator answers the same malformed frames as the firmware (the
    reference): NAK BAD_MESSAGE for the same seqs, the same rx_errors count."""
    import serial

    from galvo_driver.serial_link.emulator import FirmwareEmulator

    frames = malformed_frames()
    with FirmwareEmulator('pty', seed=1, watchdog=5.0) as emu:
        ser = serial.serial_for_url(emu.port, timeout=0.2)
        try:
            dec = p.FrameDecoder()
            ser.write(p.encode_frame(1, p.Hello(p.PROTOCOL_VERSION)))
            for _, frame, _ in frames:
                ser.write(frame)
            ser.write(p.encode_frame(99, p.GetStatus()))
            got = []
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                got += dec.feed(ser.read(4096))
                if any(isinstance(pk.msg, p.Ack) and pk.msg.acked_seq == 99 for pk in got):
                    break
        finally:
            ser.close()
    naks = {pk.msg.acked_seq: pk.msg.reason for pk in got if isinstance(pk.msg, p.Nak)}
    expected = {int.from_bytes(p.cobs_decode(f[:-1])[1:3], 'little'): p.NAK_BAD_MESSAGE
                for _, f, answered in frames if answered}
    assert naks == expected
    status = next(p.BoardStatus.unpack(pk.msg.data) for pk in got
                  if isinstance(pk.msg, p.Ack) and pk.msg.acked_seq == 99)
    assert status.rx_errors == len(frames)


@pytest.mark.parametrize('period_us', [500, 33_000, 250_000])
def test_trigger_period_from_the_shortest_to_beyond_the_timer_range(period_us):
    """500 us (the board's minimum), and periods longer than Timer1's 16-bit range
    (32.8 ms), which the firmware counts in whole timer wraps before arming the compare."""
    rng = np.random.default_rng(period_us)
    n = 40 if period_us < 100_000 else 6
    codes = rng.integers(1, 65536, (n, 4)).astype(np.uint16)
    script = sb.Script()
    session(script)
    t0 = script.upload_scan(3000.0, 1, codes, period_us)
    end = t0 + (n + 2) * period_us + 20_000
    script.heartbeats(1000.0, end)
    log = sb.run_script(script, end)
    acked(log, script)
    edges = log.rising_edges()
    events = log.events()
    assert len(edges) == len(events) == n
    assert np.abs(np.diff(edges) - period_us * 16).max() <= 4
    for edge, (_, ev) in zip(edges, events, strict=True):
        assert log.codes_at(int(edge)) == ev.codes == tuple(int(c) for c in codes[ev.index])
    assert np.all(np.diff([ev.timestamp_us for _, ev in events]) == period_us)
    # one pulse per row, each 20 us
    falls = np.array([c for c, v in log.trigger if not v])
    assert len(falls) == n and np.all(np.abs(falls - edges - 320) <= 4)
