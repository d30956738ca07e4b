"""Dynamic-camera calibration: l, d (and the G1 gains) from circle-board views (no rclpy).

docs/design.md section 3 step 2 and the paper's section III (Eqs. 9-16, 18-1):

1. Detect and identify the circles of every view (:mod:`calibration_tools.circle_board`),
   refining the model while identifying (:func:`identify_views`), so that the final
   verification of every view runs against an accurate model.
2. PnP per view gives the measured ``Vn_T_W``; with a reference view r,
   ``Vr_T_Vn = Vr_T_W @ inv(Vn_T_W)`` is measured. In the model,
   ``Vr_T_Vn = inv(G_T_V(θr)) @ G_T_V(θn)`` whose translation is linear in (l, d): the
   paper's Eq. 16 is the linear least-squares problem :func:`solve_l_d_linear`.
3. :func:`refine` minimises the reprojection error of all identified circles over all views
   (scipy ``least_squares``): l, d, optionally k and θ0 of the G1 mirrors, and the board
   pose(s). The model predicts ellipse centres, as the detector measures them.
4. :func:`transfer_matrix_error`: the paper's Eq. 18-1 comparison of model transfer
   matrices ``Vn_T_V0`` with true or measured ones at 36 G1 positions (-10..10 V, 4 V steps).

``g1_tilt.theta0`` is never refined: it is unobservable from views (see
:mod:`calibration_tools.board_fit`).

Gauge. A shift of the principal point along x is a rotation of the
camera about the pan axis, which ``g1_pan.theta0`` takes up exactly (half the angle: a
mirror doubles it): the views cannot tell them apart, so the two must not both be free.
The stage holds the intrinsics as the intrinsics stage pinned them (its lens prior, see
:mod:`calibration_tools.intrinsics`) and refines θ0; on the reference rig, seeds 0 and 7 had
moved cx by 3.6 px and θ0 by 0.24 mrad with it. The standard errors of the stage
(``StageResult.standard_errors``) are those of the reprojection fit (board poses included)
plus the stored standard errors of the held intrinsics propagated through the solution
(:func:`intrinsics_standard_errors`), so θ0's carries the principal point's uncertainty.

The building blocks live in :mod:`.circle_board`
(detection, one-view identification), :mod:`.board_identify` (all views),
:mod:`.board_fit` (PnP, refinement) and are re-exported here.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from reconstructor.model import MODEL_KINDS, RigModel, g_T_v, rigid_inverse, v0_T_v
from reconstructor.planning import aim_g1

from .board_fit import (
    RefineResult,
    ViewObservation,
    _as_transform,
    _rotation_angle,
    _transform,
    g1_frame_noise,
    pnp_view,
    refine,
)
from .board_identify import (
    IdentificationResult,
    _observations,
    board_pose_from_views,
    identify_views,
)
from .board_layout import PAPER_CIRCLE_BOARD, CircleBoard
from .circle_board import CircleDetections, detect_circles
from .stages import CaptureView, StageResult

#: The Galvanometer-1 deviations of the physical model (``reconstructor.geometry.physical``)
#: and the mounting tolerance of each (1 sigma of a careful build; SI units). A deviation is
#: freed only when the views pin it to better than ``OBSERVABLE_FRACTION`` of its tolerance.
G1_PHYSICAL_TOLERANCES = {
    "camera_rotation[0]": 2e-3, "camera_rotation[1]": 2e-3, "camera_rotation[2]": 2e-3,
    "camera_offset[0]": 5e-4, "camera_offset[1]": 5e-4, "g1_axes_angle": 1e-3,
    "g1_pan_surface_offset": 3e-4, "g1_pan_normal_tilt": 1e-3,
    "g1_tilt_surface_offset": 3e-4, "g1_tilt_normal_tilt": 1e-3,
}
OBSERVABLE_FRACTION = 0.3
#: Intrinsics the physical fit refines with the mirrors. Once the model can represent the
#: mirrors, the board's ~60 degrees of view directions pin the pinhole far better than the
#: intrinsics stage's 5-degree views (on the reference rig the principal point's error fell
#: from (-1.5, 3.4) px to (1.0, 1.5) px and the transfer rotation error from 0.012 to
#: 0.006 deg); k2 stays with the lens prior (freed it went to 26 against a true 4). The
#: camera's pan and tilt on its mount, which the principal point stands for, are then held.
PHYSICAL_INTRINSICS = ("fx", "fy", "cx", "cy")

#: The paper's verification grid: -10 V to 10 V in 4 V steps on both G1 axes (36 positions).
PAPER_GRID_VOLTAGES = np.arange(-10.0, 10.0 + 1e-9, 4.0)


def paper_grid() -> np.ndarray:
    """The paper's 36 G1 positions, shape (36, 2), volts: (U1_pan, U1_tilt)."""
    up, ut = np.meshgrid(PAPER_GRID_VOLTAGES, PAPER_GRID_VOLTAGES, indexing="ij")
    return np.column_stack([up.ravel(), ut.ravel()])


