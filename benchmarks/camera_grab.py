"""Software-triggered frames per second through galvo_driver.genicam_camera.

Starts the simulated GigE Vision camera (galvo_driver.fake_camera) at 720x540 Mono8 and
grabs software-triggered frames through GenICamCamera, Python side, in two ways:

- ``serial``: trigger, wait for that frame, trigger the next (one frame in flight);
- ``pipelined``: keep up to ``--window`` triggers in flight, as a hardware trigger at a
  fixed rate does (the frame of trigger k arrives while k+1.. are already fired).

Each is run with Aravis' packet-socket receiver and with plain UDP sockets. A frame counts
when it arrives complete; ``lost`` is triggers without a frame. The last stdout line is
one JSON object.

    .venv/bin/python benchmarks/camera_grab.py [--frames 3000] [--window 8]
"""

from __future__ import annotations

import argparse
import json
import time

from galvo_driver.fake_camera import FakeCamera
from galvo_driver.genicam_camera import GenICamCamera


def serial(cam: GenICamCamera, frames: int) -> dict:
    """Trigger, wait for the frame, repeat: frames/s with one frame in flight."""
    cam.start(n_buffers=16)
    before = cam.statistics()
    got = 0
    t0 = time.perf_counter()
    for _ in range(frames):
        cam.software_trigger()
        got += cam.grab(0.2) is not None
    dt = time.perf_counter() - t0
    return _result(cam, before, got, frames, dt)


def paced(cam: GenICamCamera, frames: int, rate_hz: float) -> dict:
    """Trigger at `rate_hz` as a hardware trigger would, grabbing in between."""
    cam.start(n_buffers=64)
    before = cam.statistics()
    fired = got = 0
    period = 1.0 / rate_hz
    t0 = time.perf_counter()
    next_t = t0
    while fired < frames:
        now = time.perf_counter()
        if now >= next_t:
            cam.software_trigger()
            fired += 1
            next_t += period
            continue
        got += cam.grab(next_t - now) is not None
    while cam.grab(0.2) is not None:
        got += 1
    dt = max(time.perf_counter() - t0 - 0.2, period * frames)
    return _result(cam, before, got, fired, dt)


def library_cost(cam: GenICamCamera, rounds: int, batch: int = 48) -> dict:
    """Python-side cost of `grab` alone: frames already queued, popped and copied to numpy."""
    cam.start(n_buffers=batch + 8)
    spent = 0.0
    n = 0
    for _ in range(rounds):
        for _ in range(batch):
            cam.software_trigger()
            time.sleep(0.001)  # one trigger per camera slot
        time.sleep(0.1)  # all frames of the batch delivered into the buffers
        t = time.perf_counter()
        for _ in range(batch):
            n += cam.grab(0.0) is not None
        spent += time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(200):
        cam.software_trigger()
    trig = (time.perf_counter() - t) / 200
    cam.stop()
    return {"grab_us_per_frame": round(1e6 * spent / max(n, 1), 1), "frames": n,
            "software_trigger_us": round(1e6 * trig, 1),
            "python_side_fps_limit": round(1.0 / (spent / max(n, 1) + trig), 1)}


def _result(cam: GenICamCamera, before: dict, got: int, fired: int, dt: float) -> dict:
    after = cam.statistics()
    cam.stop()
    return {"fps": round(got / dt, 1), "frames": got, "lost": fired - got,
            "failed_buffers": after["failed"] - before["failed"],
            "underruns": after["underrun"] - before["underrun"]}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=500.0, help="paced trigger rate [Hz]")
    ap.add_argument("--width", type=int, default=720)
    ap.add_argument("--height", type=int, default=540)
    args = ap.parse_args()
    result = {"width": args.width, "height": args.height, "pixel_format": "Mono8",
              "frames_per_case": args.frames, "paced_rate_hz": args.rate}
    with FakeCamera("GSBENCH0", width=args.width, height=args.height):
        for packet_socket in (True, False):
            cam = GenICamCamera(serial="GSBENCH0", packet_socket=packet_socket)
            cam.open()
            cam.set("PixelFormat", "Mono8")
            cam.set("TriggerMode", "On")
            cam.set("TriggerSource", "Software")
            rx = "packet_socket" if packet_socket else "udp_socket"
            for mode, fn, fargs in (("serial", serial, (args.frames,)),
                                    ("paced", paced, (args.frames, args.rate)),
                                    ("library_cost", library_cost, (5,))):
                r = fn(cam, *fargs)
                print(f"{rx:14s} {mode:12s}: {r}", flush=True)
                result[f"{rx}_{mode}"] = r
            cam.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
