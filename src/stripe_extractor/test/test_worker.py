"""The extraction thread's queue (order, bounded, survives bad items, drains on stop) and the
auto mode's rule for using it."""

import threading

import pytest

from stripe_extractor.worker import OffloadPolicy, SerialWorker


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
    assert w.pending == 2 and not w.idle
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


def test_idle_only_when_nothing_waits_or_runs():
    gate, started = threading.Event(), threading.Event()
    w = SerialWorker(lambda item: (started.set(), gate.wait(10)), capacity=2, name='t')
    assert w.idle
    assert w.submit(0) and started.wait(5)
    assert w.pending == 0 and not w.idle           # dequeued but still being processed
    gate.set()
    for _ in range(500):
        if w.idle:
            break
        threading.Event().wait(0.01)
    assert w.idle
    assert w.stop(timeout=10)


def _run_policy(policy, rate, extract_s, frames, t0=0.0, worker_idle=True):
    """Frames at ``rate`` [1/s], each extracted in ``extract_s``; the decisions made."""
    out = []
    for i in range(frames):
        out.append(policy.decide(t0 + i / rate, worker_idle))
        policy.note_extraction(extract_s)
    return out


def test_policy_offloads_when_extraction_fills_the_interval_and_comes_back():
    p = OffloadPolicy(above=0.4, below=0.3)
    # 500 fps, 0.5 ms per frame: load 0.25, stays on the caller's thread
    assert not any(_run_policy(p, 500.0, 0.5e-3, 400))
    assert p.load == pytest.approx(0.25, rel=0.02)
    # 1000 fps: load 0.5, offloads within a few dozen frames and stays there
    d = _run_policy(p, 1000.0, 0.5e-3, 400, t0=1.0)
    assert d[-1] and all(d[d.index(True):]) and d.index(True) < 80
    # back to 500 fps: returns only while the worker is idle
    assert all(_run_policy(p, 500.0, 0.5e-3, 300, t0=2.0, worker_idle=False))
    d = _run_policy(p, 500.0, 0.5e-3, 300, t0=3.0, worker_idle=True)
    assert not d[-1] and not any(d[d.index(False):])
    # between the thresholds (load 0.35) the current choice holds: no flapping
    assert not any(_run_policy(p, 500.0, 0.7e-3, 300, t0=4.0))
    p.offload = True
    assert all(_run_policy(p, 500.0, 0.7e-3, 300, t0=4.6))


def test_policy_pause_counts_as_max_interval():
    p = OffloadPolicy(above=0.4, below=0.3, max_interval=0.1)
    _run_policy(p, 1000.0, 0.6e-3, 200)
    assert p.offload
    p.decide(100.0, True)                          # a 99 s pause between scans
    assert p.interval_mean < 0.1 * 0.05 + 1e-3 + 1e-9


@pytest.mark.parametrize('kwargs', [dict(above=0.3, below=0.4), dict(below=0.0),
                                    dict(weight=0.0), dict(weight=1.5),
                                    dict(max_interval=0.0)])
def test_policy_checks_its_settings(kwargs):
    with pytest.raises(ValueError):
        OffloadPolicy(**kwargs)
