"""One frame of the rig and the galvo command range: the vocabulary every layer shares (no rclpy).

A :class:`Frame` is what a driver backend produces, what a bag holds and what replay gives
back: an image (or a bare trigger event) with the galvo voltages in effect during its
exposure. :data:`VOLTAGE_LIMIT` and :func:`check_voltages` are the one definition of the
galvo command range.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Galvo command range of every mirror channel [V].
VOLTAGE_LIMIT = 10.0

STATUS_SETTLED = 0
STATUS_MOVING = 1
STATUS_FAULT = 2


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
