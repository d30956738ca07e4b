"""Pairing of per-frame results with galvo states by stamp (and sequence), bounded both ways.

No rclpy here. The galvo driver publishes each frame's ``GalvoState`` with exactly the image's
header stamp, but either message may arrive first. :class:`StampPairer` keeps two small
buffers keyed by stamp [ns]; when both sides of a stamp are present it returns the pair.
Entries that can no longer be matched are dropped and counted:

- on a match at stamp T, every waiting entry older than T on either side (topics arrive in
  order, so its partner was lost);
- the oldest entry when a buffer is full.

The state's ``seq`` is checked on the way: gaps (lost states) and repeats are counted.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass


@dataclass
class PairingCounters:
    """Counts kept by :class:`StampPairer` [1]."""

    paired: int = 0
    unmatched_frames_dropped: int = 0
    unmatched_states_dropped: int = 0
    duplicate_stamps: int = 0
    state_seq_gaps: int = 0


class StampPairer:
    """Match frames (any payload) with states by integer stamp [ns].

    Parameters
    ----------
    capacity : int
        Largest number of entries waiting on each side, >= 1.
    """

    def __init__(self, capacity: int = 50):
        self._frames: OrderedDict[int, object] = OrderedDict()
        self._states: OrderedDict[int, object] = OrderedDict()
        self._last_seq: int | None = None
        self.counters = PairingCounters()
        self.capacity = capacity

    @property
    def capacity(self) -> int:
        return self._capacity

    @capacity.setter
    def capacity(self, value: int) -> None:
        if isinstance(value, bool) or int(value) != value or int(value) < 1:
            raise ValueError(f'capacity must be an integer >= 1, got {value!r}')
        self._capacity = int(value)
        self._trim(self._frames, 'unmatched_frames_dropped')
        self._trim(self._states, 'unmatched_states_dropped')

    @property
    def waiting(self) -> tuple[int, int]:
        """(frames, states) currently waiting for a partner."""
        return len(self._frames), len(self._states)

    def add_frame(self, stamp_ns: int, frame) -> tuple[object, object] | None:
        """Offer a frame; returns ``(frame, state)`` if its state is already here."""
        state = self._states.pop(stamp_ns, None)
        if state is not None:
            return self._matched(stamp_ns, frame, state)
        self._insert(self._frames, stamp_ns, frame, 'unmatched_frames_dropped')
        return None

    def add_state(self, stamp_ns: int, state, seq: int | None = None
                  ) -> tuple[object, object] | None:
        """Offer a state (with its sequence number); returns ``(frame, state)`` on a match."""
        if seq is not None:
            if self._last_seq is not None and seq > self._last_seq + 1:
                self.counters.state_seq_gaps += seq - self._last_seq - 1
            if self._last_seq is None or seq > self._last_seq:
                self._last_seq = seq
        frame = self._frames.pop(stamp_ns, None)
        if frame is not None:
            return self._matched(stamp_ns, frame, state)
        self._insert(self._states, stamp_ns, state, 'unmatched_states_dropped')
        return None

    def _matched(self, stamp_ns, frame, state):
        self.counters.paired += 1
        self._drop_older(self._frames, stamp_ns, 'unmatched_frames_dropped')
        self._drop_older(self._states, stamp_ns, 'unmatched_states_dropped')
        return frame, state

    def _insert(self, buf, stamp_ns, item, counter):
        if stamp_ns in buf:
            self.counters.duplicate_stamps += 1
        buf[stamp_ns] = item
        self._trim(buf, counter)

    def _trim(self, buf, counter):
        while len(buf) > self._capacity:
            buf.popitem(last=False)
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)

    def _drop_older(self, buf, stamp_ns, counter):
        old = [k for k in buf if k < stamp_ns]
        for k in old:
            del buf[k]
        if old:
            setattr(self.counters, counter, getattr(self.counters, counter) + len(old))
