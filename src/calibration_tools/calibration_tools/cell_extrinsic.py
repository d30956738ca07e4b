"""Where the scanner sits in the robot cell: ``cell_T_v0`` from a sphere at known positions.

The robot carries the calibration sphere to N >= 3 positions (not on one line) and reports
each in the cell frame (its TCP is the sphere's centre). At each position the scanner aims
G1 at the sphere and sweeps the laser over it; the swept points fit a sphere of the known
radius, whose centre is the position in V0. The rigid transform that maps the V0 centres
onto the reported cell positions is ``cell_T_v0`` (Kabsch / Umeyama without scale), with
its covariance from the residuals: each axis' standard error of translation [m] and of
rotation [rad]. The fit is refused when the positions cannot fix it: fewer than 3, or all
on one line (the rotation about that line is free), or spread less than ``min_spread``.

As a calibration stage (``cell_extrinsic`` in :mod:`calibration_tools.registry`; the node's
services and ``galvoscan calibrate cell_extrinsic``) the operator supplies a reference file
(:func:`read_reference`): the positions in the cell frame and, to aim G1 before anything is
measured, a nominal ``cell_T_v0`` (e.g. from the cell's CAD; a few millimetres and a degree
off is fine) unless the calibration already holds one. :func:`plan_steps` makes one sweep
per position, :func:`run_cell_extrinsic` measures the centres and solves; the result goes
to the calibration file's ``cell_T_v0`` (:func:`calibration_tools.stages.apply_result`).

In the simulator the cell frame is the rig file's world frame W (the robot places the
sphere at its reported position in W; the scanner's true mounting ``W_T_V0`` is the
rig's, which the calibration never reads).

No rclpy; the capture plan is :func:`capture_steps`, the solver :func:`solve_cell_T_v0`,
the measurement :func:`sphere_centres`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Sweep frames per position (full plan, quick plan).
FRAMES = (40, 16)

#: Smallest spread (RMS distance of the positions from their mean) that the fit accepts [m].
MIN_SPREAD_M = 0.05
#: Smallest ratio of the positions' second to first principal spread: below it they lie on
#: one line and the rotation about it is not determined.
MIN_PLANARITY = 0.05


@dataclass(frozen=True)
class CellExtrinsic:
    """The solved mounting of the scanner in the cell.

    Attributes
    ----------
    cell_T_v0 : ndarray, shape (4, 4)
        Maps V0 points [m] into the cell frame.
    residuals : ndarray, shape (n, 3), metres
        ``cell_T_v0 @ p_v0 - p_cell`` per position.
    rms : float, metres
        RMS of the residual vectors' lengths.
    translation_std : ndarray, shape (3,), metres
        Standard error of the translation along the cell axes.
    rotation_std : ndarray, shape (3,), radians
        Standard error of small rotations about the cell axes.
    """

    cell_T_v0: np.ndarray
    residuals: np.ndarray
    rms: float
    translation_std: np.ndarray
    rotation_std: np.ndarray


def _points(a, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f'{name}: expected shape (n, 3) metres, got {p.shape}')
    if not np.all(np.isfinite(p)):
        raise ValueError(f'{name}: not finite')
    if np.abs(p).max() > 100.0:
        raise ValueError(f'{name}: coordinates beyond 100 m (millimetres given for metres?)')
    return p


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def solve_cell_T_v0(p_v0, p_cell, *, min_spread: float = MIN_SPREAD_M) -> CellExtrinsic:
    """The rigid ``cell_T_v0`` that best maps ``p_v0`` onto ``p_cell`` (least squares).

    Parameters
    ----------
    p_v0 : array_like, shape (n, 3), metres
        Sphere centres measured by the scanner, in V0.
    p_cell : array_like, shape (n, 3), metres
        The same positions as the robot reports them, in the cell frame.
    min_spread : float, metres

    Raises
    ------
    ValueError
        Shapes, non-finite values, fewer than 3 positions, positions too close together or
        on one line (the message says which and what to do).
    """
    a, b = _points(p_v0, 'p_v0'), _points(p_cell, 'p_cell')
    if a.shape != b.shape:
        raise ValueError(f'p_v0 and p_cell differ in shape: {a.shape} vs {b.shape}')
    n = a.shape[0]
    if n < 3:
        raise ValueError(f'{n} positions: cell_T_v0 needs at least 3, not on one line')
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    qa, qb = a - ca, b - cb
    spread = np.linalg.svd(qa, compute_uv=False) / math.sqrt(n)
    if math.sqrt(float(np.sum(spread ** 2))) < min_spread:
        raise ValueError(f'the positions spread {1e3 * np.sqrt(np.sum(spread ** 2)):.1f} mm '
                         f'(RMS): at least {1e3 * min_spread:.0f} mm needed; move the sphere '
                         'farther apart')
    if spread[1] < MIN_PLANARITY * spread[0]:
        raise ValueError('the positions lie on one line: the rotation about it is '
                         'unobservable; add a position off that line')
    U, _, Vt = np.linalg.svd(qb.T @ qa)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    t = cb - R @ ca
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    res = a @ R.T + t - b
    # linearised about the solution: delta p_cell = -[R p]x w + dt for a small rotation w
    J = np.zeros((3 * n, 6))
    for i, p in enumerate(a @ R.T):
        J[3 * i:3 * i + 3, :3] = -_skew(p)
        J[3 * i:3 * i + 3, 3:] = np.eye(3)
    dof = 3 * n - 6
    sigma2 = float(np.sum(res ** 2)) / dof if dof > 0 else float('nan')
    cov = sigma2 * np.linalg.inv(J.T @ J)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return CellExtrinsic(cell_T_v0=T, residuals=res,
                         rms=float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))),
                         translation_std=std[3:], rotation_std=std[:3])


def rotation_angle(R: np.ndarray) -> float:
    """Angle of the rotation matrix ``R`` [rad] (0 for the identity)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(math.acos(min(1.0, max(-1.0, c))))


