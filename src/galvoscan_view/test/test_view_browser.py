"""The browser page in a real browser: Debian's headless Chromium, driven over the Chrome
DevTools Protocol (CDP) with the ``websockets`` client the project already has.

(a) in-process: a ViewState holds a synthetic stair cloud (seeded), an image with its
    stripe and a scan's progress; the page is served and opened, and the test waits for the
    point count, takes a screenshot and reads the 3D canvas back;
(b) end to end: the simulated graph (``galvoscan run --one-process``) and ``galvoscan view``
    as processes on a private ROS domain, scans started with ``galvoscan scan``, the page
    opened on the view's HTTP port until the scanned stair block shows;
(c) the calibration view, end to end: the real calibration node and ``galvoscan view`` as
    processes; a capture started over DDS, so that the node's own instruction shows; a camera
    image and a calibration/progress published from this process over DDS; the page draws
    the detections on their frame, the standard errors and the coverage, and its buttons
    reach the node's calibration/operator and show its answers.

Both check that the page requested nothing but its own origin, threw no exception and was
refused nothing by its Content-Security-Policy. The last screenshot is also copied to
``/tmp/view_screenshot.png`` for a person to look at.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from websockets.sync.client import connect

from galvoscan_view.state import CloudView, ImageView, ViewState
from galvoscan_view.web import serve_page

CHROMIUM = shutil.which('chromium') or '/usr/bin/chromium'
SCREENSHOT_COPY = Path('/tmp/view_screenshot.png')
WIDTH, HEIGHT = 1400, 900
#: The 3D view's background (app.js: scene.background 0x23272e).
BACKGROUND = np.array([0x23, 0x27, 0x2e])


class Chromium:
    """One headless Chromium with one page, driven over CDP.

    Events of the page (requests, exceptions, console and log entries) are kept in
    ``events`` as they arrive between command answers.
    """

    def __init__(self, tmp_path: Path):
        assert os.access(CHROMIUM, os.X_OK), \
            f'{CHROMIUM} not found: Debian chromium (make test installs it)'
        profile = tmp_path / 'chromium-profile'
        self.log_path = tmp_path / 'chromium.log'
        args = [CHROMIUM, '--headless=new', '--remote-debugging-port=0',
                f'--user-data-dir={profile}', '--no-first-run', '--no-default-browser-check',
                '--disable-extensions', '--disable-background-networking', '--disable-sync',
                '--disable-component-update', '--use-angle=swiftshader',
                '--enable-unsafe-swiftshader', f'--window-size={WIDTH},{HEIGHT}',
                '--force-device-scale-factor=1', '--hide-scrollbars', 'about:blank']
        if os.geteuid() == 0:   # Chromium refuses to run as root with its sandbox
            args.insert(1, '--no-sandbox')
        with open(self.log_path, 'wb') as log:
            self.proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        port = self._devtools_port(profile / 'DevToolsActivePort')
        with urllib.request.urlopen(f'http://127.0.0.1:{port}/json/list', timeout=10) as r:
            target = next(t for t in json.load(r) if t['type'] == 'page')
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(
            connect(target['webSocketDebuggerUrl'], max_size=None, open_timeout=30,
                    close_timeout=1))
        self.next_id, self.events = 0, []
        for domain in ('Page', 'Runtime', 'Network', 'Log'):
            self.call(f'{domain}.enable')
        self.call('Emulation.setDeviceMetricsOverride', width=WIDTH, height=HEIGHT,
                  deviceScaleFactor=1, mobile=False)

    def _devtools_port(self, path: Path, timeout: float = 30.0) -> int:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.log_path.read_text()
            if path.exists() and path.read_text().strip():
                return int(path.read_text().split()[0])
            time.sleep(0.05)
        raise AssertionError(f'Chromium did not start:\n{self.log_path.read_text()}')

    def call(self, method: str, timeout: float = 30.0, **params):
        """The result of one CDP command (events that arrive meanwhile go to ``events``)."""
        self.next_id += 1
        self.ws.send(json.dumps({'id': self.next_id, 'method': method, 'params': params}))
        deadline = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if msg.get('id') == self.next_id:
                if 'error' in msg:
                    raise RuntimeError(f'{method}: {msg["error"]}')
                return msg['result']
            self.events.append(msg)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.call('Runtime.evaluate', expression=expression, returnByValue=True,
                           awaitPromise=True)
        if 'exceptionDetails' in result:
            raise RuntimeError(f'{expression}: {result["exceptionDetails"]}')
        return result['result'].get('value')

    def navigate(self, url: str, timeout: float = 30.0) -> None:
        """Open ``url`` and wait until its document has loaded."""
        self.call('Page.navigate', url=url)
        self.wait_for(f"location.href === {json.dumps(url)} && "
                      "document.readyState === 'complete'", timeout)

    def wait_for(self, expression: str, timeout: float, why=lambda: ''):
        """Poll ``expression`` until it is truthy; its value."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.2)
        raise AssertionError(f'timed out waiting for {expression}\n{why()}\n'
                             f'problems: {self.problems("")}')

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of the page as shown."""
        data = self.call('Page.captureScreenshot', format='png')['data']
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert('RGB'))

    def requested_urls(self) -> list[str]:
        return [e['params']['request']['url'] for e in self.events
                if e.get('method') == 'Network.requestWillBeSent']

    def problems(self, origin: str) -> list[str]:
        """Exceptions, console errors, log errors (CSP refusals among them) and requests to
        anywhere but ``origin``."""
        out = []
        for e in self.events:
            method, p = e.get('method'), e.get('params', {})
            if method == 'Runtime.exceptionThrown':
                out.append(f'exception: {p["exceptionDetails"]}')
            elif method == 'Runtime.consoleAPICalled' and p['type'] in ('error', 'assert'):
                out.append(f'console.{p["type"]}: {p["args"]}')
            elif method == 'Log.entryAdded' and p['entry']['level'] == 'error':
                out.append(f'log: {p["entry"]["text"]} ({p["entry"].get("url", "")})')
        out += [f'request to {u}' for u in self.requested_urls()
                if not u.startswith((origin, 'blob:', 'data:'))]
        return out

    def close(self) -> None:
        """Stop Chromium, then drop the connection (no close handshake to wait for)."""
        os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        finally:
            self._stack.close()


@pytest.fixture(scope='module')
def _browser(tmp_path_factory):
    """One Chromium for the module's tests (it takes seconds to start)."""
    browser = Chromium(tmp_path_factory.mktemp('chromium'))
    yield browser
    browser.close()


