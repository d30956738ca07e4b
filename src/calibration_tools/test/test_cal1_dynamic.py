"""Dynamic-camera calibration: Eq. 16, refinement, transfer-matrix error, and the stage.

The acceptance test renders circle-board frames with the simulator's ideal rig and judges
the calibrated l, d, k, θ0 and every accepted circle label against the simulator's truth.
"""

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration_tools.board_fit import g1_frame_noise
from calibration_tools.board_geometry import project_circle_centres, view_T_board
from calibration_tools.board_layout import PAPER_CIRCLE_BOARD
from calibration_tools.dynamic_camera import (
    ViewObservation,
    anchor_voltages,
    paper_grid,
    pnp_view,
    refine,
    run_dynamic_camera,
    solve_l_d_linear,
    transfer_matrix_error,
)
from calibration_tools.stages import CaptureView, apply_result
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file
from reconstructor.model import (
    CameraIntrinsics,
    MirrorParams,
    PhysicalGeometry,
    RigModel,
    g_T_v,
    nominal_example_rig,
    rigid_inverse,
    v0_T_v,
)

B = PAPER_CIRCLE_BOARD
K_NOMINAL = math.radians(20.0) / 10.0


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ----------------------------------------------------------------------------- Eq. 16
@settings(max_examples=40, deadline=None)
@given(st.floats(0.04, 0.15), st.floats(0.005, 0.05), st.integers(0, 2**31 - 1))
def test_eq16_recovers_l_and_d_from_exact_transfers(l, d, seed):
    rng = np.random.default_rng(seed)
    th = math.pi / 4 + rng.uniform(-0.35, 0.35, (12, 2))
    ref = np.array([math.pi / 4 + 0.01, math.pi / 4 - 0.02])
    # Measured transfers computed independently from the three factors of docs/design.md §2.
    T = rigid_inverse(g_T_v(ref[0], ref[1], l, d)) @ g_T_v(th[:, 0], th[:, 1], l, d)
    res = solve_l_d_linear(th[:, 0], th[:, 1], T, ref)
    assert res.l == pytest.approx(l, abs=1e-12) and res.d == pytest.approx(d, abs=1e-12)
    assert res.translation_rms_m < 1e-13 and res.rotation_rms_rad < 1e-7


def test_eq16_input_checks():
    th = np.full(3, math.pi / 4)
    with pytest.raises(ValueError, match="Vr_T_Vn"):
        solve_l_d_linear(th, th, np.zeros((2, 4, 4)), (0.8, 0.8))
    with pytest.raises(ValueError, match="theta_ref"):
        solve_l_d_linear(th, th, np.tile(np.eye(4), (3, 1, 1)), (0.8, 0.8, 0.8))
    with pytest.raises(ValueError, match="constrain"):  # no motion at all
        solve_l_d_linear(th, th, np.tile(np.eye(4), (3, 1, 1)), (math.pi / 4, math.pi / 4))


@settings(max_examples=25, deadline=None)
@given(st.floats(-0.05, 0.05), st.floats(-8, 8), st.floats(-8, 8))
def test_tilt_theta0_is_unobservable_and_pan_theta0_is_not(delta, up, ut):
    # Why the stage never refines g1_tilt.theta0: V0_T_V does not depend on it.
    m = nominal_example_rig()
    tilt = dataclasses.replace(m, g1_tilt=MirrorParams(m.g1_tilt.theta0 + delta, m.g1_tilt.k))
    np.testing.assert_allclose(v0_T_v(tilt, up, ut), v0_T_v(m, up, ut), atol=1e-13)
    if abs(delta) > 1e-3 and abs(ut) > 1.0:
        pan = dataclasses.replace(m, g1_pan=MirrorParams(m.g1_pan.theta0 + delta, m.g1_pan.k))
        assert np.abs(v0_T_v(pan, up, ut) - v0_T_v(m, up, ut)).max() > 1e-6


# ----------------------------------------------------------------------------- transfer error
def test_paper_grid_is_36_positions_from_minus_10_to_10_volts():
    g = paper_grid()
    assert g.shape == (36, 2)
    np.testing.assert_allclose(np.unique(g[:, 0]), [-10, -6, -2, 2, 6, 10])
    assert len({tuple(r) for r in g}) == 36


