"""The main job end to end, reduced (--quick): graph, calibration services, scans, report."""

import json
import math
import subprocess
import sys

import pytest

pytestmark = pytest.mark.dds

KEYS = ('stair_step_error_rmse_mm', 'plate_flatness_rmse_mm', 'sphere_radius_error_mm',
        'transfer_matrix_error_rmse_mm', 'joint_error_before_mm', 'joint_error_after_mm',
        'range_x_mm', 'range_y_mm', 'runtime_s')
DISTANCES = ('100', '200', '350', '400', '650', '1000')


def test_evaluate_quick_writes_every_output(ros_env, tmp_path):
    out = tmp_path / 'out'
    proc = subprocess.run([sys.executable, '-m', 'galvoscan.cli', 'evaluate',
                           '--quick', '--out', str(out), '--seed', '1'],
                          env=ros_env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    metrics = json.loads((out / 'metrics.json').read_text())
    for key in KEYS:
        assert isinstance(metrics[key], float) and math.isfinite(metrics[key]), key
    assert metrics['calibration_source'] == 'calibrated'
    # the cell stage ran through the calibration node's services and its cell_T_v0 takes a
    # later measurement into the cell within a quick calibration's accuracy
    assert 0.0 <= metrics['cell_sphere_centre_error_mm'] < 0.5
    assert math.isfinite(metrics['cell_extrinsic_error_mm'])
    details = json.loads((out / 'details.json').read_text())
    assert details['stages']['cell_extrinsic']['positions'] == 6
    by_distance = metrics['stair_step_error_rmse_mm_by_distance']
    assert set(by_distance) == set(DISTANCES)
    for mm, value in by_distance.items():
        # a distance the rig cannot measure is null, with the reason in details.json
        if value is None:
            assert details['stair_by_distance'][mm]['reason'], mm
        else:
            assert math.isfinite(value)
    assert sum(v is not None for v in by_distance.values()) >= 4
    cvt = metrics['calibrated_vs_true']
    assert {'fx_px', 'l_m', 'd_m', 'laser_axis_direction_error_deg'} <= set(cvt)
    for name in ('report.md', 'calibration.yaml', 'stair_650mm.ply', 'plate.ply',
                 'sphere.ply', 'stair_error_vs_angle.png'):
        assert (out / name).stat().st_size > 0, name
    assert 'paper' in (out / 'report.md').read_text()
