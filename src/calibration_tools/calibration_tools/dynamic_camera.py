"""Dynamic-camera calibration: l, d (and the G1 gains) from circle-board views (no rclpy).

DESIGN.md section 3 step 2 and the paper's section III (Eqs. 9-16, 18-1):

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

Observability: ``V0_T_V`` depends on the tilt mirror's angle only through
``θ2 - θ2(0)`` (two reflections about planes through the tilt axis compose to a rotation
about that axis), so ``g1_tilt.theta0`` cannot be calibrated from views and is never
refined. ``g1_pan.theta0`` is observable (it sets the direction of the tilt axis in V0).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from reconstructor.model import (
    CameraIntrinsics,
    MirrorParams,
    RigModel,
    g_T_v,
    rigid_inverse,
    undistort_points,
    v0_T_v,
)
from scipy.optimize import least_squares

from .board_geometry import (
    ellipse_centres_normalised,
    pixels_to_board,
    project_circle_centres,
)
from .board_layout import PAPER_CIRCLE_BOARD, CircleBoard
from .circle_board import CircleDetections, ViewIdentification, detect_circles, identify_view
from .stages import CaptureView, StageResult

#: The paper's verification grid: -10 V to 10 V in 4 V steps on both G1 axes (36 positions).
PAPER_GRID_VOLTAGES = np.arange(-10.0, 10.0 + 1e-9, 4.0)


# ------------------------------------------------------------------------------ small maths
def rodrigues(rotvec) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle, radians), shape (3, 3)."""
    w = np.asarray(rotvec, dtype=np.float64)
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        K = _skew(w)
        return np.eye(3) + K + 0.5 * K @ K
    k = w / th
    K = _skew(k)
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * K @ K


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _transform(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _as_transform(T, name) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{name} must be a finite (4, 4) transform, got shape {T.shape}")
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or not np.allclose(
        T[3], [0, 0, 0, 1]
    ):
        raise ValueError(f"{name} must be a rigid transform")
    return T


def paper_grid() -> np.ndarray:
    """The paper's 36 G1 positions, shape (36, 2), volts: (U1_pan, U1_tilt)."""
    up, ut = np.meshgrid(PAPER_GRID_VOLTAGES, PAPER_GRID_VOLTAGES, indexing="ij")
    return np.column_stack([up.ravel(), ut.ravel()])


# ------------------------------------------------------------------------------ observations
@dataclass(frozen=True)
class ViewObservation:
    """Identified circles of one view.

    Attributes
    ----------
    voltages : ndarray, shape (2,), volts
        (U1_pan, U1_tilt).
    index : ndarray, shape (m,), int
        Board circle indices.
    uv : ndarray, shape (m, 2), pixels
        Detected ellipse centres.
    pose_index : int
        Board pose the view belongs to.
    view_id : int
        Caller's id of the view (e.g. its position in the input list).
    """

    voltages: np.ndarray
    index: np.ndarray
    uv: np.ndarray
    pose_index: int = 0
    view_id: int = -1

    def __post_init__(self):
        v = np.asarray(self.voltages, dtype=np.float64)
        if v.shape != (2,) or not np.isfinite(v).all():
            raise ValueError(f"voltages must be 2 finite volts, got {self.voltages!r}")
        idx = np.asarray(self.index, dtype=np.int64)
        uv = np.asarray(self.uv, dtype=np.float64)
        if idx.ndim != 1 or uv.shape != (len(idx), 2):
            raise ValueError(f"uv must have shape ({len(idx)}, 2) to match index, got {uv.shape}")
        object.__setattr__(self, "voltages", v)
        object.__setattr__(self, "index", idx)
        object.__setattr__(self, "uv", uv)


# ------------------------------------------------------------------------------ PnP
def pnp_view(
    intrinsics: CameraIntrinsics, points_w, radii, uv, *, ellipse_correction: bool = True
) -> tuple[np.ndarray, float]:
    """Board pose in one (virtual) camera from identified circle centres.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
    points_w : array_like, shape (m, 3), metres
        Circle centres in the board frame (z = 0), m >= 4.
    radii : array_like, shape (m,), metres
        Circle radii (for the ellipse-centre correction).
    uv : array_like, shape (m, 2), pixels
        Detected ellipse centres.
    ellipse_correction : bool
        Correct for the offset between ellipse centre and projected circle centre.

    Returns
    -------
    V_T_W : ndarray, shape (4, 4)
    rms_px : float
        RMS reprojection error, pixels.
    """
    P = np.asarray(points_w, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 4:
        raise ValueError(f"points_w must have shape (m >= 4, 3), got {P.shape}")
    if uv.shape != (len(P), 2):
        raise ValueError(f"uv must have shape ({len(P)}, 2), got {uv.shape}")
    if r.shape != (len(P),):
        raise ValueError(f"radii must have shape ({len(P)},), got {r.shape}")
    x_obs = undistort_points(intrinsics, uv)
    if not np.isfinite(x_obs).all():
        raise ValueError("uv: pixels could not be undistorted")
    K = np.eye(3)
    zero = np.zeros(len(P))
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            P, x_obs.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error as exc:
        raise ValueError(f"PnP failed: {exc}") from None
    best = None
    for rvec, tvec in zip(rvecs, tvecs):
        # A planar target has two PnP solutions; keep those with the board in front.
        x = x_obs.copy()
        for _ in range(3 if ellipse_correction else 1):
            rvec, tvec = cv2.solvePnPRefineLM(P, x.reshape(-1, 1, 2), K, None, rvec, tvec)
            T = _transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
            if ellipse_correction:
                x = x_obs - (ellipse_centres_normalised(T, P, r)
                             - ellipse_centres_normalised(T, P, zero))
        depth = P @ T[2, :3] + T[2, 3]
        if not np.all(depth > 0.0):
            continue
        pred = project_circle_centres(intrinsics, T, P, r if ellipse_correction else zero)
        rms = float(np.sqrt(np.mean(np.sum((pred - uv) ** 2, axis=1))))
        if np.isfinite(rms) and (best is None or rms < best[1]):
            best = (T, rms)
    if best is None:
        raise ValueError("PnP found no pose with the board in front of the camera")
    return best


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


def _rotation_angle(R) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


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


# ------------------------------------------------------------------------------ refinement
@dataclass(frozen=True)
class RefineResult:
    """Result of :func:`refine`.

    Attributes
    ----------
    model : RigModel
        Input model with the refined parameters replaced.
    board_poses : dict of int to ndarray, shape (4, 4)
        Refined ``V0_T_W`` per board pose.
    residuals_px : list of ndarray, shape (m_i, 2)
        Per view (input order), predicted minus detected ellipse centres, pixels.
    rms_px : float
        RMS reprojection error over all circles (norm of the 2-D residual), pixels.
    std : dict of str to float
        1-sigma standard errors of the refined model parameters (SI), from the Jacobian.
    names : tuple of str
        Refined model parameters (dotted names as in ``RigModel.to_dict()``).
    success : bool
    message : str
    """

    model: RigModel
    board_poses: dict
    residuals_px: list
    rms_px: float
    std: dict
    names: tuple
    success: bool
    message: str


def _param_names(refine_l_d, refine_mirrors, refine_theta0, refine_poly):
    names = []
    if refine_l_d:
        names += ["l", "d"]
    if refine_mirrors:
        names += ["g1_pan.k", "g1_tilt.k"]
    if refine_theta0:
        names += ["g1_pan.theta0"]
    for j in range(refine_poly):
        names += [f"g1_pan.poly[{j}]", f"g1_tilt.poly[{j}]"]
    return names


def _get_param(model, name):
    if name in ("l", "d"):
        return getattr(model, name)
    mirror, attr = name.split(".")
    mp = getattr(model, mirror)
    if attr.startswith("poly"):
        j = int(attr[5:-1])
        return mp.poly[j] if j < len(mp.poly) else 0.0
    return getattr(mp, attr)


def _set_params(model: RigModel, names, values) -> RigModel:
    kw = {}
    mirrors = {"g1_pan": model.g1_pan, "g1_tilt": model.g1_tilt}
    mirror_kw = {"g1_pan": {}, "g1_tilt": {}}
    polys = {key: list(mirrors[key].poly) for key in mirrors}
    for name, value in zip(names, values):
        if name in ("l", "d"):
            kw[name] = float(value)
            continue
        mirror, attr = name.split(".")
        if attr.startswith("poly"):
            j = int(attr[5:-1])
            while len(polys[mirror]) <= j:
                polys[mirror].append(0.0)
            polys[mirror][j] = float(value)
            mirror_kw[mirror]["poly"] = tuple(polys[mirror])
        else:
            mirror_kw[mirror][attr] = float(value)
    for key, changes in mirror_kw.items():
        if changes:
            kw[key] = dataclasses.replace(mirrors[key], **changes)
    return dataclasses.replace(model, **kw) if kw else model


def refine(
    model: RigModel,
    observations: Sequence[ViewObservation],
    board: CircleBoard,
    board_poses,
    *,
    refine_l_d: bool = True,
    refine_mirrors: bool = True,
    refine_theta0: bool = True,
    refine_poly: int = 0,
    refine_pose: bool = True,
    loss: str = "linear",
    f_scale_px: float = 1.0,
    ellipse_correction: bool = True,
    max_nfev: int = 200,
) -> RefineResult:
    """Nonlinear least squares on the reprojection error of all identified circles.

    Parameters
    ----------
    model : RigModel
        Starting values; intrinsics and every parameter not refined stay fixed.
    observations : sequence of ViewObservation
    board : CircleBoard
    board_poses : ndarray shape (4, 4), or dict of int to ndarray shape (4, 4)
        Initial ``V0_T_W`` (metres) per ``pose_index`` (one array: pose 0).
    refine_l_d : bool
        Refine l and d.
    refine_mirrors : bool
        Refine k of both G1 mirrors.
    refine_theta0 : bool
        Refine ``g1_pan.theta0`` (``g1_tilt.theta0`` is unobservable, see module doc).
    refine_poly : int
        Number of higher-order coefficients of both G1 responses to refine (0, 1 or 2).
    refine_pose : bool
        Refine the board poses.
    loss : str
        scipy loss ('linear', 'soft_l1', 'huber', 'cauchy', ...); robust losses for
        data that may hold outliers.
    f_scale_px : float
        Residual scale of robust losses, pixels.
    ellipse_correction : bool
        Predict ellipse centres (True) or projected circle centres.
    max_nfev : int

    Returns
    -------
    RefineResult
    """
    if not observations:
        raise ValueError("observations must not be empty")
    if isinstance(board_poses, dict):
        poses = {int(k): _as_transform(v, f"board_poses[{k}]") for k, v in board_poses.items()}
    else:
        poses = {0: _as_transform(board_poses, "board_poses")}
    if refine_poly not in (0, 1, 2):
        raise ValueError(f"refine_poly must be 0, 1 or 2, got {refine_poly}")
    obs = list(observations)
    for i, o in enumerate(obs):
        if not isinstance(o, ViewObservation):
            raise ValueError(f"observations[{i}] must be a ViewObservation")
        if o.pose_index not in poses:
            raise ValueError(f"observations[{i}].pose_index {o.pose_index} has no board pose")
    pose_keys = sorted({o.pose_index for o in obs})
    names = _param_names(refine_l_d, refine_mirrors, refine_theta0, refine_poly)
    x_model0 = np.array([_get_param(model, n) for n in names], dtype=np.float64)
    counts = np.array([len(o.index) for o in obs])
    index = np.concatenate([o.index for o in obs])
    uv_obs = np.concatenate([o.uv for o in obs])
    P = board.points(index)
    radii = board.radius(index) if ellipse_correction else np.zeros(len(index))
    volts = np.array([o.voltages for o in obs])
    view_of = np.repeat(np.arange(len(obs)), counts)
    pose_of_view = np.array([pose_keys.index(o.pose_index) for o in obs])
    R0 = [poses[k][:3, :3] for k in pose_keys]
    t0 = [poses[k][:3, 3] for k in pose_keys]
    n_model = len(names)
    n_pose = 6 * len(pose_keys) if refine_pose else 0
    # Parameter scales: lengths in mm-ish units, angles in mrad-ish units.
    scale = []
    for n in names:
        if n in ("l", "d"):
            scale.append(1e-3)
        elif n.endswith(".k"):
            scale.append(1e-5)
        elif n.endswith("theta0"):
            scale.append(1e-4)
        else:
            scale.append(1e-5)
    scale = np.array(scale + [1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3] * (n_pose // 6))

    def unpack(z):
        x = z * scale
        m = _set_params(model, names, x_model0 + x[:n_model]) if n_model else model
        Ts = []
        for j in range(len(pose_keys)):
            if refine_pose:
                w = x[n_model + 6 * j: n_model + 6 * j + 3]
                dt = x[n_model + 6 * j + 3: n_model + 6 * j + 6]
                Ts.append(_transform(rodrigues(w) @ R0[j], t0[j] + dt))
            else:
                Ts.append(_transform(R0[j], t0[j]))
        return m, Ts

    def predict(z):
        m, Ts = unpack(z)
        V_T_V0 = rigid_inverse(v0_T_v(m, volts[:, 0], volts[:, 1]))
        V_T_W = V_T_V0 @ np.stack(Ts)[pose_of_view]
        return project_circle_centres(m.intrinsics, V_T_W[view_of], P, radii)

    def fun(z):
        r = (predict(z) - uv_obs).ravel()
        return np.where(np.isfinite(r), r, 1e6)

    z0 = np.zeros(n_model + n_pose)
    if len(z0) == 0:
        sol_x = z0
        success, message = True, "nothing to refine"
        jac = np.zeros((2 * len(index), 0))
    else:
        if 2 * len(index) < len(z0):
            raise ValueError(f"{2 * len(index)} residuals cannot fix {len(z0)} parameters")
        sol = least_squares(
            fun, z0, method="trf", loss=loss, f_scale=f_scale_px, x_scale=1.0,
            max_nfev=max_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-12,
        )
        sol_x, success, message, jac = sol.x, bool(sol.success), str(sol.message), sol.jac
    m, Ts = unpack(sol_x)
    res = (predict(sol_x) - uv_obs)
    per_view = np.split(res, np.cumsum(counts)[:-1])
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    std = {}
    if n_model:
        dof = max(2 * len(index) - len(z0), 1)
        s2 = float(np.sum(res**2)) / dof
        try:
            cov = np.linalg.pinv(jac.T @ jac) * s2
            sd = np.sqrt(np.clip(np.diag(cov)[:n_model], 0.0, None)) * scale[:n_model]
            std = {n: float(v) for n, v in zip(names, sd)}
        except np.linalg.LinAlgError:
            std = {}
    return RefineResult(
        model=m,
        board_poses={k: T for k, T in zip(pose_keys, Ts)},
        residuals_px=per_view,
        rms_px=rms,
        std=std,
        names=tuple(names),
        success=success,
        message=message,
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


# ------------------------------------------------------------------------------ identification
@dataclass
class IdentificationResult:
    """Result of :func:`identify_views`.

    Attributes
    ----------
    views : list of ViewIdentification
        One per input view, in input order.
    model : RigModel
        Model refined during identification.
    board_poses : dict of int to ndarray, shape (4, 4)
    refinement : RefineResult or None
        Last refinement on the accepted views.
    verify_px : float
        Reprojection tolerance of the final verification, pixels.
    rounds : int
    """

    views: list
    model: RigModel
    board_poses: dict
    refinement: RefineResult | None
    verify_px: float
    rounds: int
    log: list = field(default_factory=list)


def _lattice_shift(offsets, period):
    """Circular mean of lattice offsets modulo ``period``; shape (2,)."""
    ang = 2.0 * np.pi * np.asarray(offsets) / period
    mean = np.arctan2(np.sin(ang).mean(axis=0), np.cos(ang).mean(axis=0))
    return mean * period / (2.0 * np.pi)


def _mean_rotation(Rs) -> np.ndarray:
    """Chordal L2 mean of rotation matrices (projection of their sum onto SO(3))."""
    U_, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U_ @ Vt))])
    return U_ @ D @ Vt


def board_pose_from_views(
    detections: Sequence[CircleDetections],
    voltages,
    model: RigModel,
    board: CircleBoard,
    prior,
    *,
    min_circles: int = 4,
    max_outlier_deg: float = 3.0,
) -> tuple[np.ndarray, int]:
    """Board orientation and plane from per-view PnP, keeping the prior's in-plane position.

    Each view with at least ``min_circles`` circles is labelled relative to its first circle
    (lattice steps predicted with the prior, which need only be right to ~10 degrees), its
    board pose is solved by PnP and mapped into V0 with the approximate model. The mean
    orientation and median plane offset of those views replace the prior's; the prior's
    board origin is moved along its V0 ray onto the new plane. The position along the board
    stays the prior's (it is fixed modulo the sub-pattern by the large circles later).

    Parameters
    ----------
    detections : sequence of CircleDetections
    voltages : array_like, shape (n, 2), volts
    model : RigModel
    board : CircleBoard
    prior : array_like, shape (4, 4)
        Approximate ``V0_T_W``, metres.
    min_circles : int
    max_outlier_deg : float
        Views whose orientation differs more from the mean are left out.

    Returns
    -------
    V0_T_W : ndarray, shape (4, 4)
    n_views : int
        Views used (0: the prior is returned unchanged).
    """
    prior = _as_transform(prior, "prior")
    U = np.asarray(voltages, dtype=np.float64)
    if U.shape != (len(detections), 2):
        raise ValueError(f"voltages must have shape ({len(detections)}, 2), got {U.shape}")
    Rs, ts = [], []
    for det, u in zip(detections, U):
        if len(det) < min_circles:
            continue
        xy = pixels_to_board(model, det.centres, u[0], u[1], prior)
        if not np.isfinite(xy).all():
            continue
        frac = board.lattice_coords(xy)
        rel = frac - frac[0]
        lab = np.rint(rel)
        if np.abs(rel - lab).max() > 0.3 or len({tuple(r) for r in lab}) != len(lab):
            continue
        rc = lab + np.rint(frac[0])
        P = np.column_stack([
            (rc[:, 1] - board.centre_col) * board.pitch,
            (rc[:, 0] - board.centre_row) * board.pitch,
            np.zeros(len(rc)),
        ])
        radii = np.where(board.is_large_rc(rc[:, 0], rc[:, 1]) & det.large & det.size_known,
                         board.large_diameter / 2.0, board.small_diameter / 2.0)
        try:
            V_T_W, _ = pnp_view(model.intrinsics, P, radii, det.centres)
        except (ValueError, cv2.error):
            continue
        T = v0_T_v(model, u[0], u[1]) @ V_T_W
        Rs.append(T[:3, :3])
        ts.append(T[:3, 3])
    if not Rs:
        return prior.copy(), 0
    Rs = np.array(Rs)
    ts = np.array(ts)
    R = _mean_rotation(Rs)
    for _ in range(2):
        ang = np.degrees(_rotation_angle(np.swapaxes(Rs, -1, -2) @ R))
        keep = ang <= max_outlier_deg
        if keep.sum() == 0:
            return prior.copy(), 0
        R = _mean_rotation(Rs[keep])
    n = R[:, 2]
    offset = float(np.median(ts[keep] @ n))  # plane: n . x = offset
    o = prior[:3, 3]
    denom = float(n @ o)
    t = o * (offset / denom) if abs(denom) > 1e-9 else o
    return _transform(R, t), int(keep.sum())


def identify_views(
    detections: Sequence[CircleDetections],
    voltages,
    model: RigModel,
    board: CircleBoard,
    board_poses,
    *,
    pose_index=None,
    refine_mirrors: bool = True,
    refine_theta0: bool = True,
    refine_poly: int = 0,
    max_offset_pitch: float = 0.25,
    verify_sigma: float = 8.0,
    verify_floor_px: float = 2.0,
    verify_max_pitch: float = 0.2,
    max_rounds: int = 8,
    progress: Callable | None = None,
) -> IdentificationResult:
    """Identify the circles of many views of the board while refining the model.

    Round 0 fixes the board position modulo the sub-pattern period with the views that show
    a large circle; each later round labels every view with :func:`identify_view`, refines
    the model and board poses on the accepted views (robust loss), and repeats until the
    accepted labels stop changing. Finally every view is verified against the refined model:
    its circles must reproject within ``verify_px`` (``verify_sigma`` robust sigmas, at least
    ``verify_floor_px``, at most ``verify_max_pitch`` pitches) or the view is rejected.

    Parameters
    ----------
    detections : sequence of CircleDetections
    voltages : array_like, shape (n, 2), volts
        (U1_pan, U1_tilt) per view.
    model : RigModel
        Approximate model (nominal rig data).
    board : CircleBoard
    board_poses : ndarray shape (4, 4), or dict of int to ndarray shape (4, 4)
        Approximate ``V0_T_W`` per board pose (metres); its position on the board needs to
        be right to within 3 pitches for absolute labels (large circles fix the rest).
    pose_index : array_like of int, shape (n,), optional
        Board pose of each view (default all 0).
    refine_mirrors, refine_theta0, refine_poly
        As :func:`refine`.
    max_offset_pitch : float
        Largest prediction error accepted when labelling a view without a large circle.
    verify_sigma, verify_floor_px, verify_max_pitch : float
        Final reprojection tolerance (see above).
    max_rounds : int
    progress : callable, optional
        ``progress(done, total, message)`` after each round.

    Returns
    -------
    IdentificationResult
    """
    n = len(detections)
    U = np.asarray(voltages, dtype=np.float64)
    if U.shape != (n, 2) or not np.isfinite(U).all():
        raise ValueError(f"voltages must have shape ({n}, 2) and be finite, got {U.shape}")
    pidx = np.zeros(n, dtype=np.int64) if pose_index is None else np.asarray(pose_index)
    if pidx.shape != (n,):
        raise ValueError(f"pose_index must have shape ({n},), got {pidx.shape}")
    if isinstance(board_poses, dict):
        poses = {int(k): _as_transform(v, f"board_poses[{k}]") for k, v in board_poses.items()}
    else:
        poses = {0: _as_transform(board_poses, "board_poses")}
    for p in set(pidx.tolist()):
        if p not in poses:
            raise ValueError(f"pose_index {p} has no entry in board_poses")
    log: list[str] = []
    period = board.sub_pattern

    def label_all(m, ps, **kw):
        return [
            identify_view(det, U[i, 0], U[i, 1], m, ps[int(pidx[i])], board, **kw)
            if len(det) else identify_view(det, 0.0, 0.0, m, ps[int(pidx[i])], board)
            for i, det in enumerate(detections)
        ]

    # Round 0: board orientation and plane from per-view PnP, then the lattice position
    # of each board pose from the large-circle views.
    for p in sorted(poses):
        sel = np.flatnonzero(pidx == p)
        poses[p], used = board_pose_from_views(
            [detections[i] for i in sel], U[sel], model, board, poses[p]
        )
        log.append(f"pose {p}: orientation from {used} PnP views")
    ids = label_all(model, poses, max_offset_pitch=0.49, max_spread_pitch=0.25)
    for p in sorted(poses):
        offs = [
            ids[i].offset_pitch for i in range(n)
            if pidx[i] == p and ids[i].mode == "large" and np.isfinite(ids[i].offset_pitch).all()
        ]
        if not offs:
            log.append(f"pose {p}: no view shows a large circle; relying on the pose prior")
            continue
        shift = _lattice_shift(offs, period)
        delta = np.array([shift[1], shift[0], 0.0]) * board.pitch  # (row, col) -> (x, y)
        poses[p] = poses[p] @ _transform(np.eye(3), -delta)
        log.append(f"pose {p}: {len(offs)} large-circle views; board prior shifted by "
                   f"({shift[0]:+.2f}, {shift[1]:+.2f}) pitch (row, col)")
    m = model
    prev = None
    rounds = 0
    ref = None
    for rounds in range(1, max_rounds + 1):
        ids = label_all(m, poses, max_offset_pitch=max_offset_pitch)
        accepted = [i for i in range(n) if ids[i].accepted]
        key = tuple((i, tuple(ids[i].index)) for i in accepted)
        if progress is not None:
            progress(rounds, max_rounds, f"identification round {rounds}: "
                     f"{len(accepted)}/{n} views labelled")
        if key == prev:
            break
        prev = key
        obs = _observations(ids, detections, U, pidx, accepted)
        n_pts = sum(len(o.index) for o in obs)
        if n_pts < 12:
            log.append(f"round {rounds}: only {n_pts} labelled circles, cannot refine")
            break
        spread = np.ptp(U[accepted], axis=0) if accepted else np.zeros(2)
        enough = len(accepted) >= 6 and spread.min() > 1.0
        ref = refine(
            m, obs, board, {p: poses[p] for p in sorted({o.pose_index for o in obs})},
            refine_l_d=enough and rounds >= 2,
            refine_mirrors=refine_mirrors and enough,
            refine_theta0=refine_theta0 and enough and rounds >= 2,
            refine_poly=refine_poly if (enough and rounds >= 3) else 0,
            loss="soft_l1", f_scale_px=2.0,
        )
        m = ref.model
        poses.update(ref.board_poses)
        log.append(f"round {rounds}: {len(accepted)} views labelled, robust fit rms "
                   f"{ref.rms_px:.3f} px")
    # Final verification against the refined model.
    pitch_px = _pitch_px(m, board, poses)
    ids = label_all(m, poses, max_offset_pitch=max_offset_pitch)
    verify_px = verify_floor_px
    for _ in range(3):
        accepted = [i for i in range(n) if ids[i].accepted]
        if not accepted:
            break
        obs = _observations(ids, detections, U, pidx, accepted)
        ref = refine(
            m, obs, board, {p: poses[p] for p in sorted({o.pose_index for o in obs})},
            refine_l_d=len(accepted) >= 6, refine_mirrors=refine_mirrors and len(accepted) >= 6,
            refine_theta0=refine_theta0 and len(accepted) >= 6,
            refine_poly=refine_poly if len(accepted) >= 6 else 0,
            loss="soft_l1", f_scale_px=max(verify_px / 4.0, 0.5),
        )
        m = ref.model
        poses.update(ref.board_poses)
        res = np.concatenate(ref.residuals_px)
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res, axis=0))))
        verify_px = float(np.clip(verify_sigma * sigma, verify_floor_px,
                                  verify_max_pitch * pitch_px))
        ids = label_all(m, poses, max_offset_pitch=max_offset_pitch, max_residual_px=verify_px)
        if [i for i in range(n) if ids[i].accepted] == accepted:
            break
    log.append(f"verification: tolerance {verify_px:.2f} px, "
               f"{sum(v.accepted for v in ids)}/{n} views accepted")
    return IdentificationResult(ids, m, poses, ref, verify_px, rounds, log)


