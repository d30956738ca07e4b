"""Screenshots of the browser page's calibration view during a real intrinsics capture of
the simulated rig, its boards placed by the simulated operator (a person's imprecision).

    .venv/bin/python src/galvoscan_view/test/calibration_screenshots.py \
        [--out docs/images] [--seed 5] [--after 3] [--quick]

On a private ROS domain it starts the sim driver and the calibration node (``galvoscan run
--nodes galvo_driver,calibration``), the simulated operator (``galvoscan operator --sim``),
``galvoscan view`` and headless Chromium (the page test's driver), calls
``calibration/capture`` of ``intrinsics``, and saves the page in the states it catches:

    calibration-move.png     a move instruction (a target put where it cannot be captured)
    calibration-place.png    the operator asked for a placement, ``--after`` placements kept
    calibration-capture.png  a placement's views taken, ``--after`` kept, the last view
                             drawn on its own frame

The simulated operator answers within a fraction of a second, so a short state may be
missed: the shots taken are printed, and it stops when the capture ends.

Everything it started is stopped at the end; the logs stay in a temporary directory it names.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_view_browser import Chromium  # noqa: E402

from galvoscan_common.runtime import private_domain  # noqa: E402

GALVOSCAN = [sys.executable, '-m', 'galvoscan.cli']


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--out', type=Path, default=Path('docs/images'))
    p.add_argument('--seed', type=int, default=5, help="the simulated operator's seed")
    p.add_argument('--after', type=int, default=3, help='placements kept before the shots')
    p.add_argument('--quick', action='store_true', help="the node's reduced plans")
    p.add_argument('--timeout', type=float, default=900.0)
    args = p.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix='galvoscan_calibration_shots_'))
    domain = private_domain(random.Random(os.getpid()))
    env = {**os.environ, 'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE':
           'LOCALHOST', 'PYTHONUNBUFFERED': '1', 'GALVOSCAN_STATE_DIR': str(tmp / 'state')}
    params = tmp / 'params.yaml'
    params.write_text(yaml.safe_dump({
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': 'reference',
                                             'seed': args.seed}},
        'calibration': {'ros__parameters': {'calibration_file': str(tmp / 'cal.yaml'),
                                            'quick': args.quick,
                                            'data_dir': str(tmp / 'data')}}}))
    procs = []

    def start(cmd, name):
        log = open(tmp / f'{name}.log', 'wb')  # noqa: SIM115 - closed with the process
        proc = subprocess.Popen([str(c) for c in cmd], stdout=log, stderr=subprocess.STDOUT,
                                env=env, start_new_session=True)
        proc.log_path = tmp / f'{name}.log'
        procs.append((proc, log))
        return proc

    print(f'logs in {tmp} (ROS_DOMAIN_ID {domain})', flush=True)
    browser = None
    try:
        start([*GALVOSCAN, 'run', '--params', params, '--nodes', 'galvo_driver,calibration'],
              'graph')
        start([*GALVOSCAN, 'operator', '--sim', '--seed', args.seed], 'operator')
        view = start([*GALVOSCAN, 'view', '--host', '127.0.0.1', '--ws-port', '0',
                      '--http-port', '0'], 'view')
        port = None
        deadline = time.monotonic() + 60
        while port is None:
            assert time.monotonic() < deadline and view.poll() is None, \
                view.log_path.read_text()
            for word in view.log_path.read_text().split():
                if word.startswith('http://127.0.0.1:'):
                    port = int(word.rsplit(':', 1)[1].strip('/,'))
            time.sleep(0.2)
        browser = Chromium(tmp)
        browser.navigate(f'http://127.0.0.1:{port}/#calibration')
        capture = start([sys.executable, '-c', CAPTURE, str(domain)], 'capture')
        args.out.mkdir(parents=True, exist_ok=True)
        kept = ("(() => { const t = document.getElementById('calib-counters').textContent;"
                " const m = t.match(/planned(\\d+) \\//); return m ? Number(m[1]) : -1; })()")
        state = "document.getElementById('instr-state').textContent"
        matched = "document.getElementById('calib-image').dataset.matched === 'true'"
        shots = {'move': ('calibration-move.png', 0, 'true'),
                 'place': ('calibration-place.png', args.after, 'true'),
                 'capture': ('calibration-capture.png', args.after, matched)}
        deadline = time.monotonic() + args.timeout
        while shots and capture.poll() is None and time.monotonic() < deadline:
            now = browser.evaluate(state)
            if now in shots and browser.evaluate(kept) >= shots[now][1] \
                    and browser.evaluate(shots[now][2]):
                path = args.out / shots.pop(now)[0]
                Image.fromarray(browser.screenshot()).save(path)
                print(f'{path}: state {now}, {browser.evaluate(kept)} placements kept',
                      flush=True)
        print(f'not caught: {", ".join(shots) or "none"}', flush=True)
    finally:
        if browser is not None:
            browser.close()
        for proc, _log in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc, log in procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            log.close()
    return 0


#: The capture call, in its own process (it returns when the stage is captured).
CAPTURE = '''
import sys, rclpy
from galvoscan_msgs.srv import CaptureCalibration
rclpy.init(domain_id=int(sys.argv[1]))
node = rclpy.create_node('calibration_screenshots')
client = node.create_client(CaptureCalibration, 'calibration/capture')
assert client.wait_for_service(timeout_sec=60), 'no calibration node'
future = client.call_async(CaptureCalibration.Request(stage='intrinsics'))
rclpy.spin_until_future_complete(node, future)
print(future.result().message)
'''


if __name__ == '__main__':
    sys.exit(main())
