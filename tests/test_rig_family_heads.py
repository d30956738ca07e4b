"""The range follows the head: G1's reach at the paper's 650 mm depth scales with the galvo
head class's scan angle, and the wide head class covers the paper's 1100 x 1300 mm."""

import math

from galvoscan.eval_scenes import g1_reach
from galvoscan_sim import rig_from_dict
from galvoscan_sim.rig_family import HEADS, draw_rig

PAPER_RANGE_MM = (1100.0, 1300.0)


def test_the_reach_follows_the_head_and_the_wide_head_covers_the_papers_range():
    reach = {}
    for head in HEADS:
        # one build (seed, sensor) set up for the reference's 650 mm deep working point
        data = draw_rig(11, 0.5444, {'sensor': 'IMX287', 'head': head})
        reach[head] = 2e3 * g1_reach(rig_from_dict(data, head), 0.65)
    order = sorted(HEADS, key=lambda h: HEADS[h].max_angle)
    assert order == ['GVS011', 'TSH8310', 'WIDE25']
    for a, b in zip(order[:-1], order[1:], strict=True):
        assert all(reach[a] < reach[b]), reach
    # the reach grows as tan(2 theta): +-12.5 deg reaches about tan(25)/tan(40) of +-20 deg
    ratio = math.tan(math.radians(25.0)) / math.tan(math.radians(40.0))
    assert abs(reach['GVS011'][0] / reach['TSH8310'][0] - ratio) < 0.05, reach
    assert reach['WIDE25'][0] >= PAPER_RANGE_MM[0] and reach['WIDE25'][1] >= PAPER_RANGE_MM[1]
    assert reach['TSH8310'][1] < PAPER_RANGE_MM[1]