# ------------------------------------------------------------------------------ Eq. 16
@dataclass(frozen=True)
class LinearLD:
    """Result of :func:`solve_l_d_linear`.

    Attributes
    ----------
    l, d : float, metres
    translation_rms_m : float
        RMS of the translation residuals of Eq. 16, metres.
    rotation_rms_rad : float
        RMS angle between measured and model rotations (independent of l and d; shows how
        well the mirror angles fit), radians.
    n_views : int
    """

    l: float
    d: float
    translation_rms_m: float
    rotation_rms_rad: float
    n_views: int


def solve_l_d_linear(theta_pan, theta_tilt, Vr_T_Vn, theta_ref) -> LinearLD:
    """The paper's Eq. 16: l and d by linear least squares on measured transfer translations.

    The model ``Vr_T_Vn = inv(G_T_V(θr; l, d)) @ G_T_V(θn; l, d)`` has a rotation that does
    not depend on (l, d) and a translation that is linear in them; stacking the three
    translation equations of every view gives an (3n x 2) least-squares problem.

    Parameters
    ----------
    theta_pan, theta_tilt : array_like, shape (n,), radians
        G1 mirror angles θ1, θ2 of each view.
    Vr_T_Vn : array_like, shape (n, 4, 4), metres
        Measured transforms from view n to its reference view r (e.g. from board PnP:
        ``Vr_T_W @ inv(Vn_T_W)``).
    theta_ref : array_like, shape (2,) or (n, 2), radians
        Mirror angles (θ1, θ2) of the reference view(s) (π/4, π/4 for V0).

    Returns
    -------
    LinearLD
    """
    tp = np.asarray(theta_pan, dtype=np.float64)
    tt = np.asarray(theta_tilt, dtype=np.float64)
    if tp.ndim != 1 or tt.shape != tp.shape:
        raise ValueError(f"theta_pan and theta_tilt must have one shape (n,), got {tp.shape}, "
                         f"{tt.shape}")
    n = len(tp)
    T = np.asarray(Vr_T_Vn, dtype=np.float64)
    if T.shape != (n, 4, 4):
        raise ValueError(f"Vr_T_Vn must have shape ({n}, 4, 4), got {T.shape}")
    ref = np.asarray(theta_ref, dtype=np.float64)
    if ref.shape == (2,):
        ref = np.broadcast_to(ref, (n, 2))
    if ref.shape != (n, 2):
        raise ValueError(f"theta_ref must have shape (2,) or ({n}, 2), got {ref.shape}")
    if n < 1 or not (np.isfinite(tp).all() and np.isfinite(tt).all() and np.isfinite(T).all()):
        raise ValueError("need at least one view with finite angles and transforms")

    def model_T(l, d):
        return rigid_inverse(g_T_v(ref[:, 0], ref[:, 1], l, d)) @ g_T_v(tp, tt, l, d)

    a = model_T(1.0, 0.0)[:, :3, 3]
    b = model_T(0.0, 1.0)[:, :3, 3]
    A = np.stack([a.ravel(), b.ravel()], axis=1)
    y = T[:, :3, 3].ravel()
    if np.linalg.matrix_rank(A) < 2:
        raise ValueError("views do not constrain l and d (need G1 motion on both axes)")
    (l, d), *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ np.array([l, d])
    Rm = model_T(l, d)[:, :3, :3]
    ang = _rotation_angle(np.swapaxes(Rm, -1, -2) @ T[:, :3, :3])
    return LinearLD(
        float(l),
        float(d),
        float(np.sqrt(np.mean(res.reshape(n, 3) ** 2) * 3.0)),
        float(np.sqrt(np.mean(ang**2))),
        n,
    )


# ------------------------------------------------------------------------------ Eq. 18-1
@dataclass(frozen=True)
class TransferMatrixError:
    """The paper's transfer-matrix comparison (Eq. 18-1).

    Attributes
    ----------
    voltages : ndarray, shape (n, 2), volts
    error_mm : ndarray, shape (n,)
        ``E(A, B) = ||A - B||_F`` of the 4x4 ``Vn_T_V0`` matrices with the translation
        column in millimetres, as in the paper (rotation entries are dimensionless).
    rmse_mm : float
        Root mean square of ``error_mm``.
    translation_error_m : ndarray, shape (n,), metres
    rotation_error_rad : ndarray, shape (n,), radians
    """

    voltages: np.ndarray
    error_mm: np.ndarray
    rmse_mm: float
    translation_error_m: np.ndarray
    rotation_error_rad: np.ndarray

    @property
    def translation_rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.translation_error_m**2)))

    @property
    def rotation_rmse_rad(self) -> float:
        return float(np.sqrt(np.mean(self.rotation_error_rad**2)))


