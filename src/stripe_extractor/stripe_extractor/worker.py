"""One background thread that processes submitted items in order, with a bounded queue.

No rclpy here. The extractor node hands each paired frame to a :class:`SerialWorker`, so the
numba kernels (compiled with ``nogil=True``) run on the second core while the executor thread
goes on taking and pairing messages. One thread keeps the output in input order.

A full queue refuses the item (``submit`` returns False) rather than blocking the executor:
the caller counts it. An exception in the handler is counted and the thread carries on.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

_STOP = object()


class SerialWorker:
    """Run ``handler(item)`` for every submitted item on one daemon thread, in order.

    Parameters
    ----------
    handler : callable
        Called with each item; should not raise (if it does, the exception is passed to
        ``on_error`` and counted in :attr:`errors`).
    capacity : int
        Items that may wait, >= 1.
    name : str
        Thread name.
    on_error : callable, optional
        Called with the exception (on the worker thread).
    """

    def __init__(self, handler: Callable[[object], None], capacity: int, name: str,
                 on_error: Callable[[BaseException], None] | None = None):
        if isinstance(capacity, bool) or int(capacity) != capacity or capacity < 1:
            raise ValueError(f'capacity must be an integer >= 1, got {capacity!r}')
        self._handler = handler
        self._on_error = on_error
        self._queue: queue.Queue = queue.Queue(maxsize=int(capacity))
        self.errors = 0
        self.processed = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def pending(self) -> int:
        """Items waiting (not counting the one being processed)."""
        return self._queue.qsize()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def submit(self, item) -> bool:
        """Queue ``item``; False (and nothing queued) if the queue is full or stopped."""
        if not self._thread.is_alive():
            return False
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            return False
        return True

    def stop(self, timeout: float = 5.0) -> bool:
        """Process what is queued, then end the thread; True if it ended within ``timeout``."""
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            try:
                self._handler(item)
            except Exception as exc:  # noqa: BLE001 - the worker outlives bad items
                self.errors += 1
                if self._on_error is not None:
                    self._on_error(exc)
            self.processed += 1
