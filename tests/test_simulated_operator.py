"""The simulated operator's decisions, without the graph: what it puts in the scene for each
instruction. A forced nudge that the scanner did not catch (its capture ended before the
nudge landed) is made again on a later placement, so a test that forces one sees it caught."""

import numpy as np
import yaml
from galvoscan_msgs.msg import CalibrationInstruction

from galvoscan.operator import SimulatedOperator

SPEC = yaml.safe_dump({'cols': 9, 'rows': 7, 'square': 0.004}, default_flow_style=True)


def _instruction(seq, state, placement, text=''):
    return CalibrationInstruction(
        sequence=seq, stage='intrinsics', state=state, placement=placement,
        target='checkerboard', target_spec=SPEC, centre=[0.0, 0.0, 0.65],
        extents=[0.06, 0.06, 0.06], orientation=[1.0, 0.0, 0.0, 0.0], text=text)


def _operator(mistakes):
    op = SimulatedOperator(0, seed=3, mistakes=mistakes, log_fn=lambda _: None)
    op.scenes, op.answers = [], []
    op._set_scene = lambda text, wait_s=0.0: op.scenes.append(yaml.safe_load(text))
    op._answer = lambda action, placement: op.answers.append((action, placement))
    return op


def _centre(scene):
    return np.asarray(scene['objects'][0]['pose']['translation'], dtype=np.float64)


def _capture(op, seq, placement):
    """Act on a capture instruction: how far [m] the target moved while it was captured
    (a hand's 10 um, or a 4 mm nudge)."""
    before = _centre(op.scenes[-1])
    op._act(_instruction(seq, 'capture', placement))
    return float(np.linalg.norm(_centre(op.scenes[-1]) - before))


def test_a_forced_nudge_the_scanner_missed_is_made_on_the_next_placement():
    op = _operator(['moved_during_capture'])
    op._act(_instruction(1, 'place', 0))
    assert 3.9e-3 < _capture(op, 2, 0) < 4.1e-3  # the nudge
    # the scanner's next instruction is the next placement, not a retake: it was missed
    op._act(_instruction(3, 'place', 1))
    assert 3.9e-3 < _capture(op, 4, 1) < 4.1e-3
    # this one was caught: the retake is placed, and nothing is nudged again
    op._act(_instruction(5, 'place', 1, 'The target moved during the capture (3.1 px): '
                                        'its views are retaken. Place ...'))
    assert _capture(op, 6, 1) < 1e-4
    op._act(_instruction(7, 'place', 2))
    assert _capture(op, 8, 2) < 1e-4
    assert op.stats['mistakes'] == {'moved_during_capture': 1}
    assert op.answers == [('placed', 0), ('placed', 1), ('placed', 1), ('placed', 2)]


def test_a_random_nudge_is_not_repeated():
    op = _operator([])
    op._act(_instruction(1, 'place', 0))
    op._current[1].mistake = 'moved_during_capture'  # as a random draw would make it
    assert 3.9e-3 < _capture(op, 2, 0) < 4.1e-3
    op._act(_instruction(3, 'place', 1))
    assert _capture(op, 4, 1) < 1e-4
