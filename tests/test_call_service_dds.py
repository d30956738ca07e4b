"""``call_service`` against a server in another process: a request left unanswered is sent
again (``resend``), a late answer still counts, and without ``resend`` the wait ends in a
clear error at ``timeout``."""

import sys
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.node import Node
from std_srvs.srv import SetBool

from galvoscan_common.executor import FIRST_RESEND_AFTER_S, call_service

pytestmark = pytest.mark.dds

PEER = Path(__file__).with_name('slow_first_answer_peer.py')


def _client(ros_env):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('call_service_test', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    return ctx, node, ex


def _wait_ready(proc, timeout=30.0):
    deadline = time.monotonic() + timeout
    while 'ready' not in proc.log_path.read_text():
        assert time.monotonic() < deadline, proc.log_path.read_text()
        assert proc.poll() is None, proc.log_path.read_text()
        time.sleep(0.05)


@pytest.mark.parametrize('resend', [True, False])
def test_an_unanswered_request_is_resent(spawn, ros_env, resend):
    delay = 2.5 * FIRST_RESEND_AFTER_S  # the first answer comes after the first resend
    peer = spawn([sys.executable, PEER, delay], name='peer')
    _wait_ready(peer)
    ctx, node, ex = _client(ros_env)
    try:
        client = node.create_client(SetBool, 'slow/set_bool')
        if resend:
            resp = call_service(ex, client, SetBool.Request(data=True), timeout=30.0,
                                resend=True)
            assert resp.success
            deadline = time.monotonic() + 10
            while 'request 2' not in peer.log_path.read_text():
                assert time.monotonic() < deadline, peer.log_path.read_text()
                ex.spin_once(timeout_sec=0.05)
        else:
            t0 = time.monotonic()
            with pytest.raises(RuntimeError, match='did not answer within'):
                call_service(ex, client, SetBool.Request(data=True), timeout=1.5)
            assert time.monotonic() - t0 < delay
            time.sleep(delay)
            assert 'request 2' not in peer.log_path.read_text()  # sent once
            assert not client._pending_requests  # the late answer has nowhere to go
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_a_shutdown_ends_the_wait(spawn, ros_env):
    """A context shut down (a signal) while waiting ends the call at once, resend or not
    (rclpy's ExternalShutdownException): no request sent again and again until the timeout."""
    import threading

    from rclpy.executors import ExternalShutdownException

    peer = spawn([sys.executable, PEER, 4.0], name='peer')
    _wait_ready(peer)
    ctx, node, ex = _client(ros_env)
    try:
        client = node.create_client(SetBool, 'slow/set_bool')
        assert client.wait_for_service(timeout_sec=20)
        threading.Timer(0.5, rclpy.shutdown, kwargs={'context': ctx}).start()
        t0 = time.monotonic()
        with pytest.raises(ExternalShutdownException):
            call_service(ex, client, SetBool.Request(data=True), timeout=30.0, resend=True)
        assert time.monotonic() - t0 < 3.0
        assert not client._pending_requests  # withdrawn
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
