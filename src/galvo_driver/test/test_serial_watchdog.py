"""Board safety when the host goes away: watchdog, killed host, emulator as a process."""

import json
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import serial

from galvo_driver.serial_link import protocol as p
from galvo_driver.serial_link.backend import SerialBackend
from galvo_driver.serial_link.emulator import FirmwareEmulator

#: Behavioural deadline of the issue: safe state within 300 ms of the last heartbeat.
SAFE_DEADLINE = 0.3


def read_line(proc: subprocess.Popen, timeout: float = 20.0) -> str:
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    assert ready, 'subprocess printed nothing'
    return proc.stdout.readline().strip()


def send(ser, seq, msg):
    ser.write(p.encode_frame(seq, msg))


def test_stopped_heartbeats_trip_the_watchdog():
    with FirmwareEmulator('pty', watchdog=0.15) as emu:
        ser = serial.serial_for_url(emu.port, timeout=0.1)
        try:
            send(ser, 1, p.Hello(p.PROTOCOL_VERSION))
            send(ser, 2, p.SetVolts(tuple(int(c) for c in p.volts_to_codes([1, -2, 3, -4]))))
            send(ser, 3, p.Laser(True))
            for _ in range(4):
                send(ser, 0, p.Heartbeat())
                time.sleep(0.03)
            assert emu.wait_until(lambda e: e.watchdog_trips, timeout=3.0)
        finally:
            ser.close()
        reasons = [a.reason for a in emu.applied()]
        assert reasons[:3] == ['boot', 'set', 'laser']  # the board was live and lasing
        last_rx, t_safe = emu.watchdog_trips[0]
        assert last_rx == emu.snapshot()['last_rx']
        assert 0.15 <= t_safe - last_rx < SAFE_DEADLINE
        last = emu.last_applied()
        assert last.reason == 'watchdog' and last.is_safe
        np.testing.assert_array_equal(last.voltages, np.zeros(4))


HOST_SCRIPT = """
import sys, time
import numpy as np
from galvo_driver.serial_link.backend import SerialBackend
be = SerialBackend(sys.argv[1])
be.open()
be.start(np.full((2000, 4), 2.5), 200.0, laser_on=True)
print('scanning', flush=True)
time.sleep(60)
"""


def test_killed_host_leaves_board_safe():
    with FirmwareEmulator('pty', watchdog=0.15) as emu:
        host = subprocess.Popen([sys.executable, '-c', HOST_SCRIPT, emu.port],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert read_line(host) == 'scanning'
            assert emu.wait_until(lambda e: e.last_applied().laser_on, timeout=3.0)
            host.send_signal(signal.SIGKILL)
            host.wait(timeout=5)
        finally:
            if host.poll() is None:
                host.kill()
                host.wait()
        assert emu.wait_until(lambda e: e.watchdog_trips, timeout=3.0)
        last_rx, t_safe = emu.watchdog_trips[-1]
        assert t_safe - last_rx < SAFE_DEADLINE
        last = emu.last_applied()
        assert last.reason == 'watchdog' and last.is_safe
        assert emu.snapshot()['state'] == p.STATE_IDLE


@pytest.mark.parametrize('mode', ['--pty', '--tcp'])
def test_emulator_process_logs_applied_outputs(tmp_path, mode):
    log_path = tmp_path / 'emu.jsonl'
    emu = subprocess.Popen([sys.executable, '-m', 'galvo_driver.serial_link.emulator', mode,
                            '--log', str(log_path)], stdout=subprocess.PIPE, text=True)
    try:
        port = read_line(emu)
        assert port.startswith('/dev/') if mode == '--pty' else port.startswith('socket://')
        be = SerialBackend(port)
        be.open()
        volts = np.random.default_rng(3).uniform(-10, 10, (20, 4))
        be.start(volts, 500.0, laser_on=True)
        frames = []
        end = time.monotonic() + 10
        while be.running and time.monotonic() < end:
            frames += be.poll(0.05)
        frames += be.poll()
        be.start(np.full((500, 4), 4.0), 500.0, laser_on=True)  # left running
        time.sleep(0.05)
        be.close()
        emu.send_signal(signal.SIGTERM)
        assert emu.wait(timeout=5) == 0
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.wait()
    entries = [json.loads(line) for line in log_path.read_text().splitlines()]
    triggers = [e for e in entries if e['reason'] == 'trigger']
    lsb = 10.0 / 32767
    expected = np.floor(volts / lsb + 0.5) * lsb
    np.testing.assert_allclose([e['volts'] for e in triggers[:20]], expected, atol=1e-12)
    np.testing.assert_allclose([f.voltages for f in frames], expected, atol=1e-12)
    assert any(e['laser'] for e in triggers[20:])  # the second scan was lasing
    last_safe = max(i for i, e in enumerate(entries) if e['reason'] == 'safe')
    assert last_safe > entries.index(triggers[-1])
    for e in entries[last_safe:]:
        assert e['volts'] == [0.0] * 4 and e['codes'] == [32768] * 4 and not e['laser']