@pytest.fixture
def chromium(_browser):
    """The module's Chromium on a blank page, with no events of an earlier test."""
    _browser.navigate('about:blank')
    _browser.events.clear()
    yield _browser
    _browser.navigate('about:blank')   # the page stops polling a server that goes away


# ---- what the page shows, read back ------------------------------------------------------------


POINTS_SHOWN = "Number(document.getElementById('point-count').dataset.drawn)"


def page_figures(browser: Chromium) -> dict:
    return browser.evaluate("""(() => {
        const count = document.getElementById('point-count');
        const image = document.getElementById('image');
        return {total: Number(count.dataset.total), drawn: Number(count.dataset.drawn),
                text: count.textContent, image_seq: image.dataset.seq,
                stripe: Number(image.dataset.stripePoints || 0),
                progress: document.getElementById('progress-text').textContent,
                legend: document.getElementById('legend-title').textContent,
                diagnostics: document.querySelectorAll('#diagnostics .status').length,
                empty_hidden: document.getElementById('cloud-empty').hidden};
    })()""")


def canvas_pixels(browser: Chromium) -> np.ndarray:
    """(H, W, 3) uint8 of the 3D canvas's own pixels (its drawing buffer is preserved)."""
    url = browser.evaluate("document.querySelector('#view3d canvas').toDataURL('image/png')")
    data = base64.b64decode(url.split(',', 1)[1])
    return np.asarray(Image.open(io.BytesIO(data)).convert('RGB'))


def drawn_colours(pixels: np.ndarray) -> np.ndarray:
    """(K, 3) the pixels of the canvas that are not its background."""
    flat = pixels.reshape(-1, 3).astype(int)
    return flat[np.abs(flat - BACKGROUND).max(axis=1) > 24]


def save_screenshot(shot: np.ndarray, path: Path) -> None:
    Image.fromarray(shot).save(path)
    shutil.copyfile(path, SCREENSHOT_COPY)


