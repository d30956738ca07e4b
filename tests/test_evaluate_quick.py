"""The main job end to end, reduced (--quick): graph, calibration services with the
simulated operator placing every target, scans, report; the by-distance evaluation (the
rig re-set, calibrated and scanned there) at one of the paper's distances, and the
off-nominal table at all six. The paper's-method recalibration is left out (it is the same
chain through the same services with another model form; the calibration tests cover
that form)."""

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest

from calibration_tools.stages import STAGES
from galvoscan_sim import load_rig
from galvoscan_sim.rig_family import working_distance, working_point

pytestmark = pytest.mark.dds

KEYS = ('stair_step_error_rmse_mm', 'plate_flatness_rmse_mm',
        'plate_flatness_rmse_mm_range_scaled', 'sphere_radius_error_mm',
        'transfer_matrix_error_rmse_mm', 'joint_error_before_mm', 'joint_error_after_mm',
        'range_x_mm', 'range_y_mm', 'range_extent_x_mm', 'range_extent_y_mm',
        'plate_coverage_fraction', 'runtime_s')
DISTANCES = ('100', '200', '350', '400', '650', '1000')
BY_DISTANCE = ('200',)   # a short one (re-set, calibrated through the operator, scanned)


def finite_or_not_measured(table, details, mm):
    """A figure is a finite error, or null with the reason it was not measured."""
    value = table[mm]
    if value is None:
        assert details[mm]['reason'].startswith('not measured: '), mm
        return False
    assert math.isfinite(value) and value >= 0.0, (mm, value)
    return True


@pytest.mark.timeout(480)  # every target searched for: ~350 s on two loaded cores
def test_evaluate_quick_writes_every_output(ros_env, tmp_path):
    out = tmp_path / 'out'
    proc = subprocess.run([sys.executable, '-m', 'galvoscan.cli', 'evaluate',
                           '--quick', '--out', str(out), '--seed', '1', '--no-paper-method',
                           '--distances', ','.join(BY_DISTANCE)],
                          env=ros_env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    metrics = json.loads((out / 'metrics.json').read_text())
    for key in KEYS:
        assert isinstance(metrics[key], float) and math.isfinite(metrics[key]), key
    assert metrics['calibration_source'] == 'calibrated'
    # every stage calibrated through the simulated operator, and metrics.json says how
    op = metrics['operator']
    assert not op['exact'] and op['seed'] == 1
    for stage in STAGES:
        assert op['placements_kept'][stage] >= 1 and op['instructions'][stage] >= 3
        assert op['placements'][stage] >= op['placements_kept'][stage]
        assert op['wall_s'][stage] > 0 and isinstance(op['views_rejected'][stage], dict)
    # the cell stage ran through the calibration node's services and its cell_T_v0 takes a
    # later measurement into the cell within a quick calibration's accuracy
    assert 0.0 <= metrics['cell_sphere_centre_error_mm'] < 0.5
    assert math.isfinite(metrics['cell_extrinsic_error_mm'])
    details = json.loads((out / 'details.json').read_text())
    # the plate scanned by a raster of views in each pose (decimated with --quick); the range
    # region's extent holds the range covered
    for row in details['plate']:
        assert row['views'] > 1 and row['points'] > 0 and 0.0 < row['coverage_fraction'] <= 1
    assert metrics['range_extent_x_mm'] >= metrics['range_x_mm']
    assert set(details['range_views']) == {'x-', 'x+', 'y-', 'y+', 'x-y-', 'x+y-', 'x-y+',
                                           'x+y+'}
    assert details['stages']['cell_extrinsic']['positions'] == 6
    # each capture is followed by its stage's compute, every stage in every calibration: a
    # capture or compute is never resent (a resend would run it again, queued behind it)
    log = (out / 'logs' / 'calibration.log').read_text()
    events = [('capture', a) if a else ('compute', b) for a, b in re.findall(
        r'\]: (?:([a-z_]+): recorded \d+/\d+ frames|([a-z_]+): \d+ used)', log)]
    assert events and len(events) % 2 == 0, events
    pairs = list(zip(events[0::2], events[1::2], strict=True))
    assert all(c == ('capture', s) and d == ('compute', s) for c, d in pairs
               for s in [c[1]]), events
    done = [c[1] for c, _ in pairs]
    assert all(done.count(stage) == done.count(STAGES[0]) for stage in STAGES), done
    assert done.count('cell_extrinsic') >= 1, done
    # the reference rig is set up for 544 mm from its G1 exit mirror, 650 mm deep along V0
    assert abs(metrics['working_distance_mm'] - 544.4) < 0.5
    assert abs(metrics['working_point_depth_mm'] - 650.0) < 1.0
    # off-nominal: calibrated at 544 mm, the object moved to each paper distance
    off = metrics['stair_step_error_rmse_mm_off_nominal']
    assert set(off) == set(DISTANCES)
    assert sum(finite_or_not_measured(off, details['stair_off_nominal'], mm)
               for mm in DISTANCES) >= 4
    # by distance: the rig re-set for each distance, calibrated and scanned there
    by_distance = metrics['stair_step_error_rmse_mm_by_distance']
    assert set(by_distance) == set(BY_DISTANCE)
    rows = details['stair_by_distance']
    assert sum(finite_or_not_measured(by_distance, rows, mm) for mm in BY_DISTANCE) >= 1
    for mm in BY_DISTANCE:
        if 'rig' not in rows[mm]:
            continue
        rig = load_rig(rows[mm]['rig'])      # the re-set rig the graph ran on
        assert abs(working_distance(rig) - int(mm) / 1e3) < 1e-3, mm
        assert np.allclose(rows[mm]['working_point_w_m'], working_point(rig))
        if by_distance[mm] is not None:
            # calibrated there: its own calibration, scored against that rig's truth
            assert (out / 'by_distance' / f'{mm}mm' / 'calibration.yaml').stat().st_size > 0
            assert math.isfinite(rows[mm]['transfer_matrix_error_rmse_mm'])
            assert rows[mm]['positions_used'] == 1
    cvt = metrics['calibrated_vs_true']
    assert {'fx_px', 'l_m', 'd_m', 'laser_axis_direction_error_deg'} <= set(cvt)
    for name in ('report.md', 'calibration.yaml', 'stair_working_point.ply', 'plate.ply',
                 'sphere.ply', 'stair_error_vs_angle.png', 'stair_error_by_distance.png',
                 'plate_deviation_map.png'):
        assert (out / name).stat().st_size > 0, name
    text = (out / 'report.md').read_text()
    assert 'paper' in text and 'by working distance' in text and 'Off-nominal' in text
