"""A stair scan through the rig's hardware-in-the-loop twin, against the same scan on ``sim``.

The twin (:mod:`galvo_driver.twin`): the driver on its ``rig`` backend opens the board
firmware running in simavr (real time, behind a pty) and Aravis' GigE Vision fake camera,
whose ``Line0`` trigger input is wired to the firmware's trigger output; each triggered
frame is the simulator's exposure at the DAC outputs of its trigger edge. The graph
(driver, stripe_extractor, reconstructor, one process each) and the evaluation's stair
block (``galvoscan.evaluate.Evaluation.stair_series``, scenes from
``galvoscan.eval_scenes``) are those of ``galvoscan evaluate``; the stair block is placed
through the twin's ``sim/set_scene``. Then the same positions are scanned on the ``sim``
backend (same rig, seed and frame rate) for the reference.

The calibration of both scans is the simulator's truth (``--truth-calibration`` of
``galvoscan evaluate``): an upper bound, not a calibration result; calibrating through the
twin is ``galvoscan evaluate --twin``.

Reported (last stdout line, JSON):

* ``frames_triggered``: rising trigger edges the firmware fired during the stair scans
  (the harness log); ``frames_paired``: frames the driver published (each paired with its
  trigger's EVENT); ``frames_rendered``: exposures the camera rendered;
* ``mistagged``: published frames whose image was rendered at DAC codes other than those
  of the EVENT the driver tagged it with (the render log holds each image's CRC-32 with the
  codes at its edge); ``images_checked``;
* ``fps``: frames paired per second of trigger time (the frame rate reached, in the board's
  time); ``frame_rate_hz``: the trigger rate asked for; ``board_rate``: the board's
  simulated seconds per wall-clock second (``--board-rate``, default half speed, so that a
  node the shared machine stalls keeps the board's watchdog fed);
  ``wall_fps``: frames paired per wall-clock second of the stair series;
* ``stair_rmse_mm_twin``, ``stair_rmse_mm_sim`` and ``stair_rmse_ratio`` (twin / sim);
* ``load_average``: the machine's 1-minute load at the start and the end.

The frame rate is reduced (``--frame-rate``, default 10 Hz, and the board at half speed):
the simulator renders a 720 x 540 exposure in 5-20 ms (laser) on a shared 2-core machine,
and the twin delays frames by that time (a real camera takes 500 fps).

Usage::

    python benchmarks/twin_scan.py [--positions 6] [--frames 8] [--frame-rate 10] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from galvoscan import metrics
from galvoscan.evaluate import Evaluation, Graph, TwinGraph, _load
from galvoscan.progress import Progress
from galvoscan_common.runtime import private_domain


def _args(ns, out: Path) -> argparse.Namespace:
    """The evaluation's arguments for these scans: the simulator truth as calibration."""
    return argparse.Namespace(rig=ns.rig, seed=ns.seed, quick=True, model='physical',
                              truth_calibration=True, frame_rate=ns.frame_rate,
                              exact_operator=True, out=str(out))


