"""Standard errors of the calibration and the gauge pinning of the narrow field.

Synthetic problems only (no rendering), so the noise is known: the stated standard errors
must match the scatter of the estimates over noise draws, shrink with more data, and the
parameters a 5-degree field cannot see must stay within their stated priors.
"""

import dataclasses
import functools
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration_tools.board_fit import ViewObservation, refine
from calibration_tools.board_geometry import project_circle_centres, view_T_board
from calibration_tools.board_layout import PAPER_CIRCLE_BOARD, Checkerboard
from calibration_tools.intrinsics import LensPrior, calibrate_intrinsics
from calibration_tools.laser_axis import axis_standard_errors, fit_axis
from calibration_tools.laser_plane import plane_standard_errors
from calibration_tools.stages import StageResult, apply_result, covariance_from_jacobian
from reconstructor import calibration_file
from reconstructor.model import CameraIntrinsics, MirrorParams, nominal_example_rig

BOARD = Checkerboard(11, 8, 0.004)
# The reference lens: 54 mm, 6.9 um pixels, a principal point 3 px off the sensor centre,
# radial and decentring distortion of the reference order.
TRUE = CameraIntrinsics(7801.4, 7798.2, 362.5, 267.0, (-0.6, 4.0, 3e-4, -2e-4, 0.0), 720, 540)


# ----------------------------------------------------------------------------- generic
def _line_problem(n, rng, sigma=0.01):
    x = np.linspace(-1.0, 1.0, n)
    y = 0.3 + 2.0 * x + rng.normal(0.0, sigma, n)
    J = np.column_stack([np.ones(n), x])
    beta = np.linalg.lstsq(J, y, rcond=None)[0]
    return beta, J, y - J @ beta


def test_covariance_matches_the_scatter_of_a_linear_fit_and_shrinks_with_data():
    rng = np.random.default_rng(1)
    est, sds = [], []
    for _ in range(300):
        beta, J, r = _line_problem(20, rng)
        cov, s = covariance_from_jacobian(J, r)
        est.append(beta)
        sds.append(np.sqrt(np.diag(cov)))
    ratio = np.std(est, axis=0) / np.mean(sds, axis=0)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    _, J, r = _line_problem(80, rng)
    big = np.sqrt(np.diag(covariance_from_jacobian(J, r)[0]))
    assert np.all(big < 0.6 * np.mean(sds, axis=0))  # 4x the data: half the error
    # A prior bounds a parameter the data leave free; a free direction is infinite.
    J2 = np.column_stack([np.ones(10), np.ones(10)])
    r2 = rng.normal(0, 0.01, 10)
    assert np.isinf(np.diag(covariance_from_jacobian(J2, r2)[0])).all()
    cov, _ = covariance_from_jacobian(J2, r2, prior_sigma=[0.1, np.inf])
    assert np.isfinite(cov).all() and math.sqrt(cov[0, 0]) <= 0.1
    for bad in (dict(jac=np.ones((3, 2)), residuals=np.ones(4)),
                dict(jac=np.ones((2, 2)), residuals=np.ones(2)),
                dict(jac=[[np.nan]] * 3, residuals=np.ones(3))):
        with pytest.raises(ValueError):
            covariance_from_jacobian(**bad)


# ----------------------------------------------------------------------------- intrinsics
def _zhang_points(n_views, rng, noise=0.03, tilt=0.6):
    obj = BOARD.object_points().astype(np.float64)
    obj = obj - obj.mean(axis=0)
    pts = []
    for i in range(n_views):
        a = 2.0 * math.pi * i / n_views + rng.uniform(0.0, 0.3)
        rvec = np.array([tilt * math.cos(a), tilt * math.sin(a), rng.uniform(-0.3, 0.3)])
        tvec = np.array([rng.uniform(-3e-3, 3e-3), rng.uniform(-2e-3, 2e-3),
                         rng.uniform(0.64, 0.72)])
        uv, _ = cv2.projectPoints(obj, rvec, tvec, TRUE.matrix(), np.array(TRUE.dist))
        pts.append(uv.reshape(-1, 2) + rng.normal(0.0, noise, (len(obj), 2)))
    return pts, obj


PRIOR = LensPrior()