# ---- (a) in-process ----------------------------------------------------------------------------


def stair_cloud(seed: int = 11) -> np.ndarray:
    """(N, 3) float32 [m] in v0: light-section stripes over a plate 700 mm away with three
    10 mm steps toward the scanner (z down 10, 20, 30 mm), 0.05 mm noise."""
    rng = np.random.default_rng(seed)
    xs = np.arange(-0.06, 0.06, 0.0015)           # one stripe every 1.5 mm
    ys = np.arange(-0.045, 0.045, 0.0004)         # a centre every 0.4 mm along it
    x, y = (a.ravel() for a in np.meshgrid(xs, ys))
    step = np.clip(np.floor((x + 0.02) / 0.02) + 1, 0, 3) * (np.abs(y) < 0.03)
    z = 0.7 - 0.01 * step + rng.normal(0, 5e-5, x.shape)
    return np.column_stack([x, y, z]).astype(np.float32)


def colour_classes(pixels: np.ndarray) -> dict:
    """Pixel counts of the drawn canvas by viridis region: violet (low), teal (middle),
    yellow (high)."""
    d = drawn_colours(pixels)
    r, g, b = d[:, 0], d[:, 1], d[:, 2]
    return {'drawn': len(d), 'violet': int(((b > g + 40) & (r > 40)).sum()),
            'teal': int(((g > 110) & (b > 100) & (r < 100)).sum()),
            'yellow': int(((r > 180) & (g > 180) & (b < 100)).sum())}


def test_page_shows_a_cloud_in_process(chromium, tmp_path):
    state = ViewState()
    xyz = stair_cloud()
    state.set_cloud(CloudView('v0', 1.0, xyz, np.ones(len(xyz), np.float32), len(xyz)))
    image = np.full((540, 720), 20, np.uint8)
    image[:, 355:365] = 230                       # a bright vertical stripe
    uv = np.column_stack([np.full(540, 360.0), np.arange(540.0)]).astype(np.float32)
    state.set_image(ImageView(5, 1.0, image, np.zeros((0, 2), np.float32)))
    state.set_stripe(5, uv)
    state.set_progress({'state': 'running', 'frames_done': 40, 'frames_total': 160,
                        'frames_dropped': 1})
    state.set_diagnostics('galvo_driver: scan', {'level': 'OK', 'message': 'scanning',
                                                 'scan/done': '40', 'frames dropped': '1'})
    # the reference: the same stair without its top step (that part 10 mm lower)
    reference = xyz.copy()
    reference[reference[:, 2] < 0.675, 2] = 0.68
    server = serve_page(state, '127.0.0.1', 0)
    try:
        origin = f'http://127.0.0.1:{server.port}/'
        chromium.navigate(origin)
        chromium.wait_for(f'{POINTS_SHOWN} > 0', 60)
        chromium.wait_for("document.getElementById('image').dataset.seq === '5'", 30)
        time.sleep(0.5)   # let the frame with the points be drawn and composited
        figures = page_figures(chromium)
        shot = chromium.screenshot()
        pixels = canvas_pixels(chromium)

        # the page's "use current" button makes the cloud the reference, and colours by error
        chromium.evaluate("document.getElementById('reference-take').click()")
        chromium.wait_for("document.getElementById('colour-mode').value === 'error'", 30)
        deadline = time.monotonic() + 30
        while state.reference is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert state.reference is state.cloud
        state.set_reference(CloudView('v0', 0.0, reference, np.ones(len(xyz), np.float32),
                                      len(xyz)))
        legend = ("document.getElementById('legend-title').textContent.startsWith('distance')"
                  " && Number(document.getElementById('legend-hi').textContent) > 5")
        chromium.wait_for(legend, 30)
        time.sleep(0.5)
        error_legend = [chromium.evaluate(f"document.getElementById('legend-{k}').textContent")
                        for k in ('lo', 'hi')]
        error_shot = chromium.screenshot()
        error_pixels = canvas_pixels(chromium)
        problems = chromium.problems(origin)
    finally:
        server.shutdown()
    save_screenshot(error_shot, tmp_path / 'view_in_process_error.png')
    save_screenshot(shot, tmp_path / 'view_in_process.png')

    assert problems == []
    assert figures['total'] == figures['drawn'] == len(xyz)
    assert figures['text'].replace(',', '') == str(len(xyz))
    assert figures['stripe'] == 540 and '40 / 160 frames' in figures['progress']
    assert figures['diagnostics'] == 1 and figures['empty_hidden']
    assert figures['legend'].startswith('height')
    assert shot.shape == (HEIGHT, WIDTH, 3)

    # coloured by height: plate violet, the two middle steps teal/green, the top step yellow
    height = colour_classes(pixels)
    assert height['drawn'] > 0.05 * pixels.shape[0] * pixels.shape[1], height
    assert min(height['violet'], height['teal'], height['yellow']) > 500, height
    # by error against the reference: 0 mm but on the top step (10 mm): no middle colours
    assert [float(v) for v in error_legend] == [0.0, pytest.approx(10.0, abs=0.3)]   # and noise
    error = colour_classes(error_pixels)
    assert error['violet'] > 500 and error['yellow'] > 500, error
    assert error['teal'] < 0.01 * error['drawn'], error


