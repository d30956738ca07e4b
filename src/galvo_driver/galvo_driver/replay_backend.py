"""The ``replay`` backend: frames and galvo states from a recorded bag (no rclpy).

A scan request plays the whole bag (the requested pattern is what was recorded, so the
voltage list of the request is not used) with its original stamps and timing, scaled by
``rate`` (0: as fast as the consumer polls). There is no hardware, so ``safe()`` has
nothing to drive.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from galvo_driver.backend import BackendError, GalvoBackend
from galvoscan_bag.frames import STATE_TOPIC, read_frames
from galvoscan_bag.reader import BagReadError, read_topics

log = logging.getLogger(__name__)

#: frames handed out per poll at most when playing as fast as possible
_BURST = 16


class ReplayBackend(GalvoBackend):
    name = 'replay'

    def __init__(self, bag, rate: float = 1.0):
        if not (rate >= 0.0):
            raise ValueError(f'rate: must be >= 0, got {rate}')
        self.bag = Path(bag) if bag else None
        self.rate = float(rate)
        self.frames_in_bag = 0
        self._iter = None
        self._next = None
        self._t0 = self._s0 = 0.0

    def open(self) -> None:
        if self.bag is None or not self.bag.exists():
            raise BackendError(f'replay_bag: no bag at {self.bag!s}')
        try:
            topics = {t.topic: t.count for t in read_topics(self.bag)}
        except BagReadError as exc:
            raise BackendError(str(exc)) from exc
        if STATE_TOPIC not in topics:
            raise BackendError(f'{self.bag}: no {STATE_TOPIC} topic to replay')
        self.frames_in_bag = topics[STATE_TOPIC]

    def start(self, voltages, frame_rate, laser_on=True) -> int:
        if self.running:
            raise BackendError('replay already running')
        log.info('replaying %s (%d frames); the requested pattern is not used',
                 self.bag, self.frames_in_bag)
        self._iter = read_frames(self.bag, states_only=True)
        self._next = next(self._iter, None)
        self._t0 = time.monotonic()
        self._s0 = self._next.stamp if self._next is not None else 0.0
        return self.frames_in_bag

    @property
    def running(self) -> bool:
        return self._next is not None

    def poll(self, timeout: float = 0.0):
        out = []
        deadline = time.monotonic() + timeout
        while self._next is not None:
            if self.rate > 0:
                due = self._t0 + (self._next.stamp - self._s0) / self.rate
                now = time.monotonic()
                if due > now:
                    if due > deadline or out:
                        break
                    time.sleep(due - now)
            elif len(out) >= _BURST:
                break
            out.append(self._next)
            self._next = next(self._iter, None)
        return out

    def stop(self) -> None:
        self._next = None
        self._iter = None

    def safe(self) -> None:
        """Nothing to drive: a bag has no galvos."""
