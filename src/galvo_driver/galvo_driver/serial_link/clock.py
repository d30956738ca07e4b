"""The board's microsecond clock in the host's ``time.time()`` base, drift included (pure).

The serial backend measures the offset between the two clocks before each scan: the
GET_STATUS exchange with the shortest round trip, its midpoint against the board's uptime.
Between those syncs a board crystal that runs fast or slow by tens to hundreds of ppm moves
the stamps away from the host's time: +200 ppm is 0.2 ms per second, 12 ms after a minute
of scanning, and the frames of a long scan no longer line up with the robot's poses or any
other host-stamped data.

The board answers every heartbeat (20 a second) with a STATUS holding its uptime, and
reports every trigger as an EVENT with its board time; the host reads each some latency
later, never earlier. So over a stretch of messages, the smallest ``host - board``
difference follows the clocks' offset, shifted by the link's least latency, and its trend
is the drift: known 2 s after the handshake, before the first scan.
:class:`BoardClock` keeps that lower envelope in bins of board time and
fits a line through the bins' minima: the slope is the drift; the offset stays the one of
the last sync, so the stamps no longer drift between syncs. The envelope outlives a scan
(the drift is the crystal's); a jump that two successive bins agree on (a board clock
step) starts it afresh, as does a board reset; a jump one bin alone shows is a host
stall and is ignored.
"""

from __future__ import annotations

import math

import numpy as np

#: Board time per envelope bin [s].
BIN_S = 0.5
#: Bins kept (the newest): the drift is fitted over at most this many bins.
MAX_BINS = 240
#: Fewest bins, and the least board time they must span [s], before a drift is fitted.
MIN_BINS = 4
MIN_SPAN_S = 2.0
#: A crystal's plausible rate error [ppm]: a fitted slope beyond it is not used.
MAX_DRIFT_PPM = 1000.0
#: A bin's minimum this far off the fitted line [s] means the clocks stepped: start afresh.
STEP_S = 0.002


class BoardClock:
    """Board clock [us] -> host ``time.time()`` [s]: the last sync's offset, then the drift
    of the EVENT arrivals' lower envelope (module docstring).

    Not thread-safe: the serial backend calls it under its own lock.
    """

    def __init__(self) -> None:
        self.offset_s = 0.0          # host - board at the last sync [s]
        self.sync_board_s = 0.0      # the board time of the last sync [s]
        self._bins: dict[int, tuple[float, float]] = {}  # bin -> (board_s, min host-board)
        self._slope = 0.0            # d(host - board) / d(board): the drift, dimensionless
        self._jump: tuple | None = None  # (bin, board_s, d) of a closed bin off the line
        self._open: tuple | None = None  # (bin, board_s, min d) of the bin being filled
        self.restarts = 0

    def sync(self, offset_s: float, board_us: float) -> None:
        """A measured offset (host - board [s]) at board time ``board_us`` (a GET_STATUS)."""
        if not (math.isfinite(offset_s) and math.isfinite(board_us)):
            return
        self.offset_s = float(offset_s)
        self.sync_board_s = float(board_us) * 1e-6

    def reset(self) -> None:
        """The board was reset: its clock restarted, the envelope means nothing now."""
        self._bins.clear()
        self._jump = self._open = None
        self._slope = 0.0
        self.restarts += 1

    def arrival(self, host_s: float, board_us: float) -> None:
        """A board message stamped ``board_us`` [us] read by the host at ``host_s`` [s]."""
        board_s = float(board_us) * 1e-6
        d = float(host_s) - board_s
        if not (math.isfinite(d) and math.isfinite(board_s)):
            return
        key = math.floor(board_s / BIN_S)
        cur = self._open
        if cur is not None and key == cur[0]:
            if d < cur[2]:
                self._open = (key, board_s, d)
            return
        if cur is not None and key > cur[0]:
            self._close(cur)
        if cur is None or key > cur[0]:
            self._open = (key, board_s, d)
        # an arrival in an earlier bin (reordered, or the board clock stepped back) is not
        # kept: the next bin tells whether the clock stepped

    def _close(self, done: tuple) -> None:
        """A bin complete: into the fit, unless its minimum is off the line (module docstring)."""
        key, board_s, d = done
        if self._bins and abs(self._residual(board_s, d)) > STEP_S:
            jump = self._jump
            self._jump = done
            if jump is None or abs(d - jump[2] - self._slope * (board_s - jump[1])) > STEP_S:
                return  # off the line alone: a host stall, or the first bin of a step
            self._bins = {jump[0]: (jump[1], jump[2])}  # two bins agree: the clock stepped
            self.restarts += 1
        self._jump = None
        self._bins[key] = (board_s, d)
        while len(self._bins) > MAX_BINS:
            del self._bins[min(self._bins)]
        self._fit()

    def _residual(self, board_s: float, d: float) -> float:
        ref_b, ref_d = min(self._bins.values(), key=lambda q: abs(q[0] - board_s))
        return d - (ref_d + self._slope * (board_s - ref_b))

    def _fit(self) -> None:
        b, d = np.array(sorted(self._bins.values())).T if self._bins else ((), ())
        if len(b) < MIN_BINS or b[-1] - b[0] < MIN_SPAN_S:
            self._slope = 0.0
            return
        b, d = b - b.mean(), d - d.mean()  # d is ~1e9 s: centred for precision
        for _ in range(2):  # least squares, then once more without the bins well above it
            slope, icpt = np.polyfit(b, d, 1)
            res = d - icpt - slope * b
            keep = res <= 3.0 * 1.4826 * float(np.median(np.abs(res))) + 1e-6
            if keep.all() or keep.sum() < MIN_BINS:
                break
            b, d = b[keep], d[keep]
        if abs(slope) * 1e6 <= MAX_DRIFT_PPM:
            self._slope = float(slope)

    @property
    def drift_ppm(self) -> float:
        """The host clock's rate against the board's, minus one [ppm] (0 until fitted): a
        board crystal 200 ppm fast reads about -200."""
        return self._slope * 1e6

    def to_host(self, board_us: float) -> float:
        """``board_us`` [us] in the host's ``time.time()`` base [s]."""
        board_s = float(board_us) * 1e-6
        return self.offset_s + board_s + self._slope * (board_s - self.sync_board_s)
