"""The supervisor removes the shared-memory segments that killed DDS processes leave."""

import logging
import signal

from galvoscan import bringup


def test_supervisor_start_removes_zombie_segments(shm_segment_owner, caplog):
    dead, segments = shm_segment_owner()
    dead.send_signal(signal.SIGKILL)
    dead.wait(10)
    assert all(s.is_file() for s in segments)
    sup = bringup.Supervisor([])
    with caplog.at_level(logging.INFO, logger=bringup.log.name):
        sup.start()
    assert not any(s.exists() for s in segments)
    assert 'shared-memory segments of processes that are gone' in caplog.text
    sup.stop()