@functools.cache
def _calibrate(seed, n_views=12, prior=PRIOR):
    rng = np.random.default_rng(seed)
    pts, obj = _zhang_points(n_views, rng)
    start = CameraIntrinsics(7800.0, 7800.0, 359.5, 269.5, (0.0,) * 5, 720, 540)
    return calibrate_intrinsics(pts, obj, (720, 540), initial=start, prior=prior)


def test_intrinsics_standard_errors_match_the_scatter_and_shrink_with_data():
    # Without priors the estimate is unbiased and its scatter over noise draws is what the
    # Jacobian's covariance states: the errors in units of their stated sigma have RMS ~1.
    runs = [_calibrate(seed, prior=None) for seed in range(8)]
    z = []
    for name in ("fx", "fy", "cx", "cy", "k1"):
        sd = np.array([r.std[name] for r in runs])
        assert np.isfinite(sd).all() and (sd > 0).all()
        vals = np.array([getattr(r.intrinsics, name) if name != "k1" else r.intrinsics.dist[0]
                         for r in runs])
        z += list((vals - (getattr(TRUE, name) if name != "k1" else TRUE.dist[0])) / sd)
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.5 < rms < 2.0, rms
    more = _calibrate(100, n_views=36, prior=None)
    for name in ("fx", "cx", "k1"):
        assert more.std[name] < 0.75 * np.mean([r.std[name] for r in runs]), name


def test_narrow_field_parameters_stay_within_their_priors():
    prior = LensPrior()
    for seed in range(3):
        res = _calibrate(seed)
        free = _calibrate(seed, prior=None)  # the same draw without priors
        it, sd = res.intrinsics, res.std
        centre = np.array([359.5, 269.5])
        # Within the stated prior, and the pinned sigma no larger than the prior's.
        assert np.all(np.abs([it.cx, it.cy] - centre) < 3 * prior.principal_point_sigma_px)
        assert abs(it.dist[1]) < 3 * prior.k2_sigma
        assert np.all(np.abs(it.dist[2:4]) < 3 * prior.tangential_sigma)
        assert sd["k2"] <= prior.k2_sigma and sd["cx"] <= prior.principal_point_sigma_px
        # The prior pins what the data leave open: smaller sigmas than without it ...
        for name in ("cx", "cy", "k2", "p1", "p2"):
            assert sd[name] < free.std[name], name
        # ... and the truth within 3 stated sigmas.
        assert abs(it.cx - TRUE.cx) < 3 * sd["cx"] and abs(it.cy - TRUE.cy) < 3 * sd["cy"]
        assert abs(it.dist[1] - TRUE.dist[1]) < 3 * sd["k2"]
        assert abs(it.fx - TRUE.fx) < 4 * sd["fx"]
    # The data's correlation shows the gauge freedom the prior pins: cx with p2.
    c = free.correlation
    names = list(free.std)
    assert abs(c[names.index("cx"), names.index("p2")]) > 0.5
    with pytest.raises(ValueError, match="principal_point_sigma_px"):
        LensPrior(principal_point_sigma_px=-1.0)
    pts, obj = _zhang_points(4, np.random.default_rng(0))
    with pytest.raises(ValueError, match="prior must be a LensPrior"):
        calibrate_intrinsics(pts, obj, (720, 540), prior={"cx": 5.0})


# ----------------------------------------------------------------------------- dynamic camera
def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _circle_observations(model, V0_T_W, n, rng, noise):
    B = PAPER_CIRCLE_BOARD
    idx = np.arange(B.n_circles)
    obs = []
    while len(obs) < n:
        U = rng.uniform(-7, 7, 2)
        uv = project_circle_centres(model.intrinsics, view_T_board(model, *U, V0_T_W),
                                    B.points(idx), B.radius(idx))
        ok = np.isfinite(uv).all(axis=1) & (uv[:, 0] > 60) & (uv[:, 0] < 660) & (
            uv[:, 1] > 60) & (uv[:, 1] < 480)
        if ok.sum() >= 2:
            obs.append(ViewObservation(U, idx[ok], uv[ok] + rng.normal(0, noise, (ok.sum(), 2)),
                                       0, len(obs)))
    return obs


