"""When a stage has enough placements, and which one would help most next (no rclpy).

Each stage states, once and here, standard-error targets for its parameters
(:func:`sigma_targets`) and the most placements it ever asks for (:data:`MAX_PLACEMENTS`).
After every placement kept, :func:`assess` predicts the parameters' standard errors from the
placements taken so far, at the poses the scanner measured for them, and says whether every
one meets its target; while one does not, it ranks the placements still to be asked for by
how far each would bring down the worst ratio of standard error to target, and names the
best one (its depth, tilt and position) as the advice.

The prediction is the Fisher information of the stage's observations with respect to its
parameters, each placement's own pose taken out (Schur complement):

- ``intrinsics``: the checkerboard's corners in the image (OpenCV's projection Jacobian, the
  stage's own lens prior added), corner noise :data:`FEATURE_NOISE_PX`;
- ``laser_plane`` and ``laser_axis``: the stripe points where the laser sheet of the
  placement's G2 voltage crosses the board, their distance from the sheet differentiated
  with respect to the sheet's parameters; each point's noise is the stripe centre's
  (:data:`STRIPE_NOISE_PX`), and all points of one board share its pose's error along its
  normal (from its pattern's corners; :func:`_board_depth_sigma`);
- ``dynamic_camera``: the circle centres in every view of the large board that showed it
  (a candidate's: the views planned around its pose, :func:`operator_flow.views_for`), with
  respect to l and d and what the stage estimates with them (G1's gains and pan zero, the
  pinhole; the intrinsics stage's standard errors as the pinhole's prior), noise
  :data:`FEATURE_NOISE_PX`.

The laser stages' prediction holds the camera fixed, as their solvers do: it is what more
laser placements can still bring down. The camera's own error moves the triangulated sheet
too (by more); the whole chain's uncertainty is the evaluation's predicted uncertainty.

The targets follow from one budget, :data:`BUDGET_M` at the design working distance (scaled
with the working depth, as the targets and views are): a parameter's target is the
standard error that alone moves what it describes (a ray's pixel, the laser sheet) by the
budget, as an RMS over the region the stage serves (the image; the stripe points of the
stage's whole plan). The principal point and the focal lengths are the exceptions: a shift
of the principal point is a turn of the camera, which the dynamic camera's mirror angles
take up, so its target is the lens prior's (:data:`PRINCIPAL_POINT_TARGET_PX`); the focal
lengths' is set by how far their error carries into the dynamic camera and the laser
sheet (:data:`FOCAL_TARGET_REL`). The dynamic camera states targets for l and d alone, each
the budget over the RMS move of points at the working depth over G1's range that the
stage's other parameters cannot reproduce (:func:`_dynamic_targets`).

``joint_correction`` (sphere positions chained through shared G1 grid nodes) needs every
placement of its plan: its standard errors come from the stage's own solution
(``calibration/compute``), and :func:`assess` reports them as not estimable before it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Budget of each parameter's standard error: how far it may move a ray or the laser sheet
#: at the design working distance (650 mm) [m]; scaled with the working depth. A tenth of
#: the paper's 0.165 mm stair error: a dozen parameters at their targets add up (root sum
#: of squares) to under a third of it.
BUDGET_M = 15e-6
#: Design working distance the budget is stated at [m].
BUDGET_DEPTH = 0.65
#: Noise of a detected checkerboard corner or circle centre [px] before any view is kept
#: (sub-pixel refinement on a sharp 8-bit image: 0.05-0.1 px; the larger is taken); then
#: the kept views' own reprojection residual (:meth:`Progress.feature_noise_px`).
FEATURE_NOISE_PX = 0.1
#: The least feature noise the prediction takes from the kept views [px] (their fitted
#: residual is an estimate; below this a few views could promise too much).
MIN_FEATURE_NOISE_PX = 0.02
#: Noise of one stripe centre across the stripe [px] (the extractor's centre of a 0.6 mm
#: line on a matte board).
STRIPE_NOISE_PX = 0.1
#: Target of the principal point's standard error [px]: the lens prior's +-10 px bound
#: (a principal-point shift is a turn of the camera; the dynamic camera's mirror angles
#: take it up, so the intrinsics need not pin it tighter).
PRINCIPAL_POINT_TARGET_PX = 10.0 / math.sqrt(3.0)
#: Target of the focal lengths' standard errors, relative to them: 0.1 %, about what a
#: dozen views give with corners good to 0.04 px (the reference rig's full plan of 30
#: views: 0.065 %). A narrow field (a few degrees) barely separates the focal length from
#: the board's distance, and what is left carries into the dynamic camera's l; that stage
#: refines fx and fy from the large board's 740 mm lever wherever it determines them
#: better, with this stage's value as their prior.
FOCAL_TARGET_REL = 0.001
#: The most placements a stage asks for (also never more than its plan has): the full
#: plans' counts, which calibrated the reference rig and the drawn rigs.
MAX_PLACEMENTS = {'intrinsics': 30, 'dynamic_camera': 5, 'laser_plane': 8,
                  'laser_axis': 36, 'joint_correction': 9}
#: Placements a stage takes before it may stop: what its solver needs, with one spare
#: (intrinsics: 4 views; the laser plane: 2 boards; the laser axis: 3 planes of 2 boards,
#: and :data:`ROW_BOARDS` on every plane of its plan). The dynamic camera takes its whole
#: plan (the centre and the four sides): its prediction covers the paper model's
#: parameters, while its solver also frees the physical model's G1 deviations wherever the
#: views around the centre pin them, which spreads l's and d's errors wider than predicted
#: (reference rig: l's standard error 0.18-0.23 mm from the solver, 0.14 mm predicted).
MIN_PLACEMENTS = {'intrinsics': 5, 'dynamic_camera': 5, 'laser_plane': 3, 'laser_axis': 6}
#: The laser axis's solver fits one plane per G2 voltage of its plan from at least this
#: many boards, then the axis and G2's response (with its curvature) from those planes:
#: the stage asks for every plane of its plan (they span G2's range, which the curvature
#: needs) before its standard errors count.
ROW_BOARDS = 2
#: A row's boards must also stand at each depth its plan places them at (near and far):
#: boards at one depth pin where the plane crosses that depth, but leave its lean (its
#: turn about the stripe) to the stripes' own few millimetres of depth, and across the
#: rows that lean is what tells G2's response curvature from the axis's position. Boards
#: a row's plan puts this far apart in depth, relative to their mean depth, are at two
#: depths (the plans' near and far boards: 17 %).
ROW_DEPTH_SPLIT = 0.05
#: The stages whose standard errors are predicted here, each with what they are predicted
#: from: the camera's projection (``camera``), one laser sheet (``sheet``) or the sheets of
#: the G2 planes about the laser axis (``axis``). The others: see the module.
PREDICTED = {'intrinsics': 'camera', 'dynamic_camera': 'dynamic', 'laser_plane': 'sheet',
             'laser_axis': 'axis'}


@dataclass
class Assessment:
    """A stage's standard errors against its targets, and the advice for the next placement.

    Attributes
    ----------
    stage : str
    names, units : list of str
        The parameters and their SI units.
    sigma : ndarray, shape (n,)
        Predicted standard errors (NaN: not estimable yet or not predicted).
    target : ndarray, shape (n,)
    best : int or None
        Index, into the candidates given, of the placement that most lowers the worst
        ``sigma / target`` (None: no candidate, or nothing predicted).
    best_ratio : float
        The worst ``sigma / target`` after that placement.
    advice : str
    """

    stage: str
    names: list
    units: list
    sigma: np.ndarray
    target: np.ndarray
    best: int | None = None
    best_ratio: float = math.nan
    advice: str = ''
    reasons: list = field(default_factory=list)

    @property
    def targets_met(self) -> bool:
        return bool(len(self.sigma)) and bool(np.all(np.isfinite(self.sigma))) and \
            bool(np.all(self.sigma <= self.target))

    @property
    def worst(self) -> float:
        """The largest ``sigma / target`` (inf when a sigma is not estimable)."""
        r = self.sigma / self.target
        return float(np.max(np.where(np.isfinite(r), r, np.inf))) if len(r) else math.inf

    def table(self) -> str:
        """The sigma-against-target table as text (the console operator prints it)."""
        rows = [f'{n:>22s} {s:11.4g} {t:11.4g} {u:4s} {"ok" if s <= t else "--"}'
                for n, u, s, t in zip(self.names, self.units, self.sigma, self.target,
                                      strict=True)]
        return '\n'.join([f'{"parameter":>22s} {"sigma":>11s} {"target":>11s}', *rows])


def stage_max(stage: str, planned: int) -> int:
    """The most placements ``stage`` asks for, given ``planned`` in its plan."""
    return min(int(planned), MAX_PLACEMENTS.get(stage, int(planned)))


def stage_min(stage: str, planned: int) -> int:
    """Placements ``stage`` takes before it may stop on its targets."""
    return min(int(planned), MIN_PLACEMENTS.get(stage, int(planned)))


def _budget(targets) -> float:
    return BUDGET_M * float(targets.depth) / BUDGET_DEPTH


# ----------------------------------------------------------------------------- intrinsics
#: The intrinsics the stage estimates (its default distortion model, k1 k2 p1 p2).
INTRINSICS_NAMES = ('fx', 'fy', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2')
_INTRINSICS_UNITS = ('px', 'px', 'px', 'px', '1', '1', '1', '1')


def _camera(model):
    intr = model.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    d = np.zeros(5)
    d[:min(5, len(intr.dist))] = np.asarray(intr.dist, np.float64)[:5]
    return K, d


def _v_T_target(model, T):
    """The target's pose in the camera frame of the view G1 aims at its centre (None when
    out of reach)."""
    from calibration_tools.capture_plans import MAX_ABS_VOLTAGE
    from reconstructor.model import v0_T_v
    from reconstructor.planning import aim_g1

    g1 = aim_g1(model, T[:3, 3], max_abs_u=MAX_ABS_VOLTAGE)
    if not np.all(np.isfinite(g1)):
        return None
    return np.linalg.inv(np.asarray(v0_T_v(model, float(g1[0]), float(g1[1])))) @ T


def _schur(info: np.ndarray, k: int) -> np.ndarray:
    """Information on the first ``k`` parameters with the rest (a pose) taken out."""
    A, B, C = info[:k, :k], info[:k, k:], info[k:, k:]
    return A - B @ np.linalg.pinv(C) @ B.T


def _intrinsics_info(model, board, T, noise_px=FEATURE_NOISE_PX) -> np.ndarray | None:
    import cv2

    from calibration_tools.intrinsics import INTRINSIC_PARAMS, projection_jacobian

    V_T_B = _v_T_target(model, T)
    if V_T_B is None:
        return None
    obj = board.object_points()
    obj = obj - obj.mean(axis=0)
    K, d = _camera(model)
    rvec = cv2.Rodrigues(V_T_B[:3, :3])[0].ravel()
    tvec = V_T_B[:3, 3]
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, d)
    proj = proj.reshape(-1, 2)
    w, h = model.intrinsics.width, model.intrinsics.height
    inside = (proj[:, 0] >= 0) & (proj[:, 0] < w) & (proj[:, 1] >= 0) & (proj[:, 1] < h)
    if inside.sum() < 6:
        return None
    _, J = projection_jacobian([obj[inside]], [proj[inside]], K, d, [rvec], [tvec])
    cols = [INTRINSIC_PARAMS.index(n) for n in INTRINSICS_NAMES] + list(range(9, 15))
    J = J[:, cols] / noise_px
    return _schur(J.T @ J, len(INTRINSICS_NAMES))


def _intrinsics_prior() -> np.ndarray:
    from calibration_tools.intrinsics import INTRINSIC_PARAMS, LensPrior

    _, sigma = LensPrior().mean_sigma(2, 2)
    s = np.array([sigma[INTRINSIC_PARAMS.index(n)] for n in INTRINSICS_NAMES])
    return np.diag(np.where(np.isfinite(s), 1.0 / s ** 2, 0.0))


def _intrinsics_targets(model, targets) -> np.ndarray:
    """Budget [px at the working depth] over the RMS image displacement of each parameter
    (over a 7 x 7 grid spanning the image)."""
    import cv2

    K, d = _camera(model)
    w, h = model.intrinsics.width, model.intrinsics.height
    uu, vv = np.meshgrid(np.linspace(0, w - 1, 7), np.linspace(0, h - 1, 7))
    pix = np.column_stack([uu.ravel(), vv.ravel()]).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(pix, K, d).reshape(-1, 2)
    pts = np.column_stack([xy, np.ones(len(xy))])
    base = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
    budget_px = _budget(targets) * model.intrinsics.fx / float(targets.depth)
    out = []
    for j, name in enumerate(INTRINSICS_NAMES):
        if name in ('cx', 'cy'):
            out.append(PRINCIPAL_POINT_TARGET_PX)
            continue
        if name in ('fx', 'fy'):
            out.append(FOCAL_TARGET_REL * float(K[j, j]))
            continue
        vec = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d[:4]])
        step = 1e-6 * max(abs(vec[j]), 1.0)
        vec[j] += step
        K2 = np.array([[vec[0], 0, vec[2]], [0, vec[1], vec[3]], [0, 0, 1.0]])
        d2 = np.concatenate([vec[4:8], d[4:]])
        moved = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K2, d2)[0].reshape(-1, 2)
        s = math.sqrt(float(np.mean(np.sum((moved - base) ** 2, axis=1)))) / step
        out.append(budget_px / max(s, 1e-300))
    return np.array(out)


# ----------------------------------------------------------------------------- laser
def _board_depth_sigma(model, board, depth: float) -> float:
    """Standard error [m] of a board's position along its normal from its pattern's corners
    (one pixel is ``depth / fx``; the board's size gives the lever)."""
    pts = board.object_points()
    size = float(np.ptp(pts[:, 0]))
    px = depth / model.intrinsics.fx
    return px * FEATURE_NOISE_PX * depth / max(size, 1e-9) / math.sqrt(len(pts))


def _stripe_points(model, board, T, u2: float) -> np.ndarray | None:
    """Where the laser sheet of G2 voltage ``u2`` crosses the board at ``T`` (its pattern's
    extent), one point a pixel apart, shape (n, 3) in V0."""
    from reconstructor.model import laser_plane_v0

    pi = np.asarray(laser_plane_v0(model, u2), dtype=np.float64)
    n, e = pi[:3], pi[3]
    R, c = T[:3, :3], T[:3, 3]
    pts = board.object_points()
    half = 0.5 * np.ptp(pts[:, :2], axis=0)
    # board points c + R [x, y, 0]: n.(c + x a + y b) + e = 0
    a, b = R[:, 0], R[:, 1]
    na, nb, r0 = float(n @ a), float(n @ b), float(n @ c + e)
    step = float(c[2]) / model.intrinsics.fx
    if abs(nb) >= abs(na):
        x = np.arange(-half[0], half[0] + step, step)
        y = -(r0 + na * x) / nb
        ok = np.abs(y) <= half[1]
    else:
        y = np.arange(-half[1], half[1] + step, step)
        x = -(r0 + nb * y) / na
        ok = np.abs(x) <= half[0]
    if ok.sum() < 5:
        return None
    return c + np.outer(x[ok], a) + np.outer(y[ok], b)


def _sheet_jacobian(model, params, points, u2):
    """d(signed distance of ``points`` from the sheet of ``u2``) / d(params), shape (n, k);
    ``params`` is a list of (name, perturb(model, h) -> model, step)."""
    from reconstructor.model import laser_plane_v0

    P = np.column_stack([points, np.ones(len(points))])
    base = P @ np.asarray(laser_plane_v0(model, u2), dtype=np.float64)
    cols = []
    for _, perturb, h in params:
        moved = P @ np.asarray(laser_plane_v0(perturb(model, h), u2), dtype=np.float64)
        cols.append((moved - base) / h)
    return np.column_stack(cols)


def _perp(v) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(v, dtype=np.float64)
    a = np.cross(v, [1.0, 0, 0] if abs(v[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    return a, np.cross(v, a)


def _sheet_params(kind: str, model, centre):
    """The sheet parameters of a ``kind`` of :data:`PREDICTED`: (name, unit, perturb,
    step)."""
    import dataclasses

    if kind == 'sheet':
        pi = np.asarray(model.laser_plane_v0, dtype=np.float64)
        t1, t2 = _perp(pi[:3])
        c = np.asarray(centre, dtype=np.float64)

        def turn(t):
            def f(m, h):  # the sheet turned by h about an axis through the region's centre
                n = pi[:3] + h * t
                n = n / np.linalg.norm(n)
                e = float(pi[:3] @ c + pi[3]) - float(n @ c)
                return dataclasses.replace(m, laser_plane_v0=np.append(n, e))
            return f

        def shift(m, h):
            return dataclasses.replace(m, laser_plane_v0=pi + np.array([0, 0, 0, h]))
        return [('sheet_turn_a', 'rad', turn(t1), 1e-6), ('sheet_turn_b', 'rad', turn(t2), 1e-6),
                ('sheet_offset', 'm', shift, 1e-7)]
    n0 = np.asarray(model.laser_axis_dir, dtype=np.float64)
    a1, a2 = _perp(n0)

    def axis_turn(t):
        return lambda m, h: dataclasses.replace(m, laser_axis_dir=(n0 + h * t)
                                                / np.linalg.norm(n0 + h * t))

    def axis_shift(t):
        return lambda m, h: dataclasses.replace(
            m, laser_axis_point=np.asarray(m.laser_axis_point) + h * t)

    def gain(m, h):
        return dataclasses.replace(m, g2_tilt=dataclasses.replace(m.g2_tilt,
                                                                  k=m.g2_tilt.k + h))
    return [('axis_dir_a', 'rad', axis_turn(a1), 1e-6), ('axis_dir_b', 'rad', axis_turn(a2), 1e-6),
            ('axis_point_a', 'm', axis_shift(a1), 1e-7),
            ('axis_point_b', 'm', axis_shift(a2), 1e-7),
            ('g2_gain', 'rad/V', gain, 1e-8)]


def _lit_voltage(p) -> float | None:
    from calibration_tools.operator_flow import lit_voltage

    return lit_voltage(p)


def _sheet_info(model, params, p, T, targets) -> np.ndarray | None:
    u2 = _lit_voltage(p)
    if u2 is None:
        return None
    pts = _stripe_points(model, p.target, T, u2)
    if pts is None:
        return None
    J = _sheet_jacobian(model, params, pts, u2)
    s2 = (STRIPE_NOISE_PX * float(T[2, 3]) / model.intrinsics.fx) ** 2
    b2 = _board_depth_sigma(model, p.target, float(T[2, 3])) ** 2
    m = len(pts)
    # covariance s2 I + b2 1 1^T (one board's common error), inverted by Sherman-Morrison
    ones = J.sum(axis=0)
    return (J.T @ J - np.outer(ones, ones) * b2 / (s2 + m * b2)) / s2


def _sheet_targets(model, params, regions, targets) -> np.ndarray:
    """Budget over each parameter's RMS move of the sheet over ``regions`` ((points, u2)
    of the stage's whole plan)."""
    sq = np.zeros(len(params))
    n = 0
    for pts, u2 in regions:
        J = _sheet_jacobian(model, params, pts, u2)
        sq += np.sum(J ** 2, axis=0)
        n += len(pts)
    rms = np.sqrt(sq / max(n, 1))
    return _budget(targets) / np.maximum(rms, 1e-300)


# ----------------------------------------------------------------------------- dynamic camera
#: The dynamic camera's parameters: the two it states targets for (l, d: where the mirrors
#: put the virtual camera, which nothing later re-estimates), then the ones it estimates
#: with them (G1's gains, the pan zero, and the pinhole it refines, with the intrinsics
#: stage's standard errors as their prior), whose errors are taken out of l's and d's.
DYNAMIC_NAMES = ('l', 'd')
_DYNAMIC_NUISANCE = ('g1_pan.k', 'g1_tilt.k', 'g1_pan.theta0', 'fx', 'fy', 'cx', 'cy')
#: G1 voltages [V] over which the dynamic camera's targets are stated: the scanner's range
#: (+-8 V, a 7 x 7 grid), where l and d move the virtual camera most at its corners.
DYNAMIC_RANGE_V = 8.0


def _dynamic_perturb(name):
    import dataclasses

    if name in ('l', 'd'):
        return lambda m, h: dataclasses.replace(m, **{name: getattr(m, name) + h})
    if name.startswith('g1_'):
        mirror, attr = name.split('.')
        return lambda m, h: dataclasses.replace(m, **{mirror: dataclasses.replace(
            getattr(m, mirror), **{attr: getattr(getattr(m, mirror), attr) + h})})
    return lambda m, h: dataclasses.replace(m, intrinsics=dataclasses.replace(
        m.intrinsics, **{name: getattr(m.intrinsics, name) + h}))


_DYNAMIC_STEP = {'l': 1e-6, 'd': 1e-6, 'g1_pan.k': 1e-8, 'g1_tilt.k': 1e-8,
                 'g1_pan.theta0': 1e-7, 'fx': 1e-3, 'fy': 1e-3, 'cx': 1e-3, 'cy': 1e-3}


def _dynamic_project(model, X, U, seen=None):
    """Pixels of V0 points ``X`` (n, 3) in the views at G1 voltages ``U`` (m, 2): one array
    (k, 2) per view, of the points ``seen[view]`` indexes (default: all), and their depths
    in that view (k,)."""
    import cv2

    from reconstructor.model import v0_T_v

    K, d = _camera(model)
    V0_T_V = np.asarray(v0_T_v(model, U[:, 0], U[:, 1]))
    out, depth = [], []
    for j, T in enumerate(V0_T_V):
        V_T_V0 = np.linalg.inv(T)
        Xj = X if seen is None else X[seen[j]]
        Xv = Xj @ V_T_V0[:3, :3].T + V_T_V0[:3, 3]
        depth.append(Xv[:, 2])
        out.append(cv2.projectPoints(Xv, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
                   if len(Xv) else np.zeros((0, 2)))
    return out, depth


def _dynamic_views(model, p, T, targets) -> np.ndarray | None:
    """The G1 voltages (m, 2) the stage's views of the circle board at ``T`` are taken at
    (:func:`operator_flow.views_for`, as the scanner plans them)."""
    from calibration_tools.operator_flow import views_for

    try:
        steps = views_for(model, p, T, targets)
    except ValueError:
        return None
    return np.vstack([np.asarray(s.voltages, np.float64)[:, :2] for s in steps])


def _dynamic_info(model, p, T, targets, noise_px, seen=None) -> np.ndarray | None:
    """Information on (:data:`DYNAMIC_NAMES`, :data:`_DYNAMIC_NUISANCE`) of one circle-board
    placement at ``T``: its circles' centres in every view of it (``seen``: the G1 voltages
    (m, 2) of the views that showed it; default: the views planned around ``T``), the
    board's pose taken out."""
    from scipy.spatial.transform import Rotation

    U = _dynamic_views(model, p, T, targets) if seen is None else \
        np.asarray(seen, dtype=np.float64).reshape(-1, 2)
    if U is None or not len(U):
        return None
    board = p.target
    X = board.points() @ T[:3, :3].T + T[:3, 3]
    w, h = model.intrinsics.width, model.intrinsics.height
    every, z = _dynamic_project(model, X, U)
    seen = [np.flatnonzero((zj > 0) & (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0)
                           & (q[:, 1] < h)) for q, zj in zip(every, z, strict=True)]
    if sum(len(s) for s in seen) < 6:
        return None
    px = np.vstack([q[s] for q, s in zip(every, seen, strict=True)])

    def moved(m, Xm):
        return (np.vstack(_dynamic_project(m, Xm, U, seen)[0]) - px).ravel()
    cols = []
    for name in (*DYNAMIC_NAMES, *_DYNAMIC_NUISANCE):
        hstep = _DYNAMIC_STEP[name]
        cols.append(moved(_dynamic_perturb(name)(model, hstep), X) / hstep)
    c = T[:3, 3]
    for j in range(6):  # the board's pose: turned about its centre, moved
        e = np.zeros(3)
        e[j % 3] = 1e-6
        Xj = (X - c) @ Rotation.from_rotvec(e).as_matrix().T + c if j < 3 else X + e
        cols.append(moved(model, Xj) / 1e-6)
    J = np.column_stack(cols) / noise_px
    return _schur(J.T @ J, len(DYNAMIC_NAMES) + len(_DYNAMIC_NUISANCE))


def _dynamic_prior(model, prior_sigma) -> np.ndarray:
    """The nuisance parameters' prior: the intrinsics stage's standard errors (``prior_sigma``
    by name), else the lens prior's principal point."""
    from calibration_tools.intrinsics import LensPrior

    pp = LensPrior().principal_point_sigma_px
    given = dict(prior_sigma or {})
    k = len(DYNAMIC_NAMES) + len(_DYNAMIC_NUISANCE)
    info = np.zeros((k, k))
    for j, name in enumerate(_DYNAMIC_NUISANCE, len(DYNAMIC_NAMES)):
        s = given.get(name, pp if name in ('cx', 'cy') else math.inf)
        if math.isfinite(s) and s > 0:
            info[j, j] = 1.0 / s ** 2
    return info


def _dynamic_targets(model, targets) -> np.ndarray:
    """Budget over the RMS move, per unit of l and of d, of points at the working depth on
    the image centre's ray over G1's range (:data:`DYNAMIC_RANGE_V`), less what the stage's
    other parameters take up (the part of the move they cannot reproduce: their errors are
    estimated with l's and d's, and what they absorb never reaches a point)."""
    from reconstructor.model import v0_T_v

    g = np.linspace(-DYNAMIC_RANGE_V, DYNAMIC_RANGE_V, 7)
    up, ut = (a.ravel() for a in np.meshgrid(g, g))
    depth = float(targets.depth)

    def points(m):
        i = m.intrinsics
        ray = np.array([(0.5 * i.width - i.cx) / i.fx, (0.5 * i.height - i.cy) / i.fy, 1.0])
        return (np.asarray(v0_T_v(m, up, ut)) @ np.append(ray * depth, 1.0))[:, :3].ravel()

    base = points(model)
    names = (*DYNAMIC_NAMES, *_DYNAMIC_NUISANCE)
    J = np.column_stack([(points(_dynamic_perturb(n)(model, _DYNAMIC_STEP[n])) - base)
                         / _DYNAMIC_STEP[n] for n in names])
    out = []
    for j in range(len(DYNAMIC_NAMES)):
        others = np.delete(J, j, axis=1)
        coef = np.linalg.lstsq(others, J[:, j], rcond=None)[0]
        rms = math.sqrt(float(np.sum((J[:, j] - others @ coef) ** 2)) / len(up))
        out.append(_budget(targets) / max(rms, 1e-300))
    return np.array(out)


# ----------------------------------------------------------------------------- assess
def _describe(model, p) -> str:
    c = p.centre * 1e3
    return (f'placement {p.index + 1}: depth {c[2]:.0f} mm, x {c[0]:+.0f} mm, y {c[1]:+.0f} '
            f'mm, tilted {math.degrees(p.tilt()):.0f} deg')


def assess(stage: str, model, targets, kept, candidates, planned=(),
           noise_px=None, prior_sigma=None) -> Assessment:
    """The stage's standard errors after the placements ``kept`` and its advice.

    Parameters
    ----------
    stage : str
    model : RigModel
        The current model (aims, projection, the laser sheet).
    targets : capture_plans.Targets
    kept : sequence of (Placement, ndarray (4, 4)[, ndarray (m, 2) or None])
        Placements kept so far, each at the pose the scanner measured, and optionally the G1
        voltages of its views that showed the target (the dynamic camera: a view that missed
        the board brings nothing; default: every view planned around the pose).
    candidates : sequence of Placement
        Placements still to be asked for (at the poses asked for).
    planned : sequence of Placement
        Every placement of the stage's plan (the region its targets are stated over; the
        laser stages).
    noise_px : float, optional
        The features' noise the kept views show [px] (default :data:`FEATURE_NOISE_PX`).
    prior_sigma : dict of str to float, optional
        The dynamic camera: the standard errors [px] of the intrinsics it refines or holds,
        as the intrinsics stage stored them (``dynamic_camera.intrinsics_standard_errors``;
        default: the lens prior's principal point, focal lengths free).
    """
    noise = FEATURE_NOISE_PX if noise_px is None else float(noise_px)
    kept = [(k[0], k[1], k[2] if len(k) > 2 else None) for k in kept]
    if stage not in PREDICTED:
        return Assessment(stage, [], [], np.zeros(0), np.zeros(0),
                          best=0 if candidates else None,
                          advice=(f'next: {_describe(model, candidates[0])} (this stage '
                                  'takes every placement of its plan)') if candidates else '')
    kind = PREDICTED[stage]
    if kind == 'dynamic':
        names, units = list(DYNAMIC_NAMES), ['m'] * len(DYNAMIC_NAMES)
        target = _dynamic_targets(model, targets)
        prior = _dynamic_prior(model, prior_sigma)

        def info(p, T, seen=None):
            return _dynamic_info(model, p, T, targets, noise, seen)
    elif kind == 'camera':
        names, units = list(INTRINSICS_NAMES), list(_INTRINSICS_UNITS)
        target = _intrinsics_targets(model, targets)
        prior = _intrinsics_prior()

        def info(p, T, seen=None):
            return _intrinsics_info(model, p.target, T, noise)
    else:
        region = []
        for p in planned or [*(q for q, _, _ in kept), *candidates]:
            u2 = _lit_voltage(p)
            pts = None if u2 is None else _stripe_points(model, p.target, p.V0_T_target, u2)
            if pts is not None:
                region.append((pts, u2))
        centre = (np.vstack([r[0] for r in region]).mean(axis=0) if region
                  else np.array([0.0, 0.0, targets.depth]))
        params = _sheet_params(kind, model, centre)
        names, units = [q[0] for q in params], [q[1] for q in params]
        sp = [(q[0], q[2], q[3]) for q in params]
        target = _sheet_targets(model, sp, region, targets)
        prior = np.zeros((len(sp), len(sp)))

        def info(p, T, seen=None):
            return _sheet_info(model, sp, p, T, targets)

    rows = _row_needs(stage, planned or [*(q for q, _, _ in kept), *candidates],
                      [q for q, _, _ in kept], candidates)
    short = {r for r, (_, helps) in rows.items() if helps}
    total = prior.copy()
    pending: dict = {}  # a row's boards count once it has enough for its plane
    for p, T, seen in kept:
        got = info(p, np.asarray(T, dtype=np.float64), seen)
        if got is not None:
            if _row(p) in short:
                pending[_row(p)] = pending.get(_row(p), 0) + got
            elif _row(p) not in rows or rows[_row(p)][0]:  # a row too few for a plane: none
                total += got
    named = len(names)  # the dynamic camera's other parameters follow its named ones
    sigma = _sigma(total)[:named] if not short else np.full(named, np.nan)
    out = Assessment(stage, names, units, sigma, target)
    best, best_ratio = None, math.inf
    # the laser axis: what rows short of boards or of a depth still need first (each row
    # is one plane of the solver)
    pool = [k for k, p in enumerate(candidates) if _row(p) in short and rows[_row(p)][1](p)] \
        or list(range(len(candidates)))
    for k in pool:
        p = candidates[k]
        got = info(p, p.V0_T_target)
        if got is None:
            continue
        extra = got + pending.get(_row(p), 0) if _row(p) in short else got
        r = float(np.max(np.nan_to_num(_sigma(total + extra)[:named] / target, nan=1e9)))
        if r < best_ratio - 1e-12:
            best, best_ratio = k, r
    out.best, out.best_ratio = best, best_ratio
    worst = int(np.argmax(np.where(np.isfinite(sigma / target), sigma / target, np.inf)))
    if out.targets_met:
        out.advice = 'every standard error meets its target: press done, or add placements'
    elif best is not None:
        now = out.worst
        out.advice = (f'next: {_describe(model, candidates[best])}: brings the worst '
                      f'sigma/target ({names[worst]}) from '
                      + ('not estimable' if not math.isfinite(now) else f'{now:.2f}')
                      + f' to {best_ratio:.2f}')
    elif candidates:
        out.best = 0
        out.advice = f'next: {_describe(model, candidates[0])}'
    return out


def _row(p):
    """The G2 voltage a laser-axis board is lit at (its plane), rounded; None otherwise."""
    from calibration_tools.operator_flow import row_key

    return row_key(p)


def _rows(stage: str, places) -> set:
    """The laser axis's planes (G2 voltages) of its plan; empty for the other stages."""
    if PREDICTED.get(stage) != 'axis':
        return set()
    return {_row(p) for p in places if _row(p) is not None}


def _depths(places) -> dict:
    """Each placement's depth within its row (0 near, 1 far; 0 for a row at one depth),
    keyed by placement index (:data:`ROW_DEPTH_SPLIT`)."""
    by_row: dict = {}
    for p in places:
        by_row.setdefault(_row(p), []).append(p)
    out = {}
    for row in by_row.values():
        z = np.array([float(q.V0_T_target[2, 3]) for q in row])
        two = z.max() - z.min() > ROW_DEPTH_SPLIT * max(float(z.mean()), 1e-9)
        mid = 0.5 * (z.max() + z.min())
        out.update({q.index: int(two and zq > mid) for q, zq in zip(row, z, strict=True)})
    return out


def _row_needs(stage: str, planned, kept, candidates) -> dict:
    """The laser axis's rows (G2 planes of its plan) and what each still needs:
    ``{row: (enough, helps)}``, ``enough`` when its kept boards fit a plane
    (:data:`ROW_BOARDS`), ``helps`` a test of whether a candidate brings it the most of
    what it lacks and the candidates can still give (boards, a depth of its plan:
    :data:`ROW_DEPTH_SPLIT`, an end of its plan along the stripe:
    :data:`~calibration_tools.operator_flow.ROW_END_FRACTION`),
    None when it lacks nothing they can give. Empty for the other stages."""
    if PREDICTED.get(stage) != 'axis':
        return {}
    every = [*planned, *kept, *candidates]
    ends = {q.index: None if q.row_end is None else q.row_end[0] for q in every}
    labels = (_depths(every), ends)
    out = {}
    for r in _rows(stage, planned):
        mine = [q for q in kept if _row(q) == r]
        left = [q for q in candidates if _row(q) == r]
        wanted = []
        for label in labels:
            have = {label[q.index] for q in mine} | {None}
            want = {label[q.index] for q in planned if _row(q) == r} - have
            wanted.append(want & {label[q.index] for q in left})
        enough = len(mine) >= ROW_BOARDS
        if any(wanted):
            def brings(q, wanted=wanted):
                return sum(label[q.index] in w for label, w in zip(labels, wanted,
                                                                   strict=True))
            most = max(brings(q) for q in left)

            def helps(q, brings=brings, most=most):
                return brings(q) == most
        elif not enough and left:
            def helps(q):
                return True
        else:
            helps = None
        out[r] = (enough, helps)
    return out


def _sigma(info: np.ndarray) -> np.ndarray:
    """Standard errors of an information matrix (NaN where it is not invertible)."""
    k = len(info)
    if k == 0:
        return np.zeros(0)
    dg = np.diag(info)
    if np.any(~(dg > 0)):
        return np.full(k, np.nan)
    # judged on the correlations (parameters of metres and of pixels side by side)
    s = 1.0 / np.sqrt(dg)
    c = 0.5 * (info + info.T) * np.outer(s, s)
    w = np.linalg.eigvalsh(c)
    if w.min() <= 1e-12 * max(w.max(), 1e-300):
        return np.full(k, np.nan)
    return s * np.sqrt(np.clip(np.diag(np.linalg.inv(c)), 0.0, None))


# ----------------------------------------------------------------------------- coverage
#: Cells of the image coverage grid (columns, rows) and of the voltage coverage grid.
IMAGE_GRID = (8, 6)
VOLTAGE_GRID = (10, 10)
#: The laser stages' coverage spans G1 pan and G2 tilt (where along the sheet, which
#: sheet); the others span G1's two axes.
LASER_STAGES = ('laser_plane', 'laser_axis')


class Progress:
    """A capture's coverage: detected features per cell of a grid over the image, and views
    per cell of a grid over the voltages (placements kept; an undone one is forgotten)."""

    def __init__(self, stage: str, model, most: int):
        from calibration_tools.capture_plans import MAX_ABS_VOLTAGE

        self.stage, self.most = stage, int(most)
        self.size = (int(model.intrinsics.width), int(model.intrinsics.height))
        self.axes = 'u1x,u2' if stage in LASER_STAGES else 'u1x,u1y'
        self.extent = (-MAX_ABS_VOLTAGE, MAX_ABS_VOLTAGE, -MAX_ABS_VOLTAGE, MAX_ABS_VOLTAGE)
        self._points: dict = {}
        self._volts: dict = {}
        self._fits: dict = {}

    def feature_noise_px(self) -> float | None:
        """The detected features' noise [px] the kept views show: the median of their
        reprojection RMS about their own pose (88 corners, 6 pose parameters: scaled by
        sqrt(176 / 170)), floored at :data:`MIN_FEATURE_NOISE_PX`; None before any."""
        fits = [r for rs in self._fits.values() for r in rs]
        if not fits:
            return None
        return max(float(np.median(fits)) * math.sqrt(176.0 / 170.0),
                   MIN_FEATURE_NOISE_PX)

    def keep(self, index: int, points, voltages, fits=()) -> None:
        """Placement ``index`` kept: its views' detected features (list of (n, 2) px), its
        views' voltages (list of (m, 4) V) and its boards' reprojection RMS [px] (the
        gates' own PnP fits)."""
        self._fits[index] = [float(r) for r in fits]
        self._points[index] = [np.asarray(p, np.float64).reshape(-1, 2) for p in points]
        self._volts[index] = [np.asarray(v, np.float64).reshape(-1, 4) for v in voltages]

    def forget(self, index: int) -> None:
        self._fits.pop(index, None)
        self._points.pop(index, None)
        self._volts.pop(index, None)

    def image_coverage(self) -> np.ndarray:
        """Features per cell, shape (rows, cols)."""
        cols, rows = IMAGE_GRID
        pts = [p for ps in self._points.values() for p in ps]
        if not pts:
            return np.zeros((rows, cols), dtype=np.int64)
        uv = np.vstack(pts)
        h, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=(rows, cols),
                                 range=((0, self.size[1]), (0, self.size[0])))
        return h.astype(np.int64)

    def voltage_coverage(self) -> np.ndarray:
        """Views per cell, shape (rows, cols): first axis of :attr:`axes` across."""
        cols, rows = VOLTAGE_GRID
        vs = [v for vv in self._volts.values() for v in vv]
        if not vs:
            return np.zeros((rows, cols), dtype=np.int64)
        V = np.vstack(vs)
        a, b = (V[:, 0], V[:, 3]) if self.axes == 'u1x,u2' else (V[:, 0], V[:, 1])
        e = self.extent
        h, _, _ = np.histogram2d(b, a, bins=(rows, cols), range=((e[2], e[3]), (e[0], e[1])))
        return h.astype(np.int64)
