"""Intrinsics (Zhang via OpenCV) at U1 = 0, judged by the simulator's camera.

With a 54 mm lens the field of view is ~5 degrees, so the focal length comes only from the
perspective of strongly tilted boards; the captures here tilt the simulator's 4 mm
checkerboard by ~34 degrees in directions all around, as a bench procedure should.
"""

import dataclasses
import math

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration_tools.board_layout import Checkerboard, CircleGrid
from calibration_tools.board_render import render_target
from calibration_tools.intrinsics import (
    calibrate_intrinsics,
    detect_target,
    refine_corners_symmetric,
    run_intrinsics,
)
from calibration_tools.stages import CaptureView, apply_result
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import SCENE_DIR, load_scene, load_scene_text
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file
from reconstructor.model import CameraIntrinsics, nominal_example_rig

BOARD = Checkerboard(11, 8, 0.004)  # the simulator's checkerboard: 12 x 9 squares of 4 mm


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _checkerboard_views(rig_name, n, seed, tilt=0.6):
    rig = load_rig(rig_name)
    base = yaml.safe_load((SCENE_DIR / "checkerboard.yaml").read_text())
    sim = Simulator(rig, load_scene("checkerboard"), seed=seed)
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n):
        a = 2.0 * math.pi * i / n + rng.uniform(0.0, 0.3)
        rotvec = [tilt * math.cos(a), tilt * math.sin(a), rng.uniform(-0.3, 0.3)]
        doc = dict(base)
        obj = dict(base["objects"][0])
        obj["pose"] = {
            "translation": [float(rng.uniform(-0.003, 0.003)), float(rng.uniform(-0.002, 0.002)),
                            float(rng.uniform(0.64, 0.72))],
            "rotation_vector": [float(v) for v in rotvec],
        }
        doc["objects"] = [obj]
        sim.set_scene(load_scene_text(yaml.safe_dump(doc)))
        f = sim.calibration_frame([0.0, 0.0, 0.0, 0.0], frame_index=i)
        views.append(CaptureView(f.image, np.zeros(4)))
    return rig, views


def _nominal_calibration():
    # Nominal lens data only: 54 mm / 6.9 um, centred principal point, no distortion.
    model = nominal_example_rig()
    intr = CameraIntrinsics(7800.0, 7800.0, 360.0, 270.0, (0.0,) * 5, 720, 540)
    return calibration_file.Calibration(model=dataclasses.replace(model, intrinsics=intr))


@pytest.mark.parametrize("rig_name, tol", [("ideal", 5e-4), ("reference", 1e-3)])
def test_zhang_on_simulator_checkerboards(rig_name, tol):
    rig, views = _checkerboard_views(rig_name, 30, seed=3)
    # Frames the stage must refuse with a reason.
    views.append(CaptureView(views[0].image, np.array([0.5, 0.0, 0.0, 0.0])))
    views.append(CaptureView(np.full((540, 720), 180, np.uint8), np.zeros(4)))
    cal = _nominal_calibration()
    result = run_intrinsics(views, cal, BOARD)
    cam = rig.camera
    u = result.updates["intrinsics"]
    # Acceptance (ideal rig): fx and fy within 0.05 %.
    assert abs(u["fx"] / cam.fx - 1) < tol
    assert abs(u["fy"] / cam.fy - 1) < tol
    assert abs(u["cx"] - cam.cx) < 15 and abs(u["cy"] - cam.cy) < 15
    assert result.samples_used == 30 and result.samples_rejected == 2
    assert any("not at 0" in r for r in result.rejected)
    assert any("target not found" in r for r in result.rejected)
    assert result.residuals["reprojection_rms_px"] < 0.05
    views_rms = result.extra["intrinsics"]["view_rms_px"]
    assert len(views_rms) == 30 and max(views_rms.values()) < 0.1
    if rig_name == "reference":
        # The lens distortion is found with the right sign and size (k1 = -0.6 moves the
        # image corner by ~0.9 px).
        assert -0.9 < u["dist"][0] < -0.3
    new = apply_result(cal, result)
    assert new.model.intrinsics.fx == u["fx"]