def test_transfer_matrix_error_follows_eq18():
    a = nominal_example_rig()
    b = dataclasses.replace(a, l=a.l + 0.001, g1_pan=MirrorParams(a.g1_pan.theta0, a.g1_pan.k
                                                                  * 1.001))
    e = transfer_matrix_error(a, a)
    assert e.rmse_mm == 0.0 and np.all(e.error_mm == 0.0)
    e = transfer_matrix_error(a, b)
    # Independent: Frobenius norm of the difference of Vn_T_V0 with translations in mm.
    U = paper_grid()
    A = np.linalg.inv(v0_T_v(a, U[:, 0], U[:, 1]))
    Bm = np.linalg.inv(v0_T_v(b, U[:, 0], U[:, 1]))
    D = A - Bm
    D[:, :3, 3] *= 1000.0
    want = np.sqrt((D**2).sum(axis=(1, 2)))
    np.testing.assert_allclose(e.error_mm, want, rtol=1e-9)
    assert e.rmse_mm == pytest.approx(np.sqrt(np.mean(want**2)))
    # The same comparison through a callable and through measured matrices.
    np.testing.assert_allclose(
        transfer_matrix_error(a, lambda p, t: v0_T_v(b, p, t)).error_mm, want, rtol=1e-9)
    np.testing.assert_allclose(transfer_matrix_error(a, Bm, U).error_mm, want, rtol=1e-9)
    with pytest.raises(ValueError, match="reference"):
        transfer_matrix_error(a, np.zeros((3, 4, 4)))


# ----------------------------------------------------------------------------- PnP, refine
def _observations(model, V0_T_W, n, seed, noise=0.0, jitter_v=0.0):
    """Views of the board at random G1 voltages; with ``jitter_v`` each is seen at voltages
    off by that much (1 sigma, per channel) from those recorded, as a galvo that scatters
    from frame to frame shows it."""
    rng = np.random.default_rng(seed)
    obs = []
    idx = np.arange(B.n_circles)
    while len(obs) < n:
        U = rng.uniform(-7, 7, 2)
        seen = U + rng.normal(0.0, jitter_v, 2) if jitter_v else U
        uv = project_circle_centres(model.intrinsics, view_T_board(model, *seen, V0_T_W),
                                    B.points(idx), B.radius(idx))
        ok = np.isfinite(uv).all(axis=1) & (uv[:, 0] > 60) & (uv[:, 0] < 660) & (
            uv[:, 1] > 60) & (uv[:, 1] < 480)
        if ok.sum() >= 2:
            obs.append(ViewObservation(U, idx[ok], uv[ok] + rng.normal(0, noise, (ok.sum(), 2)),
                                       0, len(obs)))
    return obs


def test_pnp_view_recovers_the_pose_with_the_board_in_front():
    m = nominal_example_rig(dist=(-0.3, 2.0, 1e-4, 0.0, 0.0))
    V0_T_W = _pose([0.05, -0.1, 0.02], [0.01, -0.02, 0.65])
    for o in _observations(m, V0_T_W, 20, seed=2):
        if len(o.index) < 4:
            continue
        T, rms = pnp_view(m.intrinsics, B.points(o.index), B.radius(o.index), o.uv)
        want = view_T_board(m, *o.voltages, V0_T_W)
        np.testing.assert_allclose(T, want, atol=1e-7)
        assert rms < 1e-4
    with pytest.raises(ValueError, match="points_w"):
        pnp_view(m.intrinsics, np.zeros((3, 3)), np.zeros(3), np.zeros((3, 2)))


def test_refine_recovers_the_rig_from_a_rough_start():
    truth = dataclasses.replace(
        nominal_example_rig(),
        g1_pan=MirrorParams(math.pi / 4 + 0.002, K_NOMINAL * 1.003),
        g1_tilt=MirrorParams(math.pi / 4, K_NOMINAL * 0.998),
    )
    V0_T_W = _pose([0.05, -0.1, 0.02], [0.01, -0.02, 0.65])
    obs = _observations(truth, V0_T_W, 40, seed=3, noise=0.02)
    start = dataclasses.replace(
        truth, l=truth.l + 0.003, d=truth.d - 0.002,
        g1_pan=MirrorParams(math.pi / 4, K_NOMINAL), g1_tilt=MirrorParams(math.pi / 4, K_NOMINAL),
    )
    res = refine(start, obs, B, _pose([0.06, -0.09, 0.0], [0.02, -0.01, 0.66]))
    m = res.model
    assert res.success and res.rms_px < 0.03
    for name, got, want in [("l", m.l, truth.l), ("d", m.d, truth.d),
                            ("g1_pan.k", m.g1_pan.k, truth.g1_pan.k),
                            ("g1_tilt.k", m.g1_tilt.k, truth.g1_tilt.k),
                            ("g1_pan.theta0", m.g1_pan.theta0, truth.g1_pan.theta0)]:
        assert abs(got - want) < 5 * res.std[name], name
    assert m.g1_tilt.theta0 == start.g1_tilt.theta0  # never refined
    np.testing.assert_allclose(res.board_poses[0], V0_T_W, atol=2e-5)
    with pytest.raises(ValueError, match="observations"):
        refine(start, [], B, V0_T_W)
    with pytest.raises(ValueError, match="pose_index"):
        refine(start, obs, B, {1: V0_T_W})


