"""Benchmark of the rig simulator (galvoscan_sim), single-threaded.

Measures
- stripe frames: the reference rig (every imperfection on: noise, speckle, blur, ambient
  light, distortion) scanning the 30 mm stair block with the paper's synchronised pattern;
- calibration frames: fully textured circle-board frames under room light.

The machine is shared, so each figure is given twice: from this process's CPU time (the
work one core does per frame; the headline numbers) and from wall-clock time (which also
counts time the scheduler gave to other processes). The last line of stdout is one JSON
object.
"""

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS', 'NUMBA_NUM_THREADS',
             'NUMEXPR_NUM_THREADS', 'VECLIB_MAXIMUM_THREADS'):
    os.environ[_var] = '1'

import json  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402

from galvoscan_sim import Simulator, load_rig, load_scene, patterns  # noqa: E402

cv2.setNumThreads(1)


def timed(fn, items):
    c0, w0 = time.process_time(), time.perf_counter()
    out = [fn(x) for x in items]
    return time.process_time() - c0, time.perf_counter() - w0, out


def main():
    rig = load_rig('reference')
    stair = Simulator(rig, load_scene('stair_block'), seed=1)
    volts = patterns.synchronised(rig, [-0.3, 0.0, 0.3], -0.5, steps=100, tilt_step=0.01,
                                  reaim_every=20)
    stair.render(volts[0])  # compile / warm up
    n = len(volts)
    cpu, wall, frames = timed(stair.render, volts)
    points = sum(len(f.truth.stripe) for f in frames)
    print(f'stripe frames: {n} reference-rig frames of the stair block, '
          f'{points / n:.0f} true stripe points per frame')
    print(f'  cpu  {cpu / n * 1e3:7.2f} ms/frame = {n / cpu:7.1f} frames/s (one core)')
    print(f'  wall {wall / n * 1e3:7.2f} ms/frame = {n / wall:7.1f} frames/s')

    ideal = Simulator(load_rig('ideal'), load_scene('stair_block'), seed=1)
    ideal.render(volts[0])
    icpu, iwall, _ = timed(ideal.render, volts)
    print(f'  ideal rig (no noise, blur, speckle, ambient): cpu {n / icpu:7.1f} frames/s, '
          f'wall {n / iwall:7.1f} frames/s')

    board = Simulator(rig, load_scene('circle_board'), seed=1)
    cal = patterns.g1_grid([-2.0, 0.0, 2.0], [-2.0, 0.0, 2.0])
    board.calibration_frame(cal[0])
    m = len(cal)
    ccpu, cwall, _ = timed(board.calibration_frame, cal)
    print(f'calibration frames: {m} fully textured circle-board frames')
    print(f'  cpu  {ccpu / m * 1e3:7.1f} ms/frame, wall {cwall / m * 1e3:7.1f} ms/frame')
    load = os.getloadavg()[0] if hasattr(os, 'getloadavg') else float('nan')
    print(f'load average (1 min) during the run: {load:.2f} on {os.cpu_count()} cpus')
    print(json.dumps({
        'stripe_frames_per_s': round(n / cpu, 1),
        'calibration_frame_ms': round(ccpu / m * 1e3, 1),
        'stripe_frames_per_s_wall': round(n / wall, 1),
        'calibration_frame_ms_wall': round(cwall / m * 1e3, 1),
        'stripe_frames_per_s_ideal_rig': round(n / icpu, 1),
        'load_average_1min': round(load, 2),
    }))


if __name__ == '__main__':
    main()