def test_outlier_views_are_rejected():
    K = np.array([[7801.0, 0, 359.5], [0, 7798.0, 269.5], [0, 0, 1]])
    obj = BOARD.object_points()
    rng = np.random.default_rng(0)
    pts = []
    for i in range(16):
        a = 2 * math.pi * i / 16
        R = Rotation.from_rotvec([0.6 * math.cos(a), 0.6 * math.sin(a), 0.1]).as_matrix()
        p = (obj - [0.02, 0.014, 0]) @ R.T + [0, 0, 0.68]
        uv = p[:, :2] / p[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
        pts.append(uv + rng.normal(0, 0.01, uv.shape))
    bad = [4, 11]
    for i in bad:
        pts[i] = pts[i] + rng.normal(0, 0.4, pts[i].shape)
    init = CameraIntrinsics(7700, 7700, 360, 270, (0,) * 5, 720, 540)
    res = calibrate_intrinsics(pts, obj - [0.02, 0.014, 0], (720, 540), initial=init)
    assert sorted(res.rejected) == bad
    assert all("outlier view" in r for r in res.rejected.values())
    assert np.all(res.view_rms_px[bad] > 0.2) and np.all(np.delete(res.view_rms_px, bad) < 0.03)
    assert abs(res.intrinsics.fx / K[0, 0] - 1) < 5e-4
    with pytest.raises(ValueError, match="usable views"):
        calibrate_intrinsics(pts[:3], obj, (720, 540), initial=init)
    with pytest.raises(ValueError, match="image_points"):
        calibrate_intrinsics([np.zeros((3, 2))] * 5, obj[:3], (720, 540))
    with pytest.raises(ValueError, match="dist_model"):
        calibrate_intrinsics(pts, obj, (720, 540), dist_model="k9")


def test_symmetric_corner_refinement_against_simulator_truth():
    from calibration_tools.small_board import detect_board

    rig = load_rig("ideal")
    base = yaml.safe_load((SCENE_DIR / "checkerboard.yaml").read_text())
    sim = Simulator(rig, load_scene("checkerboard"), seed=1)
    raw_err, ref_err = [], []
    for k, rot in enumerate([[0.6, 0.0, 0.1], [0.42, 0.42, -0.2], [0.0, -0.6, 0.05]]):
        obj = dict(base["objects"][0], pose={"translation": [0.0, 0.0, 0.68],
                                            "rotation_vector": rot})
        scene = load_scene_text(yaml.safe_dump(dict(base, objects=[obj])))
        sim.set_scene(scene)
        f = sim.calibration_frame([0.0, 0.0, 0.0, 0.0], frame_index=k)
        truth = sim.project_points(scene.objects[0].feature_points()["world_points"],
                                   f.truth.angles)
        raw = detect_board(BOARD, f.image)
        corners = detect_target(f.image, BOARD)
        assert raw is not None and corners is not None
        j = np.linalg.norm(corners[:, None] - truth[None], axis=2).argmin(axis=1)
        assert len(set(j)) == len(j)
        raw_err.append(raw - truth[j])
        ref_err.append(corners - truth[j])
        # Same window as detect_target: a fixed point, reached again from 0.4 px away.
        side = np.median(np.linalg.norm(np.diff(corners.reshape(8, 11, 2), axis=1), axis=2))
        start = corners + np.random.default_rng(k).uniform(-0.4, 0.4, corners.shape)
        again = refine_corners_symmetric(f.image, start, max(2.0, 0.4 * side))
        np.testing.assert_allclose(again, corners, atol=2e-3)
    raw_e, ref_e = np.concatenate(raw_err), np.concatenate(ref_err)
    rms = np.sqrt(np.mean(ref_e**2))
    assert rms < 0.02 and np.abs(ref_e).max() < 0.08
    assert rms <= np.sqrt(np.mean(raw_e**2))  # no worse than OpenCV's corners
    assert np.abs(ref_e.mean(axis=0)).max() < 0.005  # and unbiased


def test_circle_grid_target_is_found_in_order_with_ellipse_centres():
    intr = CameraIntrinsics(7801.38, 7798.24, 359.51, 269.54, (0.0,) * 5, 720, 540)
    grid = CircleGrid(9, 7, 0.005, 0.0025)
    for k, rot in enumerate([[0.5, 0.1, 0.05], [-0.2, 0.5, -0.1]]):
        T = _pose(rot, [-0.02, -0.015, 0.70])
        view = render_target(intr, grid, T, rng=k)
        found = detect_target(view.image, grid)
        assert found is not None and found.shape == (63, 2)
        if np.linalg.norm(found[0] - view.uv[0]) > np.linalg.norm(found[0] - view.uv[-1]):
            found = found[::-1]
        np.testing.assert_allclose(found, view.uv, atol=0.05)
    assert detect_target(np.full((540, 720), 200, np.uint8), grid) is None


def test_stage_input_checks():
    cal = _nominal_calibration()
    with pytest.raises(ValueError, match="board"):
        run_intrinsics([], cal, board="checkerboard")
    with pytest.raises(ValueError, match="views with the target"):
        run_intrinsics([CaptureView(np.zeros((540, 720), np.uint8), np.zeros(4))], cal, BOARD)
    img = cv2.GaussianBlur(np.zeros((540, 720), np.uint8), (3, 3), 0)
    assert detect_target(img, BOARD) is None
