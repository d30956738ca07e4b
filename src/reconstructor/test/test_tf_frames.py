"""The reconstructor's TF tree agrees with the model's ray geometry; cell_T_v0 from file or
parameter; the calibration file's cell_T_v0 key; the /tf rate limit."""

import dataclasses
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from galvoscan_common.tf_tree import TfBuffer
from reconstructor import calibration_file as cf
from reconstructor.correction import CorrectionTable
from reconstructor.model import nominal_example_rig, predict_pixels, triangulate
from reconstructor.planning import aim_laser
from reconstructor.tf_frames import (
    FrameNames,
    RateLimiter,
    cell_T_v0_source,
    check_cell_T_v0,
    static_edges,
    virtual_camera_edge,
)

NAMES = FrameNames()
S = 1_000_000_000


def cell_pose(rng):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    return T


def corrected_rig(rng):
    """The example rig with a joint-correction table of small random rigid corrections."""
    pan, tilt = np.linspace(-10, 10, 5), np.linspace(-10, 10, 4)
    table = CorrectionTable.from_rotvecs(pan, tilt, rng.normal(0, 2e-3, (5, 4, 3)),
                                         rng.normal(0, 1e-3, (5, 4, 3)))
    return dataclasses.replace(nominal_example_rig(dist=(-0.1, 0.05, 0, 0, 0)), correction=table)


