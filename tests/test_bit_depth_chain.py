"""A 12-bit rig of the family through the reduced calibration chain: every stage reads the
uint16 (Mono12) frames and calibrates as well as with the same rig's 8-bit frames."""

import dataclasses
import math

import numpy as np

from calibration_tools import registry, stage_runner
from calibration_tools.stages import STAGES, apply_result
from galvoscan import sim_scores
from galvoscan.simulated_rig import execute_in_process, nominal_calibration
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.rig import rig_from_dict
from galvoscan_sim.rig_family import build_of, draw_rig

EMPTY = load_scene_text('format_version: 1\nname: empty\nobjects:\n  - type: plane\n'
                        '    name: floor\n    pose: {translation: [0.0, 0.0, 5.0]}\n'
                        '    albedo: 0.1\n')


def _reduced(stage, steps):
    """A quick plan thinned for a fast test: every other checkerboard view and the circle
    board's first 12 views (its large-circle anchors first)."""
    if stage == 'intrinsics' and len(steps) >= 8:
        return steps[::2]
    if stage == 'dynamic_camera':
        return [dataclasses.replace(s, voltages=s.voltages[:12]) for s in steps[:1]]
    return steps


def _calibrate(depth):
    """A drawn rig built at ``depth`` bits through the reduced chain: (rig, calibration)."""
    data = draw_rig(3, 0.45, build={'sensor': 'IMX287', 'bit_depth': depth})
    assert build_of(data)['bit_depth'] == depth
    rig = rig_from_dict(data, f'drawn {depth}-bit rig')
    sim = Simulator(rig, EMPTY, seed=3)
    cal = nominal_calibration(data)
    for stage in STAGES:
        views, _ = execute_in_process(sim, _reduced(stage, registry.plan(stage, cal,
                                                                         quick=True)))
        images = [v.image for v in views if v.image is not None]
        assert images and all(img.dtype == (np.uint8 if depth == 8 else np.uint16)
                              and img.max() < 2 ** depth for img in images), stage
        result = stage_runner.compute(stage, views, cal)
        flat = stage_runner.flatten(result.updates)
        assert flat or set(result.extra) - {'coverage'}, stage
        assert all(np.isfinite(v) for v in flat.values()), stage
        assert result.extra['coverage']['used'] > 0, stage
        cal = apply_result(cal, result)
    return rig, cal


def test_a_12_bit_rig_calibrates_as_its_8_bit_build_does():
    """The same drawn rig (same seed: geometry, imperfections, sensor class) built with a
    Mono8 and a Mono12 camera: every stage reads its frames, and the 12-bit calibration
    is as good as the 8-bit one against the rig's own physics."""
    scores = {}
    for depth in (8, 12):
        rig, cal = _calibrate(depth)
        plane = sim_scores.laser_plane_errors(cal.model, rig)
        scores[depth] = (sim_scores.transfer_matrix_rmse_mm(cal.model, rig),
                         plane['normal_deg'], plane['at_work_m'] * 1e3)
        print(f'\n{depth}-bit build: transfer matrix RMSE {scores[depth][0]:.3f} mm, laser '
              f'plane {scores[depth][1]:.4f} deg, {scores[depth][2]:.3f} mm at work')
    assert all(math.isfinite(v) for v in scores[12])
    assert scores[12][0] <= 1.2 * scores[8][0] + 0.05
    assert scores[12][1] <= 1.2 * scores[8][1] + 0.01
    assert scores[12][2] <= 1.2 * scores[8][2] + 0.1
