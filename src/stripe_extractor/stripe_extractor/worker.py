"""One background thread that processes submitted items in order, with a bounded queue, and
the rule that decides when to use it.

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
    def idle(self) -> bool:
        """Nothing waiting and nothing being processed."""
        return self._queue.unfinished_tasks == 0

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
            self._queue.task_done()


class OffloadPolicy:
    """When to hand frames to the worker: the ``auto`` mode of the extractor node.

    Frames are extracted on the caller's thread (the executor) while it can carry them, and
    handed to the worker only once it cannot. A second thread does not make the work
    cheaper: it costs a hand-over and a wait for the GIL per frame, and on a loaded machine
    the GIL holder can be descheduled while the other thread waits (measured in
    ``benchmarks/pipeline.py``: in a process of its own at 500 fps, where the executor thread
    has nothing else to do, handing over lost up to half of the frames where extracting
    inline lost 2 %). It pays when the executor thread also serves other nodes, or when the
    frame rate leaves no time to extract inline.

    The policy keeps running means (weight ``weight`` for the newest value) of the interval
    between frames, of the caller thread's CPU time per frame, and of the extraction CPU
    time. The *inline load* is the share of the frame interval the caller's thread would be
    busy extracting every frame itself: its own CPU time per frame, plus the extraction time
    while frames go to the worker. Frames go to the worker once the inline load exceeds
    ``above``, and come back once it is below ``below`` and the worker is idle (so the output
    stays in order). Intervals longer than ``max_interval`` (pauses between scans) are not
    learned from.
    """

    def __init__(self, above: float = 0.9, below: float = 0.7, weight: float = 0.05,
                 max_interval: float = 0.1):
        if not 0.0 < below <= above or not 0.0 < weight <= 1.0 or max_interval <= 0.0:
            raise ValueError('need 0 < below <= above, 0 < weight <= 1 and max_interval > 0')
        self.above, self.below, self.weight, self.max_interval = above, below, weight, \
            max_interval
        self.offload = False
        self.interval_mean = None
        self.thread_cpu_mean = 0.0
        self.extract_mean = 0.0
        self._last = None

    @property
    def inline_load(self) -> float:
        """Share of the frame interval the caller's thread needs to extract inline [1]."""
        if not self.interval_mean:
            return 0.0
        own = self.thread_cpu_mean + (self.extract_mean if self.offload else 0.0)
        return own / self.interval_mean

    def note_extraction(self, seconds: float) -> None:
        """One frame's extraction CPU time [s] (from whichever thread extracted it)."""
        self.extract_mean += self.weight * (seconds - self.extract_mean)

    def decide(self, now: float, thread_cpu: float, worker_idle: bool) -> bool:
        """A frame arrived: True to hand it to the worker.

        Parameters
        ----------
        now : float
            Arrival time [s, monotonic].
        thread_cpu : float
            The caller thread's CPU time so far [s] (``time.thread_time()``).
        worker_idle : bool
            Nothing is queued or running on the worker.
        """
        if self._last is not None:
            interval = now - self._last[0]
            if 0.0 < interval <= self.max_interval:
                cpu = max(thread_cpu - self._last[1], 0.0)
                if self.interval_mean is None:
                    self.interval_mean, self.thread_cpu_mean = interval, cpu
                else:
                    self.interval_mean += self.weight * (interval - self.interval_mean)
                    self.thread_cpu_mean += self.weight * (cpu - self.thread_cpu_mean)
        self._last = (now, thread_cpu)
        load = self.inline_load
        if not self.offload and load > self.above:
            self.offload = True
        elif self.offload and load < self.below and worker_idle:
            self.offload = False
        return self.offload
