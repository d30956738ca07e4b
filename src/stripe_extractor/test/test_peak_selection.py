"""Peak selection in a machined-aluminium V-groove (each face throws the stripe onto the
other) and on synthetic two-peak columns; exposure helpers."""

from __future__ import annotations

import numpy as np
import pytest

from galvoscan_sim import Simulator, load_rig, load_scene
from stripe_extractor.exposure import auto_exposure, frame_levels, merge_hdr
from stripe_extractor.extractor import ExtractorConfig, extract
from stripe_extractor.selection import COUNT_NAMES

GROOVE_AXIS = np.array([0.0, 0.0, 0.66])  # the shipped V-groove's bottom [m]; faces 40 mm


def _groove_rows(sim, truth):
    """Rows per column where the stripe lies on the groove's faces: the true laser sheet
    cut with each face's plane (from the scene's geometry), projected; the part's nominal
    shape as prior, not the renderer's stripe."""
    rows = np.full(sim.rig.camera.width, np.nan)
    plane = truth.laser_plane_W
    for name, side in (('left_face', -1.0), ('right_face', 1.0)):
        ob = sim.scene.objects[sim.scene.object_index(name)]
        n = ob.W_T_O[:3, :3] @ np.array([0.0, 0.0, -1.0])
        d = np.cross(plane[:3], n)
        d /= np.linalg.norm(d)
        base = np.linalg.solve(np.array([plane[:3], n, d]),
                               [-plane[3], n @ GROOVE_AXIS, d @ GROOVE_AXIS])
        pts = base + np.linspace(-0.06, 0.06, 3001)[:, None] * d
        off = side * (pts[:, 0] - GROOVE_AXIS[0])
        pts = pts[(off >= 0) & (off <= 0.04 * np.sqrt(0.5))]  # on this face (40 mm, 45 deg)
        uv = sim.project_points(pts, truth.angles)
        order = np.argsort(uv[:, 0])
        cols = np.arange(len(rows))
        inside = (cols >= uv[order[0], 0]) & (cols <= uv[order[-1], 0])
        rows[inside] = np.interp(cols[inside], uv[order, 0], uv[order, 1])
    return rows


@pytest.fixture(scope='module')
def groove_frames():
    sim = Simulator(load_rig('reference'), load_scene('v_groove_machined_aluminium'), seed=1)
    # laser power 4: the exposure auto exposure picks on this part (see docs/materials.md)
    return [(sim, sim.render([0.0, 0.0, 0.0, u2], laser_power=4.0))
            for u2 in (-0.23, -0.12, 0.0)]


def _off_truth(result, truth, tol=1.0):
    tv = np.full(720, np.nan)
    tv[truth.stripe.column] = truth.stripe.v
    c = np.rint(result.u).astype(int)
    return int(np.sum(~(np.abs(result.v - tv[c]) < tol)))


def test_nearest_the_expected_row_picks_the_stripe_in_the_v_groove(groove_frames):
    """Rule: the local maximum nearest the row where the part's nominal shape puts the
    stripe, within 1.5 px of it. Strongest takes the reflection near the groove's bottom."""
    for sim, frame in groove_frames:
        assert len(frame.truth.reflection) > 100
        expected = _groove_rows(sim, frame.truth)
        strongest = extract(frame.image, ExtractorConfig())
        nearest = extract(frame.image,
                          ExtractorConfig(peak_mode='nearest', max_offset_px=1.5),
                          expected + 0.7)  # a prior 0.7 px off
        assert _off_truth(strongest, frame.truth) >= 30  # the reflection wins there
        assert _off_truth(nearest, frame.truth, tol=1.5) == 0
        assert len(nearest) >= 0.95 * len(strongest)
        assert nearest.selection['took_other'] >= 25
        assert set(nearest.selection) == set(COUNT_NAMES)


def test_unambiguous_drops_the_columns_with_two_peaks(groove_frames):
    sim, frame = groove_frames[1]
    res = extract(frame.image, ExtractorConfig(peak_mode='unambiguous', ambiguity_ratio=0.2))
    strongest = extract(frame.image, ExtractorConfig())
    assert res.selection['dropped_ambiguous'] > 20
    assert len(res) == len(strongest) - res.selection['dropped_ambiguous']
    assert _off_truth(res, frame.truth) < _off_truth(strongest, frame.truth)


