"""Board fitting through the dynamic camera: PnP per view and the joint refinement (no rclpy).

:func:`pnp_view` solves one view's board pose (both planar PnP solutions are tried; the one
with the board in front and the smaller reprojection error wins). :func:`refine` minimises
the reprojection error of identified circles over all views with scipy ``least_squares``:
l, d, optionally the G1 gains, ``g1_pan.theta0`` and higher-order response terms, and the
board pose(s) ``V0_T_W``. The model predicts ellipse centres, as the detector measures them
(:mod:`calibration_tools.board_geometry`).

``V0_T_V`` depends on the tilt mirror's angle only through ``θ2 - θ2(0)`` (two reflections in
planes through the tilt axis compose to a rotation about that axis), so ``g1_tilt.theta0``
cannot be calibrated from views and is never refined. ``g1_pan.theta0`` is observable: it sets
the direction of the tilt axis as seen from V0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative, group_columns

from reconstructor.model import (
    CameraIntrinsics,
    PhysicalGeometry,
    RigModel,
    rigid_inverse,
    undistort_points,
    v0_T_v,
)

from .board_geometry import (
    contour_offsets,
    ellipse_centres_normalised,
    project_circle_centres,
)
from .board_layout import CircleBoard
from .stages import clustered_covariance, covariance_from_jacobian


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


def _as_pose_dict(board_poses) -> dict:
    """Board pose(s) as ``{pose_index: V0_T_W}``; one (4, 4) array is pose 0."""
    if isinstance(board_poses, dict):
        return {int(k): _as_transform(v, f"board_poses[{k}]") for k, v in board_poses.items()}
    return {0: _as_transform(board_poses, "board_poses")}


def _rotation_angle(R) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))



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
_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


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
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        # A planar target has two PnP solutions; keep those with the board in front.
        x = x_obs.copy()
        for _ in range(10 if ellipse_correction else 1):
            rvec, tvec = cv2.solvePnPRefineLM(P, x.reshape(-1, 1, 2), K, None, rvec, tvec,
                                              criteria=_LM_CRITERIA)
            T = _transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
            if not ellipse_correction:
                break
            x_new = x_obs - (ellipse_centres_normalised(T, P, r)
                             - ellipse_centres_normalised(T, P, zero))
            change = float(np.abs(x_new - x).max())
            x = x_new
            if change < 1e-12:
                break
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
        1-sigma standard errors of the refined model parameters (SI), from the Jacobian,
        each view's circles one sample (:func:`_view_clustered`).
    precision : dict of str to float
        The same with every circle one sample (``s2 inv(J.T J)``): how sharply the data pin
        a parameter down, comparable with other stages' per-point figures. The stage's
        choices of what to free compare these; ``std`` is what the parameters are known to.
    names : tuple of str
        Refined model parameters (dotted names as in ``RigModel.to_dict()``).
    success : bool
    message : str
    covariance : dict
        The refined parameters' covariance record
        (:func:`reconstructor.uncertainty.covariance_record`): from the reprojection
        residuals alone (board poses included), and the sensitivity to the held intrinsics
        ``input_std`` names; empty when it cannot be formed.
    """

    model: RigModel
    board_poses: dict
    residuals_px: list
    rms_px: float
    std: dict
    names: tuple
    success: bool
    message: str
    covariance: dict = dataclasses.field(default_factory=dict)
    precision: dict = dataclasses.field(default_factory=dict)


_INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")