def test_the_fit_measures_g1s_frame_noise():
    """Views seen at voltages scattered by 2.3e-4 V (8 urad on a 2 deg/V galvo) from frame to
    frame: the views' common shifts that the fit leaves give that scatter back per channel;
    without it, next to nothing (the circles' own noise is taken out)."""
    truth = nominal_example_rig()
    V0_T_W = _pose([0.05, -0.1, 0.02], [0.01, -0.02, 0.66])
    sigma = 2.3e-4
    for jitter, check in ((sigma, lambda v: v == pytest.approx(sigma, rel=0.25)),
                          (0.0, lambda v: v < 0.25 * sigma)):
        obs = _observations(truth, V0_T_W, 60, seed=7, noise=0.03, jitter_v=jitter)
        res = refine(truth, obs, B, V0_T_W)
        got = g1_frame_noise(res, obs, B)
        assert got["frame_noise_views"] >= 30  # views of 6 circles or more
        for key in ("frame_noise_u1_pan_V", "frame_noise_u1_tilt_V"):
            assert check(got[key]), (jitter, key, got[key])


def test_the_stated_uncertainty_holds_when_a_frames_circles_move_together():
    """Galvo scatter moves all circles of a view together: over 16 draws the refined
    parameters' errors in units of their stated sigma have an RMS near 1 (the view is the
    sample: per circle they read 2.4)."""
    truth = dataclasses.replace(
        nominal_example_rig(),
        g1_pan=MirrorParams(math.pi / 4 + 0.002, K_NOMINAL * 1.003),
        g1_tilt=MirrorParams(math.pi / 4, K_NOMINAL * 0.998),
    )
    V0_T_W = _pose([0.05, -0.1, 0.02], [0.01, -0.02, 0.66])
    names = ("l", "d", "g1_pan.k", "g1_tilt.k", "g1_pan.theta0")
    z = []
    for seed in range(16):
        obs = _observations(truth, V0_T_W, 40, seed=seed, noise=0.02, jitter_v=2.3e-4)
        res = refine(truth, obs, B, V0_T_W)
        m = res.model
        got = {"l": m.l, "d": m.d, "g1_pan.k": m.g1_pan.k, "g1_tilt.k": m.g1_tilt.k,
               "g1_pan.theta0": m.g1_pan.theta0}
        want = {"l": truth.l, "d": truth.d, "g1_pan.k": truth.g1_pan.k,
                "g1_tilt.k": truth.g1_tilt.k, "g1_pan.theta0": truth.g1_pan.theta0}
        z += [(got[n] - want[n]) / res.std[n] for n in names]
    assert 0.6 < math.sqrt(np.mean(np.square(z))) < 1.5, z


# ----------------------------------------------------------------------------- the stage
def _truth_model(tp):
    """RigModel from the simulator's model-equivalent parameters."""
    return RigModel(
        intrinsics=CameraIntrinsics(tp.fx, tp.fy, tp.cx, tp.cy, tuple(tp.distortion), 720, 540),
        g1_pan=MirrorParams(tp.theta0_pan, tp.k_pan),
        g1_tilt=MirrorParams(tp.theta0_tilt, tp.k_tilt),
        l=tp.l, d=tp.d, laser_plane_v0=tp.pi0, laser_axis_dir=tp.n, laser_axis_point=tp.P,
        g2_tilt=MirrorParams(math.pi / 4, tp.k2),
    )


