"""Fuzz the serial protocol decoder with >= 10^6 random, truncated and bit-flipped frames.

Every fuzz frame goes through both entry points of :mod:`galvo_driver.serial_link.protocol`:

* ``decode_frame(frame)``: may only raise ``ProtocolError`` (or return a packet);
* a long-lived ``FrameDecoder`` fed the whole stream (fuzz frames, each followed by a
  delimiter, with a valid "canary" frame after every 8th one) in random-size chunks: ``feed``
  must never raise, its buffer must stay within ``MAX_ENCODED_FRAME`` and every canary must
  come out (the decoder resynchronised after the garbage before it).

Each chunk of frames runs under a SIGALRM watchdog (``--chunk-timeout``); a chunk that
overruns counts as a hang. A mutated frame that decodes to a packet differing from the
original counts as an undetected corruption; a packet accepted from a mangled payload (with
a valid CRC) must re-encode to the same bytes, or it counts as a re-encode mismatch.

With ``--firmware N`` it also fuzzes the board firmware in simavr (``firmware/``): N fuzz
frames of the same kinds, with HELLO first, a HEARTBEAT every 50 ms and a GET_STATUS
"canary" after every 8th frame, sent at the line rate in simulated time. Counted:
``fw_crashes`` (the simulated CPU stopped), ``fw_resets`` (a BOOT after the first),
``fw_canaries_unanswered``, ``fw_undecodable_output`` (board frames the host's decoder
rejects) and ``fw_rx_error_mismatch``: the firmware's own count of dropped host frames
(``rx_errors`` in its last canary's status) against what this module's decoder rejects
in the same byte stream (board-type packets aside, which the board ignores); all must be 0.

Usage::

    python benchmarks/protocol_fuzz.py [--frames 1000000] [--chunk 10000] [--seed 1]
                                       [--firmware 20000]

The last stdout line is one JSON object with ``frames``, ``unexpected_exceptions``,
``hangs`` and further counters.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import time
import traceback

from galvo_driver.serial_link import protocol as p


class _ChunkTimeout(BaseException):
    """Raised by the SIGALRM watchdog inside a chunk that takes too long."""


def _alarm(signum, frame):
    raise _ChunkTimeout()


def random_message(rng: random.Random) -> p.Message:
    def codes():
        return tuple(rng.randint(1, 65535) for _ in range(4))

    def u(bits):
        return rng.getrandbits(bits)

    kind = rng.randrange(16)
    if kind == 0:
        return p.Hello(u(16))
    if kind == 1:
        return p.Heartbeat()
    if kind == 2:
        return p.SetVolts(codes())
    if kind == 3:
        return p.Laser(rng.random() < 0.5)
    if kind == 4:
        return p.ScanBegin(u(16), rng.randint(1, 2**32 - 1))
    if kind == 5:
        return p.ScanData(u(16), u(32), tuple(codes() for _ in range(
            rng.randint(1, p.ROWS_PER_CHUNK))))
    if kind == 6:
        return p.ScanStart(u(16), rng.randint(1, 2**32 - 1), rng.randint(1, 2**32 - 1),
                           rng.random() < 0.5, u(32))
    if kind == 7:
        return rng.choice([p.ScanStop(), p.Safe(), p.GetStatus()])
    if kind == 8:
        return p.Ack(u(16), rng.randbytes(rng.choice([0, 0, 33, 40, rng.randrange(238)])))
    if kind == 9:
        return p.Nak(u(16), u(8))
    if kind in (10, 11, 12):  # events dominate real traffic
        return p.Event(u(32), u(16), u(32), u(64), codes(), rng.random() < 0.5,
                       rng.randrange(3))
    if kind == 13:
        return p.Boot(p.BoardInfo(u(16), 'fuzz-board', 16, 4, u(32), u(64), u(32), u(32)))
    if kind == 14:
        return p.Status(p.BoardStatus(u(32), u(64), rng.randrange(4), u(8),
                                      rng.random() < 0.5, codes(), u(16), u(32), u(32)))
    return p.Fault(u(8), u(64), u(32))


def mutate(rng: random.Random, frame: bytes) -> tuple[str, bytes]:
    """A fuzz frame (without delimiter) derived from a valid encoded frame.

    Kinds: 'random' bytes; 'truncated' frame; 'bitflip' (1 to 8 bits); 'payload': a
    mangled type/payload inside a *valid* CRC, which exercises the message parsers.
    """
    r = rng.random()
    if r < 0.25:
        return 'random', rng.randbytes(rng.randrange(0, 320))
    if r < 0.5:
        return 'truncated', frame[:rng.randrange(0, len(frame))]
    if r < 0.8:
        buf = bytearray(frame)
        for _ in range(1 if r < 0.7 else rng.randint(2, 8)):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
        return 'bitflip', bytes(buf)
    body = bytearray(p.cobs_decode(frame)[:-p.CRC_SIZE])
    how = rng.randrange(4)
    if how == 0:  # another type byte
        body[0] = rng.randrange(256)
    elif how == 1:  # shorter payload
        del body[rng.randrange(p.HEADER_SIZE, len(body) + 1):]
    elif how == 2:  # longer payload
        body += rng.randbytes(rng.randrange(1, 40))
    else:  # random payload bytes
        for _ in range(rng.randint(1, 6)):
            if len(body) > p.HEADER_SIZE:
                body[rng.randrange(p.HEADER_SIZE, len(body))] = rng.randrange(256)
    body += (p.crc32(bytes(body))).to_bytes(4, 'little')
    return 'payload', p.cobs_encode(bytes(body))


def run(n_frames: int, chunk: int, seed: int, chunk_timeout: float) -> dict:
    rng = random.Random(seed)
    pool = []
    for _ in range(4096):
        msg = random_message(rng)
        seq = rng.getrandbits(16)
        pool.append((p.encode_frame(seq, msg)[:-1], p.Packet(seq, msg)))
    canary_frame = p.encode_frame(0xCAFE, p.Safe())
    canary = p.Packet(0xCAFE, p.Safe())

    counts = {'frames': 0, 'unexpected_exceptions': 0, 'hangs': 0, 'resync_failures': 0,
              'undetected_corruptions': 0, 'reencode_mismatches': 0, 'buffer_overflows': 0}
    by_kind = {'random': 0, 'truncated': 0, 'bitflip': 0, 'payload': 0}
    examples: list[str] = []
    decoder = p.FrameDecoder()
    signal.signal(signal.SIGALRM, _alarm)
    t_start = time.perf_counter()
    next_report = 100_000
    while counts['frames'] < n_frames:
        size = min(chunk, n_frames - counts['frames'])
        signal.setitimer(signal.ITIMER_REAL, chunk_timeout)
        try:
            stream = bytearray()
            canaries = 0
            for i in range(size):
                frame, original = pool[rng.randrange(len(pool))]
                kind, fuzz = mutate(rng, frame)
                by_kind[kind] += 1
                try:
                    pkt = p.decode_frame(fuzz)
                except p.ProtocolError:
                    pass
                except Exception:  # noqa: BLE001 - this is what the benchmark counts
                    counts['unexpected_exceptions'] += 1
                    if len(examples) < 5:
                        examples.append(traceback.format_exc(limit=3))
                else:
                    if kind in ('truncated', 'bitflip') and pkt != original:
                        counts['undetected_corruptions'] += 1
                    elif kind == 'payload' and p.encode_frame(pkt.seq, pkt.msg)[:-1] != fuzz:
                        counts['reencode_mismatches'] += 1
                stream += fuzz
                stream += b'\x00'
                if i % 8 == 7:
                    stream += canary_frame
                    canaries += 1
            # stream path: feed in random-size pieces
            pos = 0
            got = 0
            while pos < len(stream):
                step = rng.randrange(1, 1024)
                try:
                    out = decoder.feed(bytes(stream[pos:pos + step]))
                except Exception:  # noqa: BLE001 - feed() must never raise
                    counts['unexpected_exceptions'] += 1
                    if len(examples) < 5:
                        examples.append(traceback.format_exc(limit=3))
                    decoder = p.FrameDecoder()
                    out = []
                got += sum(1 for pkt in out if pkt == canary)
                if decoder.buffered > p.MAX_ENCODED_FRAME:
                    counts['buffer_overflows'] += 1
                pos += step
            counts['resync_failures'] += max(0, canaries - got)
        except _ChunkTimeout:
            counts['hangs'] += 1
            decoder = p.FrameDecoder()
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        counts['frames'] += size
        if counts['frames'] >= next_report:
            dt = time.perf_counter() - t_start
            print(f'{counts["frames"]:>9d} frames  {dt:7.1f} s  '
                  f'{counts["frames"] / dt:8.0f} frames/s  unexpected '
                  f'{counts["unexpected_exceptions"]}  hangs {counts["hangs"]}', flush=True)
            next_report += 100_000
    seconds = time.perf_counter() - t_start
    for ex in examples:
        print(ex)
    print(f'kinds: {by_kind}; decoder counters: {decoder.errors}, ok {decoder.frames_ok}')
    counts['seconds'] = round(seconds, 2)
    counts['frames_per_s'] = round(counts['frames'] / seconds)
    return counts


def fuzz_firmware(n_frames: int, seed: int) -> dict:
    """Fuzz the board firmware in simavr (module docstring); returns the ``fw_*`` counters."""
    from galvo_driver.serial_link import simavr_board as sb

    rng = random.Random(seed)
    script = sb.Script()
    script.send(1000.0, p.Hello(p.PROTOCOL_VERSION))
    stream = bytearray(p.encode_frame(1, p.Hello(p.PROTOCOL_VERSION)))
    t = 3000.0
    canary_seqs = []
    byte_us = 11.0  # 1 Mbaud, 11 bits a byte in simavr
    for i in range(n_frames):
        msg = random_message(rng)
        frame = p.encode_frame(rng.getrandbits(16), msg)[:-1]
        _, fuzz = mutate(rng, frame)
        data = fuzz + b'\x00'
        script.raw(t, data)
        stream += data
        t += len(data) * byte_us + 300.0
        if i % 8 == 7:
            seq = 0xC000 + len(canary_seqs) % 0x3FFF
            canary_seqs.append(seq)
            data = p.encode_frame(seq, p.GetStatus())
            script.raw(t, data)
            stream += data
            t += len(data) * byte_us + 2000.0
    seq = 0xBFFF
    data = p.encode_frame(seq, p.GetStatus())
    script.raw(t, data)
    stream += data
    canary_seqs.append(seq)
    end = t + 20_000
    hb = p.encode_frame(0, p.Heartbeat())
    # heartbeats between frames, never inside one (the board would see a broken frame)
    times = sorted(x[0] for x in script.lines)
    for t_hb in range(10_000, int(end), 50_000):
        gap = next((tt for tt in times if tt >= t_hb), end)
        script.raw(gap - 50.0 - len(hb) * byte_us, hb)
    log = sb.run_script(script, end, boot_count=seed)
    # what the host-side decoder rejects in the same bytes, board types aside
    board_type_errors = [0]

    def count(err):
        if err.seq is not None and err.msg_type is not None and err.msg_type >= 0x80:
            board_type_errors[0] += 1

    dec = p.FrameDecoder(on_error=count)
    dec.feed(bytes(stream))
    expected_rx_errors = dec.error_count - board_type_errors[0]
    packets = log.packets()
    answers = {}
    for _, pk in packets:
        if isinstance(pk.msg, p.Ack):
            answers.setdefault(pk.msg.acked_seq, pk.msg)
    unanswered = sum(1 for s in canary_seqs if s not in answers)
    last = answers.get(0xBFFF)
    rx_errors = p.BoardStatus.unpack(last.data).rx_errors if last is not None else -1
    boots = sum(1 for _, pk in packets if isinstance(pk.msg, p.Boot))
    return {'fw_frames': n_frames, 'fw_crashes': int(log.crashed),
            'fw_resets': max(0, boots - 1), 'fw_canaries_unanswered': unanswered,
            'fw_undecodable_output': log.decode_errors,
            'fw_rx_errors': rx_errors, 'fw_rx_errors_expected': expected_rx_errors,
            'fw_rx_error_mismatch': abs(rx_errors - expected_rx_errors),
            'fw_sim_seconds': round(log.end / sb.F_CPU, 2)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=1_000_000)
    parser.add_argument('--chunk', type=int, default=10_000)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--chunk-timeout', type=float, default=60.0,
                        help='watchdog per chunk [s]; an overrun counts as a hang')
    parser.add_argument('--firmware', type=int, default=0,
                        help='also fuzz the board firmware in simavr with this many frames')
    args = parser.parse_args(argv)
    result = run(args.frames, args.chunk, args.seed, args.chunk_timeout)
    if args.firmware:
        result.update(fuzz_firmware(args.firmware, args.seed))
    print(json.dumps(result))


if __name__ == '__main__':
    main()