@dataclass(frozen=True)
class CellReference:
    """The operator's reference for the cell stage (:func:`read_reference`).

    Attributes
    ----------
    cell_frame : str
    positions : dict of int to ndarray, shape (3,), metres
        pose_index -> sphere centre in the cell frame.
    nominal_cell_T_v0 : ndarray, shape (4, 4), or None
        Where the scanner roughly is (to aim G1 before it is measured).
    """

    cell_frame: str
    positions: dict
    nominal_cell_T_v0: np.ndarray | None = None


def read_reference(path) -> CellReference:
    """The robot-reported sphere positions and the cell frame they are in.

    The file is YAML::

        cell_frame: world           # the frame the positions are in (REP 105 name)
        unit: m                     # metres; anything else is refused
        positions:                  # pose_index of the capture -> sphere centre
          0: [1.2031, -0.4112, 0.9020]
          1: [...]
        nominal_cell_T_v0:          # optional: 4 rows of 4 numbers, the scanner's mounting
          - [1, 0, 0, 0.8]          # as designed (to aim at the positions); without it the
          - ...                     # calibration's cell_T_v0 is used

    Raises
    ------
    ValueError
        Unreadable file, missing or unknown keys, a unit other than ``m``, non-finite or
        absurd coordinates (beyond 100 m), fewer than 3 positions, or a nominal pose that
        is not rigid; the key is named.
    """
    from galvoscan_common.yamlfile import read_yaml_mapping
    from reconstructor.tf_frames import check_cell_T_v0

    data = read_yaml_mapping(path, 'cell reference')
    unknown = set(data) - {'cell_frame', 'unit', 'positions', 'nominal_cell_T_v0'}
    if unknown:
        raise ValueError(f'{path}: unknown keys {sorted(unknown)}')
    if data.get('unit') != 'm':
        raise ValueError(f"{path}: unit: positions must be in metres ('m'), "
                         f"got {data.get('unit')!r}")
    frame = data.get('cell_frame')
    if not isinstance(frame, str) or not frame or any(c.isspace() for c in frame):
        raise ValueError(f'{path}: cell_frame: expected a frame name, got {frame!r}')
    positions = data.get('positions')
    if not isinstance(positions, dict) or len(positions) < 3:
        raise ValueError(f'{path}: positions: expected at least 3 pose_index: [x, y, z] '
                         'entries')
    out = {}
    for key, xyz in positions.items():
        if isinstance(key, bool) or not isinstance(key, int) or key < 0:
            raise ValueError(f'{path}: positions: key {key!r} is not a pose_index >= 0')
        try:
            out[key] = _points([xyz], f'positions.{key}')[0]
        except (ValueError, TypeError) as err:
            raise ValueError(f'{path}: {err}') from None
    nominal = data.get('nominal_cell_T_v0')
    if nominal is not None:
        try:
            nominal = check_cell_T_v0(np.asarray(nominal, dtype=np.float64),
                                      'nominal_cell_T_v0')
        except (ValueError, TypeError) as err:
            raise ValueError(f'{path}: {err}') from None
    return CellReference(frame, out, nominal)


