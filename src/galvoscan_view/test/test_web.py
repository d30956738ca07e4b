"""The browser page's HTTP server (galvoscan_view.web) over a ViewState filled in-process.

Real sockets on 127.0.0.1 (an ephemeral port): the page and its assets, the binary cloud
and image answers decoded here independently (struct + numpy, PIL for the PNG), long-polls,
references, and every kind of bad request answered with a 4xx and no change.
"""

import gzip
import http.client
import io
import json
import re
import socket
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from galvoscan_view import web
from galvoscan_view.state import CalibrationView, CloudView, ImageView, ViewState
from reconstructor.cloud import CLOUD_DTYPE, save_cloud

STATIC = Path(web.__file__).with_name('static')


@pytest.fixture
def page():
    state = ViewState()
    server = web.serve_page(state, '127.0.0.1', 0)
    yield state, server
    server.shutdown()


def request(server, method, path, body=None, headers=None):
    """(status, headers dict (lower-case names), body bytes) of one request."""
    conn = http.client.HTTPConnection('127.0.0.1', server.port, timeout=30)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
    finally:
        conn.close()


def unframe(data: bytes):
    """(metadata, [payload bytes]) of a framed answer: u32 length, JSON, pad to 4, payloads."""
    (n,) = struct.unpack_from('<I', data, 0)
    meta = json.loads(data[4:4 + n])
    offset = 4 + n + (-(4 + n) % 4)
    payloads = []
    for length in meta['payload_bytes']:
        payloads.append(data[offset:offset + length])
        offset += length
    assert offset == len(data)
    return meta, payloads


def cloud_view(n, seed=1):
    rng = np.random.default_rng(seed)
    xyz = (rng.normal(size=(n, 3)) * [0.05, 0.04, 0.01] + [0, 0, 0.7]).astype(np.float32)
    return CloudView('v0', 12.5, xyz, rng.random(n).astype(np.float32), n)


# ---- the page and its assets -----------------------------------------------------------------


def test_index_and_every_asset_it_names_are_served(page):
    _, server = page
    status, headers, body = request(server, 'GET', '/')
    assert status == 200 and headers['content-type'].startswith('text/html')
    assert body == (STATIC / 'index.html').read_bytes()
    assert "default-src 'self'" in headers['content-security-policy']
    html = body.decode()
    assets = re.findall(r'<(?:script|link)[^>]+(?:src|href)="([^"]+)"', html)
    assert sorted(assets) == ['app.js', 'favicon.svg', 'style.css']
    kinds = {'app.js': 'text/javascript', 'style.css': 'text/css', 'favicon.svg': 'image/svg+xml'}
    for name in assets:
        status, headers, body = request(server, 'GET', '/' + name,
                                        headers={'Accept-Encoding': 'gzip'})
        assert status == 200 and headers['content-type'].startswith(kinds[name])
        assert headers['content-encoding'] == 'gzip'
        assert gzip.decompress(body) == (STATIC / name).read_bytes()
    status, headers, body = request(server, 'HEAD', '/app.js')
    assert status == 200 and body == b''
    assert int(headers['content-length']) == (STATIC / 'app.js').stat().st_size


IMPORT = re.compile(r"""(?:\bimport\s*\(\s*|\bfrom\s*|^\s*import\s+)(['"])([^'"]+)\1""", re.M)
COMMENT = re.compile(r'/\*.*?\*/|^[ \t]*//[^\n]*', re.S | re.M)


def module_graph(start: str) -> set[str]:
    """Every JavaScript module the page loads from ``start``, as paths under static/.

    Fails on an import that is not a relative path to a file that exists (a bare name
    such as 'three' needs an import map; http(s):// would load from the internet)."""
    seen, todo = set(), [start]
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        seen.add(rel)
        text = COMMENT.sub('', (STATIC / rel).read_text())
        for _, spec in IMPORT.findall(text):
            assert spec.startswith(('./', '../')), f'{rel} imports {spec!r}'
            target = (STATIC / rel).parent.joinpath(spec).resolve()
            assert target.is_file() and target.is_relative_to(STATIC.resolve()), (rel, spec)
            todo.append(str(target.relative_to(STATIC.resolve())))
    return seen


