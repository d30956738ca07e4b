"""Triangulation and pixel prediction: round trips, an independent pipeline, bad input."""

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

cv2 = pytest.importorskip("cv2")

from reconstructor.model import (  # noqa: E402
    CameraIntrinsics,
    MirrorParams,
    RigModel,
    laser_plane_v0,
    nominal_example_rig,
    predict_pixels,
    triangulate,
    triangulate_batch,
    v0_T_v,
)

volts = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False)
DIST = (-0.25, 2.0, 1e-4, -1e-4, -20.0)


@st.composite
def rig_models(draw):
    """Random rigs around the paper's geometry, with G1 nonlinearity and P off pi0."""
    f = draw(st.floats(3000.0, 9000.0))
    intr = CameraIntrinsics(
        fx=f,
        fy=f * draw(st.floats(0.99, 1.01)),
        cx=draw(st.floats(340.0, 380.0)),
        cy=draw(st.floats(250.0, 290.0)),
        dist=(
            draw(st.floats(-0.5, 0.5)),
            draw(st.floats(-5.0, 5.0)),
            draw(st.floats(-1e-3, 1e-3)),
            draw(st.floats(-1e-3, 1e-3)),
            draw(st.floats(-50.0, 50.0)),
        ),
        width=720,
        height=540,
    )

    def g1():
        return MirrorParams(
            math.pi / 4 + draw(st.floats(-0.05, 0.05)),
            draw(st.sampled_from([1, -1])) * draw(st.floats(0.03, 0.04)),
            (draw(st.floats(-1e-4, 1e-4)), draw(st.floats(-1e-5, 1e-5))),
        )

    axis = np.array([1.0, draw(st.floats(-0.05, 0.05)), draw(st.floats(-0.05, 0.05))])
    axis /= np.linalg.norm(axis)
    P = np.array(
        [draw(st.floats(-0.05, 0.05)), -0.196 + draw(st.floats(-0.02, 0.02)), 0.258]
    )
    target = np.array([0.0, draw(st.floats(-0.05, 0.05)), 0.65])
    normal = np.cross(axis, target - P)
    normal /= np.linalg.norm(normal)
    plane = np.append(normal, -normal @ P + draw(st.floats(-0.002, 0.002)))
    return RigModel(
        intrinsics=intr,
        g1_pan=g1(),
        g1_tilt=g1(),
        l=draw(st.floats(0.05, 0.12)),
        d=draw(st.floats(0.01, 0.04)),
        laser_plane_v0=plane,
        laser_axis_dir=axis,
        laser_axis_point=P,
        g2_tilt=MirrorParams(math.pi / 4, draw(st.floats(0.03, 0.04))),
    )


def laser_voltage_through(model, X):
    """U2_tilt whose laser plane contains V0 point X (solved independently of the model code).

    The plane is pi0 rotated rigidly by alpha about (n, P); it contains X iff pi0 contains
    R(-alpha)(X - P) + P, i.e. A cos(alpha) + B sin(alpha) + C = 0.
    """
    n, P = np.array(model.laser_axis_dir), np.array(model.laser_axis_point)
    n0, e0 = np.array(model.laser_plane_v0[:3]), float(model.laser_plane_v0[3])
    w = X - P
    w_par = n @ w
    w_perp = w - w_par * n
    A = n0 @ w_perp
    B = -(n0 @ np.cross(n, w_perp))
    C = w_par * (n0 @ n) + n0 @ P + e0
    rho = math.hypot(A, B)
    if rho == 0.0 or abs(C) > rho:
        return None
    phi = math.atan2(B, A)
    roots = [phi + math.acos(-C / rho), phi - math.acos(-C / rho)]
    roots = [math.remainder(r, 2 * math.pi) for r in roots]
    alpha = min(roots, key=abs)
    return alpha / (2.0 * model.g2_tilt.k)


