"""The browser page of ``galvoscan view``: an HTTP server over a :class:`ViewState` (no rclpy).

:func:`serve_page` serves, from one port, the page in ``static/`` (its own HTML, CSS and
JavaScript, and three.js vendored into ``static/vendor`` at build time: nothing is fetched
from the internet, and the Content-Security-Policy of every page response forbids it) and
a compact API read from the state:

=========================  ================================================================
``GET /``                  the page (``static/index.html``); ``GET /<file>`` its assets
``GET /api/state``         JSON summary of everything (no arrays): versions, cloud size and
                           bounds, image size, galvo state, progress, diagnostics, counts,
                           transforms, reference. ``?since=V&timeout=S`` long-polls: it
                           answers once the state's version exceeds ``V`` or after ``S``
                           seconds (at most ``LONG_POLL_MAX_S``)
``GET /api/cloud``         the cloud as a :func:`framed` message: metadata, then x, y, z
                           float32 little-endian [m] (N, 3), then with ``?error=1`` and a
                           reference the distance of each point to its nearest reference
                           point, float32 (N,) [m]. ``?max=N`` decimates to at most N
                           points (every k-th point; default ``DEFAULT_MAX_POINTS``)
``GET /api/image``         the camera image as a :func:`framed` message: metadata, the
                           stripe centres float32 (M, 2) [px] (column, row), then the image
                           as an 8-bit grey PNG
``GET /api/calibration/view``  the last calibration view as a :func:`framed` message:
                           metadata (view stamp, accepted, reason, whether the image is the
                           view's own frame), the detected centres float32 (N, 2) [px]
                           (column, row), then the image as an 8-bit grey PNG (absent
                           before any image)
``POST /api/reference``    ``?from=cloud``: the current cloud becomes the reference;
                           otherwise the body is a binary PLY or PCD file as galvoscan
                           writes it (``?name=FILE.ply`` tells which)
``DELETE /api/reference``  no reference
``POST /api/operator``     ``?action=placed|undo|skip|done&placement=N[&sequence=S]``: the
                           operator's answer, sent to the calibration node's
                           ``calibration/operator``; JSON ``{accepted, message, action,
                           placement}`` of its answer (200, also when it refuses). With
                           ``sequence`` (the instruction the page shows) a 409 when the
                           node has issued another instruction since; 503 without a
                           calibration node, 504 when it does not answer in time
=========================  ================================================================

The summary's ``calibration`` holds ``instruction`` (calibration/instruction),
``progress`` (calibration/progress without its points: standard errors against targets,
coverage grids, advice) and ``view`` (the last view's stamp, number of points, verdict).

A bad request gets a 4xx answer with a one-line message (text/plain); a failure inside a
handler a 500 with its message: the server and the view go on.
"""

from __future__ import annotations

import errno
import gzip
import json
import logging
import mimetypes
import socket
import struct
import tempfile
import threading
import time
import zlib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

import numpy as np

from galvoscan_view.state import MAX_VIEW_POINTS, CloudView, ViewState

#: The page's files; ``vendor/`` is filled by ``tools/setup_venv.sh web`` (three.js from npm).
STATIC_DIR = Path(__file__).resolve().with_name('static')
#: Files the page cannot start without, relative to STATIC_DIR.
REQUIRED_FILES = ('index.html', 'app.js', 'style.css', 'vendor/three.module.js',
                  'vendor/three.core.js', 'vendor/OrbitControls.js')
#: Points sent to the browser unless it asks for another number (every k-th point beyond).
DEFAULT_MAX_POINTS = 500_000
#: Longest a long-poll of ``/api/state`` waits [s].
LONG_POLL_MAX_S = 25.0
#: Largest reference file accepted [bytes] (MAX_VIEW_POINTS points of 20 bytes, and a header).
MAX_UPLOAD_BYTES = MAX_VIEW_POINTS * 20 + 4096
#: Every page response: nothing but this origin may be loaded or connected to.
CONTENT_SECURITY_POLICY = ("default-src 'self'; script-src 'self'; style-src 'self'; "
                           "img-src 'self' blob: data:; connect-src 'self'; "
                           "object-src 'none'; base-uri 'none'; frame-ancestors 'none'")
