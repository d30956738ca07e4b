"""The libraries' Python logging reaches a node's ROS log (galvoscan_common.logbridge), through
rclpy's real logger (rcutils writes to the process's stderr)."""

import logging

import pytest
import rclpy.logging

from galvoscan_common.logbridge import RosLogHandler, forward_python_logging


@pytest.fixture
def bridge():
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    levels = {n: logging.getLogger(n).level for n in ('galvo_driver', 'somelib')}
    handler = forward_python_logging(rclpy.logging.get_logger('bridge_test'))
    yield handler
    root.handlers[:] = handlers
    root.setLevel(level)
    for n, lv in levels.items():
        logging.getLogger(n).setLevel(lv)


def test_records_reach_the_ros_logger_with_their_level_and_name(bridge, capfd):
    logging.getLogger('galvo_driver.rig_backend').info('scan 1 complete: 30 of 100 paired')
    logging.getLogger('galvo_driver.rig_backend').error('pairing lost')
    logging.getLogger('galvo_driver.rig_backend').debug('not forwarded: below INFO')
    logging.getLogger('somelib').info('not forwarded: not ours, below WARNING')
    logging.getLogger('somelib').warning('a warning of another library')
    err = capfd.readouterr().err
    assert '[INFO]' in err and '[bridge_test]: [galvo_driver.rig_backend] scan 1 complete: ' \
        '30 of 100 paired' in err, err
    assert '[ERROR]' in err and '[galvo_driver.rig_backend] pairing lost' in err
    assert '[WARN]' in err and '[somelib] a warning of another library' in err
    assert 'not forwarded' not in err


def test_forwarding_twice_installs_one_handler(bridge):
    again = forward_python_logging(rclpy.logging.get_logger('bridge_test'))
    assert [h for h in logging.getLogger().handlers if isinstance(h, RosLogHandler)] == [again]


def test_a_logger_without_the_methods_is_refused():
    with pytest.raises(ValueError, match='no warning'):
        RosLogHandler(type('Half', (), {'debug': print, 'info': print})())


def test_a_failing_ros_logger_never_raises_into_the_caller(bridge, monkeypatch, capfd):
    def broken(_text):
        raise RuntimeError('context is invalid')

    monkeypatch.setattr(bridge, 'ros_logger', type('Broken', (), dict.fromkeys(
        ('debug', 'info', 'warning', 'error', 'fatal'), staticmethod(broken)))())
    monkeypatch.setattr(logging, 'raiseExceptions', False)
    logging.getLogger('galvo_driver.x').error('still fine')  # must not raise