def _observations(ids, detections, U, pidx, accepted):
    return [
        ViewObservation(U[i], ids[i].index, detections[i].centres, int(pidx[i]), i)
        for i in accepted
    ]


def _pitch_px(model: RigModel, board: CircleBoard, poses) -> float:
    """Board pitch in pixels at the V0 view of the nearest board pose."""
    z = min(float(T[2, 3]) for T in poses.values())
    return model.intrinsics.fx * board.pitch / max(z, 1e-3)


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
    for j, a in zip(j_[~ok], ang[~ok]):
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
    min_circles: int = 2,
    dark_circles: bool = True,
    max_offset_pitch: float = 0.25,
    verify_floor_px: float = 2.0,
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
    min_circles : int
        Views with fewer complete circles are rejected.
    dark_circles : bool
        Circles darker than the board.
    max_offset_pitch, verify_floor_px
        As :func:`identify_views`.
    progress : callable, optional
        ``progress(done, total, message)``.

    Returns
    -------
    StageResult
        ``updates``: l, d, and (when refined) ``g1_pan.k``, ``g1_pan.theta0``,
        ``g1_tilt.k`` (and poly). ``residuals``: ``reprojection_rms_px``,
        ``reprojection_max_px``, ``linear_translation_rms_m`` (Eq. 16),
        ``transfer_translation_rms_m`` / ``transfer_rotation_rms_rad`` (model vs PnP-measured
        transfer matrices). ``extra['dynamic_camera']``: Eq. 16 (l, d), standard errors, board
        poses, the paper's Eq. 18-1 RMSE in mm against the measured matrices.
    """
    if not isinstance(board, CircleBoard):
        raise ValueError("board must be a CircleBoard")
    if min_circles < 1:
        raise ValueError(f"min_circles must be >= 1, got {min_circles}")
    model0: RigModel = calibration.model
    intr = model0.intrinsics
    rejected: list[str] = []
    dets: list[CircleDetections] = []
    keep: list[int] = []
    volts: list[np.ndarray] = []
    pose_idx: list[int] = []
    # Small-circle radius expected at the nominal distance, for lone circles.
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
    U = np.array(volts).reshape(-1, 2)
    pidx = np.array(pose_idx, dtype=np.int64)
    if len(dets) < 3:
        raise ValueError(f"dynamic_camera: only {len(dets)} usable views; need at least 3 "
                         f"({len(rejected)} rejected: {'; '.join(rejected[:5])})")
    if board_pose is None:
        poses = {}
        for p in sorted(set(pose_idx)):
            sel = np.flatnonzero(pidx == p)
            z = _estimate_distance(model0, board, [dets[j] for j in sel], U[sel])
            poses[p] = default_board_pose(z if z is not None else 0.65)
    elif isinstance(board_pose, dict):
        poses = {int(k): _as_transform(v, f"board_pose[{k}]") for k, v in board_pose.items()}
    else:
        T = _as_transform(board_pose, "board_pose")
        poses = {p: T.copy() for p in set(pose_idx)}
    ident = identify_views(
        dets, U, model0, board, poses, pose_index=pidx, refine_mirrors=refine_mirrors,
        refine_theta0=refine_theta0, refine_poly=refine_poly, max_offset_pitch=max_offset_pitch,
        verify_floor_px=verify_floor_px, progress=progress,
    )
    accepted = [j for j, vid in enumerate(ident.views) if vid.accepted]
    for j, vid in enumerate(ident.views):
        if not vid.accepted:
            v = U[j]
            rejected.append(f"view {keep[j]} (U1 = {v[0]:+.3f}, {v[1]:+.3f} V): {vid.reason}")
    if len(accepted) < 6:
        raise ValueError(f"dynamic_camera: only {len(accepted)} views identified; need 6 "
                         f"({'; '.join(ident.log[-3:])})")
    obs = _observations(ident.views, dets, U, pidx, accepted)

    # Eq. 16 on PnP-measured transfers (reference: the view nearest U1 = 0 of each pose).
    m_id = ident.model
    pnp: dict[int, np.ndarray] = {}
    for o in obs:
        if len(o.index) >= 4:
            try:
                T, _ = pnp_view(intr, board.points(o.index), board.radius(o.index), o.uv)
            except ValueError:
                continue
            pnp[o.view_id] = T
    lin, lin_notes = _linear_l_d(obs, pnp, m_id, U)
    start = m_id
    if lin is not None and 0.0 < lin.l < 1.0 and 0.0 < lin.d < 1.0:
        start = dataclasses.replace(m_id, l=lin.l, d=lin.d)
    if progress is not None:
        progress(1, 1, "final refinement")
    fin = refine(
        start, obs, board, {p: ident.board_poses[p] for p in sorted({o.pose_index for o in obs})},
        refine_mirrors=refine_mirrors, refine_theta0=refine_theta0, refine_poly=refine_poly,
    )
    # If the Eq. 16 start led elsewhere than the identification's model, keep the better fit.
    alt = refine(
        m_id, obs, board, {p: ident.board_poses[p] for p in sorted({o.pose_index for o in obs})},
        refine_mirrors=refine_mirrors, refine_theta0=refine_theta0, refine_poly=refine_poly,
    ) if start is not m_id else fin
    if alt.rms_px < fin.rms_px - 1e-9:
        fin = alt
    m = fin.model
    res = np.concatenate(fin.residuals_px)
    updates: dict = {"l": m.l, "d": m.d}
    if refine_mirrors or refine_poly:
        updates["g1_pan"] = {"k": m.g1_pan.k}
        updates["g1_tilt"] = {"k": m.g1_tilt.k}
    if refine_theta0:
        updates.setdefault("g1_pan", {})["theta0"] = m.g1_pan.theta0
    if refine_poly:
        updates["g1_pan"]["poly"] = list(m.g1_pan.poly)
        updates["g1_tilt"]["poly"] = list(m.g1_tilt.poly)
    residuals = {
        "reprojection_rms_px": fin.rms_px,
        "reprojection_max_px": float(np.max(np.linalg.norm(res, axis=1))),
    }
    extra = {
        "board_poses_V0_T_W": {int(k): np.asarray(v).tolist() for k, v in fin.board_poses.items()},
        "std": dict(fin.std),
        "identification_verify_px": ident.verify_px,
        "identification_log": list(ident.log) + lin_notes,
    }
    if lin is not None:
        residuals["linear_translation_rms_m"] = lin.translation_rms_m
        extra["linear_l_m"] = lin.l
        extra["linear_d_m"] = lin.d
    # Model vs measured transfer matrices (paper's verification): measured Vn_T_V0 from PnP,
    # V0 from the view at U1 = 0 of the pose when there is one, else the refined board pose.
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
    return StageResult(
        stage="dynamic_camera",
        updates=updates,
        residuals=residuals,
        samples_used=len(accepted),
        samples_rejected=len(views) - len(accepted),
        rejected=rejected,
        extra={"dynamic_camera": extra},
    )


def true_poses_voltages(model: RigModel, voltages) -> np.ndarray:
    """``V0_T_V`` of a model at voltages ``(n, 2)``; shape (n, 4, 4) (reference for tests)."""
    U = np.asarray(voltages, dtype=np.float64)
    if U.ndim != 2 or U.shape[1] != 2:
        raise ValueError(f"voltages must have shape (n, 2), got {U.shape}")
    return v0_T_v(model, U[:, 0], U[:, 1])


__all__ = [
    "PAPER_GRID_VOLTAGES",
    "IdentificationResult",
    "LinearLD",
    "MirrorParams",
    "RefineResult",
    "TransferMatrixError",
    "ViewObservation",
    "default_board_pose",
    "identify_views",
    "paper_grid",
    "pnp_view",
    "refine",
    "rodrigues",
    "run_dynamic_camera",
    "solve_l_d_linear",
    "transfer_matrix_error",
]
