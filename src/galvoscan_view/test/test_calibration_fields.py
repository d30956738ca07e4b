"""The view node's reading of calibration/instruction and calibration/progress: serialised
by rclpy (the CDR bytes DDS carries), read back by the view's decoder; malformed messages
are refused with the reason."""

import math

import numpy as np
import pytest
from galvoscan_msgs.msg import CalibrationInstruction, CalibrationProgress
from rclpy.serialization import serialize_message

from galvoscan_view.view_node import instruction_fields, progress_fields


def progress(**changes) -> CalibrationProgress:
    m = CalibrationProgress(stage='laser_plane', placements_done=2, placements_max=12,
                            parameter_names=['plane_normal_angle', 'plane_offset'],
                            parameter_units=['rad', 'm'], sigma=[math.nan, 3e-5],
                            sigma_target=[1e-4, 5e-5], targets_met=False,
                            advice='nearer: 550 mm', image_grid_cols=2, image_grid_rows=1,
                            image_coverage=[0, 5], voltage_axes='u2,u1y',
                            voltage_extent=[-1.0, 1.0, -0.5, 0.5], voltage_grid_cols=1,
                            voltage_grid_rows=2, voltage_coverage=[1, 0],
                            view_points_u=[1.5, 2.5], view_points_v=[3.0, 4.0],
                            view_accepted=False, view_reason='blurred')
    m.view_stamp.sec, m.view_stamp.nanosec = 5, 250_000_000
    for k, v in changes.items():
        setattr(m, k, v)
    return m


def test_progress_is_read_with_nan_as_not_yet_and_its_view():
    got, (stamp_ns, uv, accepted, reason) = progress_fields(serialize_message(progress()))
    assert got['parameters'] == [
        {'name': 'plane_normal_angle', 'unit': 'rad', 'sigma': None, 'target': 1e-4,
         'met': False},
        {'name': 'plane_offset', 'unit': 'm', 'sigma': 3e-5, 'target': 5e-5, 'met': True}]
    assert got['image_coverage'] == {'cols': 2, 'rows': 1, 'cells': [0, 5]}
    assert got['voltage_coverage'] == {'cols': 1, 'rows': 2, 'cells': [1, 0]}
    assert got['voltage_axes'] == ['u2', 'u1y'] and got['voltage_extent'] == [-1, 1, -0.5, 0.5]
    assert got['view_points'] == 2 and got['view_reason'] == 'blurred'
    assert stamp_ns == 5_250_000_000 and not accepted and reason == 'blurred'
    np.testing.assert_array_equal(uv, [[1.5, 3.0], [2.5, 4.0]])


@pytest.mark.parametrize('changes, message', [
    ({'sigma': [1.0]}, '2 parameter_names but 2 parameter_units, 1 sigma'),
    ({'image_coverage': [1, 2, 3]}, 'image_coverage has 3 cells, not image_grid_rows x cols'),
    ({'voltage_grid_cols': 300, 'voltage_grid_rows': 300}, 'over 65536'),
    ({'view_points_v': [1.0]}, '2 view_points_u but 1 view_points_v'),
    ({'view_points_u': [math.nan, 1.0]}, 'non-finite view_points'),
])
def test_malformed_progress_is_refused_with_the_reason(changes, message):
    with pytest.raises(ValueError, match=message.replace('(', r'\(')):
        progress_fields(serialize_message(progress(**changes)))


def test_instruction_is_read_and_malformed_ones_refused():
    m = CalibrationInstruction(sequence=4, stage='intrinsics', state='move', placement=1,
                               placements_planned=8, target='checkerboard',
                               centre=[0.0, 0.01, 0.65], extents=[0.06, 0.06, 0.06],
                               tilt=0.3, tilt_tolerance=0.21, hold_still=True,
                               move=[0.0, 0.0, -0.05], direction='move it 50 mm nearer (-z)',
                               text='Too far.', rejected_reasons=['moved'],
                               rejected_counts=[2])
    got = instruction_fields(serialize_message(m))
    assert got['centre'] == [0.0, 0.01, 0.65] and got['move'] == [0.0, 0.0, -0.05]
    assert got['rejected'] == {'moved': 2} and got['direction'].startswith('move it 50 mm')
    m.rejected_counts = [2, 1]
    with pytest.raises(ValueError, match='1 rejected_reasons but 2 rejected_counts'):
        instruction_fields(serialize_message(m))
    m.rejected_counts, m.tilt = [2], math.inf
    with pytest.raises(ValueError, match='non-finite tilt'):
        instruction_fields(serialize_message(m))