def transfer_matrix_error(model_est: RigModel, reference, voltages=None) -> TransferMatrixError:
    """Compare the model's transfer matrices with true or measured ones (paper Eq. 18-1).

    Parameters
    ----------
    model_est : RigModel
        Calibrated model (matrices A).
    reference : RigModel, callable or array_like
        Matrices B: a RigModel (e.g. the simulator's true equivalent model), a callable
        ``f(u1_pan, u1_tilt) -> V0_T_V`` taking arrays of shape (n,) and returning
        shape (n, 4, 4) (e.g. the simulator's exact virtual-camera poses), or an array of
        measured ``Vn_T_V0`` of shape (n, 4, 4), metres (the paper's measured matrices).
    voltages : array_like, shape (n, 2), volts, optional
        G1 positions; default :func:`paper_grid` (36 positions, -10..10 V in 4 V steps).

    Returns
    -------
    TransferMatrixError
    """
    U = paper_grid() if voltages is None else np.asarray(voltages, dtype=np.float64)
    if U.ndim != 2 or U.shape[1] != 2 or not np.isfinite(U).all():
        raise ValueError(f"voltages must have shape (n, 2) and be finite, got {U.shape}")
    A = rigid_inverse(v0_T_v(model_est, U[:, 0], U[:, 1]))
    if isinstance(reference, RigModel):
        B = rigid_inverse(v0_T_v(reference, U[:, 0], U[:, 1]))
    elif callable(reference):
        B0 = np.asarray(reference(U[:, 0], U[:, 1]), dtype=np.float64)
        if B0.shape != (len(U), 4, 4):
            raise ValueError(f"reference() must return shape ({len(U)}, 4, 4), got {B0.shape}")
        B = rigid_inverse(B0)
    else:
        B = np.asarray(reference, dtype=np.float64)
        if B.shape != (len(U), 4, 4):
            raise ValueError(f"reference must have shape ({len(U)}, 4, 4), got {B.shape}")
    D = A - B
    D[:, :3, 3] *= 1000.0
    err = np.sqrt(np.sum(D**2, axis=(1, 2)))
    # Translation of the V0 origin seen from Vn, and the rotation angle between A and B.
    terr = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    rerr = _rotation_angle(np.swapaxes(A[:, :3, :3], -1, -2) @ B[:, :3, :3])
    return TransferMatrixError(U, err, float(np.sqrt(np.mean(err**2))), terr, rerr)


# ------------------------------------------------------------------------------ the stage
def default_board_pose(distance: float) -> np.ndarray:
    """``V0_T_W`` of a board facing V0 with its centre circle on the V0 optical axis.

    Parameters
    ----------
    distance : float, metres

    Returns
    -------
    ndarray, shape (4, 4)
    """
    if not 0.05 < float(distance) < 20.0:
        raise ValueError(f"distance must be in metres (0.05..20), got {distance}")
    return _transform(np.eye(3), [0.0, 0.0, float(distance)])


def anchor_voltages(model: RigModel, board: CircleBoard, V0_T_W, *,
                    max_abs_u: float = 10.0) -> np.ndarray:
    """Voltages that centre each reachable large (15 mm) circle of a board placement.

    Capture a few of these per board pose: identification needs ``min_anchors`` views with
    a large circle. With nominal values the aim is good to a few millimetres, well inside a
    view (~60 x 45 mm).

    Parameters
    ----------
    model : RigModel
    board : CircleBoard
    V0_T_W : array_like, shape (4, 4)
        Nominal board placement in V0, metres.
    max_abs_u : float, volts

    Returns
    -------
    ndarray, shape (m, 2), volts
        Reachable targets only, nearest to U1 = 0 first.
    """
    T = _as_transform(V0_T_W, "V0_T_W")
    big = np.flatnonzero(board.is_large(np.arange(board.n_circles)))
    pts = board.points(big) @ T[:3, :3].T + T[:3, 3]
    u = aim_g1(model, pts, max_abs_u=max_abs_u)
    u = u[np.isfinite(u).all(axis=1)]
    return u[np.argsort(np.abs(u).sum(axis=1))]


def _estimate_distance(model, board, dets, U) -> float | None:
    """Board distance along the V0 axis from the apparent pitch of the view nearest U = 0."""
    order = np.argsort(np.abs(U).sum(axis=1))
    for i in order:
        c = dets[i].centres
        if len(c) >= 2:
            dist = np.linalg.norm(c[:, None] - c[None], axis=2)
            dist[dist == 0] = np.inf
            pitch_px = float(np.median(dist.min(axis=1)))
            return model.intrinsics.fx * board.pitch / pitch_px
        if len(c) == 1:
            r = board.small_diameter / 2.0
            if dets[i].large[0] and dets[i].size_known[0]:
                r = board.large_diameter / 2.0
            return model.intrinsics.fx * r / float(dets[i].radii[0])
    return None


