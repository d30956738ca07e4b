"""``galvoscan scan``: start a named scan pattern on a running driver and follow it.

    galvoscan scan --pattern raster --g1-pan -1 1 --g1-tilt -0.5 0.5 --g2-tilt -0.5 0.5 \\
                   --steps-pan 3 --steps-tilt 20 [--rate 500] [--scene FILE] [--laser-off]
    galvoscan scan --pattern custom --voltages scan.csv  # rows U1_pan,U1_tilt,U2_pan,U2_tilt [V]

Prints the progress (frames done, dropped, remaining time) until the scan ends, then waits
for the reconstructor's cloud of the scan on ``points/scan`` and prints how many points it
holds, or that none came back and why (from the nodes' ``diagnostics``). Ctrl-C stops the
scan (galvos to 0 V, laser off). Exit code 0 when the scan completed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

#: StartScan's step counts are uint32; a larger number would wrap around silently.
MAX_STEPS = 2**32 - 1


def _steps(text: str) -> int:
    """argparse type of a step count: a whole number from 1 to MAX_STEPS."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a whole number') from None
    if not 1 <= n <= MAX_STEPS:
        raise argparse.ArgumentTypeError(f'{n} is outside 1..{MAX_STEPS}')
    return n


def _finite(text: str) -> float:
    """argparse type of a finite float."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not np.isfinite(x):
        raise argparse.ArgumentTypeError(f'{text} is not finite')
    return x


def build_parser():
    p = argparse.ArgumentParser(prog='galvoscan scan', description=__doc__.split('\n')[0])
    p.add_argument('--pattern', default='raster', choices=('raster', 'g1_grid', 'g2_sweep',
                                                             'custom'))
    for name in ('g1-pan', 'g1-tilt', 'g2-tilt'):
        p.add_argument(f'--{name}', nargs=2, type=_finite, default=(0.0, 0.0),
                       metavar=('MIN', 'MAX'), help=f'{name} range [V]')
    p.add_argument('--steps-pan', type=_steps, default=1, help='steps along pan (>= 1)')
    p.add_argument('--steps-tilt', type=_steps, default=10, help='steps along tilt (>= 1)')
    p.add_argument('--voltages', help='custom: CSV file of rows U1_pan,U1_tilt,U2_pan,U2_tilt [V]')
    p.add_argument('--rate', type=_finite, default=0.0,
                   help='frame rate [Hz] (0: driver default)')
    p.add_argument('--laser-off', action='store_true')
    p.add_argument('--scene', help='sim backend: scene YAML to set first')
    p.add_argument('--scan-id', default='')
    p.add_argument('--timeout', type=float, default=600.0, help='give up after [s]')
    p.add_argument('--cloud-timeout', type=_finite, default=5.0,
                   help="after the scan, wait this long for its cloud on points/scan [s] "
                        "(0: do not wait)")
    return p


class ScanOutcome:
    """What came back from a scan: its cloud on ``points/scan`` and the nodes' diagnostics.

    Subscribes before the scan starts. ``points/scan`` is transient-local, so the cloud of an
    earlier scan arrives first; only a cloud stamped after ``since_ns`` counts.
    """

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.since_ns = None
        self.clouds = []          # (stamp ns, points, frame_id) of the clouds after since_ns
        self.status = {}          # diagnostic status name -> (message, {key: value})
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(PointCloud2, 'points/scan', self._on_cloud, latched, raw=True)
        node.create_subscription(DiagnosticArray, 'diagnostics', self._on_diagnostics, 50)

    def _on_cloud(self, data):
        from galvoscan_common import cdr

        try:
            header, points = cdr.parse_point_cloud(data)
        except cdr.CdrError:
            return
        stamp = header.sec * 1_000_000_000 + header.nanosec
        if self.since_ns is not None and stamp >= self.since_ns:
            self.clouds.append((stamp, points.shape[0], header.frame_id))

    def _on_diagnostics(self, msg):
        for st in msg.status:
            self.status[st.name] = (st.message, {kv.key: kv.value for kv in st.values})

    def points(self) -> int:
        return sum(n for _, n, _ in self.clouds)

    def why_no_points(self) -> str:
        """The likeliest reason the scan gave no points, from the latest diagnostics."""
        recon = [v for k, v in self.status.items() if k.startswith('reconstructor')]
        extractor = [v for k, v in self.status.items() if k.startswith('stripe_extractor')]
        if not recon:
            return ('no reconstructor answered on diagnostics: is it running on this '
                    'ROS_DOMAIN_ID? (galvoscan run starts it)')
        message, values = recon[0]
        if 'no calibration loaded' in message:
            return ('the reconstructor has no calibration loaded: set its calibration_file, '
                    'or call reconstructor/reload_calibration (galvoscan run on the simulated '
                    'rig uses the last one that galvoscan demo or galvoscan calibrate wrote)')
        skipped = {k.split('/', 1)[1]: v for k, v in values.items()
                   if k.startswith('skipped/') and v not in ('0', '')}
        if skipped:
            return 'the reconstructor skipped the frames: ' + ', '.join(
                f'{k} {v}' for k, v in sorted(skipped.items()))
        if extractor:
            ex = extractor[0][1]
            if ex.get('centers_published', '0') != '0' and values.get('frames', '0') != '0':
                return ('the reconstructor got stripe centres but no valid points: rays '
                        'nearly parallel to the laser plane or behind the camera; check the '
                        'calibration and the G2 range')
            return ('no stripe was found in the images: the laser does not reach what the '
                    'camera sees (aim G2 with --g2-tilt, check the scene and exposure)')
        return (f"no stripe centres reached the reconstructor ({message}); is the stripe "
                'extractor running?')


def main(argv=None):
    args = build_parser().parse_args(argv)
    voltages = []
    if args.pattern == 'custom':
        if not args.voltages:
            print('galvoscan scan: --pattern custom needs --voltages FILE', file=sys.stderr)
            return 2
        try:
            arr = np.loadtxt(args.voltages, delimiter=',', ndmin=2)
        except (OSError, ValueError) as exc:
            print(f'galvoscan scan: {args.voltages}: {exc}', file=sys.stderr)
            return 2
        voltages = arr.ravel().tolist()

    import rclpy
    from galvoscan_msgs.srv import GetScanProgress, SetScene, StartScan, StopScan
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from galvoscan_common.executor import ServiceClients

    # Ctrl-C stays a plain KeyboardInterrupt so that the context can still stop the scan
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node('galvoscan_scan')

    executor = SingleThreadedExecutor()
    executor.add_node(node)

    services = ServiceClients(node, executor, hint='is the driver running?')
    outcome = ScanOutcome(node)

    def call(srv, name, req, timeout=30.0):
        # every call here is safe to resend (StartScan by its request_id)
        return services.call(srv, name, req, timeout, resend=True)

    started = False
    try:
        if args.scene:
            resp = call(SetScene, 'sim/set_scene', SetScene.Request(
                scene_yaml=Path(args.scene).read_text()))
            print(resp.message)
            if not resp.success:
                return 1
        outcome.since_ns = node.get_clock().now().nanoseconds
        req = StartScan.Request(
            pattern=args.pattern, scan_id=args.scan_id, g1_pan_min=args.g1_pan[0],
            g1_pan_max=args.g1_pan[1], g1_tilt_min=args.g1_tilt[0],
            g1_tilt_max=args.g1_tilt[1], g2_tilt_min=args.g2_tilt[0],
            g2_tilt_max=args.g2_tilt[1], steps_pan=args.steps_pan,
            steps_tilt=args.steps_tilt, voltages=voltages, frame_rate=args.rate,
            laser_on=not args.laser_off)
        resp = call(StartScan, 'scan/start', req)
        print(resp.message)
        if not resp.success:
            return 1
        started = True
        t_end = time.monotonic() + args.timeout
        while time.monotonic() < t_end:
            p = call(GetScanProgress, 'scan/progress', GetScanProgress.Request())
            print(f'\r{p.scan_id}: {p.state}, {p.frames_done}/{p.frames_total} frames, '
                  f'{p.frames_dropped} dropped, {p.remaining:.1f} s left ', end='', flush=True)
            if p.state != 'running':
                print()
                started = False
                if p.state == 'done' and args.cloud_timeout > 0:
                    report_cloud(outcome, executor, args.cloud_timeout)
                return 0 if p.state == 'done' else 1
            time.sleep(0.2)
        print('\ntimed out')
        return 1
    except KeyboardInterrupt:
        return 130
    except (RuntimeError, OSError) as exc:
        print(f'galvoscan scan: {exc}', file=sys.stderr)
        return 1
    finally:
        if started and rclpy.ok():
            try:
                call(StopScan, 'scan/stop', StopScan.Request(), timeout=5.0)
            except RuntimeError:
                pass
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


def report_cloud(outcome: ScanOutcome, executor, timeout: float) -> int:
    """Wait up to ``timeout`` s for the scan's cloud; print its size, or why there is none."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and not outcome.points():
        executor.spin_once(timeout_sec=0.1)
    # a scan over scan_max_points comes in several clouds: take what follows at once
    t_more = time.monotonic() + 0.3
    while time.monotonic() < t_more:
        executor.spin_once(timeout_sec=0.05)
    n = outcome.points()
    if n:
        frame = outcome.clouds[-1][2]
        parts = f' in {len(outcome.clouds)} clouds' if len(outcome.clouds) > 1 else ''
        print(f'points/scan: {n} points{parts} in frame {frame}')
    else:
        print(f'points/scan: no cloud came back within {timeout:g} s: '
              f'{outcome.why_no_points()}', file=sys.stderr)
    return n


if __name__ == '__main__':
    sys.exit(main())
