"""The per-material scores: a point's distance to the true surface, the outlier share, the
stair error of exact points, the table; ``galvoscan evaluate --materials`` is parsed."""

import numpy as np
import pytest

from galvoscan import eval_scenes, material_scores
from galvoscan.evaluate import build_parser
from galvoscan.materials_eval import SETTINGS, TABLE_COLUMNS
from galvoscan_sim import load_rig, load_scene_text


def _stair():
    text, info = eval_scenes.stair((0.0, 0.0, 0.65), material='machined_aluminium')
    return load_scene_text(text), info


def test_surface_offsets_measure_the_distance_to_the_nearest_face():
    scene, info = _stair()
    W_T_V0 = load_rig('reference').W_T_V0
    V0_T_W = np.linalg.inv(W_T_V0)
    F = scene.faces
    rng = np.random.default_rng(0)
    finite = [k for k in range(len(F.obj)) if np.all(np.isfinite(F.half[k]))]
    on_w, off_w = [], []
    for k in finite:
        a, b = rng.uniform(-0.8, 0.8, 2) * F.half[k]
        p = F.center[k] + a * F.e1[k] + b * F.e2[k]
        on_w.append(p)
        off_w.append(p + 0.3e-3 * F.normal[k])  # 0.3 mm in front of the face
    to_v0 = lambda p: np.asarray(p) @ V0_T_W[:3, :3].T + V0_T_W[:3, 3]  # noqa: E731
    on = material_scores.surface_offsets(scene, W_T_V0, to_v0(on_w))
    off = material_scores.surface_offsets(scene, W_T_V0, to_v0(off_w))
    assert np.all(on < 1e-9)
    assert np.all(off <= 0.3e-3 + 1e-9) and np.median(off) == pytest.approx(0.3e-3, abs=1e-9)
    far = material_scores.surface_offsets(scene, W_T_V0, to_v0([F.center[finite[0]]
                                                                + 0.01 * F.normal[finite[0]]]))
    assert far[0] > material_scores.OUTLIER_M
    assert material_scores.outlier_fraction(np.r_[on, far]) == pytest.approx(1 / (len(on) + 1))
    assert np.isnan(material_scores.outlier_fraction([]))
    assert material_scores.surface_offsets(scene, W_T_V0, np.zeros((0, 3))).shape == (0,)


def test_the_table_and_the_command_line():
    rows = [{'material': 'matte_paint', 'setting': 'off', 'stair_error_mm': 0.0123,
             'plate_flatness_mm': 0.05, 'outlier_percent': 0.0, 'coverage_vs_matte': 1.0,
             'points': 1200, 'frames': 100},
            {'material': 'black_anodised', 'setting': 'off', 'stair_error_mm': float('nan'),
             'plate_flatness_mm': float('nan'), 'outlier_percent': float('nan'),
             'coverage_vs_matte': 0.0, 'points': 0, 'frames': 100}]
    text = material_scores.table_markdown(rows, TABLE_COLUMNS)
    lines = text.splitlines()
    assert len(lines) == 4 and lines[2].startswith('| matte_paint | off | +0.012 |')
    assert '| n/a |' in lines[3]
    assert set(SETTINGS) == {'off', 'peak_selection', 'two_view', 'exposure', 'all'}
    assert build_parser().parse_args(['--materials', '--quick']).materials
    assert not build_parser().parse_args([]).materials