#: Keys of :meth:`ViewState.version` reported by ``/api/state``.
VERSION_KEYS = ('cloud', 'image', 'galvo', 'tf', 'progress', 'diagnostics', 'reference',
                'instruction', 'calibration_progress', 'calibration_view')
#: The operator's actions the page may send (galvoscan_msgs/OperatorAction ``action``).
OPERATOR_ACTIONS = ('placed', 'undo', 'skip', 'done')

log = logging.getLogger('galvoscan_view.web')


class RequestError(Exception):
    """A request the server refuses: ``status`` (4xx) and a one-line message."""

    def __init__(self, status: int, message: str, headers: dict | None = None):
        super().__init__(message)
        self.status, self.headers = status, headers


# ---- encodings (pure) ----------------------------------------------------------------------


def png_gray(image: np.ndarray) -> bytes:
    """An 8-bit grey PNG of ``image``.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16 [DN]
        16-bit images are scaled so that their maximum is 255.

    Returns
    -------
    bytes
        The PNG file (one IDAT chunk, zlib level 1, no row filter).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or 0 in img.shape:
        raise ValueError(f'image must be a non-empty (H, W) uint8 or uint16 array, '
                         f'got {img.dtype} {img.shape}')
    if img.dtype != np.uint8:
        top = float(img.max()) or 1.0
        img = (img.astype(np.float32) * (255.0 / top)).astype(np.uint8)
    h, w = img.shape
    rows = np.zeros((h, w + 1), np.uint8)   # a filter-type byte (0: none) before each row
    rows[:, 1:] = img

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack('>I', len(data)) + tag + data
                + struct.pack('>I', zlib.crc32(tag + data) & 0xFFFFFFFF))

    return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, 8, 0, 0, 0, 0))
            + chunk(b'IDAT', zlib.compress(rows.tobytes(), 1)) + chunk(b'IEND', b''))


def framed(meta: dict, *payloads: bytes) -> bytes:
    """One binary message: metadata JSON and payloads, as the page's ``unframe`` reads it.

    Layout: uint32 little-endian length L of the UTF-8 JSON ``meta``, the JSON, zero bytes to
    the next multiple of 4 (so that float32 payloads are aligned), then the payloads one
    after another. ``meta['payload_bytes']`` is set to the length of each payload.
    """
    meta = {**meta, 'payload_bytes': [len(p) for p in payloads]}
    text = json.dumps(meta, separators=(',', ':')).encode()
    head = struct.pack('<I', len(text)) + text
    return b''.join([head, bytes(-len(head) % 4), *payloads])


def decimate(xyz: np.ndarray, max_points: int) -> np.ndarray:
    """Every k-th row of ``xyz`` (N, 3), k the smallest that leaves at most ``max_points``."""
    if max_points < 1:
        raise ValueError(f'max_points must be >= 1, got {max_points}')
    k = max(1, -(-len(xyz) // max_points))
    return xyz[::k]


def reference_tree(reference_xyz: np.ndarray):
    """A k-d tree (scipy ``cKDTree``) of the reference points, for :func:`nearest_distances`.

    Parameters
    ----------
    reference_xyz : ndarray, shape (R, 3), metres, R >= 1
    """
    from scipy.spatial import cKDTree

    ref = np.asarray(reference_xyz, np.float64)
    if ref.ndim != 2 or ref.shape[1] != 3 or len(ref) == 0:
        raise ValueError(f'reference_xyz must be (R, 3) with R >= 1, got {ref.shape}')
    return cKDTree(ref)


def nearest_distances(xyz: np.ndarray, tree) -> np.ndarray:
    """Distance of each point to its nearest reference point.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3), metres
    tree : cKDTree
        Of the reference points (:func:`reference_tree`).

    Returns
    -------
    ndarray, shape (N,), float32, metres
    """
    xyz = np.asarray(xyz).reshape(-1, 3)
    if len(xyz) == 0:
        return np.zeros(0, np.float32)
    return tree.query(xyz, k=1)[0].astype(np.float32)


def _bounds(xyz: np.ndarray):
    if len(xyz) == 0:
        return None
    return [np.min(xyz, axis=0).tolist(), np.max(xyz, axis=0).tolist()]


def _cloud_summary(cloud: CloudView | None) -> dict | None:
    if cloud is None:
        return None
    return {'frame_id': cloud.frame_id, 'stamp': cloud.stamp, 'points': len(cloud.xyz),
            'points_total': int(cloud.points_total)}


def state_summary(state: ViewState) -> dict:
    """The JSON-ready summary of ``/api/state`` (every value a plain Python type)."""
    versions = {k: state.version(k) for k in VERSION_KEYS}
    snap = state.snapshot()
    image, galvo = snap['image'], snap['galvo']
    out = {
        'version': snap['version'], 'versions': versions, 'time': time.time(),
        'cloud': _cloud_summary(snap['cloud']),
        'reference': _cloud_summary(snap['reference']),
        'image': None if image is None else {
            'seq': int(image.seq), 'stamp': image.stamp, 'height': int(image.image.shape[0]),
            'width': int(image.image.shape[1]), 'stripe_points': len(image.stripe_uv)},
        'galvo': None if galvo is None else {
            'seq': int(galvo.seq), 'stamp': galvo.stamp,
            'voltages': np.asarray(galvo.voltages, float).tolist(),
            'laser_on': bool(galvo.laser_on), 'status': int(galvo.status)},
        'transforms': {child: {'parent': tf.parent, 'static': bool(tf.static),
                               'translation': np.asarray(tf.parent_T_child)[:3, 3].tolist()}
                       for child, tf in snap['transforms'].items()},
        'progress': snap['progress'], 'diagnostics': snap['diagnostics'],
        'counts': snap['counts'],
        'calibration': {'instruction': snap['instruction'],
                        'progress': snap['calibration_progress'],
                        'view': _view_summary(snap['calibration_view'])}}
    return json.loads(json.dumps(out, default=_plain))   # fails here, not half-way out


def _view_summary(view) -> dict | None:
    if view is None:
        return None
    out = {'stamp': view.stamp, 'points': len(view.uv), 'accepted': bool(view.accepted),
           'reason': view.reason, 'matched': bool(view.matched), 'image_stamp': view.image_stamp,
           'width': None, 'height': None}
    if view.image is not None:
        out['height'], out['width'] = (int(n) for n in view.image.shape[:2])
    return out


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def load_reference_file(data: bytes, name: str) -> CloudView:
    """A reference cloud from the bytes of a PLY or PCD file as galvoscan writes it.

    Raises ``ValueError`` (with the reader's reason) for anything else or an empty cloud.
    """
    from reconstructor.cloud import load_cloud, xyz

    suffix = Path(name).suffix.lower()
    if suffix not in ('.ply', '.pcd'):
        raise ValueError(f'reference file {name!r}: name must end in .ply or .pcd')
    with tempfile.TemporaryDirectory(prefix='galvoscan_view_') as tmp:
        path = Path(tmp) / f'reference{suffix}'
        path.write_bytes(data)
        try:
            cloud = load_cloud(path)
        except ValueError as exc:
            raise ValueError(str(exc).replace(str(path), name)) from None
    points = xyz(cloud).astype(np.float32)
    finite = np.isfinite(points).all(axis=1)
    if not finite.any():
        raise ValueError(f'reference file {name!r} has no finite points')
    return CloudView('v0', 0.0, points[finite], cloud['intensity'][finite], int(finite.sum()))


# ---- the server ----------------------------------------------------------------------------


class _Encoded:
    """The last few encoded answers, keyed by the objects they were made of (``is``)."""

    def __init__(self, size: int = 2):
        self._lock, self._items, self._size = threading.Lock(), [], size

    def get(self, key: tuple, make):
        with self._lock:
            for k, v in self._items:
                if len(k) == len(key) and all(a is b for a, b in zip(k, key, strict=True)):
                    return v
        value = make()
        with self._lock:
            self._items = [(key, value), *self._items][:self._size]
        return value


class _StaticFiles:
    """The files under STATIC_DIR by URL path, read once (again when changed), gzip kept."""

    def __init__(self, root: Path):
        self.root, self._lock, self._cache = root.resolve(), threading.Lock(), {}

    def get(self, url_path: str):
        """(body, gzipped body, content type) of ``url_path``, or ``None`` (not a file)."""
        rel = unquote(url_path).lstrip('/') or 'index.html'
        if '\\' in rel or '\0' in rel:
            return None
        path = (self.root / rel).resolve()
        if not path.is_relative_to(self.root) or not path.is_file():
            return None
        mtime = path.stat().st_mtime_ns
        with self._lock:
            hit = self._cache.get(path)
        if hit is None or hit[0] != mtime:
            body = path.read_bytes()
            kind = {'.js': 'text/javascript', '.mjs': 'text/javascript',
                    '.css': 'text/css', '.html': 'text/html'}.get(path.suffix)
            kind = kind or mimetypes.guess_type(path.name)[0] or 'application/octet-stream'
            if kind.startswith('text/'):
                kind += '; charset=utf-8'
            hit = (mtime, body, gzip.compress(body, 6, mtime=0), kind)
            with self._lock:
                self._cache[path] = hit
        return hit[1:]


def _query(url: str) -> dict:
    try:
        return {k: v[-1] for k, v in parse_qs(urlsplit(url).query, strict_parsing=False,
                                              max_num_fields=20).items()}
    except ValueError as exc:
        raise RequestError(400, f'bad query string: {exc}') from None


def _number(query: dict, key: str, default, kind, lo, hi):
    """``query[key]`` as ``kind`` within [lo, hi], else a 400."""
    if key not in query:
        return default
    try:
        value = kind(query[key])
    except ValueError:
        raise RequestError(400, f'{key}={query[key]!r} is not a {kind.__name__}') from None
    if not lo <= value <= hi:   # NaN fails this too
        raise RequestError(400, f'{key}={query[key]} is outside {lo}..{hi}')
    return value


class _Handler(BaseHTTPRequestHandler):
    server_version = 'galvoscan-view'
    protocol_version = 'HTTP/1.1'
    page: PageServer   # set on the subclass made per server
    #: method -> path -> name of the handler method
    routes = {'GET': {'/api/state': '_state', '/api/cloud': '_cloud', '/api/image': '_image',
                      '/api/calibration/view': '_calibration_view'},
              'POST': {'/api/reference': '_set_reference', '/api/operator': '_operator'},
              'DELETE': {'/api/reference': '_clear_reference'}}

    # -- plumbing --------------------------------------------------------------------------
    def log_message(self, format, *args):  # noqa: A002 - BaseHTTPRequestHandler's signature
        log.debug('%s %s', self.address_string(), format % args)

    def _send(self, status: int, body: bytes, kind: str, headers: dict | None = None):
        self.send_response(status)
        self.send_header('Content-Type', kind)
        self.send_header('Content-Length', str(len(body)))
        self.send_header('Cache-Control', 'no-cache')
        self.send_header('X-Content-Type-Options', 'nosniff')
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != 'HEAD':
            self.wfile.write(body)

    def _dispatch(self, method: str):
        path = urlsplit(self.path).path
        try:
            name = self.routes.get(method, {}).get(path)
            allowed = ([m for m, r in self.routes.items() if path in r]
                       if path.startswith('/api/') else ['GET'])   # the rest: static files
            if name is None and allowed == ['GET'] and method == 'GET':
                name = '_static'
            if name is None:
                if allowed:
                    allow = ', '.join(allowed + ['HEAD'] * ('GET' in allowed))
                    raise RequestError(405, f'{self.command} is not allowed on {path} '
                                            f'(allowed: {allow})', {'Allow': allow})
                raise RequestError(404, f'no such resource: {path}')
            getattr(self, name)()
        except RequestError as exc:
            self._send(exc.status, f'{exc}\n'.encode(), 'text/plain; charset=utf-8',
                       exc.headers)
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True
        except Exception as exc:   # a boundary: the server goes on, the client is told
            log.exception('%s %s failed', self.command, self.path)
            try:
                self._send(500, f'internal error: {type(exc).__name__}: {exc}\n'.encode(),
                           'text/plain; charset=utf-8')
            except OSError:
                self.close_connection = True

    def do_GET(self):
        self._dispatch('GET')

    do_HEAD = do_GET

    def do_POST(self):
        self._dispatch('POST')

    def do_DELETE(self):
        self._dispatch('DELETE')

    def do_PUT(self):
        self._dispatch(self.command)

    do_PATCH = do_OPTIONS = do_PUT

    def _body(self, limit: int) -> bytes:
        try:
            n = int(self.headers.get('Content-Length', '0'))
        except ValueError:
            raise RequestError(400, 'Content-Length is not a number') from None
        if n < 0:
            raise RequestError(400, 'Content-Length is negative')
        if n > limit:
            self.close_connection = True   # the unread body must not be taken as a request
            raise RequestError(413, f'body of {n} bytes is over the limit of {limit} bytes')
        return self.rfile.read(n)

    # -- routes ----------------------------------------------------------------------------
    def _static(self):
        if urlsplit(self.path).path in ('/', '/index.html') and self.page.missing:
            raise RequestError(503, 'the page is not installed: missing ' + ', '.join(
                self.page.missing) + ' (run `make setup`, or `tools/setup_venv.sh web`)')
        found = self.page.static.get(urlsplit(self.path).path)
        if found is None:
            raise RequestError(404, f'no such file: {urlsplit(self.path).path}')
        body, zipped, kind = found
        headers = {'Content-Security-Policy': CONTENT_SECURITY_POLICY, 'Vary': 'Accept-Encoding'}
        if 'gzip' in self.headers.get('Accept-Encoding', ''):
            body, headers['Content-Encoding'] = zipped, 'gzip'
        self._send(200, body, kind, headers)

    def _state(self):
        query = _query(self.path)
        since = _number(query, 'since', -1, int, -1, 2**63)
        timeout = _number(query, 'timeout', 0.0, float, 0.0, LONG_POLL_MAX_S)
        deadline = time.monotonic() + timeout
        state = self.page.state
        while state.version() <= since and not self.page.closing.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            state.wait_newer(since, min(left, 0.5))
        body = json.dumps(state_summary(state), separators=(',', ':')).encode()
        self._send(200, body, 'application/json')

    def _cloud(self):
        query = _query(self.path)
        max_points = _number(query, 'max', DEFAULT_MAX_POINTS, int, 1, MAX_VIEW_POINTS)
        want_error = _number(query, 'error', 0, int, 0, 1) == 1
        self._send(200, self.page.cloud_message(max_points, want_error),
                   'application/octet-stream')

    def _image(self):
        self._send(200, self.page.image_message(), 'application/octet-stream')

    def _calibration_view(self):
        self._send(200, self.page.calibration_view_message(), 'application/octet-stream')

    def _operator(self):
        query = _query(self.path)
        self._body(4096)   # a body is not used; read so that the connection stays in step
        action = query.get('action', '')
        if action not in OPERATOR_ACTIONS:
            raise RequestError(400, f'action={action!r}: one of {", ".join(OPERATOR_ACTIONS)}')
        if 'placement' not in query:
            raise RequestError(400, "placement=N is required (the instruction's placement)")
        placement = _number(query, 'placement', 0, int, 0, 2**32 - 1)
        sequence = _number(query, 'sequence', None, int, 0, 2**32 - 1)
        shown = self.page.state.snapshot()['instruction']
        if sequence is not None and (shown is None or shown['sequence'] != sequence):
            now = 'none yet' if shown is None else (
                f"sequence {shown['sequence']}: {shown['state']} {shown['text']}")
            raise RequestError(409, f'the instruction changed since sequence {sequence} '
                                    f'(now {now}); look again before answering')
        operator = self.page.operator
        if operator is None:
            raise RequestError(503, 'this page has no calibration/operator client '
                                    '(run it with galvoscan view)')
        try:
            accepted, message = operator(action, placement)
        except ValueError as exc:
            raise RequestError(400, str(exc)) from None
        except LookupError as exc:
            raise RequestError(503, str(exc)) from None
        except TimeoutError as exc:
            raise RequestError(504, str(exc)) from None
        log.info('operator %s (placement %d): %s, %s', action, placement,
                 'accepted' if accepted else 'refused', message)
        body = {'accepted': bool(accepted), 'message': str(message), 'action': action,
                'placement': placement}
        self._send(200, json.dumps(body).encode(), 'application/json')

    def _set_reference(self):
        query = _query(self.path)
        state = self.page.state
        if query.get('from') == 'cloud':
            cloud = state.snapshot()['cloud']
            if cloud is None or len(cloud.xyz) == 0:
                raise RequestError(409, 'there is no cloud yet to take as the reference')
            reference = cloud
        elif 'from' in query:
            raise RequestError(400, f"from={query['from']!r}: the only source is 'cloud'")
        else:
            name = query.get('name', '')
            data = self._body(MAX_UPLOAD_BYTES)
            try:
                reference = load_reference_file(data, name)
            except ValueError as exc:
                raise RequestError(400, str(exc)) from None
        state.set_reference(reference)
        self._send(200, json.dumps(_cloud_summary(reference)).encode(), 'application/json')

    def _clear_reference(self):
        self.page.state.set_reference(None)
        self._send(200, b'{}', 'application/json')


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True   # TIME_WAIT sockets of a previous run do not block the port

    def handle_error(self, request, client_address):   # a connection's failure, logged once
        log.debug('connection from %s failed', client_address, exc_info=True)


class _HTTPServer6(_HTTPServer):
    address_family = socket.AF_INET6


class PageServer:
    """The page's HTTP server, serving on its own thread; see :func:`serve_page`."""

    def __init__(self, state: ViewState, host: str, port: int, operator=None):
        self.state, self.static, self.closing = state, _StaticFiles(STATIC_DIR), threading.Event()
        #: ``f(action, placement) -> (accepted, message)``: the calibration node's answer
        #: (ValueError: bad request, LookupError: no node, TimeoutError: no answer); None: the
        #: page has no operator client and answers 503
        self.operator = operator
        self.missing = [f for f in REQUIRED_FILES if not (STATIC_DIR / f).is_file()]
        self._clouds, self._images, self._trees = _Encoded(), _Encoded(), _Encoded(1)
        self._views = _Encoded()
        handler = type('Handler', (_Handler,), {'page': self})
        kind = _HTTPServer6 if ':' in host else _HTTPServer
        try:
            self._httpd = kind((host, port), handler)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise OSError(exc.errno, f'port {port} on {host} is already in use') from None
            raise OSError(exc.errno, f'cannot listen on {host}:{port}: '
                                     f'{exc.strerror or exc}') from None
        self.host, self.port = host, self._httpd.server_address[1]
        self._thread = threading.Thread(target=self._httpd.serve_forever,
                                        kwargs={'poll_interval': 0.2},
                                        name='galvoscan-view-http', daemon=True)
        self._thread.start()
        if self.missing:
            log.warning('the browser page is not installed (missing %s under %s): run '
                        '`make setup`', ', '.join(self.missing), STATIC_DIR)

    @property
    def url(self) -> str:
        host = f'[{self.host}]' if ':' in self.host else self.host
        return f'http://{host}:{self.port}/'

    def shutdown(self) -> None:
        """Stop serving and close the socket (long-polls still waiting answer within 0.5 s)."""
        if self.closing.is_set():
            return
        self.closing.set()
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=5)

    # -- encoded answers, cached per cloud / image object --------------------------------
    def cloud_message(self, max_points: int, want_error: bool) -> bytes:
        """The ``/api/cloud`` answer (see the module docstring)."""
        version = self.state.version('cloud')
        snap = self.state.snapshot()
        cloud, reference = snap['cloud'], snap['reference'] if want_error else None
        return self._clouds.get((cloud, reference, max_points),
                                lambda: self._encode_cloud(version, cloud, reference, max_points))

    def _encode_cloud(self, version, cloud, reference, max_points) -> bytes:
        meta = {'version': version, 'frame_id': '', 'stamp': 0.0, 'points': 0,
                'points_in_state': 0, 'points_total': 0, 'bounds': None, 'error': False}
        if cloud is None:
            return framed(meta, b'')
        xyz = np.ascontiguousarray(decimate(cloud.xyz, max_points), '<f4')
        meta.update(frame_id=cloud.frame_id, stamp=cloud.stamp, points=len(xyz),
                    points_in_state=len(cloud.xyz), points_total=int(cloud.points_total),
                    bounds=_bounds(xyz))
        payloads = [xyz.tobytes()]
        if reference is not None and len(reference.xyz):
            tree = self._trees.get((reference,), lambda: reference_tree(reference.xyz))
            distances = nearest_distances(xyz, tree).astype('<f4')
            meta.update(error=True, reference_points=len(reference.xyz))
            payloads.append(distances.tobytes())
        return framed(meta, *payloads)

    def image_message(self) -> bytes:
        """The ``/api/image`` answer (see the module docstring)."""
        version = self.state.version('image')
        image = self.state.snapshot()['image']
        if image is None:
            return framed({'version': version, 'seq': None})
        return self._images.get((image,), lambda: self._encode_image(version, image))

    @staticmethod
    def _encode_image(version, image) -> bytes:
        uv = np.ascontiguousarray(np.asarray(image.stripe_uv, '<f4').reshape(-1, 2))
        h, w = image.image.shape[:2]
        meta = {'version': version, 'seq': int(image.seq), 'stamp': image.stamp, 'width': int(w),
                'height': int(h), 'stripe_points': len(uv), 'encoding': 'png'}
        return framed(meta, uv.tobytes(), png_gray(image.image))


    def calibration_view_message(self) -> bytes:
        """The ``/api/calibration/view`` answer (see the module docstring)."""
        version = self.state.version('calibration_view')
        view = self.state.snapshot()['calibration_view']
        if view is None:
            return framed({'version': version, 'stamp': None})
        return self._views.get((view,), lambda: self._encode_view(version, view))

    @staticmethod
    def _encode_view(version, view) -> bytes:
        uv = np.ascontiguousarray(np.asarray(view.uv, '<f4').reshape(-1, 2))
        meta = {'version': version, **_view_summary(view), 'encoding': 'png'}
        payloads = [uv.tobytes()]
        if view.image is not None:
            payloads.append(png_gray(view.image))
        return framed(meta, *payloads)


def serve_page(state: ViewState, host: str, port: int, operator=None) -> PageServer:
    """Serve the browser page of ``state`` on ``host``:``port`` from a background thread.

    Parameters
    ----------
    state : ViewState
        What the page shows; read only (except the reference the page may set).
    host : str
        Address to listen on (``'0.0.0.0'`` every IPv4 interface, ``'::'`` IPv6, ...).
    port : int
        TCP port, 0 for any free one (then ``.port`` tells which).
    operator : callable, optional
        ``operator(action, placement) -> (accepted, message)`` for ``POST /api/operator``
        (:meth:`galvoscan_view.view_node.ViewNode.operator_action`); may be set later as
        ``.operator``.

    Returns
    -------
    PageServer
        ``.port`` (bound), ``.url``, ``.shutdown()``.

    Raises
    ------
    ValueError
        ``port`` outside 0..65535.
    OSError
        The port is in use, or ``host`` is not an address of this machine.
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f'port must be an integer in 0..65535 (0: any free port), got {port!r}')
    return PageServer(state, host, port, operator)