def sphere_centres(views, model, *, sphere_radius: float, min_points: int = 200):
    """Per pose_index, the centre [m] in V0 of the sphere the laser swept over, and its fit.

    Returns
    -------
    dict of int to (ndarray shape (3,), SphereFit)
        Positions whose points do not fit a sphere of ``sphere_radius`` are left out and
        listed in the second return value with the reason.
    list of str
    """
    from calibration_tools.joint_correction import reconstruct_nodes
    from calibration_tools.sphere_fit import fit_sphere

    nodes = reconstruct_nodes(views, model, use_correction=True)
    by_pose: dict[int, list] = {}
    for node in nodes:
        by_pose.setdefault(node.pose_index, []).append(node.points)
    centres, rejected = {}, []
    for pose, parts in sorted(by_pose.items()):
        pts = np.vstack(parts)
        if pts.shape[0] < min_points:
            rejected.append(f'position {pose}: {pts.shape[0]} points (< {min_points})')
            continue
        try:
            fit = fit_sphere(pts, radius=sphere_radius, seed=pose)
        except ValueError as err:
            rejected.append(f'position {pose}: no sphere fit ({err})')
            continue
        if fit.rms > 0.05 * sphere_radius:
            rejected.append(f'position {pose}: sphere fit RMS {1e6 * fit.rms:.0f} um')
            continue
        centres[pose] = (fit.centre, fit)
    return centres, rejected


def capture_steps(model, positions_v0, *, sphere_radius: float, frames: int = FRAMES[0],
                  fraction: float = 0.7, frame_rate: float = 100.0, pose_indices=None,
                  scene_positions=None):
    """One step per position: the sphere there, G1 aimed at it, G2 swept across it.

    Parameters
    ----------
    model : reconstructor.model.RigModel
        The operator's current model (aims G1).
    positions_v0 : array_like, shape (n, 3), metres
        Where the model expects the sphere (for a robot: its reported positions mapped by
        the nominal ``v0_T_cell``). The sweep covers ``fraction`` of the view's height at
        the sphere's distance.
    pose_indices : sequence of int, optional
        The steps' pose_index (default 0..n-1): the reference file's keys.
    scene_positions : array_like, shape (n, 3), metres, optional
        Where the simulator shows the sphere (its world frame W: the cell); default
        ``positions_v0``. A real rig ignores the scene; the robot places the sphere.
    """
    from calibration_tools.placement import _aim, sphere_scene_yaml
    from calibration_tools.stages import CaptureStep
    from reconstructor.planning import view_sweep

    p_v0 = _points(positions_v0, 'positions_v0')
    scene = p_v0 if scene_positions is None else _points(scene_positions, 'scene_positions')
    keys = list(range(len(p_v0))) if pose_indices is None else [int(k) for k in pose_indices]
    if scene.shape != p_v0.shape or len(keys) != len(p_v0):
        raise ValueError('positions_v0, scene_positions and pose_indices differ in length')
    steps = []
    for k, centre, shown in zip(keys, p_v0, scene, strict=True):
        aim = _aim(model, centre, f'sphere position {k}')
        distance = float(np.linalg.norm(centre)) - sphere_radius
        volts = view_sweep(model, float(aim[0]), float(aim[1]), distance, frames, fraction)
        steps.append(CaptureStep(k, sphere_scene_yaml(shown, sphere_radius), volts, True,
                                 frame_rate, note=f'sphere at position {k} (robot)'))
    return steps