def _linear_l_d(obs, pnp, model, U, max_rotation_deg: float = 0.2):
    """Eq. 16 over PnP-measured transfers; reference: the view nearest U1 = 0 of each pose.

    Views whose measured rotation disagrees with the model's by more than
    ``max_rotation_deg`` (a PnP that went wrong; the rotation does not depend on l and d)
    are left out. Returns (LinearLD or None, notes).
    """
    notes = []
    rows = []
    for p in sorted({o.pose_index for o in obs}):
        ids_p = [o.view_id for o in obs if o.pose_index == p and o.view_id in pnp]
        if len(ids_p) < 3:
            continue
        r = min(ids_p, key=lambda j: float(np.abs(U[j]).sum()))
        rows += [(j, r, pnp[r] @ rigid_inverse(pnp[j])) for j in ids_p if j != r]
    if len(rows) < 2:
        return None, ["Eq. 16: fewer than 2 PnP views per pose"]
    j_, r_ = np.array([j for j, _, _ in rows]), np.array([r for _, r, _ in rows])
    th_p, th_t = model.g1_pan.angle(U[j_, 0]), model.g1_tilt.angle(U[j_, 1])
    th_r = np.column_stack([model.g1_pan.angle(U[r_, 0]), model.g1_tilt.angle(U[r_, 1])])
    T = np.stack([t for _, _, t in rows])
    Rm = rigid_inverse(g_T_v(th_r[:, 0], th_r[:, 1], model.l, model.d)) @ g_T_v(
        th_p, th_t, model.l, model.d
    )
    ang = np.degrees(_rotation_angle(np.swapaxes(Rm[:, :3, :3], -1, -2) @ T[:, :3, :3]))
    ok = ang <= max_rotation_deg
    for j, a in zip(j_[~ok], ang[~ok], strict=True):
        notes.append(f"Eq. 16: view {j} left out, PnP rotation off by {a:.2f} deg")
    if ok.sum() < 2:
        return None, notes + ["Eq. 16: fewer than 2 consistent PnP views"]
    try:
        return solve_l_d_linear(th_p[ok], th_t[ok], T[ok], th_r[ok]), notes
    except ValueError as exc:
        return None, notes + [f"Eq. 16: {exc}"]


