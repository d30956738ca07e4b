"""The Foxglove WebSocket server, spoken to by a raw WebSocket client (no ROS, no DDS).

Real sockets on ephemeral ports of 127.0.0.1: the foxglove-sdk server behind the front,
the ``websockets`` client on the other side, as Foxglove or Lichtblick would connect.
"""

import json
import socket
import struct
import threading
import time

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from galvoscan_bag.typestore import default_typestore
from galvoscan_common import cdr
from galvoscan_view.foxglove_server import (
    SUBPROTOCOLS,
    ChannelSpec,
    FoxgloveServer,
    ros2msg_definition,
)

CLOUD = ChannelSpec('/points', 'sensor_msgs/msg/PointCloud2', lossy=True)
TF = ChannelSpec('/tf', 'tf2_msgs/msg/TFMessage')
TF_STATIC = ChannelSpec('/tf_static', 'tf2_msgs/msg/TFMessage', latched=10)
POINT_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                        ('width', '<f4')])
HEAD = struct.Struct('<BIQ')   # messageData: opcode 1, subscription id, log time [ns]
TIMEOUT_S = 20.0


def _connect(port, subprotocol=SUBPROTOCOLS[0], **kwargs):
    return connect(f'ws://127.0.0.1:{port}', subprotocols=[subprotocol], max_size=None,
                   open_timeout=TIMEOUT_S, **kwargs)


