"""A Foxglove WebSocket server of raw ROS 2 messages, with priorities per client (no rclpy).

Foxglove and Lichtblick connect to it as they do to foxglove_bridge: every channel is a ROS 2
topic with a ``ros2msg`` schema (the message definition text rosbag2 and foxglove_bridge send,
made by rosbags' type store) and ``cdr`` message encoding; the serialised bytes a raw
subscription hands over are forwarded unchanged.

Two layers, one port (``DEFAULT_WS_PORT`` 8765, foxglove_bridge's default):

- the **foxglove-sdk** WebSocket server (the protocol: ``serverInfo``, ``advertise``,
  subscriptions, message framing) listens on an ephemeral port of 127.0.0.1 only;
- a **front** (``websockets``, asyncio, one thread) listens on the public port. It accepts
  both subprotocol names, ``foxglove.sdk.v1`` (what the SDK and newer bridges accept, and
  only that one) and ``foxglove.websocket.v1`` (what older clients offer): the two names
  denote the same protocol. For each client it opens one loopback connection to the SDK
  (as ``foxglove.sdk.v1``) and relays the frames both ways, unchanged.

The front owns each client's send queue, so that a slow client loses what may be lost and
nothing else (foxglove_bridge's ``send_buffer_limit`` lesson: dropping by buffer size alone
drops TF as readily as clouds). Messages of a **lossy** channel (clouds, images) wait in a
queue of their channel, bounded by ``lossy_budget`` bytes: the oldest is dropped when it
overflows (the newest is always kept). Everything else, the **kept** messages (TF, galvo
state, diagnostics, markers, and every text frame of the protocol), waits in one queue that
is sent first and never dropped; a client that lets more than ``keep_limit`` bytes of them
pile up is disconnected (code 1008) rather than silently losing one. What has been handed
to the kernel cannot be overtaken any more, so each client socket's send buffer is kept
small (``SEND_BUFFER_BYTES``): a kept message waits behind at most that and the one message
being written. Measured with a client reading 1 MB/s while clouds (7.2 MB/s), galvo states
(500 Hz) and TF (10 Hz) are logged: every TF and galvo state arrives, in order, 0.65 s late
(3.6 s with the kernel's default buffer), and about one cloud in six.

The SDK's own per-connection queue (``SDK_BACKLOG`` messages, oldest dropped) sits between
the SDK and the front; the front reads it as fast as loopback delivers (no flow control on
that connection), so it only overflows if this process stalls for seconds.

**Latched** channels (``/tf_static``, ``points/scan``) keep their last ``latched`` messages;
a client that subscribes is sent them first, as a transient-local ROS subscription is.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Iterable
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass

import foxglove
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve
from websockets.exceptions import ConnectionClosed, WebSocketException

#: The subprotocol names accepted on the public port, preferred first.
SUBPROTOCOLS = ('foxglove.sdk.v1', 'foxglove.websocket.v1')
#: The only one the foxglove-sdk server accepts.
SDK_SUBPROTOCOL = 'foxglove.sdk.v1'
#: foxglove_bridge's default port.
DEFAULT_WS_PORT = 8765
#: Bytes of one lossy channel a client may have waiting before its oldest are dropped.
LOSSY_BUDGET_BYTES = 2 * 2**20
#: Bytes of kept messages a client may have waiting before it is disconnected.
KEEP_LIMIT_BYTES = 64 * 2**20
#: Kernel send buffer of each client's socket [bytes] (Linux doubles it; ``None``: the
#: kernel's autotuning, up to 4 MB). What the kernel holds cannot be reordered any more: a
#: kept message waits behind all of it, so it is kept small (see the module docstring).
SEND_BUFFER_BYTES = 256 * 1024
#: Messages the SDK buffers per loopback connection (its own drop-oldest queue).
SDK_BACKLOG = 8192
#: Opcode of a server's binary ``messageData`` frame: opcode, subscription id, log time.
MESSAGE_DATA = 0x01
_MESSAGE_HEAD = struct.Struct('<BIQ')
#: How long the front and the SDK may take to start or stop [s].
START_TIMEOUT_S = 10.0

log = logging.getLogger('galvoscan_view.foxglove')


def ros2msg_definition(msgtype: str, typestore=None) -> str:
    """The ``ros2msg`` definition text of ``msgtype`` (e.g. ``'sensor_msgs/msg/Image'``).

    The message's own fields, then each nested type after a ``====`` line and ``MSG: name``,
    as rosbag2 stores it in a bag and foxglove_bridge sends it (rosbags' type store, with the
    galvoscan_msgs interfaces registered: :func:`galvoscan_bag.typestore.default_typestore`).

    Raises
    ------
    KeyError
        ``msgtype`` is not in the type store.
    """
    if typestore is None:
        from galvoscan_bag.typestore import default_typestore

        typestore = default_typestore()
    if msgtype not in typestore.fielddefs:
        raise KeyError(f'{msgtype}: not a known message type')
    return typestore.generate_msgdef(msgtype, ros_version=2)[0]


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: a ROS topic, its type, whether it may be dropped, how many to latch.

    ``msgtype`` is the ROS 2 name (``package/msg/Type``); ``lossy`` channels lose their oldest
    messages for a slow client; ``latched`` > 0 sends the last ``latched`` messages to every
    new subscriber.
    """

    topic: str
    msgtype: str
    lossy: bool = False
    latched: int = 0