def plan_steps(model, quick: bool, options: dict):
    """The cell stage's capture plan (registry entry): one sweep per reference position.

    ``options`` holds ``cell_reference`` (path), ``sphere_radius`` [m] and ``calibration``
    (the current Calibration, whose ``cell_T_v0`` aims G1 when the reference file has no
    ``nominal_cell_T_v0``).

    Raises
    ------
    ValueError
        An unreadable reference, no nominal pose anywhere, or a position out of G1 reach.
    """
    ref = read_reference(options['cell_reference'])
    cell_T_v0 = ref.nominal_cell_T_v0
    if cell_T_v0 is None:
        cell_T_v0 = getattr(options.get('calibration'), 'cell_T_v0', None)
    if cell_T_v0 is None:
        raise ValueError(f"{options['cell_reference']}: nominal_cell_T_v0 is needed to aim at "
                         'the positions (the calibration holds no cell_T_v0 yet); give the '
                         "scanner's mounting as designed, a few mm and a degree off is fine")
    keys = sorted(ref.positions)
    p_cell = np.array([ref.positions[k] for k in keys])
    v0_T_cell = np.linalg.inv(np.asarray(cell_T_v0, dtype=np.float64))
    p_v0 = p_cell @ v0_T_cell[:3, :3].T + v0_T_cell[:3, 3]
    return capture_steps(model, p_v0, sphere_radius=options['sphere_radius'],
                         frames=FRAMES[1] if quick else FRAMES[0], pose_indices=keys,
                         scene_positions=p_cell)


def run_cell_extrinsic(views, calibration, options: dict, progress=None):
    """The cell stage's solver (registry entry): sphere centres, then ``cell_T_v0``.

    Returns
    -------
    calibration_tools.stages.StageResult
        No model update; ``extra['cell_extrinsic']`` holds the solution
        (:func:`result_extra`), which :func:`~calibration_tools.stages.apply_result` stores
        as the file's ``cell_T_v0``.

    Raises
    ------
    ValueError
        Fewer than 3 positions measured and reported, or positions that cannot fix the
        pose (:func:`solve_cell_T_v0`).
    """
    from calibration_tools.stages import CELL_STAGE, StageResult

    def report(done, total, message=''):
        if progress is not None:
            progress(done, total, message)

    ref = read_reference(options['cell_reference'])
    report(0, 2, f'{len(ref.positions)} reported positions; fitting the spheres')
    centres, rejected = sphere_centres(views, calibration.model,
                                       sphere_radius=options['sphere_radius'])
    unreported = sorted(set(centres) - set(ref.positions))
    rejected += [f'position {k}: measured but not in the reference file' for k in unreported]
    seen = {int(v.pose_index) for v in views if v.laser_on}
    rejected += [f'position {k}: reported but not captured' for k in
                 sorted(set(ref.positions) - seen)]
    keys = sorted(set(centres) & set(ref.positions))
    if len(keys) < 3:
        raise ValueError(f'cell_extrinsic: {len(keys)} positions both measured and reported; '
                         f'at least 3 needed' + (f"; {'; '.join(rejected)}" if rejected else ''))
    report(1, 2, f'{len(keys)} sphere centres; solving cell_T_v0')
    sol = solve_cell_T_v0(np.array([centres[k][0] for k in keys]),
                          np.array([ref.positions[k] for k in keys]))
    extra = result_extra(sol, ref.cell_frame)
    extra['positions'] = [int(k) for k in keys]
    report(2, 2, 'done')
    return StageResult(
        stage=CELL_STAGE, residuals={
            'sphere_centre_rms_m': sol.rms,
            'translation_std_max_m': float(np.max(sol.translation_std)),
            'rotation_std_max_rad': float(np.max(sol.rotation_std))},
        samples_used=len(keys), samples_rejected=len(rejected), rejected=rejected,
        extra={CELL_STAGE: extra})


def result_extra(solution: CellExtrinsic, cell_frame: str) -> dict:
    """What the calibration file keeps of a solution (plain floats)."""
    return mounting_record(solution.cell_T_v0, cell_frame, solution.translation_std,
                           solution.rotation_std, solution.rms)


def mounting_record(cell_T_v0, cell_frame: str, translation_std, rotation_std,
                    rms: float) -> dict:
    """A measured ``cell_T_v0`` as the calibration file keeps it (plain floats): the pose,
    its parent frame, each axis' standard error [m, rad] and the fit's RMS [m]. The cell
    stage and the hand-eye stage both store theirs this way
    (:func:`calibration_tools.stages.apply_result`)."""
    return {'cell_frame': cell_frame,
            'cell_T_v0': [[float(v) for v in row] for row in np.asarray(cell_T_v0)],
            'translation_std_m': [float(v) for v in translation_std],
            'rotation_std_rad': [float(v) for v in rotation_std],
            'rms_m': float(rms)}

