"""Python ``logging`` of the libraries under a node, into the node's ROS log (no rclpy here).

The libraries under the nodes (the rig backend, the serial link, the calibration stages,
the bag reader) log with :mod:`logging`, as pure libraries should. Without a handler their
INFO records (a scan's pairing summary, a stage's coverage line, the camera and board a
backend opened) went nowhere in a node, and their warnings and errors reached stderr bare,
without the node's name and never on ``/rosout``. :func:`forward_python_logging` sends them
to the node's ROS logger, so they appear where the node's own messages do: the console,
the ROS log files, ``/rosout``, rqt and Foxglove.

Records of galvoscan's own packages (:data:`PACKAGES`) are forwarded from INFO, every other
logger's from WARNING. The record's logger name stays in front of the message.
"""

from __future__ import annotations

import logging

#: The top-level logger names of galvoscan's libraries (forwarded from INFO).
PACKAGES = ('galvoscan', 'galvo_driver', 'calibration_tools', 'reconstructor',
            'stripe_extractor', 'galvoscan_bag', 'galvoscan_common', 'galvoscan_sim',
            'galvoscan_view')


class RosLogHandler(logging.Handler):
    """A :class:`logging.Handler` that writes each record to a ROS logger.

    Parameters
    ----------
    ros_logger
        Anything with ``debug``, ``info``, ``warning``, ``error`` and ``fatal`` methods taking
        one string: ``node.get_logger()``.
    """

    def __init__(self, ros_logger) -> None:
        super().__init__()
        for name in ('debug', 'info', 'warning', 'error', 'fatal'):
            if not callable(getattr(ros_logger, name, None)):
                raise ValueError(f'ros_logger has no {name}() method: {ros_logger!r}')
        self.ros_logger = ros_logger
        self.setFormatter(logging.Formatter('[%(name)s] %(message)s'))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if record.levelno >= logging.CRITICAL:
                self.ros_logger.fatal(text)
            elif record.levelno >= logging.ERROR:
                self.ros_logger.error(text)
            elif record.levelno >= logging.WARNING:
                self.ros_logger.warning(text)
            elif record.levelno >= logging.INFO:
                self.ros_logger.info(text)
            else:
                self.ros_logger.debug(text)
        except Exception:  # noqa: BLE001 - a log line must never take the node down
            self.handleError(record)


def forward_python_logging(ros_logger, level: int = logging.INFO) -> RosLogHandler:
    """Send Python ``logging`` records to ``ros_logger`` (module docstring).

    Call once in a node's process, after the node exists. Replaces a handler an earlier call
    installed; leaves other handlers (a user's) alone.

    Parameters
    ----------
    ros_logger
        ``node.get_logger()``.
    level : int
        The lowest level forwarded from galvoscan's packages (other loggers: WARNING).

    Returns
    -------
    RosLogHandler
        The handler installed on the root logger.
    """
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, RosLogHandler):
            root.removeHandler(h)
    handler = RosLogHandler(ros_logger)
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.WARNING:
        root.setLevel(logging.WARNING)
    for name in PACKAGES:
        logging.getLogger(name).setLevel(level)
    return handler
