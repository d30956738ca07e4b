"""A calibrated model scored against the simulator's truth (no rclpy).

FOR TESTS AND BENCHMARKS ONLY: these figures need the simulated rig's physical description.
On a rig with imperfections no value of a model parameter (l, d, k, ...) is exact, so the
scores compare what the parameters are for: where the model puts pixels, virtual cameras and
laser planes, against where the simulated rig's physics puts them.
"""

from __future__ import annotations

import math

import numpy as np

#: Working volume of the scores: depth of the points along the view [m] and the image half
#: extent in normalised coordinates (the 60 x 45 mm view at 650 mm).
DEPTH = 0.65
HALF_VIEW = (0.046, 0.0345)


def true_v0_T_v(rig, u1_pan, u1_tilt) -> np.ndarray:
    """The simulated rig's exact ``V0_T_V`` (no jitter) at G1 voltages, shape (n, 4, 4)."""
    up = np.atleast_1d(np.asarray(u1_pan, dtype=np.float64))
    ut = np.atleast_1d(np.asarray(u1_tilt, dtype=np.float64))
    out = []
    for a, b in zip(up, ut, strict=True):
        th = rig.mirror_angles(rig.applied_voltages(np.array([a, b, 0.0, 0.0])))
        out.append(rig.V0_T_V(th[0], th[1]))
    return np.array(out)


def intrinsics_error_px(model, rig, n: int = 9) -> float:
    """RMS pixel distance between where the model's and the true camera put the same rays,
    over an n x n grid of rays spanning the image."""
    from reconstructor.model import CameraIntrinsics, project_points

    cam = rig.camera
    true = CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.distortion),
                            cam.width, cam.height)
    x = np.linspace(-cam.cx / cam.fx, (cam.width - cam.cx) / cam.fx, n)
    y = np.linspace(-cam.cy / cam.fy, (cam.height - cam.cy) / cam.fy, n)
    X, Y = np.meshgrid(x, y)
    rays = np.column_stack([X.ravel(), Y.ravel(), np.ones(X.size)])
    d = project_points(model.intrinsics, rays) - project_points(true, rays)
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))


def pointing_error_m(model, rig, voltages=None) -> float:
    """RMS distance, in V0, between the model's and the true position of points seen at
    650 mm (view centre and corners) over G1 voltages (default: the paper's 36 positions
    from -10 to 10 V in 4 V steps). Intrinsics play no part."""
    from calibration_tools.dynamic_camera import paper_grid
    from reconstructor.model import v0_T_v

    U = paper_grid() if voltages is None else np.asarray(voltages, dtype=np.float64)
    hx, hy = HALF_VIEW
    p_v = DEPTH * np.array([[0, 0, 1], [-hx, -hy, 1], [hx, -hy, 1], [-hx, hy, 1], [hx, hy, 1]])
    A = v0_T_v(model, U[:, 0], U[:, 1])
    B = true_v0_T_v(rig, U[:, 0], U[:, 1])
    pa = p_v @ np.swapaxes(A[:, :3, :3], 1, 2) + A[:, None, :3, 3]
    pb = p_v @ np.swapaxes(B[:, :3, :3], 1, 2) + B[:, None, :3, 3]
    return float(np.sqrt(np.mean(np.sum((pa - pb) ** 2, axis=2))))


def transfer_matrix_rmse_mm(model, rig, voltages=None) -> float:
    """The paper's Eq. 18-1 RMSE against the exact virtual-camera poses (36 positions)."""
    from calibration_tools.dynamic_camera import transfer_matrix_error

    return transfer_matrix_error(model, lambda a, b: true_v0_T_v(rig, a, b), voltages).rmse_mm


def _true_planes(rig, volts):
    from galvoscan_sim.spatial import invert_transform

    V0_T_G = invert_transform(rig.G_T_V0)
    out = []
    for u in volts:
        th = rig.mirror_angles(rig.applied_voltages(np.array([0.0, 0.0, 0.0, u])))
        pl = rig.laser_sheet_G(th[2], th[3]).transformed(V0_T_G).plane
        out.append(pl / np.linalg.norm(pl[:3]))
    return np.array(out)


def laser_plane_errors(model, rig) -> dict:
    """The model's U2 = 0 laser plane against the true one.

    Returns ``normal_deg`` (angle between the normals) and ``at_work_m`` (largest distance of
    the model's plane from points of the true plane at +-100 mm along the stripe, depth
    600..700 mm).
    """
    true = _true_planes(rig, [0.0])[0]
    pl = np.asarray(model.laser_plane_v0, dtype=np.float64)
    if pl[:3] @ true[:3] < 0:
        pl = -pl
    ang = math.degrees(math.atan2(np.linalg.norm(np.cross(pl[:3], true[:3])), pl[:3] @ true[:3]))
    return {'normal_deg': ang, 'at_work_m': _plane_gap(pl, true)}


def _plane_gap(pred, true) -> float:
    """Largest distance of plane ``pred`` from points of plane ``true`` at +-100 mm along the
    stripe (V0's x for a sheet from below or above the camera, y from beside it:
    ``galvoscan_common.stripe_layout``) and depth 600..700 mm [m]."""
    from galvoscan_common.stripe_layout import stripe_layout

    layout = stripe_layout(true, 1.0, 1.0)
    worst = 0.0
    for x in (-0.1, 0.0, 0.1):
        for z in (0.6, 0.65, 0.7):
            p = layout.point_on_plane(true, x, z)
            worst = max(worst, abs(pred[:3] @ p + pred[3]) / np.linalg.norm(pred[:3]))
    return worst


