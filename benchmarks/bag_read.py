"""Bag reading speed: every 720x540 mono8 image of a bag through read_messages, with the
data-section and summary CRC check it does now, against the same reader with that check
skipped (chunk CRCs still checked by both), in the same run.

Prints per-image read time [ms] (median of repeats) and one JSON object on its last line.
Replay at the camera's 500 fps leaves 2 ms per frame.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from bag_write import _image_bytes

from galvoscan_bag import reader as bag_reader
from galvoscan_bag.typestore import default_typestore
from galvoscan_bag.writer import BagWriter


def read_once(bag: Path, sections: bool) -> tuple[float, int]:
    """Seconds per image to read every message of ``bag``, and the count read."""
    original = bag_reader._check_sections
    if not sections:
        bag_reader._check_sections = lambda file: None
    try:
        t0 = time.perf_counter()
        n = sum(1 for _ in bag_reader.read_messages(bag))
        return (time.perf_counter() - t0) / n, n
    finally:
        bag_reader._check_sections = original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--images', type=int, default=1000)
    parser.add_argument('--repeats', type=int, default=5)
    args = parser.parse_args()
    store = default_typestore()
    frames = [_image_bytes(store, i % 20) for i in range(20)]
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'b'
        with BagWriter(bag, flush_interval=None) as w:
            w.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
            for i in range(args.images):
                w.write('/camera/image_raw', frames[i % 20], i)
        size = sum(f.stat().st_size for f in bag.glob('*.mcap'))
        checked, unchecked = [], []
        for _ in range(args.repeats):
            t, n = read_once(bag, sections=True)
            checked.append(t)
            t2, n2 = read_once(bag, sections=False)
            unchecked.append(t2)
            assert n == n2 == args.images
    a, b = statistics.median(checked), statistics.median(unchecked)
    print(f'{args.images} images, {size / 1e6:.0f} MB, {args.repeats} repeats (page cache)')
    print(f'  with section CRC check     {a * 1e3:.3f} ms/image')
    print(f'  without (chunk CRCs only)  {b * 1e3:.3f} ms/image (reference)')
    print(f'  ratio {a / b:.2f}; replay budget at 500 fps: 2 ms/frame')
    print(json.dumps({'images': args.images, 'mb': round(size / 1e6, 1),
                      'ms_per_image_checked': round(a * 1e3, 4),
                      'ms_per_image_chunks_only': round(b * 1e3, 4),
                      'ratio_to_chunks_only': round(a / b, 3)}))


if __name__ == '__main__':
    main()
