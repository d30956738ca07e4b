"""Pure parts of the node: stamp pairing (no rclpy, no DDS)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stripe_extractor.pairing import StampPairer


@settings(max_examples=60, deadline=None)
@given(order=st.lists(st.booleans(), min_size=1, max_size=40), lose=st.sets(
    st.integers(0, 39), max_size=8), seed=st.integers(0, 10_000))
def test_pairs_every_frame_whatever_arrives_first(order, lose, seed):
    """Frames/states of one stamp arrive in either order, interleaved with a random lag; lost
    partners are dropped and counted once; every surviving pair is matched exactly."""
    n = len(order)
    rng = np.random.default_rng(seed)
    events = []
    for i, state_first in enumerate(order):
        # Events of frame i, each delayed by at most one frame (bounded reordering).
        ev = [('s', i), ('f', i)] if state_first else [('f', i), ('s', i)]
        events += [(i + rng.uniform(0, 0.9) * (k == 1), e) for k, e in enumerate(ev)]
    events.sort(key=lambda x: x[0])
    # Keep each topic in order (as DDS does) while the two topics interleave.
    lost_state = {i for i in lose if i < n}
    p = StampPairer(capacity=10)
    got = []
    for _, (kind, i) in events:
        if kind == 's' and i in lost_state:
            continue
        r = p.add_state(i, f's{i}', seq=i) if kind == 's' else p.add_frame(i, f'f{i}')
        if r is not None:
            got.append(r)
    expect = [(f'f{i}', f's{i}') for i in range(n) if i not in lost_state]
    assert sorted(got) == sorted(expect)
    c = p.counters
    assert c.paired == len(expect)
    assert c.unmatched_states_dropped == 0
    # Lost states: their frames are dropped once a later pair matches (or stay waiting).
    waiting_frames, _ = p.waiting
    assert c.unmatched_frames_dropped + waiting_frames == len(lost_state)


def test_capacity_bounds_both_buffers_and_counts():
    p = StampPairer(capacity=3)
    for i in range(5):
        assert p.add_frame(i, i) is None
    for i in range(100, 107):
        assert p.add_state(i, i, seq=i) is None
    assert p.waiting == (3, 3)
    assert p.counters.unmatched_frames_dropped == 2
    assert p.counters.unmatched_states_dropped == 4
    assert p.add_state(4, 'x', seq=200) == (4, 'x')          # newest frame still there
    assert p.counters.state_seq_gaps == 93
    with pytest.raises(ValueError, match='capacity'):
        p.capacity = 0


def test_match_drops_older_waiting_entries():
    p = StampPairer(capacity=50)
    p.add_frame(1, 'f1')
    p.add_frame(2, 'f2')
    p.add_state(0, 's0')
    assert p.add_state(3, 's3') is None
    assert p.add_frame(3, 'f3') == ('f3', 's3')
    assert p.waiting == (0, 0)
    assert p.counters.unmatched_frames_dropped == 2
    assert p.counters.unmatched_states_dropped == 1