def test_the_page_loads_only_its_own_files(page):
    _, server = page
    missing = [f for f in web.REQUIRED_FILES if not (STATIC / f).is_file()]
    assert not missing, f'not vendored: {missing} (run `make setup`)'
    modules = module_graph('app.js')
    assert {'app.js', 'vendor/three.module.js', 'vendor/three.core.js',
            'vendor/OrbitControls.js'} <= modules
    for rel in modules:   # served, byte for byte
        status, _, body = request(server, 'GET', '/' + rel)
        assert status == 200 and body == (STATIC / rel).read_bytes(), rel
    html = (STATIC / 'index.html').read_text()
    css = (STATIC / 'style.css').read_text()
    for ref in re.findall(r'(?:src|href)="([^"]+)"', html) + re.findall(r'url\(([^)]*)\)', css):
        assert '//' not in ref and not ref.startswith(('http', 'data:')), ref
    assert '@import' not in css
    # the page's own script talks to its origin only (relative 'api/...' addresses)
    app = (STATIC / 'app.js').read_text()
    assert not re.search(r'''\b(?:fetch|WebSocket|EventSource)\(\s*['"`](?:https?|wss?):''', app)
    assert 'api/state' in app and 'api/cloud' in app and 'api/image' in app


# ---- the API ---------------------------------------------------------------------------------


def test_cloud_bytes_decode_to_the_same_points_and_decimate_every_kth(page):
    state, server = page
    status, _, body = request(server, 'GET', '/api/cloud')
    meta, payloads = unframe(body)
    assert status == 200 and meta['points'] == 0 and payloads == [b'']

    cloud = cloud_view(1000)
    state.set_cloud(cloud)
    meta, payloads = unframe(request(server, 'GET', '/api/cloud')[2])
    xyz = np.frombuffer(payloads[0], '<f4').reshape(-1, 3)
    np.testing.assert_array_equal(xyz, cloud.xyz)
    assert meta['points'] == meta['points_total'] == 1000 and meta['frame_id'] == 'v0'
    assert meta['version'] == state.version('cloud') and meta['error'] is False
    np.testing.assert_allclose(meta['bounds'], [cloud.xyz.min(0), cloud.xyz.max(0)])

    meta, payloads = unframe(request(server, 'GET', '/api/cloud?max=300')[2])
    xyz = np.frombuffer(payloads[0], '<f4').reshape(-1, 3)
    np.testing.assert_array_equal(xyz, cloud.xyz[::4])   # ceil(1000 / 300) = 4
    assert meta['points'] == 250 and meta['points_in_state'] == 1000


def test_cloud_errors_are_distances_to_the_nearest_reference_point(page):
    state, server = page
    cloud, reference = cloud_view(400, seed=2), cloud_view(300, seed=3)
    state.set_cloud(cloud)
    meta, payloads = unframe(request(server, 'GET', '/api/cloud?error=1')[2])
    assert meta['error'] is False and len(payloads) == 1    # no reference yet
    state.set_reference(reference)
    meta, payloads = unframe(request(server, 'GET', '/api/cloud?error=1')[2])
    assert meta['error'] is True and meta['reference_points'] == 300
    got = np.frombuffer(payloads[1], '<f4')
    d = np.linalg.norm(cloud.xyz[:, None, :].astype(np.float64)
                       - reference.xyz[None, :, :].astype(np.float64), axis=2).min(axis=1)
    np.testing.assert_allclose(got, d, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize('dtype', [np.uint8, np.uint16])
def test_image_answer_holds_the_stripe_and_the_image_as_png(page, dtype):
    state, server = page
    meta, _ = unframe(request(server, 'GET', '/api/image')[2])
    assert meta['seq'] is None
    rng = np.random.default_rng(4)
    image = rng.integers(0, 4000 if dtype == np.uint16 else 256, size=(54, 72)).astype(dtype)
    state.set_image(ImageView(17, 3.0, image, np.zeros((0, 2), np.float32)))
    uv = (rng.random((30, 2)) * [72, 54]).astype(np.float32)
    state.set_stripe(17, uv)
    meta, payloads = unframe(request(server, 'GET', '/api/image')[2])
    assert (meta['seq'], meta['width'], meta['height'], meta['stripe_points']) == (17, 72, 54, 30)
    np.testing.assert_array_equal(np.frombuffer(payloads[0], '<f4').reshape(-1, 2), uv)
    png = np.asarray(Image.open(io.BytesIO(payloads[1])))
    expected = image if dtype == np.uint8 else (image.astype(np.float32)
                                               * (255.0 / image.max())).astype(np.uint8)
    np.testing.assert_array_equal(png, expected)


def test_png_gray_refuses_what_it_cannot_encode():
    for bad in (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32),
                np.zeros((0, 4), np.uint8)):
        with pytest.raises(ValueError, match='image must be'):
            web.png_gray(bad)


