"""Bag writing speed: 720x540 mono8 images through BagWriter, with chunk CRCs (as written now)
against the same writer with the CRC pass skipped, in the same run.

Prints per-image write time [ms] (median of repeats), the CRC's share, and one JSON object on
its last line. The camera's 500 fps leaves 2 ms per frame for everything.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

from galvoscan_bag import writer as bag_writer
from galvoscan_bag.typestore import default_typestore


def _image_bytes(store, i):
    Image = store.types['sensor_msgs/msg/Image']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    pixels = np.random.default_rng(i).integers(0, 255, (540, 720), dtype=np.uint8)
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=i), frame_id='cam'), height=540,
                width=720, encoding='mono8', is_bigendian=0, step=720, data=pixels.ravel())
    return bytes(store.serialize_cdr(msg, msg.__msgtype__))


def write_once(images, crc: bool) -> float:
    """Seconds per image to write ``images`` into a new bag (open and close included)."""
    original = zlib.crc32
    if not crc:  # the same writer with the chunk CRC pass made free (the reference)
        bag_writer.zlib.crc32 = lambda data, value=0: 0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            with bag_writer.BagWriter(Path(tmp) / 'b', flush_interval=None) as bag:
                bag.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
                for i, data in enumerate(images):
                    bag.write('/camera/image_raw', data, i)
            return (time.perf_counter() - t0) / len(images)
    finally:
        bag_writer.zlib.crc32 = original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--images', type=int, default=300)
    parser.add_argument('--repeats', type=int, default=5)
    args = parser.parse_args()
    store = default_typestore()
    frames = [_image_bytes(store, i % 20) for i in range(args.images)]
    with_crc, without = [], []
    for _ in range(args.repeats):
        with_crc.append(write_once(frames, crc=True))
        without.append(write_once(frames, crc=False))
    a, b = statistics.median(with_crc), statistics.median(without)
    print(f'{args.images} images of {len(frames[0])} B, {args.repeats} repeats')
    print(f'  with CRCs     {a * 1e3:.3f} ms/image')
    print(f'  without CRCs  {b * 1e3:.3f} ms/image (reference)')
    print(f'  ratio {a / b:.2f}; budget at 500 fps: 2 ms/frame')
    print(json.dumps({'images': args.images, 'ms_per_image_crc': round(a * 1e3, 4),
                      'ms_per_image_no_crc': round(b * 1e3, 4),
                      'ratio_to_no_crc': round(a / b, 3)}))


if __name__ == '__main__':
    main()
