"""Calibration II building blocks on synthetic data with known answers: plane and line fits,
board PnP, back-projection, the laser axis and angle per volt, sphere fits, registration and
the paper's errors."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration_tools.board_layout import Checkerboard, CircleGrid
from calibration_tools.laser_axis import fit_axis, line_distance, plane_rotation_angles
from calibration_tools.laser_plane import (
    backproject_to_plane,
    board_plane_from_pnp,
    fit_line_trimmed,
    fit_plane_svd,
)
from calibration_tools.registration import (
    apply_transform,
    densify_polylines,
    register_icp,
    register_sphere_centres,
    registration_errors,
)
from calibration_tools.small_board import away_from_pattern_edges, inside_convex_hull
from calibration_tools.sphere_fit import fit_circle_3d, fit_sphere, fit_sphere_algebraic
from reconstructor.model import nominal_example_rig, project_points


def _angle_deg(a, b):
    """Angle between two unit vectors, accurate near 0 (atan2 of cross and dot)."""
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def _rigid(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _plane_points(rng, plane, n, extent=0.03, centre=(0.0, 0.0, 0.65)):
    normal = plane[:3] / np.linalg.norm(plane[:3])
    c = np.asarray(centre, float)
    c = c - (normal @ c + plane[3] / np.linalg.norm(plane[:3])) * normal
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    a, b = rng.uniform(-extent, extent, (2, n))
    return c + np.outer(a, e1) + np.outer(b, e2)


# ----------------------------------------------------------------------------- plane / line
@settings(max_examples=25, deadline=None)
@given(st.integers(0, 100_000))
def test_plane_fit_recovers_a_plane_despite_outliers(seed):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    plane = np.append(n, -n @ [0.01, -0.02, 0.6])
    pts = _plane_points(rng, plane, 400)
    pts += np.outer(rng.normal(0, 2e-6, 400), n)
    bad = rng.choice(400, 40, replace=False)
    pts[bad] += np.outer(rng.uniform(5e-4, 5e-3, 40) * rng.choice([-1, 1], 40), n)
    fit = fit_plane_svd(pts, orient=n)
    assert not fit.inliers[bad].any()
    assert fit.n_inliers >= 340
    assert _angle_deg(fit.plane[:3], n) < 0.01
    # The plane goes through the (outlier-free) points' centre to well within the noise.
    good = np.setdiff1d(np.arange(400), bad)
    assert abs(fit.plane[:3] @ pts[good].mean(axis=0) + fit.plane[3]) < 5e-7
    assert 1e-6 < fit.rms < 3e-6


def test_plane_fit_weights_and_errors():
    rng = np.random.default_rng(1)
    plane = np.array([0.0, 0.908, 0.419, -0.2724])
    plane /= np.linalg.norm(plane[:3])
    a = _plane_points(rng, plane, 300)
    b = a[:10] + np.array([0.0, 0.0, 1e-4]) * 0  # same plane
    fit = fit_plane_svd(np.vstack([a, b]), weights=np.r_[np.full(300, 1 / 300), np.full(10, 0.1)])
    assert abs(abs(fit.plane[:3] @ plane[:3]) - 1) < 1e-12
    assert fit.plane[3] <= 0  # default sign: e <= 0
    with pytest.raises(ValueError, match='collinear'):
        fit_plane_svd(np.outer(np.linspace(0, 1, 10), [1, 2, 3]))
    with pytest.raises(ValueError, match='points must have shape'):
        fit_plane_svd(np.zeros((10, 2)))
    with pytest.raises(ValueError, match='weights'):
        fit_plane_svd(a, weights=np.ones(3))


def test_line_fit_drops_points_off_the_line():
    rng = np.random.default_rng(2)
    d = np.array([1.0, 0.1, -0.2]) / np.linalg.norm([1.0, 0.1, -0.2])
    pts = np.outer(np.linspace(-0.02, 0.02, 200), d) + [0.0, 0.01, 0.6]
    pts += rng.normal(0, 1e-6, pts.shape)
    pts[::20] += [0.0, 3e-4, 0.0]
    c, direction, inl, rms = fit_line_trimmed(pts)
    assert not inl[::20].any() and inl.sum() == 190
    assert abs(abs(direction @ d) - 1) < 1e-8
    assert rms < 2e-6


# ----------------------------------------------------------------------------- PnP, rays
@pytest.mark.parametrize('board', [Checkerboard(cols=11, rows=8, square=0.004),
                                   CircleGrid(cols=11, rows=8, pitch=0.0045,
                                              diameter=0.0025)])
def test_pnp_recovers_the_board_plane_and_backprojection_inverts_projection(board):
    model = nominal_example_rig(dist=(-0.3, 2.0, 1e-4, -2e-4, 0.0))
    obj = board.object_points()
    T = _rigid([0.4, -0.3, 0.05], [-0.02, -0.015, 0.66])
    p_c = obj @ T[:3, :3].T + T[:3, 3]
    uv = project_points(model.intrinsics, p_c)
    pose = board_plane_from_pnp(uv, obj, model.intrinsics)
    assert pose.reprojection_rms_px < 1e-6
    np.testing.assert_allclose(pose.V_T_B, T, atol=1e-7)
    n = T[:3, 2]
    np.testing.assert_allclose(pose.plane, np.append(n, -n @ T[:3, 3]), atol=1e-9)
    back, ok = backproject_to_plane(uv, pose.plane, model.intrinsics)
    assert ok.all()
    np.testing.assert_allclose(back, p_c, atol=1e-8)


def test_pnp_and_backprojection_reject_bad_input():
    model = nominal_example_rig()
    with pytest.raises(ValueError, match='image_points'):
        board_plane_from_pnp(np.zeros((3, 2)), np.zeros((3, 3)), model.intrinsics)
    with pytest.raises(ValueError, match='z = 0'):
        board_plane_from_pnp(np.zeros((5, 2)), np.ones((5, 3)), model.intrinsics)
    with pytest.raises(ValueError, match='plane'):
        backproject_to_plane(np.zeros((2, 2)), [0, 0, 0, 1], model.intrinsics)
    # A ray parallel to the plane, a plane behind the camera.
    _, ok = backproject_to_plane([[model.intrinsics.cx, model.intrinsics.cy]], [1, 0, 0, -1],
                                 model.intrinsics)
    assert not ok[0]
    _, ok = backproject_to_plane([[model.intrinsics.cx, model.intrinsics.cy]], [0, 0, 1, 1],
                                 model.intrinsics)
    assert not ok[0]


def test_pattern_edge_and_hull_masks():
    cb = Checkerboard(cols=5, rows=4, square=0.004)
    q = np.array([[0.002, 0.002], [0.0041, 0.002], [0.002, 0.0079], [0.006, 0.006]])
    np.testing.assert_array_equal(away_from_pattern_edges(cb, q, 0.0006),
                                  [True, False, False, True])
    cg = CircleGrid(cols=5, rows=4, pitch=0.005, diameter=0.002)
    q = np.array([[0.0025, 0.0025], [0.005, 0.0051], [0.005, 0.0025]])
    np.testing.assert_array_equal(away_from_pattern_edges(cg, q, 0.0005), [True, False, True])
    hull = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    np.testing.assert_array_equal(
        inside_convex_hull([[5, 5], [1, 5], [11, 5], [0.5, 0.5]], hull, margin=1.0),
        [True, True, False, False])


# ----------------------------------------------------------------------------- laser axis
def _axis_planes(n, P, pi0, k, volts, poly=()):
    """Planes of pi0 rotated about (n, P) by 2 theta(U) (independent Rotation-based code)."""
    out = []
    for u in volts:
        theta = k * u + sum(c * u ** (i + 2) for i, c in enumerate(poly))
        R = Rotation.from_rotvec(2 * theta * n).as_matrix()
        normal = R @ pi0[:3]
        point_on = -pi0[3] * pi0[:3]  # a point of pi0
        p = R @ (point_on - P) + P
        out.append(np.append(normal, -normal @ p))
    return np.array(out)


@pytest.fixture
def axis_truth():
    n = np.array([0.999, 0.03, -0.01])
    n /= np.linalg.norm(n)
    P0 = np.array([0.0, 0.3, 0.01])
    P = P0 - (P0 @ n) * n  # the point closest to the origin
    target = np.array([0.0, 0.0, 0.65])
    normal = np.cross(n, target - P)
    normal /= np.linalg.norm(normal)
    pi0 = np.append(normal, -normal @ P)
    return n, P, pi0


def test_axis_fit_exact_for_noise_free_planes(axis_truth):
    n, P, pi0 = axis_truth
    volts = np.linspace(-3, 3, 13)
    k = 0.0349
    planes = _axis_planes(n, P, pi0, k, volts)
    planes[1::2] *= -1.0  # arbitrary plane signs must not matter
    fit = fit_axis(planes, volts, reference_dir=[1, 0, 0])
    assert _angle_deg(fit.direction, n) < 1e-9
    np.testing.assert_allclose(fit.point, P, atol=1e-10)
    assert abs(fit.k - k) < 1e-10
    assert np.abs(fit.plane_distance_m).max() < 1e-10
    assert np.abs(fit.plane_angle_rad).max() < 1e-9
    assert fit.angle_fit_rms_rad < 1e-10
    # The opposite reference direction flips n and k together (same physical rotation).
    flipped = fit_axis(planes, volts, reference_dir=[-1, 0, 0])
    np.testing.assert_allclose(flipped.direction, -fit.direction)
    assert abs(flipped.k + k) < 1e-10


def test_axis_fit_with_noise_offset_and_polynomial(axis_truth):
    n, P, pi0 = axis_truth
    rng = np.random.default_rng(4)
    volts = np.linspace(-4, 4, 30)
    k, poly = 0.0349, (1.5e-5, -4e-6)
    # A fan plane 0.3 mm off the axis: every plane is tangent to a cylinder about it.
    rho = 3e-4
    pi_off = pi0.copy()
    pi_off[3] -= rho
    planes = _axis_planes(n, P, pi_off, k, volts, poly)
    for p in planes:  # small random tilts about the target and offsets
        dR = Rotation.from_rotvec(rng.normal(0, 2e-6, 3)).as_matrix()
        c = np.array([0.0, 0.0, 0.65])
        c -= (p[:3] @ c + p[3]) * p[:3]
        p[:3] = dR @ p[:3]
        p[3] = -p[:3] @ c + rng.normal(0, 1e-6)
    fit = fit_axis(planes, volts, reference_dir=n, fit_offset=True, poly_degree=3)
    assert _angle_deg(fit.direction, n) < 0.002
    assert line_distance(fit.point, fit.direction, P, n) < 2e-5
    # Signed like the planes (oriented as the first one): n_i . P + e_i = -rho here.
    assert abs(fit.offset + rho) < 2e-5
    assert abs(fit.k / k - 1) < 1e-4
    assert abs(fit.poly[0] - poly[0]) < 2e-6
    # Without the offset the planes (tangent to a cylinder) fit a common line worse.
    plain = fit_axis(planes, volts, reference_dir=n)
    assert (np.sqrt(np.mean(plain.plane_distance_m ** 2))
            > 2 * np.sqrt(np.mean(fit.plane_distance_m ** 2)))


def test_axis_fit_refuses_parallel_planes_and_bad_shapes():
    planes = np.array([[0, 1, 0, -0.1], [0, 1, 0, -0.2], [0, -1, 0, 0.3]], float)
    with pytest.raises(ValueError, match='parallel'):
        fit_axis(planes)
    with pytest.raises(ValueError, match='planes must have shape'):
        fit_axis(np.zeros((3, 3)))
    with pytest.raises(ValueError, match='voltages'):
        fit_axis(np.array([[0, 1, 0, 0], [0, 0, 1, 0]], float), [1.0])


def test_plane_rotation_angles_sign_follows_the_right_hand_rule():
    n = np.array([1.0, 0.0, 0.0])
    planes = np.array([[0, math.cos(a), math.sin(a), -0.1] for a in (0.0, 0.1, -0.2)])
    np.testing.assert_allclose(plane_rotation_angles(planes, n), [0.0, 0.1, -0.2], atol=1e-12)


# ----------------------------------------------------------------------------- sphere
def _sphere_arc(rng, centre, R, plane, n=300, noise=0.0):
    """Points of the circle plane x sphere, on the half facing the origin."""
    normal = plane[:3] / np.linalg.norm(plane[:3])
    d = normal @ centre + plane[3]
    cc = centre - d * normal
    rc = math.sqrt(R * R - d * d)
    e1 = np.cross(normal, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    t = np.linspace(0, 2 * math.pi, 4 * n, endpoint=False)
    pts = cc + rc * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    pts = pts[np.sum((pts - centre) * (0 - pts), axis=1) > 0.2 * R * np.linalg.norm(centre)]
    pts = pts[np.argsort(pts[:, 0])]
    return pts + rng.normal(0, noise, pts.shape)


PLANE = np.array([0.0, 0.908, 0.419, -0.2724]) / np.linalg.norm([0.0, 0.908, 0.419])


def test_sphere_fits_closed_form_and_robust():
    rng = np.random.default_rng(5)
    c, R = np.array([0.01, -0.005, 0.66]), 0.0127
    d = rng.normal(size=(200, 3))
    d[:, 2] = -np.abs(d[:, 2])
    full = c + R * d / np.linalg.norm(d, axis=1)[:, None]
    cc, rr = fit_sphere_algebraic(full)
    np.testing.assert_allclose(cc, c, atol=1e-12)
    assert abs(rr - R) < 1e-12
    with pytest.raises(ValueError, match='coplanar'):
        fit_sphere_algebraic(_sphere_arc(rng, c, R, PLANE))
    noisy = full + rng.normal(0, 5e-6, full.shape)
    noisy = np.vstack([noisy, rng.uniform(-0.02, 0.02, (40, 3)) + c])
    fit = fit_sphere(noisy)
    assert np.linalg.norm(fit.centre - c) < 5e-6 and abs(fit.radius - R) < 5e-6
    assert fit.inliers[:200].mean() > 0.97 and fit.inliers[200:].mean() < 0.1


def test_sphere_from_one_arc_needs_the_radius_and_picks_the_visible_centre():
    rng = np.random.default_rng(6)
    c, R = np.array([0.0, 0.0, 0.66]), 0.01
    arc = _sphere_arc(rng, c, R, PLANE, noise=2e-6)
    wall = np.column_stack([np.linspace(-0.03, 0.03, 200), np.full(200, -0.0092),
                            np.full(200, 0.67)])
    pts = np.vstack([arc, wall])
    fit = fit_sphere(pts, radius=R)
    assert np.linalg.norm(fit.centre - c) < 1e-5
    assert fit.inliers[:len(arc)].all() and not fit.inliers[len(arc):].any()
    # The mirror-image centre, on request.
    normal = PLANE[:3]
    mirror = c - 2 * (normal @ c + PLANE[3]) * normal
    hinted = fit_sphere(pts, radius=R, centre_hint=mirror)
    assert np.linalg.norm(hinted.centre - mirror) < 1e-5
    cc, nn, rc = fit_circle_3d(arc)
    assert abs(abs(nn @ normal) - 1) < 1e-6


# ----------------------------------------------------------------------------- registration
def _stripe_curve(rng, noise=0.0):
    c, R = np.array([0.0, 0.0, 0.66]), 0.01
    arc = _sphere_arc(rng, c, R, PLANE, n=250)
    x = np.r_[np.linspace(-0.03, -0.0095, 150), np.linspace(0.0095, 0.03, 150)]
    wall = np.column_stack([x, -(PLANE[2] * 0.67 + PLANE[3]) / PLANE[1] * np.ones_like(x),
                            np.full_like(x, 0.67)])
    pts = np.vstack([arc, wall])
    pts = pts[np.argsort(pts[:, 0])]
    return pts + rng.normal(0, noise, pts.shape)


def test_icp_recovers_a_rigid_transform_of_a_stripe_curve():
    rng = np.random.default_rng(7)
    target = _stripe_curve(rng)
    # Source -> target: a small rotation about the sphere plus a shift, as a model error.
    about = _rigid([0, 0, 0], [0, 0, 0.66])
    E = about @ _rigid([2e-3, -1e-3, 3e-3], [1e-4, -5e-5, 2e-4]) @ np.linalg.inv(about)
    source = apply_transform(np.linalg.inv(E), target[::3])
    _, tangents = densify_polylines(target, np.zeros(len(target)), factor=1)
    res = register_icp(source, target, max_distance=1e-3, target_tangents=tangents,
                       tolerance=1e-10)
    assert res.converged and res.accepted and res.fitness > 0.99
    assert np.abs(apply_transform(res.transform, source) - target[::3]).max() < 1e-6
    errs = registration_errors(source, target, res.transform, max_distance=1e-4)
    assert errs.error2.max() < 1e-8
    np.testing.assert_allclose(errs.error3, np.linalg.norm(source - target[::3], axis=1),
                               atol=1e-12)
    assert np.all(errs.error1 <= errs.error3 + 1e-15)


def test_icp_that_does_not_converge_is_reported():
    rng = np.random.default_rng(8)
    target = _stripe_curve(rng)
    about = _rigid([0, 0, 0], [0, 0, 0.66])
    E = about @ _rigid([0, 0, 5e-3], [3e-4, 0, 0]) @ np.linalg.inv(about)
    source = apply_transform(np.linalg.inv(E), target)
    res = register_icp(source, target, max_distance=2e-3, max_iterations=1, tolerance=1e-9)
    assert not res.converged and not res.accepted
    assert 'did not converge' in res.message
    _, tangents = densify_polylines(target, np.zeros(len(target)), factor=1)
    res = register_icp(source, target, max_distance=2e-3, max_iterations=1, tolerance=1e-9,
                       target_tangents=tangents)
    assert not res.converged and 'point-to-line' in res.message


def test_sphere_centre_registration_and_densify():
    T = register_sphere_centres([0, 0, 0.66], [1e-3, 0, 0.661])
    np.testing.assert_allclose(T[:3, 3], [1e-3, 0, 1e-3])
    np.testing.assert_allclose(T[:3, :3], np.eye(3))
    pts = np.array([[0, 0, 0], [1e-4, 0, 0], [2e-4, 0, 0], [5e-3, 0, 0]], float)
    dense, tangents = densify_polylines(pts, [0, 0, 0, 0], factor=4)
    assert len(dense) == 4 + 2 * 3  # the 4.8 mm gap is not bridged
    assert np.isclose(np.sort(dense[:, 0])[1], 2.5e-5)
    np.testing.assert_allclose(np.abs(tangents[:, 0]), 1.0)


def test_cone_method_handles_a_fan_rolled_about_its_beam(axis_truth):
    n, P, pi0 = axis_truth
    # The fan rolled by 0.2 deg about the beam (the direction from the axis to the target)
    # and 0.3 mm off the axis: its planes no longer contain the axis.
    beam = np.array([0.0, 0.0, 0.65]) - P
    beam -= (beam @ n) * n
    beam /= np.linalg.norm(beam)
    roll = Rotation.from_rotvec(math.radians(0.2) * beam).as_matrix()
    normal = roll @ pi0[:3]
    rolled = np.append(normal, -normal @ P - 3e-4)
    volts = np.linspace(-4, 4, 17)
    planes = _axis_planes(n, P, rolled, 0.0349, volts)
    paper = fit_axis(planes, volts, reference_dir=n)
    cone = fit_axis(planes, volts, reference_dir=n, method='cone', fit_offset=True)
    assert _angle_deg(paper.direction, n) > 0.15  # biased by about the roll
    assert _angle_deg(cone.direction, n) < 1e-6
    assert abs(abs(math.degrees(cone.cone_angle)) - 0.2) < 1e-6
    assert line_distance(cone.point, cone.direction, P, n) < 1e-9
    assert abs(abs(cone.offset) - 3e-4) < 1e-9
    assert abs(cone.k - 0.0349) < 1e-9
    with pytest.raises(ValueError, match='method must be one of'):
        fit_axis(planes, volts, method='magic')