def apply(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


@settings(max_examples=150, deadline=None)
@given(
    rig_models(),
    volts,
    volts,
    st.floats(-1.0, 1.0),
    st.floats(-1.0, 1.0),
    st.floats(0.3, 2.0),
)
def test_round_trip_v0_point_pixel_v0_point(model, u1p, u1t, fx_frac, fy_frac, depth):
    """V0 point on the current laser plane, in view -> pixel (distorted) -> triangulate."""
    intr = model.intrinsics
    x = fx_frac * 0.48 * intr.width / intr.fx
    y = fy_frac * 0.48 * intr.height / intr.fy
    X = apply(v0_T_v(model, u1p, u1t), depth * np.array([x, y, 1.0]))
    u2 = laser_voltage_through(model, X)
    assume(u2 is not None)
    pi = laser_plane_v0(model, u2)
    assert pi[:3] @ X + pi[3] == pytest.approx(0.0, abs=1e-12)  # X is on the current plane
    # Keep clear of grazing rays (conditioning, not validity).
    ray = X - v0_T_v(model, u1p, u1t)[:3, 3]
    assume(abs(pi[:3] @ ray) / np.linalg.norm(ray) > 0.02)
    uv, in_front = predict_pixels(model, X[None], u1p, u1t)
    assert in_front[0]
    assume(0.0 <= uv[0, 0] <= intr.width and 0.0 <= uv[0, 1] <= intr.height)
    res = triangulate(model, uv, u1p, u1t, u2)
    assert res.valid[0] and res.n_invalid == 0
    np.testing.assert_allclose(res.p_v0[0], X, atol=1e-9, rtol=0)
    np.testing.assert_allclose(res.p_v[0], depth * np.array([x, y, 1.0]), atol=1e-9, rtol=0)
    # Same through the batch variant.
    batch = triangulate_batch(model, uv, np.array([0]), np.array([[u1p, u1t, 0.0, u2]]))
    np.testing.assert_allclose(batch.p_v0[0], X, atol=1e-9, rtol=0)


# ------------------------------------------------------------------ independent pipeline
def householder(normal, point):
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    H = np.eye(4)
    H[:3, :3] -= 2.0 * np.outer(n, n)
    H[:3, 3] = 2.0 * (n @ np.asarray(point, dtype=float)) * n
    return H


def reference_g_T_v(t1, t2, l, d):
    G_T_C = np.array([[0, 0, 1, -l], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float)
    pan = householder([math.cos(t1), -math.sin(t1), 0.0], [0.0, 0.0, 0.0])
    tilt = householder([0.0, math.sin(t2), -math.cos(t2)], [0.0, d, 0.0])
    return tilt @ pan @ G_T_C


def reference_triangulation(model, uv, u1p, u1t, u2t):
    """OpenCV rays, Householder mirrors, scipy Rodrigues, intersection computed in V0."""
    intr = model.intrinsics
    rays = cv2.undistortPoints(
        uv.reshape(-1, 1, 2),
        intr.matrix(),
        np.array(intr.dist),
        criteria=(cv2.TERM_CRITERIA_COUNT, 300, 0.0),
    ).reshape(-1, 2)
    t0p, t0t = model.g1_pan.angle(0.0), model.g1_tilt.angle(0.0)
    V0_T_V = np.linalg.inv(reference_g_T_v(t0p, t0t, model.l, model.d)) @ reference_g_T_v(
        model.g1_pan.angle(u1p), model.g1_tilt.angle(u1t), model.l, model.d
    )
    n, P = np.array(model.laser_axis_dir), np.array(model.laser_axis_point)
    alpha = 2.0 * (model.g2_tilt.angle(u2t) - model.g2_tilt.angle(0.0))
    rot = Rotation.from_rotvec(alpha * n)
    n0 = np.array(model.laser_plane_v0[:3])
    p0 = -model.laser_plane_v0[3] * n0  # a point of pi0
    normal = rot.apply(n0)
    point = rot.apply(p0 - P) + P
    d = np.column_stack([rays, np.ones(len(rays))]) @ V0_T_V[:3, :3].T
    o = V0_T_V[:3, 3]
    s = (normal @ (point - o)) / (d @ normal)
    return o + s[:, None] * d, s


@settings(max_examples=40, deadline=None)
@given(volts, volts, st.floats(-10, 10), st.integers(0, 2**32 - 1))
def test_matches_independent_pipeline(u1p, u1t, u2t, seed):
    model = dataclasses.replace(
        nominal_example_rig(dist=DIST),
        g1_pan=MirrorParams(0.79, 0.036, (3e-5,)),
        g1_tilt=MirrorParams(0.78, -0.034, (0.0, -2e-6)),
        g2_tilt=MirrorParams(0.7, 0.035, (1e-5,)),
    )
    uv = np.random.default_rng(seed).uniform([0, 0], [720, 540], (50, 2))
    ref_v0, s = reference_triangulation(model, uv, u1p, u1t, u2t)
    res = triangulate(model, uv, u1p, u1t, u2t, min_angle=0.0)
    front = s > 0
    np.testing.assert_array_equal(res.valid, front)
    scale = np.maximum(1.0, np.abs(s[front]))[:, None]  # rays far from the laser meet it far
    np.testing.assert_allclose(res.p_v0[front] / scale, ref_v0[front] / scale, atol=1e-9)
    np.testing.assert_allclose(res.p_v[front][:, 2], s[front], rtol=1e-9)


@settings(max_examples=40, deadline=None)
@given(volts, volts, st.integers(0, 2**32 - 1))
def test_predict_pixels_matches_reference_projection(u1p, u1t, seed):
    model = nominal_example_rig(dist=DIST)
    rng = np.random.default_rng(seed)
    p_v = np.column_stack([rng.uniform(-0.03, 0.03, (30, 2)), np.ones(30)])
    p_v *= rng.uniform(0.3, 2.0, (30, 1))
    V0_T_V = np.linalg.inv(reference_g_T_v(math.pi / 4, math.pi / 4, model.l, model.d))
    V0_T_V = V0_T_V @ reference_g_T_v(
        model.g1_pan.angle(u1p), model.g1_tilt.angle(u1t), model.l, model.d
    )
    p_v0 = apply(V0_T_V, p_v)
    intr = model.intrinsics
    expected, _ = cv2.projectPoints(p_v, np.zeros(3), np.zeros(3), intr.matrix(), np.array(DIST))
    uv, in_front = predict_pixels(model, p_v0, u1p, u1t)
    assert in_front.all()
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-7)
    # Per-point voltages give the same answer.
    uv2, _ = predict_pixels(model, p_v0, np.full(30, u1p), np.full(30, u1t))
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    # A point behind the virtual camera is masked and NaN.
    behind = apply(V0_T_V, np.array([[0.0, 0.0, -1.0]]))
    uv3, front3 = predict_pixels(model, behind, u1p, u1t)
    assert not front3[0] and np.isnan(uv3).all()


def test_batch_equals_single_frames():
    model = nominal_example_rig(dist=DIST)
    rng = np.random.default_rng(3)
    volts_m = rng.uniform(-8, 8, (4, 4))
    uv = rng.uniform([0, 0], [720, 540], (200, 2))
    fi = rng.integers(0, 4, 200)
    batch = triangulate_batch(model, uv, fi, volts_m)
    for k in range(4):
        sel = fi == k
        single = triangulate(model, uv[sel], volts_m[k, 0], volts_m[k, 1], volts_m[k, 3])
        np.testing.assert_array_equal(batch.valid[sel], single.valid)
        np.testing.assert_allclose(batch.p_v0[sel], single.p_v0, atol=1e-12)
        np.testing.assert_allclose(batch.p_v[sel], single.p_v, atol=1e-12)


# ---------------------------------------------------------------------------- bad input
def good_frame():
    model = nominal_example_rig(dist=DIST)
    cols = np.arange(0.5, 720, 1.0)
    uv = np.column_stack([cols, 270.0 + 20 * np.sin(cols / 100)])
    return model, uv, (0.5, -0.3, 0.2)


def assert_clean(res, n):
    assert res.p_v.shape == (n, 3) and res.p_v0.shape == (n, 3) and res.valid.shape == (n,)
    assert np.isfinite(res.p_v).all() and np.isfinite(res.p_v0).all()
    assert (res.p_v[~res.valid] == 0).all() and (res.p_v0[~res.valid] == 0).all()
    assert res.n_invalid == int((~res.valid).sum())


def test_nonfinite_pixels_are_masked_and_counted():
    model, uv, volts3 = good_frame()
    clean = triangulate(model, uv, *volts3)
    assert clean.valid.all()
    bad = uv.copy()
    bad[[3, 10, 500], 0] = [np.nan, np.inf, -np.inf]
    bad[42, 1] = np.nan
    res = triangulate(model, bad, *volts3)
    assert_clean(res, len(uv))
    assert res.n_nonfinite == 4 and res.n_invalid == 4
    ok = np.ones(len(uv), dtype=bool)
    ok[[3, 10, 500, 42]] = False
    np.testing.assert_array_equal(res.valid, ok)
    np.testing.assert_allclose(res.p_v0[ok], clean.p_v0[ok], atol=1e-15)


@pytest.mark.parametrize("which", [0, 1, 2])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_nonfinite_voltage_invalidates_the_frame(which, value):
    model, uv, volts3 = good_frame()
    v = list(volts3)
    v[which] = value
    res = triangulate(model, uv, *v)
    assert_clean(res, len(uv))
    assert not res.valid.any() and res.n_nonfinite == len(uv)


@pytest.mark.parametrize("column", [0, 1, 2, 3])
def test_batch_nonfinite_voltage_invalidates_only_its_frame(column):
    model, uv, (a, b, c) = good_frame()
    volts_m = np.array([[a, b, 0.0, c], [a, b, 0.0, c], [a, b, 0.0, c]])
    volts_m[1, column] = np.nan
    fi = np.arange(len(uv)) % 3
    uv_bad = uv.copy()
    uv_bad[0] = np.nan  # frame 0, non-finite pixel
    res = triangulate_batch(model, uv_bad, fi, volts_m)
    assert_clean(res, len(uv))
    expected = (fi != 1) & (np.arange(len(uv)) != 0)
    np.testing.assert_array_equal(res.valid, expected)
    assert res.n_nonfinite == int((~expected).sum())


def test_parallel_and_behind_rays_are_masked():
    # Plane x = 0.01 in V0 at U2 = 0, no distortion: the ray through the principal point lies
    # parallel to it; rays to the right meet it in front, rays to the left behind.
    model = dataclasses.replace(
        nominal_example_rig(), laser_plane_v0=[1.0, 0.0, 0.0, -0.01]
    )
    intr = model.intrinsics
    uv = np.array(
        [
            [intr.cx, intr.cy],  # parallel
            [intr.cx + 0.02 * intr.fx, intr.cy],  # Z = 0.5 m
            [intr.cx - 0.02 * intr.fx, intr.cy],  # behind
            [intr.cx + 0.0005 * intr.fx, intr.cy],  # 0.0005 rad from parallel: < 1e-3
        ]
    )
    res = triangulate(model, uv, 0.0, 0.0, 0.0)
    assert_clean(res, 4)
    np.testing.assert_array_equal(res.valid, [False, True, False, False])
    assert (res.n_parallel, res.n_behind) == (2, 1)
    np.testing.assert_allclose(res.p_v0[1], [0.01, 0.0, 0.5], atol=1e-15)
    res0 = triangulate(model, uv, 0.0, 0.0, 0.0, min_angle=1e-4)
    np.testing.assert_array_equal(res0.valid, [False, True, False, True])


def test_unconverged_undistortion_is_masked():
    model, uv, volts3 = good_frame()
    uv = np.vstack([uv[:5], [[1e7, 1e7]]])
    res = triangulate(model, uv, *volts3)
    assert_clean(res, 6)
    assert res.n_unconverged == 1 and not res.valid[5] and res.valid[:5].all()


def test_empty_input():
    model, _, volts3 = good_frame()
    res = triangulate(model, np.zeros((0, 2)), *volts3)
    assert res.p_v0.shape == (0, 3) and res.n_invalid == 0
    res = triangulate_batch(model, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 4)))
    assert res.p_v0.shape == (0, 3)