# ---- (b) end to end, during a scan of the simulated rig ----------------------------------------


GALVOSCAN = [sys.executable, '-m', 'galvoscan.cli']


def graph_params(tmp_path: Path, sim_graph_params):
    """Parameters of the simulated graph (stair block, seeded) and a short scan's CSV."""
    from galvoscan_sim import load_rig, patterns

    params = sim_graph_params(seed=7, reconstructor={'scan_end_timeout': 0.5})
    scan = tmp_path / 'scan.csv'
    voltages = patterns.synchronised(load_rig('reference'), [-0.8, -0.4, 0.0, 0.4, 0.8], -0.6,
                                     steps=30, tilt_step=0.05)
    np.savetxt(scan, voltages, delimiter=',')
    return params, scan


def api_cloud(port: int) -> np.ndarray:
    """(N, 3) float32 of the view's ``/api/cloud``, decoded here."""
    with urllib.request.urlopen(f'http://127.0.0.1:{port}/api/cloud', timeout=30) as r:
        data = r.read()
    (n,) = struct.unpack_from('<I', data, 0)
    meta = json.loads(data[4:4 + n])
    start = 4 + n + (-(4 + n) % 4)
    return np.frombuffer(data, '<f4', 3 * meta['points'], start).reshape(-1, 3)


def screenshot_during_a_scan(chromium, spawn, scan_csv, logs, timeout=150.0):
    """Start scans until the page shows points and a stripe while one runs, 60 % done; then
    the page's figures, a screenshot and the 3D canvas's pixels (taken during that scan)."""
    running = ("(() => { const $ = (id) => document.getElementById(id);"
               " const p = $('progress-text').dataset;"
               " return $('scan-state').textContent === 'running' && p.done >= 0.6 * p.total"
               f" && {POINTS_SHOWN} > 0 && Number($('image').dataset.stripePoints || 0) > 0;"
               " })()")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:   # discovery takes its time: scan again if needed
        scan = spawn([*GALVOSCAN, 'scan', '--pattern', 'custom', '--voltages', scan_csv,
                      '--rate', '25', '--timeout', '60'], name='scan')
        while scan.poll() is None:
            if chromium.evaluate(running):
                time.sleep(0.5)   # this cloud and image drawn and composited
                shot, pixels = chromium.screenshot(), canvas_pixels(chromium)
                figures = page_figures(chromium)
                # a newer image may be shown before its centres came: take the next one then
                if figures['stripe'] > 0 and figures['drawn'] > 0:
                    assert scan.wait(timeout=90) == 0, scan.log_path.read_text()
                    return figures, shot, pixels
            time.sleep(0.2)
        assert scan.returncode == 0, scan.log_path.read_text() + logs()
    raise AssertionError(f'no points and stripe shown during a scan\n{logs()}')


