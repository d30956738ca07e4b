"""In-process hand-off of serialised messages between nodes composed in one process.

No rclpy here. rclpy has no intra-process communication (rclcpp's
``use_intra_process_comms``): a message between two nodes of one process goes through
Fast DDS like any other, and a 720x540 image is copied about five times on the way (into
the publisher's std::string, the writer's history, the reader's history, the taken
serialised message and the Python bytes). Measured with ``benchmarks/pipeline.py``'s floor
(player, relay and sink in one process, no extraction) at 1000 fps: 0.52-0.53 ms of CPU per
frame over DDS, 0.26-0.28 ms handed over.

So the nodes of ``galvoscan run --one-process`` hand the camera frames and galvo states
over directly:

- a :class:`HandOffPublisher` gives each message, as the CDR bytes it would publish, to
  every callback subscribed to its topic on the :class:`Bus` of its rclpy Context
  (:func:`bus_for`), in subscription order, on the publisher's own thread; then it
  publishes the message over DDS only if DDS subscribers exist (a recorder, a viewer, a node
  in another process);
- a node that subscribes on the bus does not also subscribe over DDS to the same topic, so
  it hears each message once, and hears only publishers in its own process.

The callbacks run on the publisher's thread, so the publishing and the subscribing node
must be served by the same single-threaded executor (``galvoscan run --one-process`` puts
them on one EventsExecutor). Topics are the fully resolved names (``/camera/image_raw``).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable


class Subscription:
    """What :meth:`Bus.subscribe` returns; give it to :meth:`Bus.unsubscribe`."""

    __slots__ = ('topic', 'callback')

    def __init__(self, topic: str, callback: Callable[[bytes], None]):
        self.topic, self.callback = topic, callback


class Bus:
    """The in-process subscribers of one rclpy Context, by resolved topic name."""

    def __init__(self):
        self._lock = threading.Lock()
        self._subs: dict[str, tuple[Subscription, ...]] = {}
        self._callbacks: dict[str, tuple[Callable, ...]] = {}

    def subscribe(self, topic: str, callback: Callable[[bytes], None]) -> Subscription:
        """Call ``callback(data)`` with every message handed over on ``topic``."""
        if not (isinstance(topic, str) and topic.startswith('/')):
            raise ValueError(f'topic must be a resolved name starting with /, got {topic!r}')
        if not callable(callback):
            raise ValueError(f'callback must be callable, got {type(callback).__name__}')
        sub = Subscription(topic, callback)
        with self._lock:
            self._set(topic, (*self._subs.get(topic, ()), sub))
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Remove one subscription; removing it twice is a no-op."""
        with self._lock:
            self._set(sub.topic, tuple(s for s in self._subs.get(sub.topic, ()) if s is not sub))

    def _set(self, topic: str, subs: tuple) -> None:
        if subs:
            self._subs[topic] = subs
            self._callbacks[topic] = tuple(s.callback for s in subs)
        else:
            self._subs.pop(topic, None)
            self._callbacks.pop(topic, None)

    def callbacks(self, topic: str) -> tuple[Callable, ...]:
        """The callbacks subscribed to ``topic`` now (a snapshot), in subscription order."""
        return self._callbacks.get(topic, ())


_buses: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_buses_lock = threading.Lock()


def bus_for(context) -> Bus:
    """The :class:`Bus` of an rclpy Context (one per context, dropped with it)."""
    with _buses_lock:
        bus = _buses.get(context)
        if bus is None:
            bus = _buses[context] = Bus()
        return bus


class HandOffPublisher:
    """Publish CDR bytes to in-process subscribers directly, and over DDS when heard there.

    ``publisher`` is an rclpy publisher (raw ``bytes`` are published as the serialised
    message). A lifecycle publisher that is not activated hands nothing over either. An
    exception raised by a subscriber's callback is counted in :attr:`errors`,
    given to ``on_error`` and does not stop the delivery to the others, nor the DDS publish.
    """

    def __init__(self, publisher, bus: Bus, on_error: Callable[[BaseException], None]
                 | None = None):
        self.publisher = publisher
        self.topic = publisher.topic_name
        self.bus = bus
        self.on_error = on_error
        self.errors = 0
        self.handed_off = 0
        self.published = 0

    def publish(self, data: bytes) -> None:
        if not isinstance(data, bytes):
            raise TypeError(f'data must be the serialised message as bytes, got '
                            f'{type(data).__name__}')
        if not getattr(self.publisher, 'is_activated', True):
            return
        for callback in self.bus.callbacks(self.topic):
            self.handed_off += 1
            try:
                callback(data)
            except Exception as exc:  # noqa: BLE001 - one subscriber must not stop the rest
                self.errors += 1
                if self.on_error is not None:
                    self.on_error(exc)
        if self.publisher.get_subscription_count():
            self.publisher.publish(data)
            self.published += 1
