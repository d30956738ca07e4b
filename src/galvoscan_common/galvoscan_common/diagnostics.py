"""Every node's health on ``diagnostics`` (diagnostic_msgs/DiagnosticArray), built one way.

A node hands :func:`publish_periodically` a function returning its counters and its
:class:`~galvoscan_common.boundary.CallbackErrors`; one ``DiagnosticStatus`` named
``<node>: <title>`` is published every ``period`` seconds with every counter as a key/value,
``callback_errors`` (the total) and ``callback_errors/<callback>`` for each callback that
failed. The level is WARN while any callback has failed or ``warn`` counters are non-zero,
OK otherwise. Nested counter dicts are flattened with ``/`` (``skipped/laser_off``).

rqt_runtime_monitor, Foxglove's diagnostics panel and ``galvoscan view`` read this topic.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from galvoscan_common.boundary import CallbackErrors

#: Default period of the diagnostics message [s] (REP 107's aggregator expects about 1 Hz).
DIAGNOSTICS_PERIOD_S = 1.0


def flatten(counters: dict, prefix: str = '') -> dict[str, object]:
    """``{'a': 1, 'b': {'c': 2}}`` -> ``{'a': 1, 'b/c': 2}``."""
    out = {}
    for key, value in counters.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            out.update(flatten(value, f'{name}/'))
        else:
            out[name] = value
    return out


def status(name: str, counters: dict, errors: CallbackErrors, message: str = '',
           warn: Iterable[str] = ()) -> DiagnosticStatus:
    """One ``DiagnosticStatus`` of ``counters`` and the callback failures in ``errors``.

    Parameters
    ----------
    name : str
        The status name, ``<node>: <what it does>``.
    counters : dict
        Counter name -> value (nested dicts are flattened with ``/``).
    errors : CallbackErrors
    message : str
        The one-line summary; a note of failed callbacks is appended when there are any.
    warn : iterable of str
        Flattened counter names whose non-zero value makes the status WARN.
    """
    values = flatten(counters)
    failed = errors.as_dict()
    values['callback_errors'] = sum(failed.values())
    values.update({f'callback_errors/{k}': v for k, v in failed.items()})
    bad = values['callback_errors'] or any(values.get(k) for k in warn)
    out = DiagnosticStatus()
    out.name = name
    out.hardware_id = ''
    out.level = DiagnosticStatus.WARN if bad else DiagnosticStatus.OK
    if failed:
        message = f"{message}; {values['callback_errors']} failed callbacks".lstrip('; ')
    out.message = message or 'ok'
    out.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(values.items())]
    return out


def publish_periodically(node, title: str, counters: Callable[[], dict], errors: CallbackErrors,
                         *, message: Callable[[], str] = lambda: '', warn: Iterable[str] = (),
                         period: float = DIAGNOSTICS_PERIOD_S):
    """Publish the node's status on ``diagnostics`` every ``period`` s; returns the timer.

    The timer callback is itself a boundary: a counter function that raises is logged and
    counted (as ``diagnostics``), never allowed to stop the node.
    """
    pub = node.create_publisher(DiagnosticArray, 'diagnostics', 10)
    warn = tuple(warn)
    name = f'{node.get_name()}: {title}'

    def tick():
        try:
            msg = DiagnosticArray()
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.status = [status(name, counters(), errors, message(), warn)]
            pub.publish(msg)
        except Exception as exc:  # noqa: BLE001 - the diagnostics must not stop the node
            n = errors.add('diagnostics')
            node.get_logger().error(f'diagnostics failed: {exc!r} (failure {n})')

    return node.create_timer(period, tick)