def test_shape_errors_name_the_argument():
    model, uv, volts3 = good_frame()
    with pytest.raises(ValueError, match="uv"):
        triangulate(model, np.zeros((5, 3)), *volts3)
    with pytest.raises(ValueError, match="uv"):
        triangulate(model, np.zeros(10), *volts3)
    with pytest.raises(ValueError, match="u1_pan"):
        triangulate(model, uv, np.zeros(2), 0.0, 0.0)
    with pytest.raises(ValueError, match="u2_tilt"):
        triangulate(model, uv, 0.0, 0.0, "1")
    with pytest.raises(ValueError, match="min_angle"):
        triangulate(model, uv, *volts3, min_angle=2.0)
    fi = np.zeros(len(uv), dtype=int)
    with pytest.raises(ValueError, match="voltages"):
        triangulate_batch(model, uv, fi, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="frame_index"):
        triangulate_batch(model, uv, fi[:-1], np.zeros((1, 4)))
    with pytest.raises(ValueError, match="frame_index"):
        triangulate_batch(model, uv, fi + 1, np.zeros((1, 4)))
    with pytest.raises(ValueError, match="frame_index"):
        triangulate_batch(model, uv, fi - 1, np.zeros((1, 4)))
    with pytest.raises(ValueError, match="frame_index"):
        triangulate_batch(model, uv, fi.astype(float), np.zeros((1, 4)))
    with pytest.raises(ValueError, match="p_v0"):
        predict_pixels(model, np.zeros((3, 2)), 0.0, 0.0)
    with pytest.raises(ValueError, match="u1_tilt"):
        predict_pixels(model, np.zeros((3, 3)), 0.0, np.zeros(2))


