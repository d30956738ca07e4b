"""The one interface behind which the driver's backends (sim, serial, replay) sit.

The driver node (``driver_node.py``) is a thin lifecycle adapter over a :class:`GalvoBackend`:

============  ====================================================================
lifecycle     backend call
============  ====================================================================
configure     ``open()``: open the device, check its protocol version
activate      ``arm()``
scan service  ``start(voltages, frame_rate, laser_on)`` then ``poll()`` repeatedly
stop service  ``stop()``
deactivate    ``safe()``: galvos to 0 V, laser off; never raises
cleanup       ``close()``
============  ====================================================================

No rclpy here.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

#: Galvo command range of every mirror channel [V].
VOLTAGE_LIMIT = 10.0

STATUS_SETTLED = 0
STATUS_MOVING = 1
STATUS_FAULT = 2


class BackendError(RuntimeError):
    """A backend cannot do what was asked; the message says why."""


@dataclass
class Frame:
    """One camera frame (or, without a camera, one trigger event) and the galvo state it had.

    Attributes
    ----------
    seq : int
        Frame sequence number; consecutive frames differ by 1.
    stamp : float
        Middle of the exposure [s] (backend clock, seconds since the epoch for sim/replay).
    voltages : ndarray, shape (4,), volts
        (U1_pan, U1_tilt, U2_pan, U2_tilt) that applied during the exposure.
    laser_on : bool
    status : int
        One of STATUS_SETTLED, STATUS_MOVING, STATUS_FAULT.
    image : ndarray, shape (H, W), uint8 or uint16, or None
        The camera image; None for a backend without a camera (serial trigger events).
    truth : dict
        Backend-specific ground truth (the simulator fills it); empty otherwise.
    stamp_ns : int or None
        The stamp in integer nanoseconds where it is known exactly (replayed frames);
        a float of seconds since the epoch cannot hold every nanosecond.
    """

    seq: int
    stamp: float
    voltages: np.ndarray
    laser_on: bool = True
    status: int = STATUS_SETTLED
    image: np.ndarray | None = None
    truth: dict = field(default_factory=dict)
    stamp_ns: int | None = None


def check_voltages(voltages, name: str = 'voltages') -> np.ndarray:
    """Validate a scan's voltage list.

    Parameters
    ----------
    voltages : array_like, shape (n, 4), volts
        Rows of (U1_pan, U1_tilt, U2_pan, U2_tilt).

    Returns
    -------
    ndarray, shape (n, 4), float64

    Raises
    ------
    ValueError
        Wrong shape, a non-finite value, or a value outside +-VOLTAGE_LIMIT.
    """
    arr = np.asarray(voltages, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f'{name}: expected shape (n, 4) in volts, got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name}: contains NaN or infinite values')
    worst = float(np.max(np.abs(arr))) if arr.size else 0.0
    if worst > VOLTAGE_LIMIT:
        raise ValueError(
            f'{name}: |U| = {worst:.6g} V exceeds the galvo range of +-{VOLTAGE_LIMIT} V')
    return arr


class GalvoBackend(abc.ABC):
    """A source of frames tagged with the galvo voltages they were taken at."""

    #: Short name used in parameters and logs ('sim', 'serial', 'replay').
    name = 'abstract'

    @abc.abstractmethod
    def open(self) -> None:
        """Open the device (or load the scene / bag) and check its version."""

    def arm(self) -> None:  # noqa: B027 - optional hook
        """Make the device ready to scan (lifecycle activate)."""

    @abc.abstractmethod
    def start(self, voltages: np.ndarray, frame_rate: float, laser_on: bool = True) -> int:
        """Begin a scan over ``voltages`` (shape (n, 4), V) at ``frame_rate`` [Hz].

        Returns the number of frames the scan will produce.
        """

    @abc.abstractmethod
    def poll(self, timeout: float = 0.0) -> list[Frame]:
        """Return the frames produced since the last call, waiting up to ``timeout`` [s]."""

    @property
    @abc.abstractmethod
    def running(self) -> bool:
        """True while a scan is in progress."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Abort the scan and go to the safe state."""

    @abc.abstractmethod
    def safe(self) -> None:
        """Drive every galvo to 0 V and switch the laser off. Must never raise."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device. Calls :meth:`safe` first where that makes sense."""
