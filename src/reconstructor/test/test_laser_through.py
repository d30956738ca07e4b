"""The G2 voltage whose laser sheet passes through a point: the sheet at that voltage holds
the point, and a point out of reach or a malformed one is refused by name."""

import numpy as np
import pytest

from reconstructor.model import laser_plane_v0, nominal_example_rig, v0_T_v
from reconstructor.planning import laser_through

MODEL = nominal_example_rig()


@pytest.mark.parametrize('depth', [0.4, 0.65, 1.0])
def test_the_sheet_at_the_voltage_holds_the_point(depth):
    T = v0_T_v(MODEL, 2.0, -1.5)
    point = T[:3, 3] + depth * T[:3, 2]
    u2 = laser_through(MODEL, point)
    assert abs(u2) <= 10.0
    plane = laser_plane_v0(MODEL, u2)
    assert abs(plane[:3] @ point + plane[3]) < 1e-9


def test_a_point_no_sheet_reaches_is_refused():
    T = v0_T_v(MODEL, 0.0, 0.0)
    near, mid = T[:3, 3] + 0.3 * T[:3, 2], T[:3, 3] + 0.5 * T[:3, 2]
    with pytest.raises(ValueError, match='cannot reach'):
        laser_through(MODEL, near)  # nearer than the sheet sweeps at +-10 V
    assert abs(laser_through(MODEL, mid)) > 1.0  # reached, but not within +-1 V
    with pytest.raises(ValueError, match='cannot reach'):
        laser_through(MODEL, mid, max_abs_u=1.0)


@pytest.mark.parametrize(('point', 'kw', 'match'), [
    ([np.nan, 0.0, 0.65], {}, 'point_v0'),
    ([0.0, 0.65], {}, 'point_v0'),
    ([0.0, 0.0, 0.65], {'max_abs_u': -1.0}, 'max_abs_u'),
    ([0.0, 0.0, 0.65], {'max_abs_u': float('inf')}, 'max_abs_u'),
])
def test_malformed_input_is_refused(point, kw, match):
    with pytest.raises(ValueError, match=match):
        laser_through(MODEL, point, **kw)