def _param_names(refine_l_d, refine_mirrors, refine_theta0, refine_poly, refine_intrinsics=(),
                 refine_physical=()):
    names = [f"intrinsics.{n}" for n in refine_intrinsics]
    names += [f"physical.{n}" for n in refine_physical]
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
    if mirror == "intrinsics":
        return getattr(model.intrinsics, attr)
    if mirror == "physical":
        return (model.physical or PhysicalGeometry()).value(attr)
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
    intr_kw = {}
    phys = {}
    for name, value in zip(names, values, strict=True):
        if name in ("l", "d"):
            kw[name] = float(value)
            continue
        mirror, attr = name.split(".")
        if mirror == "intrinsics":
            intr_kw[attr] = float(value)
            continue
        if mirror == "physical":
            phys[attr] = value
            continue
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
    if intr_kw:
        kw["intrinsics"] = dataclasses.replace(model.intrinsics, **intr_kw)
    if phys:
        kw["physical"] = (model.physical or PhysicalGeometry()).replaced(phys)
    return dataclasses.replace(model, **kw) if kw else model


def _check_observations(observations, poses) -> list:
    """The observations as a list, each a ViewObservation of a known board pose."""
    obs = list(observations)
    for i, o in enumerate(obs):
        if not isinstance(o, ViewObservation):
            raise ValueError(f"observations[{i}] must be a ViewObservation")
        if o.pose_index not in poses:
            raise ValueError(f"observations[{i}].pose_index {o.pose_index} has no board pose")
    return obs


