"""galvoscan_common.intra: the in-process bus (DDS side: tests/test_intra_process_dds.py)."""

import gc

import pytest

from galvoscan_common import intra


def test_callbacks_are_called_in_subscription_order_per_topic():
    bus = intra.Bus()
    got = []
    a = bus.subscribe('/camera/image_raw', lambda d: got.append(('a', d)))
    bus.subscribe('/camera/image_raw', lambda d: got.append(('b', d)))
    bus.subscribe('/galvo/state', lambda d: got.append(('s', d)))
    for cb in bus.callbacks('/camera/image_raw'):
        cb(b'x')
    assert got == [('a', b'x'), ('b', b'x')]
    assert bus.callbacks('/nobody') == ()
    bus.unsubscribe(a)
    bus.unsubscribe(a)                      # twice: no-op
    assert len(bus.callbacks('/camera/image_raw')) == 1
    assert len(bus.callbacks('/galvo/state')) == 1


def test_the_same_callback_twice_is_two_subscriptions():
    bus = intra.Bus()
    got = []
    first = bus.subscribe('/t', got.append)
    bus.subscribe('/t', got.append)
    assert len(bus.callbacks('/t')) == 2
    bus.unsubscribe(first)                  # removes that subscription only
    assert len(bus.callbacks('/t')) == 1


def test_bad_subscriptions_are_refused_and_change_nothing():
    bus = intra.Bus()
    with pytest.raises(ValueError, match='resolved'):
        bus.subscribe('camera/image_raw', print)
    with pytest.raises(ValueError, match='resolved'):
        bus.subscribe(None, print)
    with pytest.raises(ValueError, match='callable'):
        bus.subscribe('/t', 'not callable')
    assert bus.callbacks('/t') == () and bus.callbacks('camera/image_raw') == ()


def test_one_bus_per_context_dropped_with_it():
    class Context:                          # any weak-referenceable key, like rclpy.Context
        pass

    a, b = Context(), Context()
    assert intra.bus_for(a) is intra.bus_for(a)
    assert intra.bus_for(a) is not intra.bus_for(b)
    n = len(intra._buses)
    del a
    gc.collect()
    assert len(intra._buses) == n - 1