def test_state_summary_and_long_poll(page):
    state, server = page
    state.set_progress({'state': 'running', 'frames_done': 3, 'frames_total': 10,
                        'frames_dropped': 0})
    state.set_diagnostics('galvo_driver', {'level': 'OK', 'message': 'ok', 'scan/done': '3'})
    state.count('/points')
    state.set_cloud(cloud_view(50))
    summary = json.loads(request(server, 'GET', '/api/state')[2])
    assert summary['progress']['frames_done'] == 3
    assert summary['diagnostics']['galvo_driver']['scan/done'] == '3'
    assert summary['counts'] == {'/points': 1}
    assert summary['cloud']['points'] == 50 and summary['image'] is None
    assert summary['versions']['cloud'] == state.version('cloud')

    version = summary['version']
    answers = []
    poll = threading.Thread(target=lambda: answers.append(request(
        server, 'GET', f'/api/state?since={version}&timeout=20')))
    poll.start()
    threading.Timer(0.3, state.set_progress, [{'state': 'done', 'frames_done': 10,
                                               'frames_total': 10}]).start()
    poll.join(30)
    status, _, body = answers[0]
    summary = json.loads(body)
    assert status == 200 and summary['version'] > version
    assert summary['progress']['state'] == 'done'


# ---- bad requests ----------------------------------------------------------------------------


@pytest.mark.parametrize('method, path, status, message', [
    ('GET', '/nothing.js', 404, 'no such file'),
    ('GET', '/api/nothing', 404, 'no such resource'),
    ('GET', '/../../../../etc/passwd', 404, 'no such file'),
    ('GET', '/%2e%2e/%2e%2e/setup.py', 404, 'no such file'),
    ('GET', '/vendor/', 404, 'no such file'),
    ('GET', '/api/cloud?max=0', 400, 'outside'),
    ('GET', '/api/cloud?max=lots', 400, 'not a int'),
    ('GET', '/api/cloud?error=2', 400, 'outside'),
    ('GET', '/api/state?since=x', 400, 'not a int'),
    ('GET', '/api/state?timeout=nan', 400, 'outside'),
    ('GET', '/api/state?timeout=1e9', 400, 'outside'),
    ('POST', '/api/state', 405, 'not allowed'),
    ('PUT', '/', 405, 'not allowed'),
    ('DELETE', '/index.html', 405, 'allowed: GET, HEAD'),
    ('POST', '/api/cloud', 405, 'allowed: GET, HEAD'),
    ('POST', '/api/reference?from=cloud', 409, 'no cloud'),
    ('POST', '/api/reference?from=disk', 400, "only source is 'cloud'"),
    ('POST', '/api/operator?action=jump&placement=0', 400, 'one of placed, undo, skip, done'),
    ('POST', '/api/operator?placement=0', 400, "action=''"),
    ('POST', '/api/operator?action=placed', 400, 'placement=N is required'),
    ('POST', '/api/operator?action=placed&placement=-1', 400, 'outside'),
    ('POST', '/api/operator?action=placed&placement=4294967296', 400, 'outside'),
    ('POST', '/api/operator?action=placed&placement=two', 400, 'not a int'),
    ('POST', '/api/operator?action=done&placement=0&sequence=3', 409, 'instruction changed'),
    ('POST', '/api/operator?action=done&placement=0', 503, 'no calibration/operator client'),
    ('GET', '/api/operator', 405, 'allowed: POST'),
    ('POST', '/api/calibration/view', 405, 'allowed: GET, HEAD'),
])
def test_bad_requests_get_a_4xx_with_a_message_and_change_nothing(page, method, path, status,
                                                                  message):
    state, server = page
    before = state.version()
    got, headers, body = request(server, method, path)
    assert got == status and message in body.decode(), body
    assert headers['content-type'].startswith('text/plain')
    assert state.version() == before
    assert request(server, 'GET', '/')[0] == 200   # and the server goes on


