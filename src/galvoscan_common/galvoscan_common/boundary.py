"""Callbacks as boundaries: nothing a caller sends kills a node (no rclpy).

A ROS callback that raises takes the executor, and with it the node process, down. Every
service and subscription callback of a galvoscan node is therefore wrapped by
:func:`guard_service` or :func:`guard_subscription`: an exception becomes an error log, a
count in :class:`CallbackErrors` (which the node reports) and, for a service, a failed
response whose message says what went wrong. ``MemoryError`` is an ``Exception`` and is
caught the same way; ``KeyboardInterrupt`` and ``SystemExit`` are not.

Each wrapper logs from one call site at one severity: rclpy refuses a second severity from
the same line ("Logger severity cannot be changed between calls").
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


class CallbackErrors:
    """Thread-safe counts of failed callbacks, by callback name."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}

    def add(self, name: str) -> int:
        """Count one failure of ``name``; returns its new count."""
        with self._lock:
            self._counts[name] = self._counts.get(name, 0) + 1
            return self._counts[name]

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


def _describe(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text if isinstance(exc, ValueError) else f'{type(exc).__name__}: {text}'


def guard_service(name: str, callback: Callable[[Any, Any], Any], logger,
                  errors: CallbackErrors) -> Callable[[Any, Any], Any]:
    """``callback(request, response)`` that answers with ``success = False`` instead of raising.

    Parameters
    ----------
    name : str
        The service name, for the log, the count and the response message.
    callback : callable
        ``(request, response) -> response``.
    logger
        Has ``error(str)`` (an rclpy logger or a ``logging.Logger``).
    errors : CallbackErrors
    """

    def guarded(request, response):
        try:
            return callback(request, response)
        except Exception as exc:  # noqa: BLE001 - the boundary: every failure is answered
            n = errors.add(name)
            message = f'{name} failed: {_describe(exc)}'
            logger.error(f'{message} (failure {n} of this service)')
            if hasattr(response, 'success'):
                response.success = False
            if hasattr(response, 'message'):
                response.message = message
            return response

    return guarded


def guard_subscription(name: str, callback: Callable[..., None], logger,
                       errors: CallbackErrors) -> Callable[..., None]:
    """``callback(message)`` (or a timer's ``callback()``) that logs and counts a failure.

    What failed is skipped: the message is dropped, the timer fires again next period.
    """

    def guarded(*args) -> None:
        try:
            callback(*args)
        except Exception as exc:  # noqa: BLE001 - the boundary: a bad message is skipped
            n = errors.add(name)
            logger.error(f'{name}: skipped: {_describe(exc)} (failure {n})')

    return guarded
