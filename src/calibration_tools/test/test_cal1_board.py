"""Circle board: layout, circle-image geometry, ellipse fit, detection (Calibration I).

Ground truth: the simulator's own board definition and rendered frames, and images rendered
through the geometric model with exact analytic ellipse centres.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration_tools.board_geometry import (
    contour_offsets,
    ellipse_centres_normalised,
    pixels_to_board,
    project_circle_centres,
    view_T_board,
)
from calibration_tools.board_layout import PAPER_CIRCLE_BOARD, Checkerboard, CircleBoard
from calibration_tools.board_render import render_circle_board
from calibration_tools.circle_board import detect_circles, fit_ellipse, identify_view
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor.model import CameraIntrinsics, nominal_example_rig, project_points

B = PAPER_CIRCLE_BOARD


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ----------------------------------------------------------------------------- layout
def test_board_matches_the_simulators_board_definition():
    obj = load_scene("circle_board").objects[0]
    fp = obj.feature_points()
    cols, rows = fp["ids"][:, 0], fp["ids"][:, 1]
    idx = B.index_of(rows, cols)
    assert np.all(idx >= 0) and len(np.unique(idx)) == B.n_circles == 35 * 35
    np.testing.assert_allclose(B.points(idx), fp["object_points"], atol=1e-12)
    np.testing.assert_array_equal(B.is_large(idx), fp["big"])
    np.testing.assert_allclose(2.0 * B.radius(idx), fp["diameters"], atol=1e-12)
    assert B.is_large(idx).sum() == 25
    # The board frame origin is the centre circle, a large one.
    centre = B.index_of(17, 17)
    np.testing.assert_allclose(B.points(np.array([centre]))[0], 0.0, atol=1e-15)
    assert B.is_large(np.array([centre]))[0]


@given(st.integers(0, 34), st.integers(0, 34))
def test_index_row_col_round_trip(row, col):
    i = int(B.index_of(row, col))
    r, c = B.row_col(np.array([i]))
    assert (r[0], c[0]) == (row, col)
    frac = B.lattice_coords(B.points(np.array([i]))[:, :2])
    np.testing.assert_allclose(frac[0], [row, col], atol=1e-12)


def test_layout_validation_names_the_problem():
    with pytest.raises(ValueError, match="pitch"):
        CircleBoard(pitch=20.0, small_diameter=10.0, large_diameter=15.0)
    with pytest.raises(ValueError, match="sub_pattern"):
        CircleBoard(sub_pattern=4)
    with pytest.raises(ValueError, match="square"):
        Checkerboard(11, 8, 4.0)
    with pytest.raises(ValueError, match="index"):
        B.points(np.array([B.n_circles]))
    assert B.index_of(-1, 3) == -1 and B.index_of(3, 35) == -1


# ----------------------------------------------------------------------------- circle images
def _conic_centre_from_rim(V_T_W, centre, radius):
    """Independent: project 400 rim points, fit a conic by SVD, return its centre."""
    a = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    rim = np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a),
                           np.zeros_like(a)])
    p = rim @ V_T_W[:3, :3].T + V_T_W[:3, 3]
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    m, s = np.array([x.mean(), y.mean()]), x.std() + y.std()
    xn, yn = (x - m[0]) / s, (y - m[1]) / s
    D = np.column_stack([xn * xn, xn * yn, yn * yn, xn, yn, np.ones_like(xn)])
    A, Bq, C, Dq, E, _ = np.linalg.svd(D)[2][-1]
    M = np.array([[2 * A, Bq], [Bq, 2 * C]])
    return np.linalg.solve(M, [-Dq, -E]) * s + m


@settings(max_examples=30, deadline=None)
@given(
    st.floats(-0.7, 0.7), st.floats(-0.7, 0.7), st.floats(-0.5, 0.5),
    st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(0.3, 1.5),
    st.floats(0.002, 0.01),
)
def test_ellipse_centre_formula_matches_a_conic_fit_of_the_projected_rim(
    rx, ry, rz, cx, cy, z, r
):
    T = _pose([rx, ry, rz], [0.01, -0.02, z])
    centre = np.array([cx, cy, 0.0])
    p = centre @ T[:3, :3].T + T[:3, 3]
    if p[2] < 0.2:
        return
    got = ellipse_centres_normalised(T, centre[None], np.array([r]))[0]
    want = _conic_centre_from_rim(T, centre, r)
    np.testing.assert_allclose(got, want, atol=1e-9)
    # Radius zero is the plain projection of the centre.
    plain = ellipse_centres_normalised(T, centre[None], np.array([0.0]))[0]
    np.testing.assert_allclose(plain, p[:2] / p[2], atol=1e-14)


def test_ellipse_bias_is_significant_for_oblique_views():
    # Why the fit models ellipse centres: 10 mm circles at 650 mm seen at 30 deg move by
    # a sizeable fraction of a pixel (the detector is good to ~0.01 px).
    intr = nominal_example_rig().intrinsics
    T = _pose([0.0, math.radians(30), 0.0], [0.0, 0.0, 0.65])
    c = np.array([[0.0, 0.0, 0.0]])
    biased = project_circle_centres(intr, T, c, np.array([0.005]))
    plain = project_circle_centres(intr, T, c, np.array([0.0]))
    assert 0.1 < np.linalg.norm(biased - plain) < 2.0


@settings(max_examples=40, deadline=None)
@given(st.floats(20, 300), st.floats(5, 300), st.floats(-3.2, 3.2), st.floats(-50, 50),
       st.floats(-50, 50))
def test_fit_ellipse_recovers_exact_ellipses(a, b, ang, x0, y0):
    a, b = max(a, b), min(a, b)
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    pts = (R @ np.vstack([a * np.cos(t), b * np.sin(t)])).T + [x0, y0]
    centre, axes, angle, rms = fit_ellipse(pts)
    np.testing.assert_allclose(centre, [x0, y0], atol=1e-6 * a)
    np.testing.assert_allclose(axes, [a, b], rtol=1e-7)
    assert rms < 1e-6 * a
    if a > 1.01 * b:
        d = (angle - ang) % math.pi
        assert min(d, math.pi - d) < 1e-6


def test_fit_ellipse_refuses_too_few_points():
    with pytest.raises(ValueError, match="points"):
        fit_ellipse(np.zeros((5, 2)))


# ----------------------------------------------------------------------------- detection
def _match(truth_uv, centres):
    d = np.linalg.norm(centres[:, None, :] - truth_uv[None, :, :], axis=2)
    return d.argmin(axis=1), d.min(axis=1)


def test_detection_on_model_rendered_views_is_subpixel_and_rejects_partial_circles():
    rig = nominal_example_rig(dist=(-0.4, 3.0, 2e-4, -1e-4, 0.0))
    T = _pose([0.06, -0.1, 0.02], [0.004, -0.006, 0.65])
    rng = np.random.default_rng(7)
    errors, n_large = [], 0
    for k in range(14):
        U = rng.uniform(-6.0, 6.0, 2)
        view = render_circle_board(rig, B, T, *U, rng=k)
        det = detect_circles(view.image)
        j, dist = _match(view.uv, det.centres)
        assert np.all(dist < 0.1), "every detection is a real circle"
        assert np.all(view.complete[j]), "no partial circle is reported"
        # Every circle at least 3 px clear of the border is found.
        clear = view.complete & (view.uv[:, 0] > 70) & (view.uv[:, 0] < 650) & (
            view.uv[:, 1] > 70) & (view.uv[:, 1] < 470)
        assert set(np.flatnonzero(clear)) <= set(j)
        truth_large = B.is_large(view.index[j])
        known = det.size_known
        np.testing.assert_array_equal(det.large[known], truth_large[known])
        if len(det) >= 2:
            assert known.all()
        n_large += int(truth_large.sum())
        errors.append(det.centres - view.uv[j])
    e = np.concatenate(errors)
    assert len(e) > 40 and n_large >= 1
    assert np.abs(e).max() < 0.05
    assert np.sqrt(np.mean(e**2)) < 0.02


@pytest.mark.parametrize("rig_name, tol_max, tol_rms", [("ideal", 0.05, 0.02),
                                                        ("reference", 0.12, 0.05)])
def test_detection_on_simulator_frames_against_simulator_truth(rig_name, tol_max, tol_rms):
    rig = load_rig(rig_name)
    scene = load_scene("circle_board")
    sim = Simulator(rig, scene, seed=11)
    cam = rig.camera
    intr = CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.distortion),
                            cam.width, cam.height)
    W_T_O = scene.objects[0].W_T_O
    errors = []
    for k, U in enumerate([(0.4, -0.3), (-3.1, 2.2), (4.6, 3.9)]):
        frame = sim.calibration_frame([U[0], U[1], 0.0, 0.0], frame_index=k)
        V_T_O = np.linalg.inv(frame.truth.W_T_V) @ W_T_O
        idx = np.arange(B.n_circles)
        uv = project_circle_centres(intr, V_T_O, B.points(idx), B.radius(idx))
        ok = np.isfinite(uv).all(axis=1)
        det = detect_circles(frame.image)
        assert len(det) >= 2
        j, dist = _match(uv[ok], det.centres)
        assert np.all(dist < 0.5)
        np.testing.assert_array_equal(det.large, B.is_large(idx[ok][j]))
        errors.append(det.centres - uv[ok][j])
    e = np.concatenate(errors)
    assert np.abs(e).max() < tol_max
    assert np.sqrt(np.mean(e**2)) < tol_rms


def test_the_distorted_outline_offset_is_what_the_detector_sees():
    """The detector fits an ellipse to the distorted outline: on the reference rig's frames
    (k1 = -0.6) its centres sit inwards of the distorted ellipse centres by up to 0.02 px
    at the image edge. Ellipse centre plus :func:`contour_offsets` takes that out."""
    rig = load_rig("reference").without_jitter()
    scene = load_scene("circle_board")
    sim = Simulator(rig, scene, seed=11)
    cam = rig.camera
    intr = CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.distortion),
                            cam.width, cam.height)
    plain, fixed, where = [], [], []
    for k, U in enumerate([(0.4, -0.3), (-3.1, 2.2), (4.6, 3.9), (-5.0, -4.0), (2.0, 6.0)]):
        frame = sim.calibration_frame([U[0], U[1], 0.0, 0.0], frame_index=k)
        V_T_O = np.linalg.inv(frame.truth.W_T_V) @ scene.objects[0].W_T_O
        idx = np.arange(B.n_circles)
        uv = project_circle_centres(intr, V_T_O, B.points(idx), B.radius(idx))
        ok = np.isfinite(uv).all(axis=1)
        off = contour_offsets(intr, V_T_O, B.points(idx[ok]), B.radius(idx[ok]))
        det = detect_circles(frame.image)
        j, dist = _match(uv[ok], det.centres)
        plain.append(det.centres - uv[ok][j])
        fixed.append(det.centres - (uv[ok][j] + off[j]))
        where.append(uv[ok][j] - [cam.cx, cam.cy])
    plain, fixed, where = (np.concatenate(x) for x in (plain, fixed, where))
    outer = np.linalg.norm(where, axis=1) > 200.0
    radial = np.einsum("ij,ij->i", plain, where) / np.linalg.norm(where, axis=1)
    radial_fixed = np.einsum("ij,ij->i", fixed, where) / np.linalg.norm(where, axis=1)
    assert radial[outer].mean() < -0.01  # the bias is there
    assert abs(radial_fixed[outer].mean()) < 0.003  # and taken out
    assert np.sqrt(np.mean(fixed**2)) < 0.6 * np.sqrt(np.mean(plain**2))


def test_contour_offsets_vanish_without_distortion_and_match_an_ellipse_fit():
    T = _pose([0.3, -0.4, 0.1], [0.01, -0.02, 0.65])
    clean = CameraIntrinsics(7800.0, 7800.0, 360.0, 270.0, (0.0,) * 5, 720, 540)
    idx = np.arange(B.n_circles)
    uv = project_circle_centres(clean, T, B.points(idx), B.radius(idx))
    seen = idx[(uv[:, 0] > 60) & (uv[:, 0] < 660) & (uv[:, 1] > 60) & (uv[:, 1] < 480)]
    assert len(seen) >= 3
    board, radii = B.points(seen), B.radius(seen)
    np.testing.assert_allclose(contour_offsets(clean, T, board, radii), 0.0, atol=1e-8)
    bent = CameraIntrinsics(7800.0, 7800.0, 360.0, 270.0, (-0.6, 4.0, 3e-4, -2e-4, 0.0),
                            720, 540)
    got = contour_offsets(bent, T, board, radii)
    centre = project_circle_centres(bent, T, board, radii)
    a = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    for k, (p, r) in enumerate(zip(board, radii, strict=True)):
        rim = p + r * np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        uv = project_points(bent, rim @ T[:3, :3].T + T[:3, 3])
        np.testing.assert_allclose(fit_ellipse(uv)[0] - centre[k], got[k], atol=1e-3)
    with pytest.raises(ValueError, match="points_w"):
        contour_offsets(bent, T, np.zeros((3, 2)), np.zeros(3))


def test_detect_circles_input_checks_and_blank_image():
    with pytest.raises(ValueError, match="image"):
        detect_circles(np.zeros((4, 5, 3), np.uint8))
    det = detect_circles(np.full((540, 720), 128, np.uint8))
    assert len(det) == 0 and det.centres.shape == (0, 2)


def test_a_lone_circle_gets_its_size_only_from_an_expected_radius():
    img = np.full((300, 300), 220, np.uint8)
    yy, xx = np.mgrid[0:300, 0:300]
    img[(xx - 150.3) ** 2 + (yy - 140.7) ** 2 < 90.0**2] = 30
    det = detect_circles(img)
    assert len(det) == 1 and not det.size_known[0]
    np.testing.assert_allclose(det.centres[0], [150.3, 140.7], atol=0.05)
    det = detect_circles(img, expected_small_radius_px=60.0)
    assert det.size_known[0] and det.large[0]


# ----------------------------------------------------------------------------- one view
def test_identify_view_labels_truth_and_rejects_an_ambiguous_prediction():
    rig = nominal_example_rig()
    T = _pose([0.05, -0.08, 0.0], [0.0, 0.0, 0.65])
    U = (2.3, -1.7)
    view = render_circle_board(rig, B, T, *U, rng=3)
    det = detect_circles(view.image)
    assert len(det) >= 3 and not det.large.any()
    j, _ = _match(view.uv, det.centres)
    ident = identify_view(det, *U, rig, T, B, max_residual_px=1.0)
    assert ident.accepted and ident.mode == "model"
    np.testing.assert_array_equal(ident.index, view.index[j])
    assert np.abs(ident.residual_px).max() < 0.1
    # Board prior off by half a pitch along x and no large circle: refuse to guess.
    shifted = T @ _pose([0, 0, 0], [0.5 * B.pitch, 0.0, 0.0])
    ident = identify_view(det, *U, rig, shifted, B)
    assert not ident.accepted and "ambiguous" in ident.reason
    assert np.all(ident.index == -1)
    # Off by a whole pitch: one view without a large circle cannot tell (its labels are
    # consistently one column off and agree with the same wrong prior). This is why
    # identify_views fixes the board position with the large circles and verifies every
    # view against a model refined on all views (test_cal1_identify.py).
    shifted = T @ _pose([0, 0, 0], [B.pitch, 0.0, 0.0])
    ident = identify_view(det, *U, rig, shifted, B, max_residual_px=5.0)
    assert ident.accepted
    np.testing.assert_array_equal(ident.index, view.index[j] - 1)

def test_identify_view_uses_the_large_circle_to_fix_a_shifted_prior():
    rig = nominal_example_rig()
    T = _pose([0.05, -0.08, 0.0], [0.0, 0.0, 0.65])
    # Look at the large circle at the board centre.
    xy = np.array([[0.0, 0.0]])
    p_v0 = np.c_[xy, 0.0] @ T[:3, :3].T + T[:3, 3]
    U = (0.0, 0.0)
    view = render_circle_board(rig, B, T, *U, rng=4)
    det = detect_circles(view.image)
    assert det.large.sum() == 1 and det.size_known.all()
    j, _ = _match(view.uv, det.centres)
    for shift in [(1.4, -2.2), (-2.9, 0.6), (0.0, 3.3)]:
        prior = T @ _pose([0, 0, 0], [shift[0] * B.pitch, shift[1] * B.pitch, 0.0])
        ident = identify_view(det, *U, rig, prior, B)
        assert ident.accepted and ident.mode == "large"
        np.testing.assert_array_equal(ident.index, view.index[j])
    assert np.isfinite(p_v0).all()
    # Beyond half the sub-pattern period the large circle cannot help.
    prior = T @ _pose([0, 0, 0], [3.6 * B.pitch, 0.0, 0.0])
    ident = identify_view(det, *U, rig, prior, B)
    assert not ident.accepted or not np.array_equal(ident.index, view.index[j])


def test_pixels_to_board_inverts_the_projection():
    rig = nominal_example_rig(dist=(-0.5, 2.0, 1e-4, 2e-4, 0.0))
    T = _pose([0.1, -0.05, 0.03], [0.01, 0.02, 0.7])
    U = (3.0, -2.0)
    xy = np.array([[0.01, 0.02], [-0.03, 0.05], [0.0, 0.0]])
    V_T_W = view_T_board(rig, *U, T)
    uv = project_points(rig.intrinsics, np.c_[xy, np.zeros(3)] @ V_T_W[:3, :3].T + V_T_W[:3, 3])
    np.testing.assert_allclose(pixels_to_board(rig, uv, *U, T), xy, atol=1e-10)
    with pytest.raises(ValueError, match="uv"):
        pixels_to_board(rig, np.zeros(3), *U, T)
