"""The stripe's direction from the laser plane seen by the camera."""

import math

import numpy as np
import pytest

from galvoscan_common.stripe_layout import MAX_STRIPE_TILT, stripe_layout


def _plane(turn_deg, depth=0.65, tri_deg=25.0):
    """A sheet from a laser below the camera turned by ``turn_deg`` about the optical axis,
    crossing the axis at ``depth``."""
    a, t = math.radians(turn_deg), math.radians(tri_deg)
    n_below = np.array([0.0, math.cos(t), math.sin(t)])
    R = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                  [0.0, 0.0, 1.0]])
    n = R @ n_below
    return np.append(n, -n[2] * depth)


@pytest.mark.parametrize('turn, orientation, across', [
    (0.0, 'horizontal', 1), (180.0, 'horizontal', 1), (90.0, 'vertical', 0),
    (-90.0, 'vertical', 0), (15.0, 'horizontal', 1), (70.0, 'vertical', 0)])
def test_the_side_of_the_laser_gives_the_stripe_direction(turn, orientation, across):
    lay = stripe_layout(_plane(turn), 7800.0, 7800.0)
    assert (lay.orientation, lay.across, lay.along) == (orientation, across, 1 - across)
    off = abs(turn) % 90.0
    assert math.degrees(lay.tilt) == pytest.approx(min(off, 90.0 - off), abs=1e-6)
    assert lay.refusal() is None
    # a point of the plane along the stripe, at the crossing's depth
    p = lay.point_on_plane(_plane(turn), 0.01, 0.65)
    assert abs(_plane(turn)[:3] @ p + _plane(turn)[3]) < 1e-12 and p[lay.along] == 0.01


@pytest.mark.parametrize('turn, side', [(0.0, 1.0), (180.0, -1.0), (-90.0, 1.0), (90.0, -1.0),
                                         (15.0, 1.0), (-110.0, 1.0)])
def test_the_laser_side_and_the_turn_from_a_laser_below(turn, side):
    """Below (+y, V0's y down) and right (+x) are the + side; the turn is the laser side's
    (rig_family.LASER_SIDES), nearest to the plane's own turn."""
    for depth in (0.1, 0.65, 1.5):
        lay = stripe_layout(_plane(turn, depth), 7800.0, 5000.0)
        assert lay.side == side
        nearest = 90.0 * round(turn / 90.0)
        assert math.degrees(lay.turn) == pytest.approx(math.remainder(nearest, 360.0) or 0.0)


def test_an_oblique_stripe_is_refused_with_the_reason():
    lay = stripe_layout(_plane(35.0), 7800.0, 7800.0)
    assert lay.tilt > MAX_STRIPE_TILT
    assert 'off the nearest of the image rows and columns' in lay.refusal()
    with pytest.raises(ValueError, match='stripe_layout'):
        stripe_layout([np.nan, 0, 1, 0], 1.0, 1.0)
    with pytest.raises(ValueError, match='no direction'):
        stripe_layout([0.0, 0.0, 1.0, -0.5], 1000.0, 1000.0)


def test_the_sense_follows_the_sheet_motion():
    below = stripe_layout(_plane(0.0), 7800.0, 7800.0, plane_moved=_plane(0.0, 0.66))
    above = stripe_layout(_plane(180.0), 7800.0, 7800.0, plane_moved=_plane(180.0, 0.66))
    assert below.sign == -above.sign