# ------------------------------------------------------------------------- correction
class FixedCorrection:
    """A known rigid correction (test double for the joint-correction table)."""

    def __init__(self):
        self.T = np.eye(4)
        self.T[:3, :3] = Rotation.from_rotvec([0.001, -0.002, 0.0005]).as_matrix()
        self.T[:3, 3] = [0.0005, -0.001, 0.002]
        self.calls = []

    def V0c_T_V0(self, u1_pan, u1_tilt):  # noqa: N802
        self.calls.append((np.shape(u1_pan), np.shape(u1_tilt)))
        return np.broadcast_to(self.T, np.broadcast_shapes(np.shape(u1_pan)) + (4, 4))


def test_correction_is_applied_after_v0_and_inverted_by_prediction():
    model, uv, volts3 = good_frame()
    corr = FixedCorrection()
    corrected = dataclasses.replace(model, correction=corr)
    plain = triangulate(model, uv, *volts3)
    res = triangulate(corrected, uv, *volts3)
    np.testing.assert_allclose(res.p_v0, apply(corr.T, plain.p_v0), atol=1e-15)
    np.testing.assert_allclose(res.p_v, plain.p_v, atol=0)
    batch = triangulate_batch(
        corrected, uv, np.zeros(len(uv), int), np.array([[volts3[0], volts3[1], 0, volts3[2]]])
    )
    np.testing.assert_allclose(batch.p_v0, res.p_v0, atol=1e-12)
    back, front = predict_pixels(corrected, res.p_v0, volts3[0], volts3[1])
    assert front.all()
    np.testing.assert_allclose(back, uv, atol=1e-7)
    assert corr.calls  # the table was consulted


