"""Serial DAC-board link: wire protocol, firmware emulator and the ``serial`` backend.

* :mod:`.protocol` - framing (COBS + CRC-32), messages, voltage <-> DAC code conversion,
  streaming decoder; raises only :class:`~.protocol.ProtocolError`.
* :mod:`.emulator` - the board firmware in a thread on a pty or TCP socket, with fault
  injection; ``python -m galvo_driver.serial_link.emulator --pty`` runs it as a process.
* :mod:`.backend` - :class:`SerialBackend`, the driver backend named 'serial'.
* :mod:`.simavr_board` - the board firmware (``firmware/``) in simavr: behind a pty in real
  time, or against a scripted host in simulated time, with its cycle-stamped log.

The protocol is specified in ``docs/board-protocol.md``.

No rclpy here.
"""

from galvo_driver.serial_link.backend import SerialBackend
from galvo_driver.serial_link.protocol import PROTOCOL_VERSION, ProtocolError

__all__ = ['PROTOCOL_VERSION', 'ProtocolError', 'SerialBackend']
