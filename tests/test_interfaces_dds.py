"""Every galvoscan_msgs message and service crosses DDS between two real processes."""

import importlib.util
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.node import Node

from galvoscan_common.executor import call_service

PEER = Path(__file__).with_name('dds_echo_peer.py')
_spec = importlib.util.spec_from_file_location('dds_echo_peer', PEER)
peer = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(peer)

pytestmark = pytest.mark.dds


def test_message_and_service_types_are_all_covered():
    import galvoscan_msgs.msg
    import galvoscan_msgs.srv
    assert {t.__name__ for t in peer.MESSAGE_TYPES} == {
        n for n in dir(galvoscan_msgs.msg) if not n.startswith('_')}
    assert len(peer.SERVICE_TYPES) >= 9


def test_every_interface_over_dds(spawn, venv_python, ros_env):
    proc = spawn([venv_python, PEER], name='peer')
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = Node('interfaces_test', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        received = {}
        pubs = {}
        for mtype in peer.MESSAGE_TYPES:
            name = mtype.__name__
            pubs[name] = node.create_publisher(mtype, f'echo_in/{name}', 10)
            node.create_subscription(
                mtype, f'echo_out/{name}',
                lambda m, n=name: received.setdefault(n, m), 10)
        sent = {m.__name__: peer.fill(m(), 1000 + i) for i, m in enumerate(peer.MESSAGE_TYPES)}
        deadline = time.monotonic() + 40
        while len(received) < len(sent) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.log_path.read_text()
            for name, msg in sent.items():
                if name not in received:
                    pubs[name].publish(msg)
            executor.spin_once(timeout_sec=0.2)
        assert set(received) == set(sent), f'no echo for {set(sent) - set(received)}'
        for name, msg in sent.items():
            assert received[name] == msg, name

        for i, stype in enumerate(peer.SERVICE_TYPES):
            client = node.create_client(stype, f'peer/{stype.__name__}')
            assert client.wait_for_service(timeout_sec=20), stype.__name__
            request = peer.fill(stype.Request(), 2000 + i)
            # the echo peer answers from the request alone: safe to resend
            response = call_service(executor, client, request, timeout=20.0, resend=True)
            expected = peer.expected_response(stype, request)
            assert response.message == peer.request_digest(request), stype.__name__
            assert response == expected, stype.__name__
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