@pytest.mark.dds
def test_page_shows_the_cloud_of_a_sim_scan(chromium, spawn, tmp_path, sim_graph_params,
                                            logged_port):
    params, scan_csv = graph_params(tmp_path, sim_graph_params)
    graph = spawn([*GALVOSCAN, 'run', '--one-process', '--params', params], name='graph')
    view = spawn([*GALVOSCAN, 'view', '--host', '127.0.0.1', '--ws-port', '0',
                  '--http-port', '0'], name='view')
    port = logged_port(view, 'browser page')
    origin = f'http://127.0.0.1:{port}/'
    chromium.navigate(origin)
    chromium.wait_for("document.getElementById('connection').textContent === 'live'", 30)

    def logs():
        assert graph.poll() is None and view.poll() is None, 'a process died'
        return f'view:\n{view.log_path.read_text()}\ngraph:\n{graph.log_path.read_text()}'

    figures, shot, pixels = screenshot_during_a_scan(chromium, spawn, scan_csv, logs)
    save_screenshot(shot, tmp_path / 'view_sim_scan.png')
    xyz = api_cloud(port)

    assert chromium.problems(origin) == []
    assert figures['drawn'] > 0 and figures['total'] >= figures['drawn']
    assert figures['stripe'] > 0 and figures['diagnostics'] > 0
    assert re.search(r'\d+ / \d+ frames', figures['progress']), figures['progress']
    assert len(drawn_colours(pixels)) > 2000
    # what the page is served is the stair block and its wall, 0.6 to 0.7 m from the scanner
    assert len(xyz) > 0 and 0.6 < np.median(xyz[:, 2]) < 0.71, np.median(xyz[:, 2])

    view.send_signal(signal.SIGTERM)
    assert view.wait(timeout=20) == 0, view.log_path.read_text()
    assert 'Traceback' not in view.log_path.read_text()


# ---- (c) the calibration view, end to end ------------------------------------------------------


#: The detected points of the published view: an 11 x 8 grid of corners, 24 px apart [px].
VIEW_UV = np.array([(200.0 + 24 * c, 150.0 + 24 * r) for r in range(8) for c in range(11)])
VIEW_STAMP = (1234, 500_000_000)
#: The stamp as calibration/progress may carry it: float seconds, rounded (0.1 us off).
VIEW_STAMP_SENT = (1234, 500_000_100)


def camera_image():
    """A grey 720 x 540 mono8 frame with dark squares between the grid's corners."""
    img = np.full((540, 720), 150, np.uint8)
    for r in range(-1, 8):
        for c in range(-1, 11):
            if (r + c) % 2 == 0:
                v0, u0 = 150 + 24 * r, 200 + 24 * c
                img[max(v0, 0):v0 + 24, max(u0, 0):u0 + 24] = 40
    return img


def progress_message(accepted: bool, reason: str = ''):
    from galvoscan_msgs.msg import CalibrationProgress

    m = CalibrationProgress(stage='intrinsics', placements_done=3, placements_max=30)
    m.header.frame_id = 'v0'
    m.parameter_names = ['fx', 'cx', 'k1', 'l']
    m.parameter_units = ['px', 'px', '1', 'm']
    m.sigma = [0.8, 0.21, float('nan'), 2.0e-5]
    m.sigma_target = [0.5, 0.5, 0.01, 5.0e-5]
    m.targets_met = False
    m.advice = 'tilt the board 30 deg about its vertical axis'
    m.image_grid_cols, m.image_grid_rows = 8, 6
    cells = np.zeros((6, 8), np.uint32)
    cells[1:4, 2:5] = [[4, 8, 4], [8, 16, 8], [4, 8, 4]]
    m.image_coverage = cells.ravel().tolist()
    m.voltage_axes = 'u1x,u1y'
    m.voltage_extent = [-1.0, 1.0, -0.8, 0.8]
    m.voltage_grid_cols, m.voltage_grid_rows = 5, 4
    m.voltage_coverage = [0, 1, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0]
    m.view_stamp.sec, m.view_stamp.nanosec = VIEW_STAMP_SENT
    m.view_points_u = VIEW_UV[:, 0].tolist()
    m.view_points_v = VIEW_UV[:, 1].tolist()
    m.view_accepted, m.view_reason = accepted, reason
    return m


