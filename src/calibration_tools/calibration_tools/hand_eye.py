"""A scanner on a robot flange: ``flange_T_v0`` by hand-eye calibration (AX = XB).

The robot shows a fixed artefact (three or more calibration spheres on a bar or plate, their
centres known in the artefact's own frame) to the scanner from N >= 5 flange poses that
differ in rotation about at least two axes. At each pose the scanner sweeps every sphere;
the centres in V0 fitted to the artefact's layout give ``v0_T_target`` (the same rigid fit
as the cell extrinsic). With the robot's ``base_T_flange`` per pose, AX = XB is solved over
every pair of poses in closed form (Park & Martin 1994, the method OpenCV's
``calibrateHandEye`` defaults to; OpenCV 5.0's PyPI wheels ship only its constants, not the
function) and then refined by least squares on what is used: ``base_T_target =
base_T_flange @ flange_T_v0 @ v0_T_target`` must be the same at every pose. The scatter of
that is the residual; the closed form's distance from the refined answer is reported too.

The result is stored like the cell extrinsic, as the calibration file's ``cell_T_v0`` with
the flange frame (e.g. ``tool0``) as its parent: the reconstructor then publishes
``tool0 -> v0`` on ``/tf_static`` (set its ``cell_frame`` parameter to the same name).
:func:`solve_hand_eye` states each axis' standard error of the mounting from the
refinement's Jacobian and residuals.

As a calibration stage (``hand_eye`` in :mod:`calibration_tools.registry`; the node's
services and ``galvoscan calibrate hand_eye``) the operator supplies the robot's flange poses
(:func:`calibration_tools.robot_poses.read_robot_poses`, or the node records them from the
robot's pose topic, one per capture) and the artefact (:func:`read_artefact`: its layout,
sphere radius, where it stands, and the mounting as designed to aim G1). :func:`plan_steps`
makes one sweep per sphere per robot pose (``pose_index = pose * POSE_STRIDE + sphere``),
:func:`run_hand_eye` fits the spheres, the artefact's pose at each robot pose, and solves.
In the simulator the rig's world frame W is the flange: each step's scene is the artefact
where the flange sees it, ``inv(base_T_flange) @ base_T_target``, and the true mounting is
the rig's ``W_T_V0``, which the calibration never reads.

No rclpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration_tools.robot_poses import MIN_POSES  # the fewest robot poses accepted

#: The second-largest spread of the pose-to-pose rotation axes must reach this [rad]:
#: rotations all about one axis leave the translation along it undetermined.
MIN_ROTATION_SPREAD = math.radians(5.0)
#: Lever arm that weighs rotation residuals against translation ones in the refinement [m].
LEVER_M = 0.1


@dataclass(frozen=True)
class HandEye:
    """The solved mounting of the scanner on the flange.

    Attributes
    ----------
    flange_T_v0 : ndarray, shape (4, 4), metres
    base_T_target : ndarray, shape (4, 4), metres
        Where the artefact stands in the robot base frame (mean over the poses).
    translation_rms : float, metres
        RMS over poses of how far each pose's ``base_T_target`` origin lies from the mean.
    rotation_rms : float, radians
        The same for its orientation.
    closed_form_step : tuple of (float, float)
        How far the refinement moved the closed-form (Park-Martin) answer: (metres, radians).
    translation_std : ndarray, shape (3,), metres
        Standard error of ``flange_T_v0``'s translation along the flange axes, from the
        refinement's Jacobian and its residuals (:func:`calibration_tools.stages.
        covariance_from_jacobian`): the scatter of the poses, robot and scanner together.
    rotation_std : ndarray, shape (3,), radians
        Standard error of small rotations of ``flange_T_v0`` about the flange axes.
    """

    flange_T_v0: np.ndarray
    base_T_target: np.ndarray
    translation_rms: float
    rotation_rms: float
    closed_form_step: tuple
    translation_std: np.ndarray
    rotation_std: np.ndarray


def _transforms(T, name: str) -> np.ndarray:
    from reconstructor.tf_frames import check_cell_T_v0

    a = np.asarray(T, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4):
        raise ValueError(f'{name}: expected shape (n, 4, 4), got {a.shape}')
    return np.stack([check_cell_T_v0(t, f'{name}[{i}]') for i, t in enumerate(a)])


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _check_diversity(base_T_flange: np.ndarray) -> None:
    """Refuse poses whose relative rotations are too small or all about one axis."""
    rel = [_rotvec(base_T_flange[0][:3, :3].T @ T[:3, :3]) for T in base_T_flange[1:]]
    spread = np.linalg.svd(np.array(rel), compute_uv=False) / math.sqrt(len(rel))
    if spread[0] < MIN_ROTATION_SPREAD:
        raise ValueError(f'the flange turns by {math.degrees(spread[0]):.1f} deg (RMS) '
                         f'between poses: at least {math.degrees(MIN_ROTATION_SPREAD):.0f} '
                         'deg needed; tilt the flange more')
    if spread[1] < MIN_ROTATION_SPREAD:
        raise ValueError('the flange turns about one axis only: the translation along it is '
                         'undetermined; add poses tilted about another axis')


def park_martin(base_T_flange: np.ndarray, v0_T_target: np.ndarray) -> np.ndarray:
    """Closed-form ``flange_T_v0`` from every pair of poses (Park & Martin 1994).

    For poses i, j: ``A = inv(T_j) T_i`` (flange motion), ``B = C_j inv(C_i)`` (the
    artefact's motion seen from V0), ``A X = X B``. Rotation: ``alpha = R_X beta`` for the
    log maps, ``R_X = (M^T M)^(-1/2) M^T`` with ``M = sum beta alpha^T``; translation:
    least squares of ``(R_A - I) t_X = R_X t_B - t_A``.
    """
    n = len(base_T_flange)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    A = [np.linalg.inv(base_T_flange[j]) @ base_T_flange[i] for i, j in pairs]
    B = [v0_T_target[j] @ np.linalg.inv(v0_T_target[i]) for i, j in pairs]
    M = sum(np.outer(_rotvec(b[:3, :3]), _rotvec(a[:3, :3])) for a, b in zip(A, B, strict=True))
    w, V = np.linalg.eigh(M.T @ M)
    R = V @ np.diag(1.0 / np.sqrt(np.clip(w, 1e-30, None))) @ V.T @ M.T
    lhs = np.vstack([a[:3, :3] - np.eye(3) for a in A])
    rhs = np.concatenate([R @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B, strict=True)])
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return X


def _residuals(base_T_flange, v0_T_target, X, Y) -> np.ndarray:
    """Per pose, how far ``base_T_flange @ X @ v0_T_target`` is from ``Y`` (in the target's
    frame): translation [m], then rotation [rad] times :data:`LEVER_M`."""
    out = []
    for T, C in zip(base_T_flange, v0_T_target, strict=True):
        D = np.linalg.inv(Y) @ T @ X @ C
        out += [D[:3, 3], LEVER_M * _rotvec(D[:3, :3])]
    return np.concatenate(out)


def _refine(base_T_flange, v0_T_target, X0) -> tuple[np.ndarray, np.ndarray]:
    """``flange_T_v0`` and ``base_T_target`` that make every pose agree (least squares)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def unpack(q):
        X, Y = np.eye(4), np.eye(4)
        X[:3, :3], X[:3, 3] = Rotation.from_rotvec(q[:3]).as_matrix(), q[3:6]
        Y[:3, :3], Y[:3, 3] = Rotation.from_rotvec(q[6:9]).as_matrix(), q[9:12]
        return X, Y

    def residuals(q):
        return _residuals(base_T_flange, v0_T_target, *unpack(q))

    Y0 = _mean_pose(base_T_flange @ X0 @ v0_T_target)
    q0 = np.concatenate([_rotvec(X0[:3, :3]), X0[:3, 3], _rotvec(Y0[:3, :3]), Y0[:3, 3]])
    return unpack(least_squares(residuals, q0, method='lm', xtol=1e-15, ftol=1e-15).x)


def _left(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T`` turned by the small rotation vector ``d[:3]`` about its parent's axes (origin
    kept) and moved by ``d[3:]``."""
    from scipy.spatial.transform import Rotation

    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(d[:3]).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + d[3:]
    return out


def _standard_errors(base_T_flange, v0_T_target, X, Y) -> np.ndarray:
    """1-sigma of (rotation about the flange axes [rad], translation [m]) of ``X``.

    The Jacobian of :func:`_residuals` with respect to small changes of X and Y (central
    differences) and the residuals at the solution give the covariance
    (:func:`calibration_tools.stages.covariance_from_jacobian`).
    """
    from calibration_tools.stages import covariance_from_jacobian

    h = 1e-6
    r0 = _residuals(base_T_flange, v0_T_target, X, Y)
    J = np.empty((r0.size, 12))
    for j in range(12):
        d = np.zeros(12)
        d[j] = h
        plus = _residuals(base_T_flange, v0_T_target, _left(X, d[:6]), _left(Y, d[6:]))
        minus = _residuals(base_T_flange, v0_T_target, _left(X, -d[:6]), _left(Y, -d[6:]))
        J[:, j] = (plus - minus) / (2 * h)
    cov, _ = covariance_from_jacobian(J, r0)
    return np.sqrt(np.clip(np.diag(cov)[:6], 0.0, None))


def _mean_pose(Ts: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = Ts[:, :3, 3].mean(axis=0)
    return out


def solve_hand_eye(base_T_flange, v0_T_target) -> HandEye:
    """``flange_T_v0`` from robot poses and the artefact's pose seen by the scanner.

    Parameters
    ----------
    base_T_flange : array_like, shape (n, 4, 4), metres
        The robot's flange pose per capture (its controller's report).
    v0_T_target : array_like, shape (n, 4, 4), metres
        The artefact's pose in V0 measured at the same captures.

    Raises
    ------
    ValueError
        Shapes, non-rigid or non-finite transforms, translations in millimetres, fewer than
        5 poses, or rotations too small or all about one axis (the message says which).
    """
    A = _transforms(base_T_flange, 'base_T_flange')
    B = _transforms(v0_T_target, 'v0_T_target')
    if A.shape != B.shape:
        raise ValueError(f'base_T_flange and v0_T_target differ in count: {len(A)} vs {len(B)}')
    if len(A) < MIN_POSES:
        raise ValueError(f'{len(A)} poses: hand-eye calibration needs at least {MIN_POSES}')
    _check_diversity(A)
    X0 = park_martin(A, B)
    X, Y = _refine(A, B, X0)
    std = _standard_errors(A, B, X, Y)
    targets = A @ X @ B
    mean = _mean_pose(targets)
    dt = targets[:, :3, 3] - mean[:3, 3]
    dr = np.array([_rotvec(mean[:3, :3].T @ T[:3, :3]) for T in targets])
    step = (float(np.linalg.norm(X0[:3, 3] - X[:3, 3])),
            float(np.linalg.norm(_rotvec(X[:3, :3].T @ X0[:3, :3]))))
    return HandEye(flange_T_v0=X, base_T_target=mean,
                   translation_rms=float(np.sqrt(np.mean(np.sum(dt ** 2, axis=1)))),
                   rotation_rms=float(np.sqrt(np.mean(np.sum(dr ** 2, axis=1)))),
                   closed_form_step=step, translation_std=std[3:], rotation_std=std[:3])


def target_pose(centres_v0, layout) -> np.ndarray:
    """``v0_T_target`` (4, 4) from the artefact's sphere centres measured in V0.

    Parameters
    ----------
    centres_v0 : array_like, shape (k, 3), metres
        The measured centres, in the order of ``layout``.
    layout : array_like, shape (k, 3), metres
        The same centres in the artefact's frame (k >= 3, not on one line).
    """
    from calibration_tools.cell_extrinsic import solve_cell_T_v0

    # the cell extrinsic's rigid fit (Kabsch), here mapping the layout into V0
    return solve_cell_T_v0(layout, centres_v0, min_spread=0.02).cell_T_v0


def artefact_scene_yaml(centres_w, radius: float) -> str:
    """Simulator scene text: the artefact's spheres at ``centres_w`` (k, 3) [m] in W."""
    objects = ''.join(
        f'  - type: sphere\n    name: sphere{k}\n    pose: {{translation: '
        f'{[float(v) for v in c]}, rotation_vector: [0.0, 0.0, 0.0]}}\n'
        f'    radius: {float(radius)}\n    albedo: 0.75\n'
        for k, c in enumerate(np.asarray(centres_w, dtype=np.float64)))
    return f'format_version: 1\nname: hand_eye_artefact\nobjects:\n{objects}'


# ----------------------------------------------------------------------------- the stage
#: A capture's ``pose_index`` is ``robot pose * POSE_STRIDE + sphere``: which robot pose and
#: which of the artefact's spheres its sweep is of.
POSE_STRIDE = 100
#: Sweep frames per sphere (full plan, quick plan).
FRAMES = (40, 16)
_ARTEFACT_KEYS = {'unit', 'sphere_radius', 'layout', 'base_T_target', 'nominal_flange_T_v0'}


@dataclass(frozen=True, eq=False)
class Artefact:
    """The hand-eye stage's artefact (:func:`read_artefact`).

    Attributes
    ----------
    layout : ndarray, shape (k, 3), metres
        The sphere centres in the artefact's frame.
    sphere_radius : float, metres
    base_T_target : ndarray, shape (4, 4), metres
        Where the artefact stands in the robot's base frame, as placed (aims G1).
    nominal_flange_T_v0 : ndarray, shape (4, 4), or None
        The scanner's mounting as designed (aims G1 before it is measured).
    """

    layout: np.ndarray
    sphere_radius: float
    base_T_target: np.ndarray
    nominal_flange_T_v0: np.ndarray | None = None


def read_artefact(path) -> Artefact:
    """The artefact the scanner measures at every robot pose, and where it roughly is.

    The file is YAML::

        unit: m                 # metres; anything else is refused
        sphere_radius: 0.01
        layout:                 # the sphere centres in the artefact's frame (>= 3, not on
          - [0.0, 0.0, 0.0]     # one line, spread >= 20 mm), e.g. from its drawing
          - [0.12, 0.0, 0.0]
          - [0.0, 0.10, 0.0]
        base_T_target:          # where it stands in the robot's base frame, 4 rows of 4
          - [1, 0, 0, 1.1]      # (a few mm and a degree off is fine: it aims G1)
          - ...
        nominal_flange_T_v0:    # optional: the scanner's mounting as designed (aims G1);
          - ...                 # without it, the cell_T_v0 of an earlier hand_eye result

    Raises
    ------
    ValueError
        Unreadable file, missing or unknown keys, a unit other than ``m``, a radius not in
        (0, 0.1] m, a layout of fewer than 3 spheres, on one line or in millimetres, or a
        pose that is not rigid; the key is named.
    """
    from calibration_tools.cell_extrinsic import _points, solve_cell_T_v0
    from galvoscan_common.yamlfile import read_yaml_mapping
    from reconstructor.tf_frames import check_cell_T_v0

    data = read_yaml_mapping(path, 'hand-eye artefact file')
    unknown = set(data) - _ARTEFACT_KEYS
    if unknown:
        raise ValueError(f'{path}: unknown keys {sorted(unknown)} '
                         f'(known: {sorted(_ARTEFACT_KEYS)})')
    missing = sorted({'unit', 'sphere_radius', 'layout', 'base_T_target'} - set(data))
    if missing:
        raise ValueError(f'{path}: missing {missing}')
    if data['unit'] != 'm':
        raise ValueError(f"{path}: unit: lengths must be in metres ('m'), got {data['unit']!r}")
    radius = data['sphere_radius']
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) \
            or not 0.0 < radius <= 0.1:
        raise ValueError(f'{path}: sphere_radius: expected metres in (0, 0.1], got {radius!r}')
    try:
        layout = _points(data['layout'], 'layout')
        if not 3 <= len(layout) <= POSE_STRIDE:
            raise ValueError(f'layout: {len(layout)} spheres; 3 to {POSE_STRIDE} needed')
        try:  # the rigid fit target_pose runs: refuses a line or a cluster
            solve_cell_T_v0(layout, layout, min_spread=0.02)
        except ValueError as err:
            raise ValueError(f'layout: {err}') from None
        poses = {k: check_cell_T_v0(np.asarray(data[k], dtype=np.float64), k)
                 for k in ('base_T_target', 'nominal_flange_T_v0') if data.get(k) is not None}
    except (ValueError, TypeError) as err:
        raise ValueError(f'{path}: {err}') from None
    return Artefact(layout, float(radius), poses['base_T_target'],
                    poses.get('nominal_flange_T_v0'))


def _robot_poses(source):
    """A :class:`~calibration_tools.robot_poses.RobotPoses`, or the file that holds them."""
    from calibration_tools.robot_poses import RobotPoses, read_robot_poses

    return source if isinstance(source, RobotPoses) else read_robot_poses(source)


def capture_steps(model, base_T_flange: dict, artefact: Artefact, flange_T_v0, *,
                  frames: int = FRAMES[0]):
    """Per robot pose, one sweep per sphere of the artefact, G1 aimed at it.

    Parameters
    ----------
    model : reconstructor.model.RigModel
        The operator's current model (aims G1).
    base_T_flange : dict of int to ndarray shape (4, 4), metres
        Robot pose number -> the flange pose the scanner measures from.
    artefact : Artefact
    flange_T_v0 : ndarray, shape (4, 4)
        The mounting that aims G1 (as designed, or an earlier result).

    Returns
    -------
    list of CaptureStep
        ``pose_index = pose * POSE_STRIDE + sphere``. The scene of each step is the whole
        artefact as the flange sees it: in the simulator the rig's world frame W is the
        flange (the robot carries the rig; its true mounting is the rig's ``W_T_V0``). A
        real rig ignores the scene: the robot holds the pose.
    """
    import dataclasses

    from calibration_tools.cell_extrinsic import capture_steps as sphere_steps

    v0_T_flange = np.linalg.inv(np.asarray(flange_T_v0, dtype=np.float64))
    layout, steps = artefact.layout, []
    for key, T in sorted(base_T_flange.items()):
        flange_T_target = np.linalg.inv(T) @ artefact.base_T_target
        shown = layout @ flange_T_target[:3, :3].T + flange_T_target[:3, 3]
        aim = shown @ v0_T_flange[:3, :3].T + v0_T_flange[:3, 3]
        scene = artefact_scene_yaml(shown, artefact.sphere_radius)
        for step in sphere_steps(model, aim, sphere_radius=artefact.sphere_radius,
                                 frames=frames, scene_positions=shown,
                                 pose_indices=[key * POSE_STRIDE + k for k in range(len(aim))]):
            steps.append(dataclasses.replace(
                step, scene_yaml=scene,
                note=f'robot pose {key}, sphere {step.pose_index % POSE_STRIDE}'))
    return steps


def _aiming_mounting(artefact: Artefact, calibration, source) -> np.ndarray:
    from calibration_tools.stages import HAND_EYE_STAGE

    if artefact.nominal_flange_T_v0 is not None:
        return artefact.nominal_flange_T_v0
    entry = getattr(calibration, 'stages', {}).get(HAND_EYE_STAGE)
    if entry and not entry.get('superseded_by') and calibration.cell_T_v0 is not None:
        return calibration.cell_T_v0
    raise ValueError(f'{source}: nominal_flange_T_v0 is needed to aim at the artefact (the '
                     'calibration holds no hand_eye result yet); give the scanner\'s mounting '
                     'as designed, a few mm and a degree off is fine')


def plan_steps(model, quick: bool, options: dict):
    """The hand-eye stage's capture plan (registry entry): every sphere from every robot pose.

    ``options`` holds ``robot_poses`` (a file, or the
    :class:`~calibration_tools.robot_poses.RobotPoses` the node read from the robot's pose
    topic), ``hand_eye_artefact`` (a file, :func:`read_artefact`) and ``calibration``.

    Raises
    ------
    ValueError
        Unreadable inputs, no mounting to aim with, or a sphere out of G1 reach.
    """
    poses = _robot_poses(options['robot_poses'])
    artefact = read_artefact(options['hand_eye_artefact'])
    X = _aiming_mounting(artefact, options.get('calibration'), options['hand_eye_artefact'])
    return capture_steps(model, poses.by_key(), artefact, X,
                         frames=FRAMES[1] if quick else FRAMES[0])


def run_hand_eye(views, calibration, options: dict, progress=None):
    """The hand-eye stage's solver (registry entry): sphere centres, artefact poses, AX = XB.

    Returns
    -------
    calibration_tools.stages.StageResult
        No model update; ``extra['hand_eye']`` (:func:`result_extra`) becomes the file's
        ``cell_T_v0`` with the flange as its ``cell_frame``
        (:func:`calibration_tools.stages.apply_result`).

    Raises
    ------
    ValueError
        Fewer than ``MIN_POSES`` robot poses both reported and measured (three spheres or
        more each), or poses that cannot fix the mounting (:func:`solve_hand_eye`).
    """
    from calibration_tools.cell_extrinsic import sphere_centres
    from calibration_tools.stages import HAND_EYE_STAGE, StageResult

    def report(done, total, message=''):
        if progress is not None:
            progress(done, total, message)

    poses = _robot_poses(options['robot_poses'])
    artefact = read_artefact(options['hand_eye_artefact'])
    reported = poses.by_key()
    report(0, 3, f'{len(reported)} robot poses; fitting the spheres')
    centres, rejected = sphere_centres(views, calibration.model,
                                       sphere_radius=artefact.sphere_radius)
    by_pose: dict[int, dict] = {}
    for index, (centre, _) in centres.items():
        key, k = divmod(index, POSE_STRIDE)
        if k >= len(artefact.layout):
            rejected.append(f'pose_index {index}: sphere {k} is not in the layout')
            continue
        by_pose.setdefault(key, {})[k] = centre
    report(1, 3, f'{len(centres)} sphere centres; the artefact at each robot pose')
    measured = {}
    for key, found in sorted(by_pose.items()):
        if key not in reported:
            rejected.append(f'robot pose {key}: measured but not in {poses.source}')
            continue
        ks = sorted(found)
        try:
            measured[key] = target_pose([found[k] for k in ks], artefact.layout[ks])
        except ValueError as err:
            rejected.append(f'robot pose {key}: spheres {ks} measured: {err}')
    seen = {int(v.pose_index) // POSE_STRIDE for v in views if v.laser_on}
    rejected += [f'robot pose {k}: reported but not captured' for k in sorted(set(reported)
                                                                               - seen)]
    keys = sorted(measured)
    if len(keys) < MIN_POSES:
        raise ValueError(f'hand_eye: {len(keys)} robot poses both reported and measured; at '
                         f'least {MIN_POSES} needed'
                         + (f"; {'; '.join(rejected)}" if rejected else ''))
    report(2, 3, f'{len(keys)} robot poses; solving AX = XB')
    sol = solve_hand_eye(np.array([reported[k] for k in keys]),
                         np.array([measured[k] for k in keys]))
    extra = result_extra(sol, poses.flange_frame, poses.base_frame)
    extra['poses'] = [int(k) for k in keys]
    report(3, 3, 'done')
    return StageResult(
        stage=HAND_EYE_STAGE, residuals={
            'base_T_target_rms_m': sol.translation_rms,
            'base_T_target_rms_rad': sol.rotation_rms,
            'translation_std_max_m': float(np.max(sol.translation_std)),
            'rotation_std_max_rad': float(np.max(sol.rotation_std))},
        samples_used=len(keys), samples_rejected=len(rejected), rejected=rejected,
        extra={HAND_EYE_STAGE: extra})


def result_extra(solution: HandEye, flange_frame: str, base_frame: str) -> dict:
    """What the calibration file keeps of a solution (plain floats)."""
    from calibration_tools.cell_extrinsic import mounting_record

    return {**mounting_record(solution.flange_T_v0, flange_frame, solution.translation_std,
                              solution.rotation_std, solution.translation_rms),
            'base_frame': base_frame,
            'base_T_target': [[float(v) for v in row] for row in solution.base_T_target],
            'base_T_target_rms_rad': solution.rotation_rms,
            'closed_form_step': [float(v) for v in solution.closed_form_step]}