def test_reference_from_a_galvoscan_ply_and_refusals(page, tmp_path):
    state, server = page
    rng = np.random.default_rng(5)
    cloud = np.zeros(200, CLOUD_DTYPE)
    for name in ('x', 'y', 'z'):
        cloud[name] = rng.random(200)
    save_cloud(cloud, tmp_path / 'ref.ply')
    data = (tmp_path / 'ref.ply').read_bytes()

    for path, body, status, message in (
            ('/api/reference?name=ref.txt', data, 400, 'must end in .ply or .pcd'),
            ('/api/reference?name=ref.ply', data[:-7], 400, 'ref.ply: header or size'),
            ('/api/reference?name=ref.ply', b'hello', 400, 'not a binary galvoscan PLY')):
        got, _, answer = request(server, 'POST', path, body=body)
        assert got == status and message in answer.decode(), answer
        assert state.reference is None
    got, _, answer = request(server, 'POST', '/api/reference?name=ref.ply', body=data)
    assert got == 200 and json.loads(answer)['points'] == 200
    np.testing.assert_array_equal(
        state.reference.xyz, np.column_stack([cloud['x'], cloud['y'], cloud['z']]))

    state.set_cloud(cloud_view(20))
    assert request(server, 'POST', '/api/reference?from=cloud')[0] == 200
    assert state.reference is state.cloud
    assert request(server, 'DELETE', '/api/reference')[0] == 200
    assert state.reference is None


def test_an_oversized_upload_is_refused_before_it_is_read(page):
    state, server = page
    with socket.create_connection(('127.0.0.1', server.port), timeout=30) as sock:
        sock.sendall(b'POST /api/reference?name=a.ply HTTP/1.1\r\nHost: x\r\n'
                     b'Content-Length: %d\r\n\r\n' % (web.MAX_UPLOAD_BYTES + 1))
        answer = b''
        while chunk := sock.recv(4096):   # the server closes the connection after its answer
            answer += chunk
        answer = answer.decode()
    assert answer.startswith('HTTP/1.1 413') and 'over the limit' in answer
    assert state.reference is None


# ---- binding ---------------------------------------------------------------------------------


def test_a_port_in_use_or_a_bad_address_is_a_clear_error_and_shutdown_frees_the_port(page):
    state, server = page
    with pytest.raises(OSError, match=f'port {server.port} on 127.0.0.1 is already in use'):
        web.serve_page(state, '127.0.0.1', server.port)
    for port in (-1, 65536, 8080.0, '8080'):
        with pytest.raises(ValueError, match='port must be an integer'):
            web.serve_page(state, '127.0.0.1', port)
    with pytest.raises(OSError, match='cannot listen on 192.0.2.1'):   # TEST-NET: not ours
        web.serve_page(state, '192.0.2.1', 0)
    port = server.port
    server.shutdown()
    again = web.serve_page(state, '127.0.0.1', port)   # free again
    try:
        assert again.port == port and request(again, 'GET', '/')[0] == 200
    finally:
        again.shutdown()