class CameraAndProgress:
    """This process's node on the test's domain: publishes the camera frame of a view and
    the view's calibration/progress (latched, as the calibration node publishes it)."""

    def __init__(self, domain: int):
        import rclpy
        from galvoscan_msgs.msg import CalibrationProgress
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image as ImageMsg

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node('calibration_view_test', context=self.ctx)
        self.progress = self.node.create_publisher(CalibrationProgress, 'calibration/progress',
                                                   QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.camera = self.node.create_publisher(ImageMsg, 'camera/image_raw', 5)
        img = camera_image()
        self.image = ImageMsg(height=540, width=720, encoding='mono8', step=720,
                              data=img.tobytes())
        self.image.header.stamp.sec, self.image.header.stamp.nanosec = VIEW_STAMP
        self.image.header.frame_id = 'camera_optical'
        self.pixels = img

    def close(self):
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def calibration_canvas(browser: Chromium) -> np.ndarray:
    url = browser.evaluate("document.getElementById('calib-image').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(',', 1)[1])))
                      .convert('RGB')).astype(int)


def canvas_rgb(browser: Chromium, canvas_id: str) -> np.ndarray:
    url = browser.evaluate(f"document.getElementById('{canvas_id}').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(',', 1)[1])))
                      .convert('RGB')).astype(int)


def text_of(browser: Chromium, element_id: str) -> str:
    return browser.evaluate(f"document.getElementById('{element_id}').textContent")


@pytest.mark.dds
def test_the_page_shows_the_live_detection(chromium, spawn, ros_env, tmp_path, logged_port):
    import rclpy
    import yaml
    from galvoscan_msgs.srv import CaptureCalibration

    params = tmp_path / 'calibration.yaml'
    params.write_text(yaml.safe_dump({'calibration': {'ros__parameters': {
        'calibration_file': str(tmp_path / 'cal.yaml'), 'quick': True,
        'data_dir': str(tmp_path / 'data')}}}))
    graph = spawn([*GALVOSCAN, 'run', '--params', params, '--nodes', 'calibration'],
                  name='calibration')
    view = spawn([*GALVOSCAN, 'view', '--host', '127.0.0.1', '--ws-port', '0',
                  '--http-port', '0', '--operator-timeout', '20'], name='view')
    peer = CameraAndProgress(int(ros_env['ROS_DOMAIN_ID']))
    executor = rclpy.executors.SingleThreadedExecutor(context=peer.ctx)
    executor.add_node(peer.node)

    def logs():
        return (f'view:\n{view.log_path.read_text()}\n'
                f'calibration:\n{graph.log_path.read_text()}')

    try:
        port = logged_port(view, 'browser page')
        origin = f'http://127.0.0.1:{port}/'
        chromium.navigate(origin + '#calibration')
        # the node's own idle instruction, latched; a button is answered by the node itself
        chromium.wait_for("document.getElementById('instr-state').textContent === 'idle'",
                          60, logs)
        assert 'no capture running' in text_of(chromium, 'instr-text')
        chromium.evaluate("document.getElementById('op-done').click()")
        chromium.wait_for("document.getElementById('operator-answer').dataset.action === 'done'",
                          30, logs)
        refused = text_of(chromium, 'operator-answer')

        # a capture: the node asks for its first placement
        capture = peer.node.create_client(CaptureCalibration, 'calibration/capture')
        assert capture.wait_for_service(timeout_sec=30), logs()
        captured = capture.call_async(CaptureCalibration.Request(stage='intrinsics'))
        chromium.wait_for("document.getElementById('instr-state').textContent === 'place'",
                          60, logs)
        instruction = {k: text_of(chromium, k) for k in ('instr-text', 'instr-numbers',
                                                          'instr-placement', 'calib-counters')}

        # the camera frame of a view and its detections, from this process over DDS
        peer.progress.publish(progress_message(True))
        matched = "document.getElementById('calib-image').dataset.matched === 'true'"
        deadline = time.monotonic() + 60
        while not chromium.evaluate(matched):
            assert time.monotonic() < deadline, logs()
            peer.camera.publish(peer.image)   # best effort, as a camera: until it is shown
            executor.spin_once(timeout_sec=0.2)
        time.sleep(0.3)
        kept = calibration_canvas(chromium)
        sigma_rows = chromium.evaluate(
            "[...document.querySelectorAll('#sigma-table tbody tr')]"
            ".map((tr) => [...tr.children].map((td) => td.textContent))")
        coverage = {c: chromium.evaluate(f"({{...document.getElementById('{c}').dataset}})")
                    for c in ('coverage-image', 'coverage-voltage')}
        image_cov = canvas_rgb(chromium, 'coverage-image')
        advice = text_of(chromium, 'advice')
        shot = chromium.screenshot()

        # the next view is rejected: marked so, with its reason
        peer.progress.publish(progress_message(False, 'moved'))
        chromium.wait_for("document.getElementById('calib-image').dataset.accepted === 'false'",
                          30, logs)
        time.sleep(0.3)
        rejected = calibration_canvas(chromium)
        verdict = text_of(chromium, 'view-verdict')

        # skip: the node takes it and asks for the next placement; done ends the capture
        chromium.evaluate("document.getElementById('op-skip').click()")
        chromium.wait_for("document.getElementById('operator-answer').dataset.action === 'skip'",
                          30, logs)
        skipped = text_of(chromium, 'operator-answer')
        chromium.wait_for("document.getElementById('instr-placement').textContent"
                          ".startsWith('placement 2 ')", 30, logs)
        chromium.evaluate("document.getElementById('op-done').click()")
        chromium.wait_for("document.getElementById('operator-answer').dataset.action === 'done'"
                          " && document.getElementById('operator-answer').textContent"
                          ".includes('accepted')", 30, logs)
        executor.spin_until_future_complete(captured, timeout_sec=30)
        problems = chromium.problems(origin)
    finally:
        executor.shutdown()
        peer.close()
    save_screenshot(shot, tmp_path / 'view_calibration.png')

    assert problems == []
    assert 'refused: no capture is waiting for the operator' in refused, refused
    # the instruction in words and numbers, as the node issued it
    assert 'checkerboard' in instruction['instr-text'], instruction
    assert instruction['instr-placement'].startswith('placement 1 of '), instruction
    for words in ('region centre', 'depth z', 'mm ±', 'tilt to the scanner', '°', 'hold still',
                  'square'):
        assert words in instruction['instr-numbers'], instruction
    assert 'placements kept / planned0 / ' in instruction['calib-counters'], instruction

    # the detections drawn on their own frame: a green mark on each point, the image between
    green = np.array([0x3f, 0xb9, 0x50])
    red = np.array([0xf8, 0x51, 0x49])
    u, v = np.rint(VIEW_UV).astype(int).T
    assert kept.shape == (540, 720, 3)
    assert (np.abs(kept[v, u] - green).max(axis=1) < 40).all()
    assert (np.abs(rejected[v, u] - red).max(axis=1) < 40).all()
    far = kept[500:530, 600:700]      # no mark there: the published frame itself
    assert np.abs(far - peer.pixels[500:530, 600:700, None]).max() <= 2
    assert verdict == 'rejected: moved'
    # standard errors against targets (SI values shown in mm, um, ...)
    assert sigma_rows == [['fx', 'px', '0.80', '0.50', '✗'], ['cx', 'px', '0.21', '0.50', '✓'],
                          ['k1', '1', 'not yet', '0.010', '✗'], ['l', 'µm', '20.0', '50.0', '✓']]
    assert 'tilt the board 30 deg' in advice and '3 of at most 30' in advice
    # coverage: 9 of 48 image cells, 3 of 20 voltage cells, the fullest cell bright
    assert coverage['coverage-image'] == {'covered': '9', 'cells': '48', 'max': '16'}
    assert coverage['coverage-voltage'] == {'covered': '3', 'cells': '20', 'max': '3'}
    cell_h, cell_w = image_cov.shape[0] / 6, image_cov.shape[1] / 8
    top = image_cov[int(2.5 * cell_h), int(3.5 * cell_w)]
    empty = image_cov[int(5.5 * cell_h), int(7.5 * cell_w)]
    assert top[0] > 200 and top[1] > 200 and top[2] < 100, top   # viridis' yellow
    assert np.abs(empty - [0x2a, 0x2f, 0x37]).max() < 10, empty
    # the buttons reached the node: skip taken for placement 1, done ended the capture
    assert 'skip (placement 1): accepted: skip: received' in skipped, skipped
    assert captured.done(), logs()
    assert graph.poll() is None and view.poll() is None
    assert 'Traceback' not in view.log_path.read_text()