def _stalling_client(port):
    """A client whose socket takes almost nothing while it is not read (4 kB receive buffer,
    at most two frames held by the library), as a slow link behaves."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(('127.0.0.1', port))
    return _connect(port, sock=sock, max_queue=(2, 1))


def _hello(ws):
    """serverInfo, then the advertised channels by topic."""
    info = json.loads(ws.recv(timeout=TIMEOUT_S))
    assert info['op'] == 'serverInfo', info
    channels = {}
    while not channels:
        msg = json.loads(ws.recv(timeout=TIMEOUT_S))
        if msg['op'] == 'advertise':
            channels = {c['topic']: c for c in msg['channels']}
    return info, channels


def _subscribe(ws, channels, topics):
    """Subscribe to ``topics``; returns subscription id -> topic."""
    subs = {i + 1: t for i, t in enumerate(topics)}
    ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
        {'id': i, 'channelId': channels[t]['id']} for i, t in subs.items()]}))
    return subs


def _message(frame):
    """(subscription id, log time [ns], payload) of a messageData frame."""
    assert isinstance(frame, bytes) and frame[0] == 1, frame[:16]
    _, sub, log_time = HEAD.unpack_from(frame)
    return sub, log_time, frame[HEAD.size:]


def _probe_until_received(server, ws, topic, payload=b'probe'):
    """Log ``payload`` on ``topic`` until ``ws`` gets it: its subscription is live."""
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        server.log(topic, payload)
        try:
            frame = ws.recv(timeout=0.1)
        except TimeoutError:
            continue
        if isinstance(frame, bytes) and _message(frame)[2] == payload:
            return
    raise AssertionError(f'{topic}: no message arrived within {TIMEOUT_S} s')


def _cloud(n, seed):
    rng = np.random.default_rng(seed)
    points = np.zeros(n, POINT_DTYPE)
    for name in POINT_DTYPE.names:
        points[name] = rng.uniform(-1, 1, n)
    return points, cdr.serialize_point_cloud(points, cdr.Header(12, 345, 'v0'))


@pytest.mark.parametrize('subprotocol', SUBPROTOCOLS)
def test_a_client_of_either_subprotocol_gets_the_channels_and_a_cloud(subprotocol):
    with FoxgloveServer([CLOUD, TF], host='127.0.0.1', port=0) as server, \
            _connect(server.port, subprotocol) as ws:
        assert ws.subprotocol == subprotocol
        info, channels = _hello(ws)
        assert set(channels) == {'/points', '/tf'}
        points_channel = channels['/points']
        assert (points_channel['encoding'], points_channel['schemaName'],
                points_channel['schemaEncoding']) == ('cdr', 'sensor_msgs/msg/PointCloud2',
                                                      'ros2msg')
        assert points_channel['schema'] == ros2msg_definition('sensor_msgs/msg/PointCloud2')
        assert points_channel['schema'].startswith('std_msgs/Header header\n')
        assert '\nMSG: sensor_msgs/PointField\n' in points_channel['schema']

        subs = _subscribe(ws, channels, ['/points'])
        _probe_until_received(server, ws, '/points')
        points, data = _cloud(500, seed=3)
        server.log('/points', data, log_time_ns=1_700_000_000_123_456_789)
        sub, log_time, payload = _message(ws.recv(timeout=TIMEOUT_S))
        assert subs[sub] == '/points' and log_time == 1_700_000_000_123_456_789
        assert payload == data
        # decoded independently of galvoscan's codec, by rosbags
        msg = default_typestore().deserialize_cdr(payload, 'sensor_msgs/msg/PointCloud2')
        assert (msg.header.frame_id, msg.header.stamp.sec, msg.width) == ('v0', 12, 500)
        assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
            (n, POINT_DTYPE.fields[n][1], 7) for n in POINT_DTYPE.names]
        decoded = np.frombuffer(msg.data.tobytes(), POINT_DTYPE)
        np.testing.assert_array_equal(decoded, points)


def test_the_view_reads_the_cloud_as_it_was_written():
    from galvoscan_common.cdr import parse_point_cloud
    from galvoscan_view.view_node import cloud_xyz

    points, _ = _cloud(300, seed=5)
    points['x'][7] = np.nan
    data = cdr.serialize_point_cloud(points, cdr.Header(12, 345, 'v0'), is_dense=False)
    header, read = parse_point_cloud(data)
    assert (header.sec, header.nanosec, header.frame_id) == (12, 345, 'v0')
    np.testing.assert_array_equal(read[~np.isnan(read['x'])], points[~np.isnan(points['x'])])
    xyz, intensity = cloud_xyz(read)
    keep = np.ones(300, bool)
    keep[7] = False
    np.testing.assert_array_equal(xyz, np.column_stack([points[c] for c in 'xyz'])[keep])
    np.testing.assert_array_equal(intensity, points['intensity'][keep])
    with pytest.raises(cdr.CdrError):
        parse_point_cloud(data[:-30])


@pytest.mark.parametrize('offered', [None, ['foxglove.websocket.v2']])
def test_a_client_without_a_foxglove_subprotocol_is_refused(offered):
    with FoxgloveServer([CLOUD], host='127.0.0.1', port=0) as server:
        with pytest.raises(InvalidStatus) as err:
            connect(f'ws://127.0.0.1:{server.port}', subprotocols=offered,
                    open_timeout=TIMEOUT_S)
        assert err.value.response.status_code == 400


def test_a_port_in_use_is_an_os_error():
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        with pytest.raises(OSError):
            FoxgloveServer([CLOUD], host='127.0.0.1', port=taken.getsockname()[1])


def test_a_late_subscriber_gets_the_latched_messages_first():
    with FoxgloveServer([TF_STATIC], host='127.0.0.1', port=0) as server:
        for i in range(3):
            server.log('/tf_static', b'static %d' % i, log_time_ns=100 + i)
        with _connect(server.port) as ws:
            _, channels = _hello(ws)
            _subscribe(ws, channels, ['/tf_static'])
            got = [_message(ws.recv(timeout=TIMEOUT_S))[1:] for _ in range(3)]
        assert got == [(100 + i, b'static %d' % i) for i in range(3)]


def _read_until(ws, subs, done, timeout=TIMEOUT_S):
    """Read messageData frames until ``done(received)``; received: topic -> list of
    (index, payload size); payloads start with a uint32 index."""
    received = {t: [] for t in subs.values()}
    deadline = time.monotonic() + timeout
    while not done(received):
        frame = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
        if isinstance(frame, bytes):
            sub, _, payload = _message(frame)
            if payload != b'probe':
                received[subs[sub]].append(struct.unpack_from('<I', payload)[0])
    return received


def test_a_slow_client_loses_clouds_never_tf_and_holds_back_no_one():
    n_clouds, tf_every, cloud_bytes = 2000, 40, 20_000
    n_tf = n_clouds // tf_every
    with FoxgloveServer([CLOUD, TF], host='127.0.0.1', port=0,
                        lossy_budget=256 * 1024) as server, \
            _stalling_client(server.port) as slow, _connect(server.port) as fast:
        subs = {}
        for ws in (slow, fast):
            _, channels = _hello(ws)
            subs[ws] = _subscribe(ws, channels, ['/points', '/tf'])
            for topic in ('/points', '/tf'):
                _probe_until_received(server, ws, topic)
        fast_got = {}
        reader = threading.Thread(target=lambda: fast_got.update(_read_until(
            fast, subs[fast], lambda r: len(r['/tf']) == n_tf)))
        reader.start()
        # the slow client reads nothing from here on
        filler = bytes(cloud_bytes)
        for i in range(n_clouds):
            server.log('/points', struct.pack('<I', i) + filler)
            if i % tf_every == tf_every - 1:
                server.log('/tf', struct.pack('<I', i // tf_every) + b'transform')
        reader.join(TIMEOUT_S)
        assert not reader.is_alive(), 'the fast client did not get every TF message'
        assert fast_got['/tf'] == list(range(n_tf))
        dropped = sum(c['dropped'].get('/points', 0) for c in server.stats()['per_client'])
        assert dropped > 0, server.stats()

        slow_got = _read_until(slow, subs[slow], lambda r: len(r['/tf']) == n_tf
                               and r['/points'] and r['/points'][-1] == n_clouds - 1)
    assert slow_got['/tf'] == list(range(n_tf))          # every TF, in order
    clouds = slow_got['/points']
    assert len(clouds) < n_clouds / 2, len(clouds)      # most clouds were dropped ...
    assert clouds == sorted(set(clouds))                # ... the rest in order
    assert clouds[-1] == n_clouds - 1                   # and the newest was kept


def test_a_client_that_lets_kept_messages_pile_up_is_disconnected():
    with FoxgloveServer([TF], host='127.0.0.1', port=0, keep_limit=256 * 1024) as server, \
            _stalling_client(server.port) as slow:
        _, channels = _hello(slow)
        _subscribe(slow, channels, ['/tf'])
        _probe_until_received(server, slow, '/tf')
        # far more than the socket buffers (4 MB here) and the limit hold
        for i in range(600):
            server.log('/tf', struct.pack('<I', i) + bytes(16_000))
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                slow.recv(timeout=TIMEOUT_S)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
        deadline = time.monotonic() + TIMEOUT_S
        while server.stats()['clients'] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert server.stats() == {**server.stats(), 'clients': 0, 'clients_total': 1}


# ---- what the view node reads from the graph (pure helpers of galvoscan_view.view_node) ----
def test_the_view_reads_transforms_as_parent_T_child():
    from scipy.spatial.transform import Rotation

    from galvoscan_view.view_node import transform_views

    store = default_typestore()
    t = store.types
    rot = Rotation.from_euler('xyz', [0.3, -0.2, 1.1])
    x, y, z, w = rot.as_quat()
    tf = t['geometry_msgs/msg/TransformStamped'](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](sec=3, nanosec=5),
                                        frame_id='v0'),
        child_frame_id='camera_optical',
        transform=t['geometry_msgs/msg/Transform'](
            translation=t['geometry_msgs/msg/Vector3'](x=0.1, y=-0.2, z=0.3),
            rotation=t['geometry_msgs/msg/Quaternion'](x=x, y=y, z=z, w=w)))
    data = bytes(store.serialize_cdr(t['tf2_msgs/msg/TFMessage'](transforms=[tf]),
                                     'tf2_msgs/msg/TFMessage'))
    [view] = transform_views(data, static=True)
    assert (view.parent, view.child, view.static) == ('v0', 'camera_optical', True)
    assert view.stamp == pytest.approx(3 + 5e-9)
    p_child = np.array([0.05, 0.02, -0.4])
    expected = rot.apply(p_child) + [0.1, -0.2, 0.3]
    np.testing.assert_allclose((view.parent_T_child @ [*p_child, 1.0])[:3], expected,
                               atol=1e-12)


def test_the_view_reads_statuses_and_the_scan_progress_from_diagnostics():
    from galvoscan_view.view_node import diagnostic_statuses

    store = default_typestore()
    t = store.types

    def status(name, level, values):
        return t['diagnostic_msgs/msg/DiagnosticStatus'](
            level=level, name=name, message=f'{name} says hi', hardware_id='',
            values=[t['diagnostic_msgs/msg/KeyValue'](key=k, value=v) for k, v in values])

    array = t['diagnostic_msgs/msg/DiagnosticArray'](
        header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](sec=1, nanosec=0),
                                        frame_id=''),
        status=[status('stripe_extractor: extraction', 0, [('frames_extracted', '12')]),
                status('galvo_driver: galvo driver', 1, [
                    ('scan/state', 'running'), ('scan/done', '10'), ('scan/total', '25'),
                    ('scan/dropped', '1')])])
    data = bytes(store.serialize_cdr(array, 'diagnostic_msgs/msg/DiagnosticArray'))
    statuses, progress = diagnostic_statuses(data)
    assert statuses['stripe_extractor: extraction'] == {
        'frames_extracted': '12', 'level': 'OK', 'message': 'stripe_extractor: extraction says hi'}
    assert statuses['galvo_driver: galvo driver']['level'] == 'WARN'
    assert progress == {'state': 'running', 'frames_done': 10, 'frames_total': 25,
                        'frames_dropped': 1}


def test_the_stripe_is_drawn_on_its_image():
    from galvoscan_view.view_node import STRIPE_RGB, serialize_rgb8, stripe_overlay

    rng = np.random.default_rng(11)
    image = rng.integers(0, 200, (40, 60)).astype(np.uint8)
    uv = np.array([[10.2, 5.7], [59.4, 39.4], [-3.0, 2.0], [np.nan, 1.0]], np.float32)
    rgb = stripe_overlay(image, uv)
    assert rgb.shape == (40, 60, 3) and rgb.dtype == np.uint8
    red = (rgb == STRIPE_RGB).all(axis=2)
    expected = np.zeros((40, 60), bool)
    for r, c in ((6, 10), (5, 10), (7, 10), (6, 9), (6, 11), (39, 59), (38, 59), (39, 58)):
        expected[r, c] = True
    np.testing.assert_array_equal(red, expected)
    np.testing.assert_array_equal(rgb[~red], np.repeat(image[~red][:, None], 3, axis=1))
    msg = default_typestore().deserialize_cdr(
        serialize_rgb8(rgb, cdr.Header(1, 2, 'camera_optical')), 'sensor_msgs/msg/Image')
    assert (msg.encoding, msg.height, msg.width, msg.step) == ('rgb8', 40, 60, 180)
    np.testing.assert_array_equal(msg.data.reshape(40, 60, 3), rgb)
