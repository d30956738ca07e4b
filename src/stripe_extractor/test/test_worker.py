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


class _Thread:
    """The caller's thread: ``other_s`` of other work per frame, plus each kept extraction."""

    def __init__(self, policy):
        self.policy, self.now, self.cpu = policy, 0.0, 0.0

    def run(self, rate, other_s, extract_s, frames, worker_idle=True):
        """``frames`` frames at ``rate`` [1/s]; the decisions made."""
        out = []
        for _ in range(frames):
            self.now += 1.0 / rate
            offload = self.policy.decide(self.now, self.cpu, worker_idle)
            self.policy.note_extraction(extract_s)
            self.cpu += other_s + (0.0 if offload else extract_s)
            out.append(offload)
        return out


def test_policy_extracts_inline_while_the_thread_can_carry_it():
    p = OffloadPolicy(above=0.9, below=0.7)
    t = _Thread(p)
    # a process of its own at 500 fps: 0.3 ms other work + 0.7 ms extraction = load 0.5
    assert not any(t.run(500.0, 0.3e-3, 0.7e-3, 400))
    assert p.inline_load == pytest.approx(0.5, rel=0.02)
    # the same at 1000 fps: load 1.0, offloads within a few dozen frames and stays there
    d = t.run(1000.0, 0.3e-3, 0.7e-3, 400)
    assert d[-1] and all(d[d.index(True):]) and d.index(True) < 80
    assert p.inline_load == pytest.approx(1.0, rel=0.02)    # extraction counted while offloaded
    # back to 500 fps: returns only while the worker is idle, then stays inline
    assert all(t.run(500.0, 0.3e-3, 0.7e-3, 300, worker_idle=False))
    d = t.run(500.0, 0.3e-3, 0.7e-3, 300)
    assert not d[-1] and not any(d[d.index(False):])
    # a busy executor thread (other nodes on it: 1.2 ms + 0.7 ms at 500 fps, load 0.95) offloads
    assert t.run(500.0, 1.2e-3, 0.7e-3, 300)[-1]


def test_policy_holds_its_choice_between_the_thresholds():
    p = OffloadPolicy(above=0.9, below=0.7)
    t = _Thread(p)
    assert not any(t.run(500.0, 0.9e-3, 0.7e-3, 300))            # load 0.8, inline
    p.offload = True
    assert all(t.run(500.0, 0.9e-3, 0.7e-3, 300))                # load 0.8, offloaded


def test_policy_does_not_learn_from_pauses():
    p = OffloadPolicy(above=0.9, below=0.7, max_interval=0.1)
    t = _Thread(p)
    t.run(1000.0, 0.3e-3, 0.8e-3, 200)
    assert p.offload
    before = p.interval_mean, p.thread_cpu_mean
    t.now += 99.0                                   # a 99 s pause between scans
    t.cpu += 0.5
    p.decide(t.now, t.cpu, True)
    assert (p.interval_mean, p.thread_cpu_mean) == before and p.offload


@pytest.mark.parametrize('kwargs', [dict(above=0.3, below=0.4), dict(below=0.0),
                                    dict(weight=0.0), dict(weight=1.5),
                                    dict(max_interval=0.0)])
def test_policy_checks_its_settings(kwargs):
    with pytest.raises(ValueError):
        OffloadPolicy(**kwargs)