@pytest.fixture(scope="module")
def ideal_run():
    rig = load_rig("ideal")
    scene = load_scene("circle_board")
    sim = Simulator(rig, scene, seed=4)
    cam = rig.camera
    intr = CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.distortion),
                            cam.width, cam.height)
    rng = np.random.default_rng(8)
    views, truths = [], []
    # Capture plan: 27 random voltages and 3 aimed, with nominal values and the nominal
    # board placement of the scene file, at large circles (identification needs 2).
    k = math.radians(20.0) / 10.0
    plan_model = dataclasses.replace(nominal_example_rig(), g1_pan=MirrorParams(math.pi / 4, k),
                                     g1_tilt=MirrorParams(math.pi / 4, k))
    nominal_placement = _pose([0.05, -0.08, 0.0], [0.0, 0.0, 0.65])
    aimed = anchor_voltages(plan_model, B, nominal_placement)[[0, 3, 6]]
    assert len(aimed) == 3
    plan = np.vstack([aimed, rng.uniform(-6.5, 6.5, (27, 2))])
    for i in range(30):
        # Voltages on the DAC grid: what a driver commanding DAC codes reports.
        U = rig.dac.quantize(plan[i])
        f = sim.calibration_frame([U[0], U[1], 0.0, 0.0], frame_index=i)
        views.append(CaptureView(f.image, np.r_[U, 0.0, 0.0], pose_index=0))
        V_T_O = np.linalg.inv(f.truth.W_T_V) @ scene.objects[0].W_T_O
        truths.append(project_circle_centres(intr, V_T_O, B.points(np.arange(B.n_circles)),
                                             B.radius(np.arange(B.n_circles))))
    clean = list(views)
    # Extra frames the stage must refuse with a reason.
    views.append(CaptureView(views[0].image, views[0].voltages, laser_on=True))
    views.append(CaptureView(np.zeros((10, 10), np.uint8), np.zeros(4)))
    tp = rig.true_model_parameters()
    truth = _truth_model(tp)
    # Start: datasheet values a few mm / percent off, and intrinsics off by what Zhang's
    # method leaves at this field of view (see test_cal1_intrinsics.py): 0.04 % in focal
    # length, 4-5 px of principal point, a little spurious distortion.
    zhang = CameraIntrinsics(cam.fx * 1.0004, cam.fy * 1.0003, cam.cx - 4.0, cam.cy + 5.0,
                             (0.004, -0.2, 0.0, 0.0, 0.0), cam.width, cam.height)
    nominal = dataclasses.replace(
        truth, l=0.0855, d=0.0205, intrinsics=zhang,
        g1_pan=MirrorParams(math.pi / 4 + math.radians(0.1), K_NOMINAL * 1.01),
        g1_tilt=MirrorParams(math.pi / 4, K_NOMINAL * 0.99),
    )
    # The stage given the rig's intrinsics (the intrinsics have their own test).
    cal = calibration_file.Calibration(model=dataclasses.replace(nominal, intrinsics=intr))
    calls = []
    result = run_dynamic_camera(views, cal, progress=lambda *a: calls.append(a))
    # Zhang-quality intrinsics, refined jointly (the refine_intrinsics option).
    zhang_cal = calibration_file.Calibration(model=nominal)
    joint = run_dynamic_camera(views, zhang_cal, refine_intrinsics=("fx", "fy", "cx", "cy"))
    return result, truth, truths, cal, calls, joint, clean


def test_ideal_rig_physical_model_finds_no_deviation_it_does_not_have(ideal_run):
    """The physical fit on the simulator's images of the ideal rig (its mirrors on their
    axes, camera square): every deviation it frees comes out within 4 standard errors of
    the truth, 0, and it says why it held the others."""
    _, truth, _, cal, _, _, views = ideal_run
    res = run_dynamic_camera(views, cal, model="physical")
    ex = res.extra["dynamic_camera"]
    assert res.updates["model"] == "physical"
    freed = [n for n in ex["physical_freed"] if not n.startswith("intrinsics.")]
    assert freed, ex["physical_fixed"]
    phys = PhysicalGeometry.from_dict(res.updates["physical"])
    se = res.standard_errors["physical"]
    for name in freed:
        field_name, _, j = name.partition("[")
        got, sd = getattr(phys, field_name), se[field_name]
        if j:
            got, sd = got[int(j[:-1])], sd[int(j[:-1])]
        assert abs(got) < 4.0 * sd, (name, got, sd)
    assert all(isinstance(why, str) and why for why in ex["physical_fixed"].values())
    assert abs(res.updates["l"] - truth.l) < 0.1e-3 and abs(res.updates["d"] - truth.d) < 0.1e-3
    assert res.residuals["reprojection_rms_px"] < 0.05


