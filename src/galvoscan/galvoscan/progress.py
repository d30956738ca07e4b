"""A terminal progress display: stage, counts and an ETA (no rclpy)."""

from __future__ import annotations

import sys
import time


class Progress:
    """One line per stage; on a terminal the line updates in place, otherwise it is
    printed at most every ``every`` seconds and when the stage ends."""

    def __init__(self, stream=None, every: float = 2.0):
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty()
        self.every = every
        self.t_start = time.monotonic()
        self._stage = None
        self._note = ''

    def stage(self, name: str, total: int, unit: str = 'items'):
        self._stage, self._total, self._unit = name, max(int(total), 0), unit
        self._done, self._t0, self._last = 0, time.monotonic(), 0.0
        self._note = ''
        self._show(force=True)

    def advance(self, n: int = 1, note: str = ''):
        self._done += n
        self._note = note
        self._show(force=self._done >= self._total)

    def _show(self, force=False):
        now = time.monotonic()
        if not force and not self.tty and now - self._last < self.every:
            return
        self._last = now
        elapsed = now - self._t0
        eta = ''
        if 0 < self._done < self._total:
            eta = f', ETA {elapsed / self._done * (self._total - self._done):.0f} s'
        note = self._note
        line = (f'[{now - self.t_start:6.1f} s] {self._stage}: {self._done}/{self._total} '
                f'{self._unit}{eta}{" - " + note if note else ""}')
        if self.tty:
            self.stream.write('\r\033[K' + line + ('\n' if self._done >= self._total else ''))
        else:
            self.stream.write(line + '\n')
        self.stream.flush()

    def log(self, message: str):
        if self.tty:
            self.stream.write('\r\033[K')
        self.stream.write(f'[{time.monotonic() - self.t_start:6.1f} s] {message}\n')
        self.stream.flush()
