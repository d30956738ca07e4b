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

import numpy as np

from galvoscan_common.frame import Frame


class BackendError(RuntimeError):
    """A backend cannot do what was asked; the message says why."""


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
