"""Camera model: plumb_bob projection and undistortion against OpenCV and ground truth."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

cv2 = pytest.importorskip("cv2")

from reconstructor.model import (  # noqa: E402
    CameraIntrinsics,
    project_points,
    undistort_points,
)

# Long-focus camera like the rig's (f ~ 7800 px, 720 x 540) and a short one (wide field).
TELE = dict(fx=7801.38, fy=7798.24, cx=359.51, cy=269.54, width=720, height=540)
WIDE = dict(fx=700.0, fy=690.0, cx=355.0, cy=275.0, width=720, height=540)

tele_dist = st.tuples(
    st.floats(-1.0, 1.0),
    st.floats(-20.0, 20.0),
    st.floats(-2e-3, 2e-3),
    st.floats(-2e-3, 2e-3),
    st.floats(-300.0, 300.0),
)
wide_dist = st.tuples(
    st.floats(-0.3, 0.1),
    st.floats(-0.05, 0.1),
    st.floats(-1e-3, 1e-3),
    st.floats(-1e-3, 1e-3),
    st.floats(-0.02, 0.02),
)


def cv_undistort(intr, uv, iterations=300):
    out = cv2.undistortPoints(
        np.ascontiguousarray(uv.reshape(-1, 1, 2)),
        intr.matrix(),
        np.array(intr.dist),
        criteria=(cv2.TERM_CRITERIA_COUNT, iterations, 0.0),
    )
    return out.reshape(-1, 2)


def cv_project(intr, p_c):
    out, _ = cv2.projectPoints(p_c, np.zeros(3), np.zeros(3), intr.matrix(), np.array(intr.dist))
    return out.reshape(-1, 2)


def image_points(rng, intr, n):
    uv = rng.uniform([0.0, 0.0], [intr.width, intr.height], (n, 2))
    corners = [[0, 0], [intr.width, 0], [0, intr.height], [intr.width, intr.height]]
    return np.vstack([uv, corners])


@settings(max_examples=60, deadline=None)
@given(tele_dist, st.integers(0, 2**32 - 1))
def test_undistort_matches_opencv_telephoto(dist, seed):
    intr = CameraIntrinsics(dist=dist, **TELE)
    uv = image_points(np.random.default_rng(seed), intr, 300)
    np.testing.assert_allclose(undistort_points(intr, uv), cv_undistort(intr, uv), atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(wide_dist, st.integers(0, 2**32 - 1))
def test_undistort_matches_opencv_wide(dist, seed):
    """Where OpenCV's iteration reaches a true inverse (its answer re-projects), ours is the
    same; where it does not (beyond the fold of a strong barrel distortion OpenCV returns a
    point that re-projects elsewhere), ours is NaN or re-projects exactly."""
    intr = CameraIntrinsics(dist=dist, **WIDE)
    uv = image_points(np.random.default_rng(seed), intr, 300)
    ours, cv = undistort_points(intr, uv), cv_undistort(intr, uv)
    cv_error = np.abs(project_points(intr, np.column_stack([cv, np.ones(len(cv))])) - uv)
    inverted = cv_error.max(axis=1) < 1e-6
    np.testing.assert_allclose(ours[inverted], cv[inverted], atol=1e-12)
    rest = ours[~inverted]
    finite = np.isfinite(rest).all(axis=1)
    back = project_points(intr, np.column_stack([rest[finite], np.ones(finite.sum())]))
    np.testing.assert_allclose(back, uv[~inverted][finite], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(tele_dist, st.integers(0, 2**32 - 1))
def test_undistort_recovers_ground_truth_rays(dist, seed):
    """Known rays -> OpenCV projection with distortion -> our undistortion: error < 1e-12."""
    intr = CameraIntrinsics(dist=dist, **TELE)
    rng = np.random.default_rng(seed)
    half_w = 0.5 * intr.width / intr.fx
    half_h = 0.5 * intr.height / intr.fy
    xy = rng.uniform([-half_w, -half_h], [half_w, half_h], (400, 2))
    p_c = np.column_stack([xy, np.ones(len(xy))]) * rng.uniform(0.2, 3.0, (len(xy), 1))
    uv = cv_project(intr, p_c)
    np.testing.assert_allclose(undistort_points(intr, uv), xy, atol=1e-12, rtol=0)


@settings(max_examples=60, deadline=None)
@given(st.one_of(tele_dist.map(lambda d: (d, TELE)), wide_dist.map(lambda d: (d, WIDE))))
def test_project_matches_opencv(case):
    dist, cam = case
    intr = CameraIntrinsics(dist=dist, **cam)
    rng = np.random.default_rng(0)
    half = 0.5 * intr.width / intr.fx
    p_c = np.column_stack([rng.uniform(-half, half, (200, 2)), np.ones(200)])
    p_c *= rng.uniform(0.3, 2.0, (200, 1))
    np.testing.assert_allclose(project_points(intr, p_c), cv_project(intr, p_c), atol=1e-9)


def test_points_outside_the_image_still_converge_or_are_nan():
    intr = CameraIntrinsics(dist=(-0.25, 2.0, 1e-4, -1e-4, -20.0), **TELE)
    # Just outside the image margin: slow path, still exact.
    uv = np.array([[-150.0, 300.0], [900.0, -120.0], [360.0, 700.0]])
    np.testing.assert_allclose(undistort_points(intr, uv), cv_undistort(intr, uv), atol=1e-12)
    # Non-finite input and points with no preimage (beyond the fold) come back as NaN rows.
    uv = np.array([[np.nan, 3.0], [np.inf, 5.0], [1e7, 1e7], [100.0, 200.0]])
    out = undistort_points(intr, uv)
    assert np.isnan(out[:3]).all()
    np.testing.assert_allclose(out[3], cv_undistort(intr, uv[3:])[0], atol=1e-12)


def test_no_distortion_is_pinhole():
    intr = CameraIntrinsics(dist=(0, 0, 0, 0, 0), **TELE)
    uv = np.array([[0.0, 0.0], [720.0, 540.0], [-5000.0, 1e4]])
    expected = (uv - [intr.cx, intr.cy]) / [intr.fx, intr.fy]
    np.testing.assert_allclose(undistort_points(intr, uv), expected, rtol=1e-15)


def test_project_behind_camera_is_nan():
    intr = CameraIntrinsics(dist=(0.1, 0, 0, 0, 0), **TELE)
    out = project_points(intr, np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.01, 0, 1.0]]))
    assert np.isnan(out[:2]).all()
    assert np.isfinite(out[2]).all()


def test_camera_matrix():
    intr = CameraIntrinsics(dist=(0, 0, 0, 0, 0), **TELE)
    np.testing.assert_array_equal(
        intr.matrix(), [[7801.38, 0, 359.51], [0, 7798.24, 269.54], [0, 0, 1]]
    )


@pytest.mark.parametrize(
    "change, name",
    [
        ({"fx": 0.0}, "fx"),
        ({"fy": float("nan")}, "fy"),
        ({"cx": float("inf")}, "cx"),
        ({"dist": (0.1, 0.2)}, "dist"),
        ({"dist": (0.1, 0.2, 0, 0, float("nan"))}, "dist"),
        ({"width": 720.5}, "width"),
        ({"height": 0}, "height"),
    ],
)
def test_intrinsics_validation(change, name):
    args = dict(TELE, dist=(0, 0, 0, 0, 0))
    args.update(change)
    with pytest.raises(ValueError, match=name):
        CameraIntrinsics(**args)


def test_shape_errors_name_the_argument():
    intr = CameraIntrinsics(dist=(0.1, 0, 0, 0, 0), **TELE)
    with pytest.raises(ValueError, match="uv"):
        undistort_points(intr, np.zeros((4, 3)))
    with pytest.raises(ValueError, match="uv"):
        undistort_points(intr, np.zeros(4))
    with pytest.raises(ValueError, match="p_C"):
        project_points(intr, np.zeros((4, 2)))
    assert undistort_points(intr, np.zeros((0, 2))).shape == (0, 2)


def test_undistort_strong_barrel_corner_is_inverted():
    """Pinned (hypothesis found it): the corner (720, 0) of a wide lens with strong barrel
    distortion was NaN although OpenCV inverts it and its answer re-projects exactly."""
    intr = CameraIntrinsics(dist=(-0.2988, -0.0469, 0.0, 0.0, 0.0), **WIDE)
    uv = np.array([[720.0, 0.0], [0.0, 0.0], [720.0, 540.0], [0.0, 540.0]])
    ours = undistort_points(intr, uv)
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours, cv_undistort(intr, uv), atol=1e-12)
    reprojected = project_points(intr, np.column_stack([ours, np.ones(len(ours))]))
    np.testing.assert_allclose(reprojected, uv, atol=1e-9)


def test_undistort_is_nan_only_where_no_inverse_exists():
    """Beyond the fold of the radial polynomial no ray maps to the pixel: NaN, and OpenCV's
    answer there does not re-project to it either."""
    intr = CameraIntrinsics(dist=(-0.2988, -0.0469, 0.0, 0.0, 0.0), **WIDE)
    uv = np.array([[3000.0, 275.0], [355.0 - 2500.0, 275.0 + 2000.0]])
    assert np.isnan(undistort_points(intr, uv)).all()
    cv = cv_undistort(intr, uv)
    reprojected = project_points(intr, np.column_stack([cv, np.ones(len(cv))]))
    assert (np.abs(reprojected - uv).max(axis=1) > 1.0).all()
