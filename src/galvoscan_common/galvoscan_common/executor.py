"""The executor loop of the galvoscan node processes: one EventsExecutor, stopped by signals.

ROS process plumbing only (no maths): :func:`spin_nodes` spins nodes, :func:`run_node` is the
whole ``main`` of a one-node process.

rclpy's ``rclpy.experimental.EventsExecutor`` costs the least per message here (the
SingleThreadedExecutor's per-message overhead, with a 389 kB image, is about twice as
large; MultiThreadedExecutor loses most 500 Hz frames: TOOLCHAIN.md). Its ``spin()`` ignores
SIGINT and SIGTERM in rclpy 7.1, so :func:`spin_nodes` drives it with ``spin_once`` in a
loop that ends on either signal, on context shutdown, or after ``duration``.
"""

from __future__ import annotations

import time
import uuid

#: Longest wait inside one ``spin_once`` [s]: how late a stop request is noticed.
SPIN_TIMEOUT_S = 0.1


def spin_nodes(nodes, context=None, duration: float | None = None) -> None:
    """Spin ``nodes`` on one EventsExecutor until shutdown, SIGINT/SIGTERM or ``duration`` [s].

    The objects alive when it starts are exempted from garbage collection
    (:func:`~galvoscan_common.runtime.freeze_startup_heap`).

    Returns normally in every case; the caller destroys the nodes and shuts rclpy down.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor

    from galvoscan_common.runtime import freeze_startup_heap

    executor = EventsExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    freeze_startup_heap()
    t_end = None if duration is None else time.monotonic() + duration
    try:
        while rclpy.ok(context=context) and (t_end is None or time.monotonic() < t_end):
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()


def run_node(factory, args=None) -> None:
    """``main`` of a process holding one node: settings, init, spin, clean shutdown.

    ``factory()`` builds the node after ``rclpy.init``; the process settings of
    :mod:`galvoscan_common.runtime` are applied first, and the libraries' Python logging
    goes to the node's ROS log (:mod:`galvoscan_common.logbridge`). Ctrl-C and SIGTERM end
    it normally.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from galvoscan_common.logbridge import forward_python_logging
    from galvoscan_common.runtime import tune_this_process

    tune_this_process()
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        forward_python_logging(node.get_logger())
        spin_nodes([node])
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


#: First wait for an answer before a request is resent [s]; each later wait is twice as long.
FIRST_RESEND_AFTER_S = 1.0


def call_service(executor, client, request, timeout: float = 60.0, hint: str = '',
                 resend: bool = False):
    """Call one ROS service and wait for its answer, spinning ``executor`` meanwhile.

    The one service-call helper of the project (calibration node, evaluation, scan client,
    the DDS tests).

    A DDS service's answer can be lost: the server answers before it has discovered the
    client's reply reader (a new client on a busy machine; Fast DDS waits only briefly for
    that match), and the client then waits in vain. With ``resend`` the request is sent
    again after 1, 2, 4, ... s without an answer, until ``timeout``. Only for requests that
    are safe to repeat: queries, stops, scene changes, and a StartScan: a request with a
    ``request_id`` field gets a fresh unique id here when it has none, and the driver
    answers a resend with its first answer.

    Parameters
    ----------
    executor : rclpy executor holding the client's node; spun until the answer arrives.
    client : rclpy ``Client``.
    request : the service's ``Request``.
    timeout : float, seconds
        How long to wait for the service to appear, and again for its answer.
    hint : str
        Appended to the "not available" error (e.g. ``'is the driver running?'``).
    resend : bool
        Resend the request while no answer has come (see above).

    Raises
    ------
    RuntimeError
        The service did not appear, or did not answer within ``timeout``; the pending
        requests are then withdrawn so that a late answer is dropped.
    """
    name = client.srv_name
    if not client.wait_for_service(timeout_sec=timeout):
        raise RuntimeError(f'service {name} is not available' + (f': {hint}' if hint else ''))
    if resend and getattr(request, 'request_id', None) == '':
        request.request_id = uuid.uuid4().hex
    t_end = time.monotonic() + timeout
    wait = FIRST_RESEND_AFTER_S if resend else timeout
    pending = []
    try:
        while True:
            future = client.call_async(request)
            pending.append(future)
            left = t_end - time.monotonic()
            executor.spin_until_future_complete(future, timeout_sec=max(min(wait, left), 0.0))
            for f in pending:  # an earlier request's late answer is as good
                if f.done() and f.result() is not None:
                    return f.result()
            if not resend or time.monotonic() >= t_end - 1e-3:
                raise RuntimeError(f'service {name} did not answer within {timeout} s'
                                   + (f' ({len(pending)} requests sent)' if resend else ''))
            wait *= 2.0
    finally:
        for f in pending:
            if not f.done():
                f.cancel()
                client.remove_pending_request(f)


class ServiceClients:
    """One node's service clients by name, each made on first use and called through
    :func:`call_service` (a client kept for the next call is already discovered).

    Parameters
    ----------
    node, executor : the rclpy node the clients are made on, and the executor spinning it.
    hint : str
        For the "not available" error (e.g. ``'is the driver running?'``).
    on_error : callable, optional
        ``f(RuntimeError) -> BaseException`` raised instead of a call's error (a test adds
        the server's log).
    """

    def __init__(self, node, executor, hint: str = '', on_error=None) -> None:
        self.node, self.executor, self.hint, self.on_error = node, executor, hint, on_error
        self.clients = {}

    def call(self, srv_type, name: str, request, timeout: float = 60.0, resend: bool = False):
        """The answer of service ``name`` to ``request`` (see :func:`call_service`)."""
        client = self.clients.get(name)
        if client is None:
            client = self.clients[name] = self.node.create_client(srv_type, name)
        try:
            return call_service(self.executor, client, request, timeout, self.hint, resend)
        except RuntimeError as exc:
            if self.on_error is None:
                raise
            raise self.on_error(exc) from exc