def test_ideal_rig_meets_the_acceptance_tolerances(ideal_run):
    alone, truth = ideal_run[0], ideal_run[1]
    u = alone.updates
    assert abs(u["l"] - truth.l) < 0.05e-3
    assert abs(u["d"] - truth.d) < 0.05e-3
    assert abs(u["g1_pan"]["k"] / truth.g1_pan.k - 1) < 1e-4
    assert abs(u["g1_tilt"]["k"] / truth.g1_tilt.k - 1) < 1e-4
    assert abs(math.degrees(u["g1_pan"]["theta0"] - truth.g1_pan.theta0)) < 1e-3
    assert "theta0" not in u["g1_tilt"] and "intrinsics" not in u
    assert alone.residuals["reprojection_rms_px"] < 0.05
    # The paper's linear step (Eq. 16, PnP per view) alone is coarser but close.
    extra = alone.extra["dynamic_camera"]
    assert abs(extra["linear_l_m"] - truth.l) < 0.3e-3
    assert abs(extra["linear_d_m"] - truth.d) < 0.3e-3


def test_ideal_rig_from_zhang_quality_intrinsics_with_joint_refinement(ideal_run):
    # Joint refinement of fx, fy, cx, cy repairs Zhang-sized intrinsic errors (which alone
    # bias l by ~0.2 mm and theta0 by ~0.015 deg) on a rig that matches the model.
    result, truth = ideal_run[5], ideal_run[1]
    u = result.updates
    assert abs(u["l"] - truth.l) < 0.05e-3
    assert abs(u["d"] - truth.d) < 0.05e-3
    assert abs(u["g1_pan"]["k"] / truth.g1_pan.k - 1) < 1e-4
    assert abs(u["g1_tilt"]["k"] / truth.g1_tilt.k - 1) < 1e-4
    assert abs(u["intrinsics"]["fx"] / truth.intrinsics.fx - 1) < 2e-4
    assert abs(u["intrinsics"]["fy"] / truth.intrinsics.fy - 1) < 2e-4
    assert abs(u["intrinsics"]["cx"] - truth.intrinsics.cx) < 1.5
    # Pan theta0 and a camera yaw (cx) differ only by a ~3 um shift of the camera centre:
    # theta0 is as good as cx allows (0.3 px ~ 0.001 deg), within a few of its std.
    assert abs(math.degrees(u["g1_pan"]["theta0"] - truth.g1_pan.theta0)) < 3e-3
    assert result.residuals["reprojection_rms_px"] < 0.05
    # Eq. 16 on PnP with Zhang-quality intrinsics: a starting value, a few mm off at worst.
    extra = result.extra["dynamic_camera"]
    assert abs(extra["linear_l_m"] - truth.l) < 3e-3 and abs(extra["linear_d_m"] - truth.d) < 3e-3


def test_ideal_rig_labels_are_the_simulators_circles(ideal_run):
    result, truths = ideal_run[0], ideal_run[2]
    assert result.samples_used == 30 and result.samples_rejected == 2
    extra = result.extra["dynamic_camera"]
    assert sorted(extra["labels"]) == list(range(30))
    wrong = 0
    for i, uv_true in enumerate(truths):
        centres = np.array(extra["centres_px"][i])
        d = np.linalg.norm(uv_true[None, :, :] - centres[:, None, :], axis=2)
        nearest = np.nanargmin(d, axis=1)
        assert np.nanmin(d, axis=1).max() < 0.1  # detections sit on true ellipse centres
        wrong += int(np.sum(nearest != np.array(extra["labels"][i])))
    assert wrong == 0


def test_stage_result_reports_rejections_and_merges_into_the_calibration(ideal_run, tmp_path):
    result, truth, _, cal, calls, _, _ = ideal_run
    assert result.stage == "dynamic_camera"
    assert any("laser on" in r for r in result.rejected)
    assert any("image shape" in r for r in result.rejected)
    assert calls and all(len(c) == 3 for c in calls)
    new = apply_result(cal, result)
    assert new.model.l == result.updates["l"] and new.model.g1_tilt.theta0 == \
        cal.model.g1_tilt.theta0
    calibration_file.save(new, tmp_path / "cal.yaml")
    loaded = calibration_file.load(tmp_path / "cal.yaml")
    assert loaded.stages["dynamic_camera"]["residuals"]["reprojection_rms_px"] < 0.05
    # Transfer-matrix error against the ideal rig (exactly the model) is tiny.
    assert transfer_matrix_error(new.model, truth).rmse_mm < 0.02


def test_stage_refuses_too_little_data():
    cal = calibration_file.Calibration(model=nominal_example_rig())
    blank = CaptureView(np.full((540, 720), 200, np.uint8), np.zeros(4))
    with pytest.raises(ValueError, match="usable views"):
        run_dynamic_camera([blank] * 3, cal)