class Tap:
    """The published frames (image and state by stamp), for the mistag check."""

    def __init__(self, node):
        from galvoscan_msgs.msg import GalvoState
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.states, self.images = {}, {}
        self.recording = False
        node.create_subscription(GalvoState, 'galvo/state', self._state, qos)
        node.create_subscription(Image, 'camera/image_raw', self._image, qos)

    @staticmethod
    def _stamp(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def _state(self, msg):
        if self.recording:
            self.states[self._stamp(msg)] = msg

    def _image(self, msg):
        if self.recording:
            from galvo_driver.twin import image_crc

            self.images[self._stamp(msg)] = image_crc(np.frombuffer(bytes(msg.data),
                                                                    np.uint8))


def _series(graph, args, rig, site, positions, frames, progress):
    cal, _ = graph.calibrate(args, rig, quick=True)
    ev = Evaluation(args, graph.client, progress, cal.model, rig.W_T_V0, site)
    t0 = time.monotonic()
    rows, _ = ev.stair_series(f'stair block at {len(positions)} positions', positions, frames)
    wall = time.monotonic() - t0
    errors = [r['error_mm'] for r in rows if r['error_mm'] is not None]
    return rows, errors, wall, ev.lost_frames


def twin_run(ns, rig, site, positions, out, progress) -> dict:
    from galvo_driver.serial_link.protocol import codes_to_volts
    from galvo_driver.twin import read_render_log, renders_by_image

    args = _args(ns, out / 'twin')
    env = {**os.environ, 'ROS_DOMAIN_ID': str(private_domain()),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    (out / 'twin').mkdir(parents=True, exist_ok=True)
    with TwinGraph(args, ns.rig, out / 'twin', env, progress, quick=True,
                   board_rate=ns.board_rate) as graph:
        tap = Tap(graph.client.node)
        graph.client.spin(1.0)
        before = graph.twin_counts()
        tap.recording = True
        rows, errors, wall, lost = _series(graph, args, rig, site, positions, ns.frames,
                                           progress)
        graph.client.spin(1.0)  # the last messages on their way
        tap.recording = False
        after = graph.twin_counts()
        renders = renders_by_image(read_render_log(graph.twin_dir / 'render.log'))
    # the warm-up scan of calibrate() (one frame) is inside the window: count it too
    triggered = after['frames_triggered'] - before['frames_triggered']
    mistagged, checked, unknown = 0, 0, 0
    for stamp, crc in tap.images.items():
        state = tap.states.get(stamp)
        rec = renders.get(crc)
        if state is None or rec is None:
            unknown += 1
            continue
        got = [state.g1_pan_voltage, state.g1_tilt_voltage, state.g2_pan_voltage,
               state.g2_tilt_voltage]
        checked += 1
        if not (np.array_equal(got, codes_to_volts(np.array(rec.codes)))
                and bool(state.laser_on) == rec.laser_on):
            mistagged += 1
    paired = len(tap.states)
    return {'rows': rows, 'errors': errors, 'wall': wall, 'lost': lost,
            'frames_triggered': triggered, 'frames_paired': paired,
            'frames_rendered': after['frames_rendered'] - before['frames_rendered'],
            'images_checked': checked, 'images_unmatched': unknown, 'mistagged': mistagged}


def sim_run(ns, rig, site, positions, out, progress) -> dict:
    args = _args(ns, out / 'sim')
    env = {**os.environ, 'ROS_DOMAIN_ID': str(private_domain()),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    (out / 'sim').mkdir(parents=True, exist_ok=True)
    with Graph(args, ns.rig, out / 'sim', env, progress, quick=True) as graph:
        rows, errors, wall, lost = _series(graph, args, rig, site, positions, ns.frames,
                                           progress)
    return {'rows': rows, 'errors': errors, 'wall': wall, 'lost': lost}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--rig', default='reference')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--positions', type=int, default=6,
                   help='stair positions across the working point (a row of the grid)')
    p.add_argument('--frames', type=int, default=8, help='stripe lines per view (3 views)')
    p.add_argument('--frame-rate', type=float, default=10.0, help='trigger rate [Hz]')
    p.add_argument('--board-rate', type=float, default=0.5,
                   help="the twin board's simulated seconds per wall-clock second")
    p.add_argument('--out', default=None, help='folder for logs (default: temporary)')
    ns = p.parse_args(argv)
    load0 = os.getloadavg()[0]
    tmp = None
    if ns.out is None:
        tmp = tempfile.TemporaryDirectory(prefix='twin_scan_')
        ns.out = tmp.name
    out = Path(ns.out)
    out.mkdir(parents=True, exist_ok=True)
    rig, _, site, _, _ = _load(argparse.Namespace(rig=ns.rig, out=str(out)))
    positions = site.stair_grid(ns.positions, 1)
    progress = Progress()
    t0 = time.monotonic()
    twin = twin_run(ns, rig, site, positions, out, progress)
    sim = sim_run(ns, rig, site, positions, out, progress)
    rmse_twin = metrics.rmse(twin['errors']) if twin['errors'] else float('nan')
    rmse_sim = metrics.rmse(sim['errors']) if sim['errors'] else float('nan')
    result = {
        'frames_triggered': twin['frames_triggered'],
        'frames_paired': twin['frames_paired'],
        'frames_rendered': twin['frames_rendered'],
        'mistagged': twin['mistagged'],
        'images_checked': twin['images_checked'],
        'images_unmatched': twin['images_unmatched'],
        'frame_rate_hz': ns.frame_rate,
        'board_rate': ns.board_rate,
        'fps': (twin['frames_paired'] * ns.frame_rate / twin['frames_triggered']
                if twin['frames_triggered'] else 0.0),
        'wall_fps': twin['frames_paired'] / twin['wall'] if twin['wall'] > 0 else 0.0,
        'stair_rmse_mm_twin': rmse_twin,
        'stair_rmse_mm_sim': rmse_sim,
        'stair_rmse_ratio': rmse_twin / rmse_sim if rmse_sim > 0 else float('nan'),
        'stair_errors_mm_twin': twin['errors'],
        'stair_errors_mm_sim': sim['errors'],
        'positions': len(positions), 'frames_per_view': ns.frames,
        'frames_lost_twin': twin['lost'], 'frames_lost_sim': sim['lost'],
        'calibration': 'simulator truth (both)',
        'load_average': [load0, os.getloadavg()[0]],
        'wall_s': time.monotonic() - t0,
    }
    print(json.dumps(result, default=float))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