#: G2 tilt voltages of :func:`laser_sweep_error_m` [V].
SWEEP_VOLTS = tuple(float(u) for u in np.linspace(-4.0, 4.0, 17))


def laser_sweep_error_m(model, rig, volts=SWEEP_VOLTS) -> float:
    """Largest distance between the model's laser plane and the true one at G2 tilt voltages
    (default +-4 V), over points of the true plane at +-100 mm along the stripe, depth
    600..700 mm."""
    from reconstructor.model import laser_plane_v0

    worst = 0.0
    for u, true in zip(volts, _true_planes(rig, volts), strict=True):
        worst = max(worst, _plane_gap(np.asarray(laser_plane_v0(model, float(u))), true))
    return worst


def _kabsch_residual(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Residuals of P after the best rigid motion onto Q."""
    cp, cq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - cp).T @ (Q - cq))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return (P - cp) @ R.T + cq - Q


def reconstruction_errors(model, rig, *, span: float = 8.0, n: int = 5,
                          depth: float = 0.65, seed: int = 0) -> dict:
    """Triangulation of the true stripe pixels against the true surface points.

    A wall at ``depth`` is scanned at an n x n grid of G1 voltages over +-``span`` V; at each,
    G2 is set (with the model) so that the stripe crosses the view's centre. The simulator's
    exact stripe pixels (no extraction error) are triangulated with ``model`` (its joint
    correction included) at the DAC-quantised voltages and compared with the true points.

    Returns
    -------
    dict
        ``absolute_rms_m`` (in V0), ``aligned_rms_m`` (after the best rigid motion of all
        points together: the shape error, free of where V0 is), ``points``.
    """
    from galvoscan_sim import Simulator, load_scene_text
    from reconstructor.model import triangulate, v0_T_v
    from reconstructor.planning import laser_through

    wall = (f'format_version: 1\nname: score_wall\nobjects:\n  - type: plane\n'
            f'    name: wall\n    pose: {{translation: [0.0, 0.0, {float(depth)}]}}\n'
            f'    albedo: 0.5\n')
    sim = Simulator(rig, load_scene_text(wall), seed=seed)
    pred, true = [], []
    grid = np.linspace(-span, span, n)
    for up in grid:
        for ut in grid:
            T = v0_T_v(model, up, ut)
            ray, o = T[:3, 2], T[:3, 3]
            try:  # the plane through the view centre
                u2 = laser_through(model, o + (depth - o[2]) / ray[2] * ray, max_abs_u=9.9)
            except ValueError:
                continue  # no sheet reaches it: nothing to score there
            q = rig.dac.quantize(np.array([up, ut, 0.0, u2]))
            st = sim.render(q).truth.stripe
            if len(st) == 0:
                continue
            res = triangulate(model, np.column_stack([st.u, st.v]), q[0], q[1], q[3])
            pred.append(res.p_v0[res.valid])
            true.append(st.points_V0[res.valid])
    P, Q = np.concatenate(pred), np.concatenate(true)
    rms = float(np.sqrt(np.mean(np.sum((P - Q) ** 2, axis=1))))
    aligned = _kabsch_residual(P, Q)
    return {'absolute_rms_m': rms,
            'aligned_rms_m': float(np.sqrt(np.mean(np.sum(aligned ** 2, axis=1)))),
            'points': int(len(P))}


def scores(model, rig) -> dict:
    """All scores of a model (SI units, names carry the unit)."""
    import dataclasses

    lp = laser_plane_errors(model, rig)
    rec = reconstruction_errors(model, rig)
    plain = reconstruction_errors(dataclasses.replace(model, correction=None), rig)
    return {
        'reconstruction_rms_m': rec['absolute_rms_m'],
        'reconstruction_shape_rms_m': rec['aligned_rms_m'],
        'reconstruction_rms_without_joint_m': plain['absolute_rms_m'],
        'intrinsics_rms_px': intrinsics_error_px(model, rig),
        'fx_rel_error': model.intrinsics.fx / rig.camera.fx - 1.0,
        'pointing_rms_m': pointing_error_m(model, rig),
        'transfer_matrix_rmse_mm': transfer_matrix_rmse_mm(model, rig),
        'laser_plane_normal_deg': lp['normal_deg'],
        'laser_plane_at_work_m': lp['at_work_m'],
        'laser_sweep_max_m': laser_sweep_error_m(model, rig),
    }


def stripe_point_errors(model, views, truths) -> np.ndarray:
    """Distances [m] of each view's reconstructed stripe points from the simulator's true
    points (matched by column, within 2 px in v).

    Parameters
    ----------
    views : sequence of CaptureView
        Laser-on views; the stripe is extracted with the default extractor settings.
    truths : sequence of FrameTruth
        The simulator's truth of each view.
    """
    from reconstructor.model import triangulate
    from stripe_extractor.extractor import extract

    out = []
    for view, truth in zip(views, truths, strict=True):
        s = extract(view.image)
        uv = np.column_stack([s.u, s.v]).astype(np.float64)
        res = triangulate(model, uv, *view.voltages[[0, 1, 3]])
        for k in np.flatnonzero(res.valid):
            same = np.flatnonzero(truth.stripe.column == round(uv[k, 0]))
            if same.size:
                j = same[np.argmin(np.abs(truth.stripe.v[same] - uv[k, 1]))]
                if abs(truth.stripe.v[j] - uv[k, 1]) < 2.0:
                    out.append(np.linalg.norm(res.p_v0[k] - truth.stripe.points_V0[j]))
    return np.array(out)