class ClientTooSlowError(Exception):
    """A client let more kept (never dropped) bytes pile up than the limit allows."""


class Outbox:
    """One client's queue: kept frames first, in order; lossy frames by channel, bounded.

    ``put`` and ``pop`` run on the front's event loop only (not thread-safe).
    """

    def __init__(self, lossy_budget: int = LOSSY_BUDGET_BYTES,
                 keep_limit: int = KEEP_LIMIT_BYTES):
        self.lossy_budget, self.keep_limit = int(lossy_budget), int(keep_limit)
        self._keep: deque = deque()
        self._keep_bytes = 0
        self._lossy: dict[int, deque] = {}   # channel id -> deque of (seq, frame)
        self._lossy_bytes: dict[int, int] = {}
        self._seq = 0
        self.dropped: dict[int, int] = {}    # channel id -> lossy frames dropped
        self.ready = asyncio.Event()

    def put(self, frame, channel: int | None = None, lossy: bool = False) -> None:
        """Queue ``frame`` (bytes or str); ``channel`` is the channel id of a lossy frame.

        Raises
        ------
        ClientTooSlowError
            The kept frames waiting exceed ``keep_limit`` bytes.
        """
        size = len(frame)
        if lossy:
            queue = self._lossy.setdefault(channel, deque())
            queue.append((self._seq, frame))
            self._seq += 1
            total = self._lossy_bytes.get(channel, 0) + size
            while total > self.lossy_budget and len(queue) > 1:
                total -= len(queue.popleft()[1])
                self.dropped[channel] = self.dropped.get(channel, 0) + 1
            self._lossy_bytes[channel] = total
        else:
            self._keep.append(frame)
            self._keep_bytes += size
            if self._keep_bytes > self.keep_limit:
                raise ClientTooSlowError(f'{self._keep_bytes} bytes of undroppable messages '
                                         f'waiting (limit {self.keep_limit})')
        self.ready.set()

    def pop(self):
        """The next frame to send, or ``None``: a kept one, else the oldest lossy one."""
        if self._keep:
            frame = self._keep.popleft()
            self._keep_bytes -= len(frame)
            return frame
        heads = [(q[0][0], ch) for ch, q in self._lossy.items() if q]
        if not heads:
            self.ready.clear()
            return None
        channel = min(heads)[1]
        frame = self._lossy[channel].popleft()[1]
        self._lossy_bytes[channel] -= len(frame)
        return frame

    async def get(self):
        """Wait for, and return, the next frame."""
        while True:
            frame = self.pop()
            if frame is not None:
                return frame
            await self.ready.wait()

    @property
    def waiting_bytes(self) -> int:
        """Bytes queued, kept and lossy."""
        return self._keep_bytes + sum(self._lossy_bytes.values())


