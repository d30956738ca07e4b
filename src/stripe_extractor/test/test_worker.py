"""The extraction thread's queue: order, bounded, survives bad items, drains on stop."""

import threading

import pytest

from stripe_extractor.worker import SerialWorker


def test_items_are_processed_in_order_and_stop_drains_the_queue():
    done = []
    w = SerialWorker(done.append, capacity=1000, name='t')
    for i in range(500):
        assert w.submit(i)
    assert w.stop(timeout=10)
    assert done == list(range(500)) and w.processed == 500
    assert not w.alive and not w.submit(1)          # stopped: refused, nothing queued


def test_full_queue_refuses_without_blocking():
    gate = threading.Event()
    started = threading.Event()

    def handler(item):
        started.set()
        gate.wait(10)

    w = SerialWorker(handler, capacity=2, name='t')
    assert w.submit(0)
    assert started.wait(5)                         # item 0 is being processed
    assert w.submit(1) and w.submit(2)
    assert not w.submit(3)                         # two waiting: full
    assert w.pending == 2
    gate.set()
    assert w.stop(timeout=10) and w.processed == 3


def test_handler_errors_are_counted_and_the_thread_carries_on():
    seen, errors = [], []

    def handler(item):
        if item % 3 == 0:
            raise ValueError(f'bad {item}')
        seen.append(item)

    w = SerialWorker(handler, capacity=50, name='t', on_error=errors.append)
    for i in range(10):
        w.submit(i)
    assert w.stop(timeout=10)
    assert seen == [1, 2, 4, 5, 7, 8]
    assert w.errors == 4 and [str(e) for e in errors] == ['bad 0', 'bad 3', 'bad 6', 'bad 9']


@pytest.mark.parametrize('capacity', [0, -1, 1.5, True])
def test_capacity_is_checked(capacity):
    with pytest.raises(ValueError, match='capacity'):
        SerialWorker(print, capacity=capacity, name='t')