def test_model_rejects_correction_without_method():
    with pytest.raises(ValueError, match="correction"):
        dataclasses.replace(nominal_example_rig(), correction=object())


@settings(max_examples=60, deadline=None)
@given(model=rig_models(), u1p=st.floats(-3.0, 3.0), u1t=st.floats(-3.0, 3.0),
       u2t=st.floats(-3.0, 3.0), seed=st.integers(0, 10_000))
def test_compiled_hot_path_equals_the_numpy_path(model, u1p, u1t, u2t, seed):
    """The numba pass gives the numpy path's points to round-off, and declines (falls back)
    whenever the numpy path would not take its own hot path."""
    import reconstructor.geometry.triangulation as tri

    rng = np.random.default_rng(seed)
    intr = model.intrinsics
    uv = np.column_stack([rng.uniform(0, intr.width, 300), rng.uniform(0, intr.height, 300)])
    compiled = triangulate(model, uv, u1p, u1t, u2t)
    original = tri._try_hot_path
    tri._try_hot_path = lambda *a: None
    try:
        reference = triangulate(model, uv, u1p, u1t, u2t)
    finally:
        tri._try_hot_path = original
    np.testing.assert_array_equal(compiled.valid, reference.valid)
    scale = 1.0 + np.abs(reference.p_v0).max()
    np.testing.assert_allclose(compiled.p_v0, reference.p_v0, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(compiled.p_v, reference.p_v, rtol=0, atol=1e-12 * scale)


def test_compiled_hot_path_is_taken_for_an_ordinary_frame_and_declines_otherwise():
    import reconstructor.geometry.triangulation as tri

    model = nominal_example_rig(dist=DIST)
    T = v0_T_v(model, 0.3, -0.2)
    plane = T.T @ laser_plane_v0(model, 0.1)
    uv = np.column_stack([np.arange(0.0, 720.0, 1.0), np.full(720, 270.0)])
    sin_min = math.sin(1e-3)
    assert tri._try_hot_path(model.intrinsics, uv, plane, sin_min, T) is not None
    bad = uv.copy()
    bad[5] = np.nan                                      # one non-finite pixel
    assert tri._try_hot_path(model.intrinsics, bad, plane, sin_min, T) is None
    far = uv.copy()
    far[0] = (1e5, 1e5)                                  # outside the undistortion disk
    assert tri._try_hot_path(model.intrinsics, far, plane, sin_min, T) is None
    assert tri._try_hot_path(model.intrinsics, uv[:0], plane, sin_min, T) is None
    edge = plane.copy()
    edge[3] = 0.0                                        # plane through the centre
    assert tri._try_hot_path(model.intrinsics, uv, edge, sin_min, T) is None