def test_dynamic_camera_errors_match_the_scatter_and_carry_the_held_principal_point():
    k = math.radians(20.0) / 10.0
    truth = dataclasses.replace(nominal_example_rig(), g1_pan=MirrorParams(math.pi / 4, k),
                                g1_tilt=MirrorParams(math.pi / 4, k))
    V0_T_W = _pose([0.05, -0.1, 0.02], [0.01, -0.02, 0.65])
    fits = []
    for seed in range(5):
        obs = _circle_observations(truth, V0_T_W, 12, np.random.default_rng(seed), 0.05)
        fits.append(refine(truth, obs, PAPER_CIRCLE_BOARD, V0_T_W, refine_mirrors=False))
    for name in ("l", "d", "g1_pan.theta0"):
        sd = np.array([f.std[name] for f in fits])
        assert np.isfinite(sd).all() and (sd > 0).all()
        vals = np.array([f.model.l if name == "l" else f.model.d if name == "d"
                         else f.model.g1_pan.theta0 for f in fits])
        ratio = np.std(vals, ddof=1) / np.mean(sd)
        assert 0.3 < ratio < 2.5, (name, ratio)
    # A principal point held at +-4 px: theta0 takes it up (half the angle, a mirror doubles
    # it), and its standard error says so.
    held = refine(truth, obs, PAPER_CIRCLE_BOARD, V0_T_W, refine_mirrors=False,
                  input_std={"cx": 4.0})
    want = 0.5 * 4.0 / truth.intrinsics.fx
    assert held.std["g1_pan.theta0"] > 0.7 * want > 5 * fits[-1].std["g1_pan.theta0"]
    assert held.std["l"] >= fits[-1].std["l"]


# ----------------------------------------------------------------------------- laser plane
def test_plane_standard_errors_follow_the_per_view_shifts():
    rng = np.random.default_rng(4)
    err, tilt, sds = [], [], []
    for _ in range(60):
        pts, views = [], []
        for v in range(6):  # six lines on one plane z = 0.65, each shifted and tilted whole
            x = rng.uniform(-0.05, 0.05)
            t = np.linspace(-0.02, 0.02, 50)
            z = 0.65 + rng.normal(0, 1e-5) + rng.normal(0, 2e-4) * t
            p = np.column_stack([np.full(50, x), t, z])
            pts.append(p + rng.normal(0, 1e-6, p.shape))
            views.append(np.full(50, v))
        p = np.concatenate(pts)
        c = p.mean(axis=0)
        n = np.linalg.svd(p - c)[2][2]
        n = n if n[2] > 0 else -n
        plane = np.append(n, -n @ c)
        err.append(plane[3] + 0.65)
        tilt.append(plane[:3] @ [0.0, 1.0, 0.0])
        sds.append(plane_standard_errors(p, plane, np.concatenate(views)))
    sd = np.mean(sds, axis=0)
    assert np.all(sd[1:] > 0)
    ratio = np.array([np.std(err), np.std(tilt)]) / sd[[3, 1]]
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio
    with pytest.raises(ValueError, match="views"):
        plane_standard_errors(p[:100], plane, np.concatenate(views)[:100])


# ----------------------------------------------------------------------------- the file
def test_apply_result_stores_standard_errors_and_refuses_bad_ones():
    cal = calibration_file.Calibration(model=nominal_example_rig())
    good = StageResult("dynamic_camera", updates={"l": 0.0834, "g1_pan": {"k": 0.0349}},
                       standard_errors={"l": 1e-4, "g1_pan": {"k": 6e-6}})
    new = apply_result(cal, good)
    assert new.stages["dynamic_camera"]["standard_errors"] == {"l": 1e-4, "g1_pan.k": 6e-6}
    assert "dynamic_camera" not in cal.stages
    for errors, match in [({"d": 1e-4}, "does not update"), ({"l": -1.0}, "finite"),
                          ({"l": float("nan")}, "finite")]:
        bad = dataclasses.replace(good, standard_errors=errors)
        with pytest.raises(ValueError, match=match):
            apply_result(cal, bad)
    assert "dynamic_camera" not in cal.stages