def fill(buf, model, cell_T_v0, u1_pan, u1_tilt, stamp=S):
    for edge in static_edges(NAMES, cell_T_v0):
        buf.set_transform(edge.parent, edge.child, edge.parent_T_child, static=True)
    edge = virtual_camera_edge(NAMES, model, u1_pan, u1_tilt)
    buf.set_transform(edge.parent, edge.child, edge.parent_T_child, stamp=stamp)
    return buf


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10**6), st.floats(-9, 9), st.floats(-4.5, 4.5), st.booleans())
def test_camera_frame_carries_the_models_rays(seed, u1_pan, u1_tilt, corrected):
    """Triangulated points, mapped by the published chain, are where the model says."""
    rng = np.random.default_rng(seed)
    model = corrected_rig(rng) if corrected else nominal_example_rig()
    cell_T_v0 = cell_pose(rng)
    buf = fill(TfBuffer(), model, cell_T_v0, u1_pan, u1_tilt)
    # a stripe of pixels of this frame, triangulated against the laser plane
    u2 = aim_laser(model, u1_pan, u1_tilt, float(rng.uniform(0.5, 0.8)))
    uv = np.column_stack([np.linspace(20, 700, 30), rng.uniform(100, 440, 30)])
    res = triangulate(model, uv, u1_pan, u1_tilt, u2)
    assert res.valid.sum() > 20
    p_v0, p_cam = res.p_v0[res.valid], res.p_v[res.valid]
    h = np.ones((len(p_v0), 1))
    cam_T_v0 = buf.lookup('camera_optical', 'v0')
    np.testing.assert_allclose((cam_T_v0 @ np.hstack([p_v0, h]).T).T[:, :3], p_cam, atol=1e-9)
    world = (buf.lookup('world', 'camera_optical') @ np.hstack([p_cam, h]).T).T[:, :3]
    np.testing.assert_allclose(world, (cell_T_v0 @ np.hstack([p_v0, h]).T).T[:, :3],
                               atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(st.floats(-9, 9), st.floats(-4.5, 4.5))
def test_optical_axes_are_the_chief_ray_and_the_image_directions(u1_pan, u1_tilt):
    """z: the ray of the principal point; x: towards larger u; y: towards larger v."""
    model = nominal_example_rig(dist=(-0.2, 0.1, 1e-3, -1e-3, 0.0))
    intr = model.intrinsics
    v0_T_cam = fill(TfBuffer(), model, np.eye(4), u1_pan, u1_tilt).lookup('v0', 'camera_optical')
    origin, x, y, z = v0_T_cam[:3, 3], v0_T_cam[:3, 0], v0_T_cam[:3, 1], v0_T_cam[:3, 2]
    depth, step = 0.65, 0.002
    pts = np.array([origin + depth * z, origin + depth * z + step * x,
                    origin + depth * z + step * y])
    uv, ok = predict_pixels(model, pts, u1_pan, u1_tilt)
    assert ok.all()
    np.testing.assert_allclose(uv[0], (intr.cx, intr.cy), atol=1e-6)
    assert uv[1, 0] > intr.cx + 1.0 and abs(uv[1, 1] - intr.cy) < 0.05 * (uv[1, 0] - intr.cx)
    assert uv[2, 1] > intr.cy + 1.0 and abs(uv[2, 0] - intr.cx) < 0.05 * (uv[2, 1] - intr.cy)
    # the principal point's ray, triangulated, lies on that axis in front of the camera
    res = triangulate(model, [[intr.cx, intr.cy]], u1_pan, u1_tilt,
                      aim_laser(model, u1_pan, u1_tilt, depth))
    assert res.valid[0]
    d = res.p_v0[0] - origin
    np.testing.assert_allclose(d, depth * z, atol=1e-9)


def test_at_zero_volts_v_is_v0():
    edge = virtual_camera_edge(NAMES, nominal_example_rig(), 0.0, 0.0)
    assert (edge.parent, edge.child) == ('v0', 'v')
    np.testing.assert_allclose(edge.parent_T_child, np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match='finite'):
        virtual_camera_edge(NAMES, nominal_example_rig(), math.nan, 0.0)


def test_static_edges_and_frame_names():
    T = cell_pose(np.random.default_rng(1))
    edges = static_edges(NAMES, T)
    assert [(e.parent, e.child) for e in edges] == [('world', 'v0'), ('v', 'camera_optical')]
    np.testing.assert_array_equal(edges[0].parent_T_child, T)
    np.testing.assert_array_equal(edges[1].parent_T_child, np.eye(4))
    names = FrameNames(cell='cell', v0='scanner_v0', v='scanner_v', camera='')
    assert [(e.parent, e.child) for e in static_edges(names, T)] == [('cell', 'scanner_v0')]
    with pytest.raises(ValueError, match="frame names must differ: cell_frame='v0', "
                                         "frame_id='v0'"):
        FrameNames(cell='v0')
    with pytest.raises(ValueError, match="cell_frame '/world': tf2 frame ids have no leading"):
        FrameNames(cell='/world')
    with pytest.raises(ValueError, match='virtual_camera_frame must be a non-empty'):
        FrameNames(v='')


def test_cell_T_v0_checks_and_sources():
    T = cell_pose(np.random.default_rng(2))
    np.testing.assert_array_equal(check_cell_T_v0(T.ravel().tolist()), T)
    far = T.copy()
    far[:3, 3] = (0.0, 0.0, 650.0)  # millimetres
    with pytest.raises(ValueError, match='cell_T_v0: translation of 650 m is not under 100 m'):
        check_cell_T_v0(far)
    mirrored = T @ np.diag([1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match='determinant -1'):
        check_cell_T_v0(mirrored)
    identity = np.eye(4).ravel().tolist()
    got, source = cell_T_v0_source(T, identity)
    assert source == 'calibration file'
    np.testing.assert_array_equal(got, T)
    got, source = cell_T_v0_source(None, T.ravel().tolist())
    assert source == 'parameter'
    np.testing.assert_array_equal(got, T)
    with pytest.raises(ValueError, match=r'parameter cell_T_v0 must be a 4x4 matrix \(or 16 '
                                         r'numbers\), got shape \(15,\)'):
        cell_T_v0_source(None, [1.0] * 15)


# ---- the calibration file's cell_T_v0 ------------------------------------------------------
def test_calibration_file_round_trips_cell_T_v0(tmp_path):
    T = cell_pose(np.random.default_rng(4))
    cal = cf.Calibration(model=nominal_example_rig(), cell_T_v0=T)
    cf.save(cal, tmp_path / 'c.yaml')
    text = (tmp_path / 'c.yaml').read_text()
    assert 'cell_T_v0:' in text
    loaded = cf.load(tmp_path / 'c.yaml')
    np.testing.assert_array_equal(loaded.cell_T_v0, T)
    got, source = cell_T_v0_source(loaded.cell_T_v0, np.eye(4).ravel().tolist())
    assert source == 'calibration file'
    np.testing.assert_array_equal(got, T)
    # optional: a file without it has none
    cf.save(cf.Calibration(model=nominal_example_rig()), tmp_path / 'n.yaml')
    assert 'cell_T_v0' not in (tmp_path / 'n.yaml').read_text()
    assert cf.load(tmp_path / 'n.yaml').cell_T_v0 is None


def _bad(T):
    T = np.array(T, dtype=object)
    return [[v if isinstance(v, str) else float(v) for v in row] for row in T]


@pytest.mark.parametrize('value, message', [
    ([[1.0, 0.0, 0.0, 0.0]] * 3, r'cell_T_v0 must be a 4x4 matrix: 4 rows of 4 numbers'),
    (np.eye(4).ravel().tolist(), r'cell_T_v0 must be a 4x4 matrix'),
    (_bad([[1, 0, 0, 'x'], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     r"cell_T_v0\[0\]\[3\] must be a number, got 'x'"),
    ([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, float('nan')], [0, 0, 0, 1.0]],
     r'cell_T_v0 must be finite'),
    ([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1.0]],
     r'cell_T_v0: rotation block has determinant -1'),
    ([[1.0, 0, 0, 250.0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
     r'cell_T_v0: translation of 250 m is not under 100 m'),
    ([[1.01, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
     r'cell_T_v0: rotation block is not orthonormal'),
])
def test_calibration_file_refuses_a_bad_cell_T_v0_naming_it(tmp_path, value, message):
    data = cf.Calibration(model=nominal_example_rig()).to_dict()
    data['cell_T_v0'] = value
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=rf'{path}: {message}'):
        cf.load(path)
    with pytest.raises(ValueError, match=message):
        cf.save(cf.Calibration(model=nominal_example_rig(),
                               cell_T_v0=np.array(value, dtype=object)), tmp_path / 'out.yaml')
    assert not (tmp_path / 'out.yaml').exists()


# ---- the /tf rate limit ------------------------------------------------------------------
def test_rate_limiter_bounds_sends_and_keeps_the_last_pose():
    limiter, sent = RateLimiter(), []
    for k in range(500):  # 1 s of frames at 500 fps, 50 Hz allowed
        item = limiter.offer(k, k / 500, 50.0)
        if item is not None:
            sent.append(item)
        if k % 25 == 0:  # a 20 Hz timer
            item = limiter.due(k / 500, 50.0)
            if item is not None:
                sent.append(item)
    assert len(sent) == 50 and sent == sorted(sent)
    assert np.diff(sent).min() >= 10  # never closer than 1/50 s (10 frames)
    assert limiter.pending == 499  # the last frame waits for its turn...
    assert limiter.due(0.999, 50.0) is None
    assert limiter.due(1.0, 50.0) == 499  # ...and then goes out
    assert limiter.due(2.0, 50.0) is None
    assert limiter.offer(500, 3.0, 0.0) is None and limiter.pending is None  # 0 Hz: none