def _two_peaks(narrow_row=20.0, wide_row=45.0, narrow_amp=120.0, wide_amp=160.0):
    rows = np.arange(80, dtype=np.float64)[:, None]
    img = (5.0 + narrow_amp * np.exp(-0.5 * ((rows - narrow_row) / 1.5) ** 2)
           + wide_amp * np.exp(-0.5 * ((rows - wide_row) / 5.0) ** 2)) * np.ones((1, 40))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def test_modes_on_synthetic_columns():
    img = _two_peaks()
    strongest = extract(img, ExtractorConfig())
    widest = extract(img, ExtractorConfig(peak_mode='widest'))
    narrow = extract(img, ExtractorConfig(peak_mode='nearest'), 22.0)
    inner = slice(8, -8)  # away from the borders
    assert np.allclose(strongest.v[inner], 45.0, atol=0.2)
    assert np.allclose(widest.v[inner], 45.0, atol=0.2)
    assert np.allclose(narrow.v[inner], 20.0, atol=0.2)
    assert narrow.selection['took_other'] == 40
    # the wide one weaker: strongest takes the narrow one, widest still the wide one
    img2 = _two_peaks(narrow_amp=200.0, wide_amp=90.0)
    assert np.allclose(extract(img2, ExtractorConfig()).v[inner], 20.0, atol=0.2)
    assert np.allclose(extract(img2, ExtractorConfig(peak_mode='widest')).v[inner], 45.0,
                       atol=0.2)
    none = extract(img2, ExtractorConfig(peak_mode='unambiguous', ambiguity_ratio=0.3))
    assert len(none) == 0 and none.selection['dropped_ambiguous'] == 40
    # no expectation (NaN): nearest is strongest
    assert np.allclose(extract(img2, ExtractorConfig(peak_mode='nearest')).v[inner], 20.0,
                       atol=0.2)


def test_a_stripe_along_the_columns_takes_its_prior_per_row():
    """Vertical: the expected column per row; the image transposed gives the same picks."""
    img = np.ascontiguousarray(_two_peaks().T)  # 40 rows, the two stripes along the columns
    config = ExtractorConfig(peak_mode='nearest', orientation='vertical')
    prior = np.full(img.shape[0], 22.0)
    prior[:5] = np.nan  # no expectation there: the strongest
    res = extract(img, config, prior)
    inner = slice(8, -8)
    assert np.allclose(res.v, np.arange(img.shape[0]))  # one centre per row
    assert np.allclose(res.u[inner], 20.0, atol=0.2)
    assert np.allclose(res.u[:5], 45.0, atol=0.2)
    with pytest.raises(ValueError, match='expected_v'):
        extract(img, config, np.full(img.shape[1], 22.0))  # one per column: refused


def test_bad_selection_parameters_are_refused():
    with pytest.raises(ValueError, match='peak_mode'):
        ExtractorConfig(peak_mode='loudest')
    with pytest.raises(ValueError, match='ambiguity_ratio'):
        ExtractorConfig(ambiguity_ratio=0.0)
    with pytest.raises(ValueError, match='max_offset_px'):
        ExtractorConfig(max_offset_px=-1.0)
    with pytest.raises(ValueError, match='expected_v'):
        extract(_two_peaks(), ExtractorConfig(peak_mode='nearest'), np.zeros(3))


def test_frame_levels_and_auto_exposure():
    img = _two_peaks(narrow_amp=60.0, wide_amp=0.0)
    sat, peak = frame_levels(img)
    assert sat == 0.0 and peak == pytest.approx(65 / 255, abs=2 / 255)
    # linear sensor: the exposure that puts the peak at 0.7 of full scale
    t = auto_exposure([img], 1e-3, (1e-5, 5e-3), target=0.7, background=5 / 255)
    assert t == pytest.approx(1e-3 * (0.7 - 5 / 255) / (peak - 5 / 255), rel=1e-6)
    # capped by the frame period
    assert auto_exposure([img], 1e-3, (1e-5, 1.2e-3), target=0.7) == 1.2e-3
    # clipped: at least halved
    hot = _two_peaks(narrow_amp=400.0, wide_amp=0.0)
    assert frame_levels(hot)[0] == 1.0
    assert auto_exposure([hot], 1e-3, (1e-5, 2e-3)) <= 0.5e-3
    with pytest.raises(ValueError):
        auto_exposure([img], -1.0, (1e-5, 2e-3))


def test_hdr_merge_takes_the_short_exposure_where_the_long_one_clips():
    long_img = _two_peaks(narrow_amp=0.0, wide_amp=0.0)
    long_img[:] = 5
    short_img = long_img.copy()
    rows = np.arange(80)[:, None]
    prof = np.exp(-0.5 * ((rows - 30.3) / 1.5) ** 2)
    long_img[:, :20] = np.clip(5 + 600 * prof, 0, 255).astype(np.uint8)[:, :1]   # clipped
    long_img[:, 20:] = np.clip(5 + 150 * prof, 0, 255).astype(np.uint8)[:, :1]
    short_img[:] = np.clip(5 + 150 * prof, 0, 255).astype(np.uint8)[:, :1]
    cfg = ExtractorConfig()
    lr, sr = extract(long_img, cfg), extract(short_img, cfg)
    u, v, w, s, n_short = merge_hdr(lr, sr, long_img)
    assert n_short >= 15 and np.all(np.diff(u) > 0)
    assert np.allclose(v[4:-4], 30.3, atol=0.1)