def test_reference_tree_refuses_what_is_not_points():
    for bad in (np.zeros((0, 3)), np.zeros((5, 2)), np.zeros(3)):
        with pytest.raises(ValueError, match='reference_xyz must be'):
            web.reference_tree(bad)
    assert web.nearest_distances(np.zeros((0, 3)), web.reference_tree(np.ones((1, 3)))).shape \
        == (0,)


# ---- the calibration view --------------------------------------------------------------------


INSTRUCTION = {'sequence': 7, 'stage': 'intrinsics', 'state': 'place', 'placement': 2,
               'text': 'Place the checkerboard'}


def test_calibration_summary_and_view_with_its_detections(page):
    state, server = page
    summary = json.loads(request(server, 'GET', '/api/state')[2])
    assert summary['calibration'] == {'instruction': None, 'progress': None, 'view': None}
    assert unframe(request(server, 'GET', '/api/calibration/view')[2])[0]['stamp'] is None

    state.set_instruction(INSTRUCTION)
    state.set_calibration_progress({'stage': 'intrinsics', 'parameters': [
        {'name': 'k1', 'unit': '1', 'sigma': None, 'target': 0.01, 'met': False}]})
    image = (np.arange(540 * 720) % 251).astype(np.uint8).reshape(540, 720)
    uv = np.array([[10.5, 20.25], [700.0, 530.0]])
    state.set_calibration_view(CalibrationView(12.5, uv, False, 'moved', image, 12.5, True))
    summary = json.loads(request(server, 'GET', '/api/state')[2])
    cal = summary['calibration']
    assert cal['instruction'] == INSTRUCTION
    assert cal['progress']['parameters'][0]['sigma'] is None
    assert cal['view'] == {'stamp': 12.5, 'points': 2, 'accepted': False, 'reason': 'moved',
                           'matched': True, 'image_stamp': 12.5, 'width': 720, 'height': 540}
    assert summary['versions']['calibration_view'] == state.version('calibration_view')

    meta, (points, png) = unframe(request(server, 'GET', '/api/calibration/view')[2])
    assert meta['points'] == 2 and meta['reason'] == 'moved' and not meta['accepted']
    np.testing.assert_array_equal(np.frombuffer(points, '<f4').reshape(-1, 2), uv)
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png))), image)

    # a view with no image yet: its points alone
    state.set_calibration_view(CalibrationView(13.0, uv[:1], True, '', None, 0.0, False))
    meta, payloads = unframe(request(server, 'GET', '/api/calibration/view')[2])
    assert len(payloads) == 1 and meta['width'] is None and not meta['matched']


def test_operator_answers_and_failures_are_passed_on(page):
    state, server = page
    state.set_instruction(INSTRUCTION)
    calls = []

    def operator(action, placement):
        calls.append((action, placement))
        if placement == 9:
            raise TimeoutError('calibration/operator did not answer within 1 s')
        if placement == 8:
            raise LookupError('calibration/operator is not available')
        return action == 'placed', f'{action}: received' if action == 'placed' else 'no'

    server.operator = operator
    status, _, body = request(server, 'POST', '/api/operator?action=placed&placement=2&sequence=7')
    assert status == 200 and json.loads(body) == {'accepted': True, 'message': 'placed: received',
                                                  'action': 'placed', 'placement': 2}
    status, _, body = request(server, 'POST', '/api/operator?action=undo&placement=2')
    assert status == 200 and not json.loads(body)['accepted']
    assert request(server, 'POST', '/api/operator?action=skip&placement=9')[0] == 504
    status, _, body = request(server, 'POST', '/api/operator?action=skip&placement=8')
    assert status == 503 and b'not available' in body
    # a page showing an older instruction is not passed on
    status, _, body = request(server, 'POST', '/api/operator?action=placed&placement=2&sequence=6')
    assert status == 409 and b'now sequence 7: place Place the checkerboard' in body
    assert calls == [('placed', 2), ('undo', 2), ('skip', 9), ('skip', 8)]