def run_dynamic_camera(
    views: Sequence[CaptureView],
    calibration,
    board: CircleBoard = PAPER_CIRCLE_BOARD,
    *,
    board_pose=None,
    refine_mirrors: bool = True,
    refine_theta0: bool = True,
    refine_poly: int = 0,
    refine_intrinsics: Sequence[str] = (),
    model: str = "paper",
    min_circles: int = 2,
    dark_circles: bool = True,
    max_offset_pitch: float = 0.25,
    verify_floor_px: float = 2.0,
    min_anchors: int = 2,
    progress: Callable | None = None,
) -> StageResult:
    """Calibrate the dynamic camera (l, d and optionally the G1 gains) from circle-board views.

    Parameters
    ----------
    views : sequence of CaptureView
        Board frames at many G1 voltages (laser off); ``pose_index`` groups frames of one
        board placement.
    calibration : reconstructor.calibration_file.Calibration
        Current calibration: calibrated intrinsics and nominal l, d, k, θ0.
    board : CircleBoard
    board_pose : ndarray shape (4, 4), or dict of int to ndarray shape (4, 4), optional
        Approximate ``V0_T_W`` per board pose, metres. Default: the board faces V0 with its
        centre circle on the V0 optical axis, at the distance its apparent pitch implies.
        Absolute circle labels need the position right to within ~3 pitches (60 mm).
    refine_mirrors, refine_theta0, refine_poly
        As :func:`refine`.
    refine_intrinsics : sequence of str
        Pinhole intrinsics to refine jointly in the final fit, any of fx, fy, cx, cy
        (distortion always stays as the intrinsics stage found it). Off by default. On a
        rig that matches the model (the simulator's ideal rig) the ~60 degrees of view
        directions of the large board pin them far better than Zhang's 5-degree views and
        remove the ~0.2 mm bias of l that Zhang-sized errors cause. On the reference rig the
        freedom absorbs mechanical imperfections instead (cx moved 39 px; cx and θ0 trade,
        module docstring), and the transfer matrices got worse, hence off.
    model : str
        ``'paper'``: the paper's model (l, d, ideal mirrors). ``'physical'``: the physical
        mirror model; its Galvanometer-1 deviations (:data:`G1_PHYSICAL_TOLERANCES`) are
        refined jointly in the final fit with the intrinsics ``refine_intrinsics`` names
        (default :data:`PHYSICAL_INTRINSICS`), each only where the views determine it
        (:func:`fit_observable`); the rest keep their starting value (zero from the paper's
        model) and ``extra['dynamic_camera']['physical_fixed']`` says why.
    min_circles : int
        Views with fewer complete circles are rejected.
    dark_circles : bool
        Circles darker than the board.
    max_offset_pitch, verify_floor_px, min_anchors
        As :func:`identify_views` (capture at least ``min_anchors`` views showing a 15 mm
        circle for every board pose).
    progress : callable, optional
        ``progress(done, total, message)``.

    Returns
    -------
    StageResult
        ``updates``: l, d, and (when refined) ``g1_pan.k``, ``g1_pan.theta0``,
        ``g1_tilt.k`` (and poly), ``intrinsics`` fx, fy, cx, cy (when refined).
        ``residuals``: ``reprojection_rms_px``, ``reprojection_max_px``,
        ``linear_translation_rms_m`` (Eq. 16), ``transfer_translation_rms_m`` and
        ``transfer_rotation_rms_rad`` (model vs PnP-measured transfer matrices).
        ``extra['dynamic_camera']``: Eq. 16 (l, d), board poses, the paper's Eq. 18-1 RMSE
        in mm against the measured matrices, per accepted view its circle labels and
        centres. ``standard_errors``: keyed as ``updates`` (module docstring, Gauge).
    """
    if not isinstance(board, CircleBoard):
        raise ValueError("board must be a CircleBoard")
    if min_circles < 1:
        raise ValueError(f"min_circles must be >= 1, got {min_circles}")
    if model not in MODEL_KINDS:
        raise ValueError(f"model must be one of {', '.join(MODEL_KINDS)}, got {model!r}")
    model0: RigModel = calibration.model
    if model == "paper":  # the paper's method as published: no physical deviations
        model0 = dataclasses.replace(model0, physical=None)
    elif not refine_intrinsics:
        refine_intrinsics = PHYSICAL_INTRINSICS
    intr, input_std = model0.intrinsics, intrinsics_standard_errors(calibration)
    det = _detect_views(views, intr, min_circles, dark_circles, progress)
    dets, U, pidx = det.dets, det.U, det.pidx
    poses = _prior_board_poses(board_pose, model0, board, dets, U, pidx)
    refine_kw = dict(refine_mirrors=refine_mirrors, refine_theta0=refine_theta0,
                     refine_poly=refine_poly)
    ident = identify_views(
        dets, U, model0, board, poses, pose_index=pidx, **refine_kw,
        max_offset_pitch=max_offset_pitch, verify_floor_px=verify_floor_px,
        min_anchors=min_anchors, progress=progress,
    )
    accepted = _accepted_views(ident, det)
    obs = _observations(ident.views, dets, U, pidx, accepted)

    # Eq. 16 on PnP-measured transfers (reference: the view nearest U1 = 0 of each pose).
    pnp = _pnp_transfers(intr, board, obs)
    lin, lin_notes = _linear_l_d(obs, pnp, ident.model, U)
    if progress is not None:
        progress(1, 1, "final refinement")
    fit_kw = dict(refine_intrinsics=refine_intrinsics, input_std=input_std, **refine_kw)
    physical_fixed = {}
    if model == "physical":
        fin, physical_fixed, refine_intrinsics = observable_physical_fit(
            ident, lin, obs, board, **fit_kw)
    else:
        fin = _final_fit(ident, lin, obs, board, **fit_kw)
    residuals, extra = _fit_figures(fin, ident, lin, lin_notes, det.keep, obs)
    residuals.update(g1_frame_noise(fin, obs, board))
    if model == "physical":
        extra["physical_fixed"] = physical_fixed
        extra["physical_freed"] = [n for n in G1_PHYSICAL_TOLERANCES
                                   if f"physical.{n}" not in physical_fixed] + [
            f"intrinsics.{n}" for n in refine_intrinsics]
    if refine_intrinsics:  # PnP again with the final intrinsics
        pnp = _pnp_transfers(fin.model.intrinsics, board, obs, only=pnp)
    _verify_transfers(fin.model, fin, obs, pnp, U, residuals, extra)
    updates = _stage_updates(fin.model, refine_intrinsics=refine_intrinsics, **refine_kw)
    if model == "physical":
        updates["model"] = "physical"
        updates["physical"] = fin.model.physical.to_dict()
    elif calibration.model.physical is not None:
        updates["model"] = "paper"
    return StageResult(
        stage="dynamic_camera", residuals=residuals, rejected=det.rejected, updates=updates,
        samples_used=len(accepted), samples_rejected=len(views) - len(accepted),
        extra={"dynamic_camera": {**extra, "intrinsics_standard_errors_held": input_std}},
        standard_errors=_stage_errors(updates, fin.std),
        covariance=fin.covariance,
    )