class FoxgloveServer:
    """foxglove-sdk's WebSocket server behind a front that accepts both subprotocol names.

    Parameters
    ----------
    channels : iterable of ChannelSpec
        Channels advertised from the start (more with :meth:`add_channel`).
    host, port : str, int
        Where the front listens (``port`` 0: an ephemeral port, see :attr:`port`).
    name : str
        The server name clients show.
    lossy_budget, keep_limit : int, bytes
        Per client: the bound of each lossy channel's queue, and of the kept queue.
    send_buffer : int or None, bytes
        Kernel send buffer of each client socket (``None``: the kernel's default).
    typestore
        rosbags type store for the definitions (default: galvoscan_bag's).

    Raises
    ------
    OSError
        The port is in use, or the host cannot be bound.
    """

    def __init__(self, channels: Iterable[ChannelSpec] = (), *, host: str = '0.0.0.0',
                 port: int = DEFAULT_WS_PORT, name: str = 'galvoscan view',
                 lossy_budget: int = LOSSY_BUDGET_BYTES, keep_limit: int = KEEP_LIMIT_BYTES,
                 send_buffer: int | None = SEND_BUFFER_BYTES, typestore=None):
        self.lossy_budget, self.keep_limit = lossy_budget, keep_limit
        self.send_buffer = send_buffer
        self._typestore = typestore
        self._context = foxglove.Context()
        self._lock = threading.Lock()
        self._channels: dict[str, foxglove.Channel] = {}
        self._specs: dict[int, ChannelSpec] = {}          # channel id -> spec
        self._latched: dict[int, deque] = {}              # channel id -> (log_time, data)
        self._clients: dict[int, Outbox] = {}
        self._clients_total = 0
        for spec in channels:
            self.add_channel(spec)
        self._sdk = foxglove.start_server(name=name, host='127.0.0.1', port=0,
                                          context=self._context,
                                          message_backlog_size=SDK_BACKLOG)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever,
                                        name='foxglove-front', daemon=True)
        self._thread.start()
        try:
            self._front = asyncio.run_coroutine_threadsafe(
                self._start_front(host, port), self._loop).result(START_TIMEOUT_S)
        except BaseException:
            self._stop_loop()
            self._sdk.stop()
            raise

    # -- channels ---------------------------------------------------------------------
    def add_channel(self, spec: ChannelSpec) -> None:
        """Advertise one more channel (to connected clients too).

        Raises
        ------
        ValueError
            A channel of this topic exists, or ``latched`` is negative.
        KeyError
            Unknown message type.
        """
        if spec.latched < 0:
            raise ValueError(f'{spec.topic}: latched must be >= 0, got {spec.latched}')
        text = ros2msg_definition(spec.msgtype, self._typestore)
        with self._lock:
            if spec.topic in self._channels:
                raise ValueError(f'{spec.topic}: channel exists')
            channel = foxglove.Channel(
                spec.topic, message_encoding='cdr', context=self._context,
                schema=foxglove.Schema(name=spec.msgtype, encoding='ros2msg',
                                       data=text.encode('utf-8')))
            self._channels[spec.topic] = channel
            self._specs[channel.id()] = spec
            if spec.latched:
                self._latched[channel.id()] = deque(maxlen=spec.latched)

    @property
    def topics(self) -> list[str]:
        """The topics of the channels, in the order they were added."""
        with self._lock:
            return list(self._channels)

    def log(self, topic: str, data, log_time_ns: int | None = None) -> None:
        """Send one serialised message (CDR bytes) to the clients subscribed to ``topic``.

        ``log_time_ns`` is the message's receive time [ns since the epoch] (default now), as
        foxglove_bridge stamps it. Raises ``KeyError`` for a topic without a channel.
        """
        channel = self._channels[topic]
        data = bytes(data)
        log_time_ns = time.time_ns() if log_time_ns is None else int(log_time_ns)
        latched = self._latched.get(channel.id())
        if latched is not None:
            with self._lock:
                latched.append((log_time_ns, data))
        channel.log(data, log_time=log_time_ns)

    def has_subscribers(self, topic: str) -> bool:
        """Whether any client is subscribed to ``topic`` (to skip work nobody would see)."""
        return self._channels[topic].has_sinks()

    def stats(self) -> dict:
        """Clients connected and ever accepted; per connected client, bytes waiting and
        lossy messages dropped by topic."""
        with self._lock:
            clients = dict(self._clients)
        names = {cid: spec.topic for cid, spec in self._specs.items()}
        return {'clients': len(clients), 'clients_total': self._clients_total,
                'per_client': [{'waiting_bytes': box.waiting_bytes,
                                'dropped': {names.get(c, c): n for c, n in box.dropped.items()}}
                               for box in clients.values()]}

    @property
    def port(self) -> int:
        """The public (front) port."""
        return self._front.sockets[0].getsockname()[1]

    def stop(self) -> None:
        """Close every client connection and both servers (idempotent)."""
        if self._thread.is_alive():
            try:
                asyncio.run_coroutine_threadsafe(
                    self._stop_front(), self._loop).result(START_TIMEOUT_S)
            except (FutureTimeout, RuntimeError) as exc:
                log.warning(f'front did not close cleanly: {exc!r}')
            self._stop_loop()
            self._sdk.stop()

    def __enter__(self) -> FoxgloveServer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the front (runs on its event loop) ---------------------------------------------
    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT_S)

    async def _start_front(self, host: str, port: int):
        return await serve(self._serve_client, host, port, subprotocols=list(SUBPROTOCOLS),
                           compression=None, max_size=2**20, close_timeout=2.0)

    async def _stop_front(self) -> None:
        self._front.close()
        await self._front.wait_closed()

    async def _serve_client(self, front) -> None:
        try:
            backend = await connect(f'ws://127.0.0.1:{self._sdk.port}',
                                    subprotocols=[SDK_SUBPROTOCOL], compression=None,
                                    max_size=None, max_queue=None, ping_interval=None,
                                    open_timeout=START_TIMEOUT_S, close_timeout=1.0)
        except (OSError, TimeoutError, WebSocketException) as exc:
            log.error(f'client {front.remote_address}: the SDK server did not accept: {exc}')
            await front.close(1011, 'foxglove server unavailable')
            return
        sock = front.transport.get_extra_info('socket')
        if self.send_buffer is not None and sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer)
        box = Outbox(self.lossy_budget, self.keep_limit)
        subscriptions: dict[int, int] = {}   # client's subscription id -> channel id
        with self._lock:
            self._clients[id(box)] = box
            self._clients_total += 1
        log.info(f'client {front.remote_address} connected ({front.subprotocol})')
        tasks = [asyncio.create_task(coro) for coro in (
            self._upstream(front, backend, box, subscriptions),
            self._downstream(backend, box, subscriptions), self._send(front, box))]
        code, reason = 1000, ''
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            exc = next(iter(done)).exception()
            if isinstance(exc, ClientTooSlowError):
                code, reason = 1008, 'too slow for kept messages'
                log.warning(f'client {front.remote_address} disconnected: {exc}')
            elif exc is not None and not isinstance(exc, ConnectionClosed):
                code, reason = 1011, 'internal error'
                log.error(f'client {front.remote_address}: {exc!r}')
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            with self._lock:
                self._clients.pop(id(box), None)
            await asyncio.gather(front.close(code, reason), backend.close())
            log.info(f'client {front.remote_address} left')

    async def _upstream(self, front, backend, box: Outbox, subscriptions: dict) -> None:
        """Client -> SDK, unchanged; subscriptions are noted (and latched messages sent)."""
        async for frame in front:
            if isinstance(frame, str):
                self._note_request(frame, box, subscriptions)
            await backend.send(frame)

    def _note_request(self, text: str, box: Outbox, subscriptions: dict) -> None:
        try:
            request = json.loads(text)
            op = request.get('op')
            if op == 'subscribe':
                for sub in request['subscriptions']:
                    sub_id, channel_id = int(sub['id']), int(sub['channelId'])
                    subscriptions[sub_id] = channel_id
                    self._send_latched(box, sub_id, channel_id)
            elif op == 'unsubscribe':
                for sub_id in request['subscriptionIds']:
                    subscriptions.pop(int(sub_id), None)
        except (ValueError, TypeError, KeyError, AttributeError):
            pass   # forwarded as it is: the SDK answers a malformed request with a status

    def _send_latched(self, box: Outbox, sub_id: int, channel_id: int) -> None:
        latched = self._latched.get(channel_id)
        if latched is None or not 0 <= sub_id < 2**32:
            return
        with self._lock:
            messages = list(latched)
        lossy = self._specs[channel_id].lossy
        for log_time, data in messages:
            box.put(_MESSAGE_HEAD.pack(MESSAGE_DATA, sub_id, log_time) + data, channel_id, lossy)

    async def _downstream(self, backend, box: Outbox, subscriptions: dict) -> None:
        """SDK -> the client's outbox, classified by the channel of each message."""
        async for frame in backend:
            channel_id, lossy = None, False
            if isinstance(frame, bytes) and len(frame) >= 5 and frame[0] == MESSAGE_DATA:
                channel_id = subscriptions.get(int.from_bytes(frame[1:5], 'little'))
                spec = self._specs.get(channel_id)
                lossy = spec is not None and spec.lossy
            box.put(frame, channel_id, lossy)

    @staticmethod
    async def _send(front, box: Outbox) -> None:
        while True:
            await front.send(await box.get())