def _param_scale(names, n_pose: int) -> np.ndarray:
    """Scale of each parameter of the solver vector (model parameters, then pose deltas)."""
    # Parameter scales: lengths in mm-ish units, angles in mrad-ish units.
    scale = []
    for n in names:
        if n.startswith("intrinsics."):
            scale.append(1.0)
        elif n in ("l", "d"):
            scale.append(1e-3)
        elif n.startswith("physical."):
            scale.append(1e-4)
        elif n.endswith(".k"):
            scale.append(1e-5)
        elif n.endswith("theta0"):
            scale.append(1e-4)
        else:
            scale.append(1e-5)
    return np.array(scale + [1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3] * (n_pose // 6))


@dataclass
class _RefineProblem:
    """Stacked circles of all views and the map from solver vector to model and poses."""

    model: RigModel
    names: list
    x_model0: np.ndarray
    pose_keys: list
    R0: list
    t0: list
    refine_pose: bool
    scale: np.ndarray
    counts: np.ndarray
    uv_obs: np.ndarray
    P: np.ndarray
    radii: np.ndarray
    volts: np.ndarray
    view_of: np.ndarray
    pose_of_view: np.ndarray
    offset: np.ndarray | float = 0.0

    @property
    def n_model(self) -> int:
        return len(self.names)

    @property
    def n_params(self) -> int:
        return len(self.scale)

    @property
    def n_residuals(self) -> int:
        return 2 * len(self.uv_obs)

    def unpack(self, z):
        """Model and board poses (list of (4, 4), ``pose_keys`` order) of solver vector z."""
        n_model = self.n_model
        x = z * self.scale
        m = self.model
        if n_model:
            m = _set_params(self.model, self.names, self.x_model0 + x[:n_model])
        Ts = []
        for j in range(len(self.pose_keys)):
            if self.refine_pose:
                w = x[n_model + 6 * j: n_model + 6 * j + 3]
                dt = x[n_model + 6 * j + 3: n_model + 6 * j + 6]
                Ts.append(_transform(rodrigues(w) @ self.R0[j], self.t0[j] + dt))
            else:
                Ts.append(_transform(self.R0[j], self.t0[j]))
        return m, Ts

    def view_T_board(self, z) -> tuple:
        """The model and every circle's board-to-view transform, shape (N, 4, 4)."""
        m, Ts = self.unpack(z)
        V_T_V0 = rigid_inverse(v0_T_v(m, self.volts[:, 0], self.volts[:, 1]))
        return m, (V_T_V0 @ np.stack(Ts)[self.pose_of_view])[self.view_of]

    def predict(self, z):
        """Predicted centres of all circles as the detector measures them, shape (N, 2),
        pixels: ellipse centres, and the distorted outline's offset (``offset``)."""
        m, V_T_W = self.view_T_board(z)
        return project_circle_centres(m.intrinsics, V_T_W, self.P, self.radii) + self.offset

    def fun(self, z):
        """Flat residual vector for the solver (non-finite residuals replaced by 1e6 px; a
        trial step beyond a physical deviation's plausible size gets 1e6 px everywhere)."""
        try:
            r = (self.predict(z) - self.uv_obs).ravel()
        except ValueError:
            return np.full(self.n_residuals, 1e6)
        return np.where(np.isfinite(r), r, 1e6)


def _build_problem(model, obs, board, poses, names, refine_pose, ellipse_correction):
    """Stack the circles of all observations into a :class:`_RefineProblem`.

    With ``ellipse_correction`` the prediction also carries each circle's distorted-outline
    offset (:func:`calibration_tools.board_geometry.contour_offsets`), computed once at the
    starting model and poses: it is a second-order effect of the distortion that a fit's
    steps hardly change.
    """
    pose_keys = sorted({o.pose_index for o in obs})
    counts = np.array([len(o.index) for o in obs])
    index = np.concatenate([o.index for o in obs])
    n_pose = 6 * len(pose_keys) if refine_pose else 0
    prob = _RefineProblem(
        model=model,
        names=names,
        x_model0=np.array([_get_param(model, n) for n in names], dtype=np.float64),
        pose_keys=pose_keys,
        R0=[poses[k][:3, :3] for k in pose_keys],
        t0=[poses[k][:3, 3] for k in pose_keys],
        refine_pose=refine_pose,
        scale=_param_scale(names, n_pose),
        counts=counts,
        uv_obs=np.concatenate([o.uv for o in obs]),
        P=board.points(index),
        radii=board.radius(index) if ellipse_correction else np.zeros(len(index)),
        volts=np.array([o.voltages for o in obs]),
        view_of=np.repeat(np.arange(len(obs)), counts),
        pose_of_view=np.array([pose_keys.index(o.pose_index) for o in obs]),
    )
    if ellipse_correction:
        m, V_T_W = prob.view_T_board(np.zeros(prob.n_params))
        offset = contour_offsets(m.intrinsics, V_T_W, prob.P, prob.radii)
        prob.offset = np.where(np.isfinite(offset), offset, 0.0)
    return prob


def _grouped_jacobian(prob: _RefineProblem):
    """Forward-difference Jacobian that perturbs the columns of all board poses together.

    A board pose moves only the circles of its own views, so the columns of different poses
    never share a row: one evaluation serves one column of every pose (scipy's column
    grouping), and the model's columns are dense. Returned dense, as ``least_squares``'s
    exact trust-region solver takes it; the same steps as its own '2-point' differences.
    """
    n_model = prob.n_model
    rows_pose = np.repeat(prob.pose_of_view[prob.view_of], 2)
    n_pose = (prob.n_params - n_model) // 6
    pattern = np.zeros((prob.n_residuals, prob.n_params), dtype=bool)
    pattern[:, :n_model] = True
    for j in range(n_pose):
        pattern[rows_pose == j, n_model + 6 * j: n_model + 6 * j + 6] = True
    groups = group_columns(pattern)

    def jac(z):
        return approx_derivative(prob.fun, z, method="2-point",
                                 sparsity=(pattern, groups)).toarray()

    return jac


def _solve(prob: _RefineProblem, loss, f_scale_px, max_nfev):
    """Run ``least_squares`` from z = 0: (z, success, message, jacobian)."""
    z0 = np.zeros(prob.n_params)
    if len(z0) == 0:
        return z0, True, "nothing to refine", np.zeros((prob.n_residuals, 0))
    if prob.n_residuals < len(z0):
        raise ValueError(f"{prob.n_residuals} residuals cannot fix {len(z0)} parameters")
    sol = least_squares(
        prob.fun, z0, jac=_grouped_jacobian(prob), method="trf", loss=loss,
        f_scale=f_scale_px, x_scale=1.0, max_nfev=max_nfev, xtol=1e-12, ftol=1e-12,
        gtol=1e-12,
    )
    return sol.x, bool(sol.success), str(sol.message), sol.jac


def _perturbed(model: RigModel, name: str, delta: float) -> RigModel:
    """The model with one intrinsic parameter (``fx``.. ``cy`` or ``dist[j]``) moved by delta."""
    intr = model.intrinsics
    if name.startswith("dist["):
        dist = list(intr.dist)
        dist[int(name[5:-1])] += delta
        return dataclasses.replace(model, intrinsics=dataclasses.replace(intr, dist=tuple(dist)))
    return dataclasses.replace(
        model, intrinsics=dataclasses.replace(intr, **{name: getattr(intr, name) + delta}))


def _input_jacobian(prob: _RefineProblem, z, input_std: dict) -> tuple[np.ndarray, np.ndarray]:
    """Residual derivatives (central differences over +-1 sigma) wrt the held intrinsics.

    Returns the Jacobian, shape (m, k), in residual units per unit parameter, and the k
    standard errors.
    """
    cols, sig = [], []
    for name, sd in input_std.items():
        if not sd > 0 or f"intrinsics.{name}" in prob.names:
            continue
        plus = dataclasses.replace(prob, model=_perturbed(prob.model, name, sd)).fun(z)
        minus = dataclasses.replace(prob, model=_perturbed(prob.model, name, -sd)).fun(z)
        cols.append((plus - minus) / (2.0 * sd))
        sig.append(sd)
    return np.array(cols).reshape(len(cols), -1).T, np.array(sig)


def _model_std(prob: _RefineProblem, res, jac, z, input_std: dict | None = None,
               held_priors: dict | None = None) -> tuple[dict, dict]:
    """1-sigma standard errors of the model parameters from the Jacobian (SI units), and the
    covariance record behind them (:attr:`RefineResult.covariance`).

    The covariance of the reprojection fit (board poses included; per view, not per circle:
    :func:`_view_clustered`), plus, when
    ``input_std`` gives the standard errors of intrinsics the fit holds fixed, their effect
    propagated through the solution: ``G diag(sd**2) G.T`` with ``G = -inv(J.T J) J.T J_in``
    (the intrinsics taken as independent here; the record keeps G itself, so that their full
    covariance can be used instead). ``held_priors`` (full names to 1-sigma tolerances) of
    parameters the fit holds at their starting value enter the record only: their
    sensitivity, and the tolerance as their prior.
    """
    from reconstructor.uncertainty import covariance_record

    n_model = prob.n_model
    if not n_model:
        return {}, {}, {}
    try:
        per_circle, _ = covariance_from_jacobian(jac, res.ravel(), n_params=prob.n_params)
    except ValueError:
        return {}, {}, {}
    cov = _view_clustered(prob, res, jac, per_circle)
    scale = prob.scale[:n_model]
    own = cov[:n_model, :n_model] * np.outer(scale, scale)
    inputs, G_x, added = [], np.zeros((n_model, 0)), 0.0
    if input_std:
        J_in, sd = _input_jacobian(prob, z, input_std)
        if len(sd):
            G = -np.linalg.pinv(jac.T @ jac) @ (jac.T @ J_in)
            added = (G * sd**2) @ G.T
            G_x = G[:n_model] * scale[:, None]
            inputs = [f"intrinsics.{n}" for n, s in input_std.items()
                      if s > 0 and f"intrinsics.{n}" not in prob.names]

    def sigmas(c):
        var = np.diag(c + added)[:n_model]
        sd_model = np.sqrt(np.where(np.isfinite(var), np.clip(var, 0.0, None), np.inf))
        return {n: float(v) for n, v in zip(prob.names, sd_model * scale, strict=True)}

    std, precision = sigmas(cov), sigmas(per_circle)
    record = {}
    held = {n: float(t) for n, t in (held_priors or {}).items()
            if t > 0 and n not in prob.names}
    if held:  # held parameters: their tolerance's effect, for the record only
        cols = []
        for name, t in held.items():
            x0 = _get_param(prob.model, name)
            plus = dataclasses.replace(prob, model=_set_params(prob.model, [name], [x0 + t]))
            minus = dataclasses.replace(prob, model=_set_params(prob.model, [name], [x0 - t]))
            cols.append((plus.fun(z) - minus.fun(z)) / (2.0 * t))
        G = -np.linalg.pinv(jac.T @ jac) @ (jac.T @ np.array(cols).T)
        G_x = np.hstack([G_x, G[:n_model] * scale[:, None]])
        inputs = inputs + list(held)
    if np.isfinite(own).all():
        record = covariance_record(prob.names, own, inputs, G_x, priors=held)
    return std, record, precision


def _view_clustered(prob: _RefineProblem, res, jac, cov) -> np.ndarray:
    """The solution's covariance with each view's circles taken as one sample.

    The circles of one view share that frame's errors: a galvo's scatter from frame to frame
    moves them all together (:func:`g1_frame_noise`), so they are not independent and
    ``s2 inv(J.T J)`` over circles counts each view's shift as many times as it has circles.
    The cluster-robust sandwich over views
    (:func:`calibration_tools.stages.clustered_covariance`) holds whatever the correlation
    within a view; with too few views for that, ``cov`` (per circle) is kept.
    """
    if not np.isfinite(cov).all():  # undetermined: as the fit says
        return cov
    out = clustered_covariance(jac, res.ravel(), np.repeat(prob.view_of, 2))
    return cov if out is None else out


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
    refine_intrinsics: Sequence[str] = (),
    refine_physical: Sequence[str] = (),
    loss: str = "linear",
    f_scale_px: float = 1.0,
    ellipse_correction: bool = True,
    max_nfev: int = 200,
    input_std: dict | None = None,
    held_priors: dict | None = None,
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
    refine_intrinsics : sequence of str
        Intrinsics to refine jointly, any of ``('fx', 'fy', 'cx', 'cy')`` (distortion stays).
        The large board spans ~60 degrees of view directions, so it constrains the focal
        lengths far better than a 5-degree view of a small target does.
    loss : str
        scipy loss ('linear', 'soft_l1', 'huber', 'cauchy', ...); robust losses for
        data that may hold outliers.
    f_scale_px : float
        Residual scale of robust losses, pixels.
    ellipse_correction : bool
        Predict ellipse centres (True) or projected circle centres.
    max_nfev : int
    input_std : dict of str to float, optional
        1-sigma standard errors of the intrinsics the fit holds fixed (``fx``, ``fy``,
        ``cx``, ``cy`` in px, ``dist[j]``), propagated into ``RefineResult.std``.
    held_priors : dict of str to float, optional
        1-sigma tolerances of model parameters the fit holds (full names, e.g.
        ``physical.g1_pan_surface_offset``); their effect enters ``RefineResult.covariance``
        (not ``std``).

    Returns
    -------
    RefineResult
    """
    if not observations:
        raise ValueError("observations must not be empty")
    poses = _as_pose_dict(board_poses)
    if refine_poly not in (0, 1, 2):
        raise ValueError(f"refine_poly must be 0, 1 or 2, got {refine_poly}")
    obs = _check_observations(observations, poses)
    bad = [n for n in refine_intrinsics if n not in _INTRINSIC_NAMES]
    if bad:
        raise ValueError(f"refine_intrinsics must name {_INTRINSIC_NAMES}, got {bad}")
    names = _param_names(refine_l_d, refine_mirrors, refine_theta0, refine_poly,
                         tuple(dict.fromkeys(refine_intrinsics)),
                         tuple(dict.fromkeys(refine_physical)))
    prob = _build_problem(model, obs, board, poses, names, refine_pose, ellipse_correction)
    sol_x, success, message, jac = _solve(prob, loss, f_scale_px, max_nfev)
    m, Ts = prob.unpack(sol_x)
    res = (prob.predict(sol_x) - prob.uv_obs)
    per_view = np.split(res, np.cumsum(prob.counts)[:-1])
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    std, record, precision = _model_std(prob, res, jac, sol_x, input_std, held_priors)
    return RefineResult(
        model=m,
        board_poses={k: T for k, T in zip(prob.pose_keys, Ts, strict=True)},
        residuals_px=per_view,
        rms_px=rms,
        std=std,
        names=tuple(names),
        success=success,
        message=message,
        covariance=record,
        precision=precision,
    )


# ------------------------------------------------------------------------------ frame noise
#: Fewest circles a view needs to enter the frame-noise estimate (its mean shift).
FRAME_NOISE_MIN_CIRCLES = 6


def g1_frame_noise(result: RefineResult, observations: Sequence[ViewObservation],
                   board: CircleBoard, *, ellipse_correction: bool = True,
                   step_v: float = 1e-3) -> dict:
    """G1's per-frame noise, in volts, from the views' common shifts the fit leaves.

    A galvo's angle scatters from frame to frame about its response (its repeatability,
    8 µrad on the paper's galvos): every circle of a view then moves together, as if the
    view had been taken at slightly other voltages. Per view, the mean residual of its
    circles is solved for that voltage offset (the 2 x 2 derivative of the circles' mean
    pixel with respect to U1 pan and tilt, at the fitted model and board pose); the noise
    of each view's mean (its circles' scatter over their number) is subtracted from the
    offsets' mean square. What the fitted model cannot represent and that varies from view
    to view counts here too: it is noise to anyone using the model.

    Returns
    -------
    dict
        ``frame_noise_u1_pan_V``, ``frame_noise_u1_tilt_V`` (1 sigma, volts) and
        ``frame_noise_views``; empty when fewer than 3 views have enough circles.
    """
    from reconstructor.model import rigid_inverse, v0_T_v

    m = result.model
    offsets, floors = [], []
    for o, r in zip(observations, result.residuals_px, strict=True):
        r = np.asarray(r, dtype=np.float64)
        if len(r) < FRAME_NOISE_MIN_CIRCLES or o.pose_index not in result.board_poses:
            continue
        P = board.points(o.index)
        radii = board.radius(o.index) if ellipse_correction else np.zeros(len(o.index))
        T = result.board_poses[o.pose_index]

        def mean_px(up, ut, T=T, P=P, radii=radii):
            V_T_W = rigid_inverse(v0_T_v(m, up, ut)) @ T
            return project_circle_centres(m.intrinsics, V_T_W, P, radii).mean(axis=0)

        up, ut = float(o.voltages[0]), float(o.voltages[1])
        J = np.column_stack([(mean_px(up + step_v, ut) - mean_px(up - step_v, ut)),
                             (mean_px(up, ut + step_v) - mean_px(up, ut - step_v))])
        J /= 2.0 * step_v
        if not np.isfinite(J).all() or abs(np.linalg.det(J)) < 1e-12:
            continue
        Jinv = np.linalg.inv(J)
        offsets.append(Jinv @ r.mean(axis=0))
        floors.append(np.diag(Jinv @ (np.cov(r.T) / len(r)) @ Jinv.T))
    # the fit took up part of the offsets: scale by shifts over shifts less its parameters
    n_fit = len(result.names) + 6 * len(result.board_poses)
    if len(offsets) < 3 or len(offsets) <= n_fit:  # more views than the fit's parameters
        return {}
    dof = 2 * len(offsets) / (2 * len(offsets) - n_fit)
    var = dof * np.mean(np.square(offsets), axis=0) - np.mean(floors, axis=0)
    sd = np.sqrt(np.clip(var, 0.0, None))
    return {'frame_noise_u1_pan_V': float(sd[0]), 'frame_noise_u1_tilt_V': float(sd[1]),
            'frame_noise_views': len(offsets)}