def intrinsics_standard_errors(calibration) -> dict:
    """Standard errors of the calibrated intrinsics, as the intrinsics stage stored them.

    Parameters
    ----------
    calibration : reconstructor.calibration_file.Calibration

    Returns
    -------
    dict of str to float
        ``fx``, ``fy``, ``cx``, ``cy`` [px] and ``dist[j]`` [1] (those > 0); empty when the
        calibration holds none (e.g. design values).
    """
    stored = (calibration.stages.get("intrinsics") or {}).get("standard_errors") or {}
    out = {}
    for key, value in stored.items():
        name = key.removeprefix("intrinsics.")
        if name in ("fx", "fy", "cx", "cy") and float(value) > 0:
            out[name] = float(value)
        elif name == "dist":
            out.update({f"dist[{j}]": float(v) for j, v in enumerate(value) if float(v) > 0})
    return out


def _stage_errors(updates: dict, std: dict) -> dict:
    """The refinement's standard errors keyed as the stage's ``updates`` (lists as lists)."""
    out: dict = {}
    for key, value in updates.items():
        if isinstance(value, dict):
            sub = {k: (std.get(f"{key}.{k}") if not isinstance(v, list) else
                       [std.get(f"{key}.{k}[{j}]", 0.0) for j in range(len(v))])
                   for k, v in value.items()}
            out[key] = {k: v for k, v in sub.items() if v is not None}
        elif key in std:
            out[key] = std[key]
    return out


def _accepted_views(ident, det) -> list[int]:
    """Indices (into the detections) of the identified views; the others go to rejected."""
    accepted = [j for j, vid in enumerate(ident.views) if vid.accepted]
    for j, vid in enumerate(ident.views):
        if not vid.accepted:
            v = det.U[j]
            det.rejected.append(
                f"view {det.keep[j]} (U1 = {v[0]:+.3f}, {v[1]:+.3f} V): {vid.reason}")
    if len(accepted) < 6:
        raise ValueError(f"dynamic_camera: only {len(accepted)} views identified; need 6 "
                         f"({'; '.join(ident.log[-3:])})")
    return accepted


def _fit_figures(fin, ident, lin, lin_notes, keep, obs) -> tuple[dict, dict]:
    """The stage's residuals and its ``extra['dynamic_camera']`` from the final fit."""
    res = np.concatenate(fin.residuals_px)
    residuals = {
        "reprojection_rms_px": fin.rms_px,
        "reprojection_max_px": float(np.max(np.linalg.norm(res, axis=1))),
    }
    extra = {
        "board_poses_V0_T_W": {int(k): np.asarray(v).tolist() for k, v in fin.board_poses.items()},
        "std": dict(fin.std),
        "identification_verify_px": ident.verify_px,
        "identification_log": list(ident.log) + lin_notes,
        # Input view index -> board circle index and detected centre (px) of its circles.
        "labels": {keep[o.view_id]: o.index.tolist() for o in obs},
        "centres_px": {keep[o.view_id]: o.uv.tolist() for o in obs},
    }
    if lin is not None:
        residuals["linear_translation_rms_m"] = lin.translation_rms_m
        extra["linear_l_m"] = lin.l
        extra["linear_d_m"] = lin.d
    return residuals, extra


@dataclass
class _Detections:
    """Circle detections of the usable views (input index ``keep``), and why others were not."""

    dets: list
    keep: list
    U: np.ndarray  # shape (n, 2), volts
    pidx: np.ndarray  # shape (n,), pose index
    rejected: list


def _detect_views(views, intr, min_circles, dark_circles, progress) -> _Detections:
    """Detect the circles of every laser-off view of the right size; reject the rest."""
    rejected: list[str] = []
    dets: list[CircleDetections] = []
    keep: list[int] = []
    volts: list[np.ndarray] = []
    pose_idx: list[int] = []
    total = len(views)
    for i, view in enumerate(views):
        v = np.asarray(view.voltages, dtype=np.float64)
        label = f"view {i}"
        if v.shape != (4,) or not np.isfinite(v).all():
            rejected.append(f"{label}: voltages must be 4 finite values")
            continue
        label = f"view {i} (U1 = {v[0]:+.3f}, {v[1]:+.3f} V)"
        if view.laser_on:
            rejected.append(f"{label}: laser on")
            continue
        img = np.asarray(view.image)
        if img.ndim != 2 or img.shape != (intr.height, intr.width):
            rejected.append(f"{label}: image shape {img.shape} does not match the intrinsics")
            continue
        det = detect_circles(img, dark_circles=dark_circles)
        if len(det) < min_circles:
            rejected.append(f"{label}: {len(det)} complete circle(s), need {min_circles}")
            continue
        dets.append(det)
        keep.append(i)
        volts.append(v[:2])
        pose_idx.append(int(view.pose_index))
        if progress is not None and (i % 10 == 0 or i == total - 1):
            progress(i + 1, total, "detecting circles")
    if len(dets) < 3:
        raise ValueError(f"dynamic_camera: only {len(dets)} usable views; need at least 3 "
                         f"({len(rejected)} rejected: {'; '.join(rejected[:5])})")
    return _Detections(dets, keep, np.array(volts).reshape(-1, 2),
                       np.array(pose_idx, dtype=np.int64), rejected)