# ----------------------------------------------------------------------------- laser axis
def test_axis_standard_errors_match_the_scatter():
    rng = np.random.default_rng(5)
    n = np.array([0.99, 0.02, -0.0004]) / np.linalg.norm([0.99, 0.02, -0.0004])
    P = np.array([0.0, 0.05, 0.1])
    t1 = np.cross(n, [0.0, 0.0, 1.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    u = np.linspace(-4.0, 4.0, 9)
    fits, sds = [], []
    for _ in range(100):
        planes = []
        for a in 2 * 0.0349 * u:
            m = np.cos(a) * t1 + np.sin(a) * t2 + rng.normal(0, 1e-4, 3)
            m /= np.linalg.norm(m)
            planes.append(np.append(m, -m @ P + rng.normal(0, 1e-5)))
        fit = fit_axis(np.array(planes), u)
        fits.append(np.concatenate([fit.direction, fit.point, [fit.k]]))
        se = axis_standard_errors(fit, np.array(planes), u)
        sds.append(se["laser_axis_dir"] + se["laser_axis_point"] + [se["g2_tilt"]["k"]])
    sd = np.mean(sds, axis=0)
    assert np.all(sd > 0)
    ratio = np.std(fits, axis=0) / sd
    # n is nearly x: its x component moves only to second order, so is not compared.
    big = np.array([False, True, True, True, True, True, True])
    assert np.all((ratio[big] > 0.7) & (ratio[big] < 1.4)), ratio


def test_axis_covariance_propagated_from_the_planes_matches_the_joint_scatter():
    # The physical model's fit (a cone with an offset, G2's square): direction, point and
    # response all come from the same planes, so their errors are correlated. The covariance
    # carried from each plane's own covariance keeps that; its diagonal and its correlations
    # match the scatter of repeated fits.
    from calibration_tools.laser_axis import _axis_vector, propagated_covariance

    rng = np.random.default_rng(11)
    n = np.array([0.99, 0.02, -0.0004]) / np.linalg.norm([0.99, 0.02, -0.0004])
    P = np.array([0.0, 0.05, 0.1])
    t1 = np.cross(n, [0.0, 0.0, 1.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    u = np.linspace(-7.0, 7.0, 9)
    s_n, s_e = 1e-4, 1e-5
    names = ([f"laser_axis_dir[{j}]" for j in range(3)]
             + [f"laser_axis_point[{j}]" for j in range(3)] + ["g2_tilt.k", "g2_tilt.poly[0]"])
    kw = dict(method="cone", fit_offset=True, poly_degree=2)
    fits, covs = [], []
    for trial in range(60):
        planes, plane_covs = [], []
        for a in 2 * (0.0349 * u + 2e-4 * u ** 2):
            m0 = np.cos(a) * t1 + np.sin(a) * t2
            d = rng.normal(0, s_n, 3)
            d -= (d @ m0) * m0
            m = m0 + d
            m /= np.linalg.norm(m)
            planes.append(np.append(m, -m @ P + rng.normal(0, s_e)))
            Cn = s_n ** 2 * (np.eye(3) - np.outer(m0, m0))
            C = np.zeros((4, 4))
            C[:3, :3], C[:3, 3], C[3, :3] = Cn, -Cn @ P, -P @ Cn
            C[3, 3] = P @ Cn @ P + s_e ** 2
            plane_covs.append(C)
        fit = fit_axis(np.array(planes), u, **kw)
        fits.append(_axis_vector(fit, names))
        if trial < 5:
            def estimate(pl, ref=fit.direction):
                return _axis_vector(fit_axis(np.array(pl), u, reference_dir=ref, **kw), names)
            covs.append(propagated_covariance(estimate, planes, plane_covs))
    fits, cov = np.array(fits), np.mean(covs, axis=0)
    big = [1, 2, 3, 4, 5, 6, 7]  # n's x component moves only to second order
    ratio = fits.std(axis=0)[big] / np.sqrt(np.diag(cov))[big]
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    sd = np.sqrt(np.diag(cov))[big]
    corr_pred = cov[np.ix_(big, big)] / np.outer(sd, sd)
    corr_seen = np.corrcoef(fits[:, big].T)
    strong = np.abs(corr_pred) > 0.5
    assert strong.sum() > len(big)  # correlated outputs exist, off the diagonal too
    assert np.abs(corr_pred - corr_seen)[strong].max() < 0.25