def _prior_board_poses(board_pose, model0, board, dets, U, pidx) -> dict:
    """``V0_T_W`` prior per board pose: as given, or facing V0 at the apparent distance."""
    if board_pose is None:
        poses = {}
        for p in sorted(set(pidx.tolist())):
            sel = np.flatnonzero(pidx == p)
            z = _estimate_distance(model0, board, [dets[j] for j in sel], U[sel])
            poses[p] = default_board_pose(z if z is not None else 0.65)
        return poses
    if isinstance(board_pose, dict):
        return {int(k): _as_transform(v, f"board_pose[{k}]") for k, v in board_pose.items()}
    T = _as_transform(board_pose, "board_pose")
    return {p: T.copy() for p in set(pidx.tolist())}


def _pnp_transfers(intrinsics, board, obs, only=None) -> dict:
    """PnP ``Vn_T_W`` of every observation with >= 4 circles (or of those in ``only``)."""
    pnp: dict[int, np.ndarray] = {}
    for o in obs:
        if (only is None and len(o.index) < 4) or (only is not None and o.view_id not in only):
            continue
        try:
            T, _ = pnp_view(intrinsics, board.points(o.index), board.radius(o.index), o.uv)
        except ValueError:
            continue
        pnp[o.view_id] = T
    return pnp


def _final_fit(ident, lin, obs, board, **refine_kw):
    """Bundle refinement from the Eq. 16 (l, d) when plausible, else the identification's.

    If the Eq. 16 start led elsewhere than the identification's model, keep the better fit.
    """
    m_id = ident.model
    start = m_id
    if lin is not None and 0.0 < lin.l < 1.0 and 0.0 < lin.d < 1.0:
        start = dataclasses.replace(m_id, l=lin.l, d=lin.d)
    poses = {p: ident.board_poses[p] for p in sorted({o.pose_index for o in obs})}
    fin = refine(start, obs, board, poses, **refine_kw)
    alt = refine(m_id, obs, board, poses, **refine_kw) if start is not m_id else fin
    return alt if alt.rms_px < fin.rms_px - 1e-9 else fin


def observable_physical_fit(ident, lin, obs, board, *, refine_intrinsics=(), input_std=None,
                            **fit_kw):
    """The final fit with every G1 deviation of the physical model that the views determine
    (:func:`fit_observable`), started from the paper model's final fit (its l, d, responses
    and board poses).

    ``refine_intrinsics`` are freed only where these views determine them better than the
    intrinsics stage did (standard error below the stored one, ``input_std``); the camera's
    pan and tilt on its mount, which the principal point then stands for, are held. Returns
    the fit and ``{name: reason}`` of every held deviation or intrinsic.
    """
    input_std = input_std or {}
    paper = _final_fit(ident, lin, obs, board, input_std=input_std, **fit_kw)
    poses = paper.board_poses
    intr = list(refine_intrinsics)
    held_intr: dict = {}
    tolerances = dict(G1_PHYSICAL_TOLERANCES)
    if intr:
        gauge = ("camera_rotation[0]", "camera_rotation[1]")
        trial = refine(paper.model, obs, board, poses, input_std=input_std,
                       refine_intrinsics=intr,
                       refine_physical=[n for n in tolerances if n not in gauge], **fit_kw)
        for name in list(intr):
            sd, before = trial.precision.get(f"intrinsics.{name}", math.inf), input_std.get(name)
            if before is None or not sd < before:
                intr.remove(name)
                held_intr[f"intrinsics.{name}"] = (
                    f"held as the intrinsics stage left it: these views give a standard error "
                    f"of {sd:.3g}, the stage had {before if before is not None else 'none'}")
        if {"cx", "cy"} & set(intr):
            for n in gauge:
                del tolerances[n]
                held_intr[f"physical.{n}"] = ("held: the principal point, refined here, stands "
                                              "for the camera's pan and tilt on its mount")
    def priors(free=()):  # held deviations: their tolerance enters the covariance record
        return {f"physical.{n}": t for n, t in G1_PHYSICAL_TOLERANCES.items() if n not in free}

    fin, held = fit_observable(
        lambda free: refine(paper.model, obs, board, poses, refine_physical=free,
                            refine_intrinsics=intr, input_std=input_std,
                            held_priors=priors(free), **fit_kw),
        lambda: refine(paper.model, obs, board, poses, refine_intrinsics=intr,
                       input_std=input_std, held_priors=priors(), **fit_kw),
        tolerances)
    return fin, {**held_intr, **{f"physical.{n}": why for n, why in held.items()}}, intr


def fit_observable(fit, fit_without, tolerances=None, fraction: float = OBSERVABLE_FRACTION):
    """Free the physical deviations the data determine, hold the rest where they start.

    All candidates (``tolerances``' keys, default :data:`G1_PHYSICAL_TOLERANCES`) are freed;
    those whose standard error (board poses free, the held intrinsics' uncertainty
    propagated; every circle one sample, :attr:`RefineResult.precision`, as ``fraction``
    was set for) exceeds ``fraction`` of their mounting tolerance are held at their starting
    value (zero from the paper's model), the worst first, and the fit repeated.

    Parameters
    ----------
    fit : callable
        ``fit(free_names) -> RefineResult`` with those physical deviations free.
    fit_without : callable
        ``fit_without() -> RefineResult`` with none free (when every one is held).

    Returns
    -------
    (RefineResult, dict of str to str)
        The fit and, per held deviation, why.
    """
    tolerances = G1_PHYSICAL_TOLERANCES if tolerances is None else tolerances
    free = list(tolerances)
    fixed = {}
    while free:
        fin = fit(free)
        ratio = {n: fin.precision.get(f"physical.{n}", math.inf) / tolerances[n] for n in free}
        bad = {n: r for n, r in ratio.items() if not r <= fraction}
        if not bad:
            return fin, fixed
        worst = max(bad, key=lambda n: bad[n] if math.isfinite(bad[n]) else math.inf)
        sd = fin.precision.get(f"physical.{worst}", math.inf)
        fixed[worst] = (f"not determined by these views: standard error {sd:.3g} would exceed "
                        f"{fraction:g} x its mounting tolerance {tolerances[worst]:.3g} "
                        f"(SI units); held at its starting value")
        free.remove(worst)
    return fit_without(), fixed


def _stage_updates(m, *, refine_mirrors, refine_theta0, refine_poly, refine_intrinsics) -> dict:
    """The model parameters the stage estimated, keyed as in ``RigModel.to_dict()``."""
    updates: dict = {"l": m.l, "d": m.d}
    if refine_intrinsics:
        updates["intrinsics"] = {k: getattr(m.intrinsics, k) for k in refine_intrinsics}
    if refine_mirrors or refine_poly:
        updates["g1_pan"] = {"k": m.g1_pan.k}
        updates["g1_tilt"] = {"k": m.g1_tilt.k}
    if refine_theta0:
        updates.setdefault("g1_pan", {})["theta0"] = m.g1_pan.theta0
    if refine_poly:
        updates["g1_pan"]["poly"] = list(m.g1_pan.poly)
        updates["g1_tilt"]["poly"] = list(m.g1_tilt.poly)
    return updates


def _verify_transfers(m, fin, obs, pnp, U, residuals: dict, extra: dict) -> None:
    """Model vs measured transfer matrices (the paper's verification), into the result.

    Measured ``Vn_T_V0`` from PnP, V0 from the view at U1 = 0 of the pose when there is
    one, else the refined board pose.
    """
    meas, vv = [], []
    for o in obs:
        if o.view_id not in pnp:
            continue
        p = o.pose_index
        zero = [q.view_id for q in obs
                if q.pose_index == p and q.view_id in pnp and np.all(U[q.view_id] == 0.0)]
        V0_T_W = pnp[zero[0]] if zero else fin.board_poses[p]
        meas.append(pnp[o.view_id] @ rigid_inverse(V0_T_W))
        vv.append(U[o.view_id])
    if meas:
        tme = transfer_matrix_error(m, np.stack(meas), np.array(vv))
        residuals["transfer_translation_rms_m"] = tme.translation_rmse_m
        residuals["transfer_rotation_rms_rad"] = tme.rotation_rmse_rad
        extra["transfer_matrix_rmse_mm_measured"] = tme.rmse_mm
        extra["transfer_matrix_views"] = len(meas)

__all__ = [
    "PAPER_GRID_VOLTAGES",
    "anchor_voltages",
    "IdentificationResult",
    "LinearLD",
    "RefineResult",
    "TransferMatrixError",
    "ViewObservation",
    "board_pose_from_views",
    "default_board_pose",
    "identify_views",
    "paper_grid",
    "pnp_view",
    "refine",
    "run_dynamic_camera",
    "solve_l_d_linear",
    "transfer_matrix_error",
]
