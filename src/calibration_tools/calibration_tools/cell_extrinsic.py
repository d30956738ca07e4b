"""Where the scanner sits in the robot cell: ``cell_T_v0`` from a sphere at known positions.

The robot carries the calibration sphere to N >= 3 positions (not on one line) and reports
each in the cell frame (its TCP is the sphere's centre). At each position the scanner aims
G1 at the sphere and sweeps the laser over it; the swept points fit a sphere of the known
radius, whose centre is the position in V0. The rigid transform that maps the V0 centres
onto the reported cell positions is ``cell_T_v0`` (Kabsch / Umeyama without scale), with
its covariance from the residuals: each axis' standard error of translation [m] and of
rotation [rad]. The fit is refused when the positions cannot fix it: fewer than 3, or all
on one line (the rotation about that line is free), or spread less than ``min_spread``.

No rclpy; the capture plan is :func:`capture_steps`, the solver :func:`solve_cell_T_v0`,
the measurement :func:`sphere_centres`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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


def read_reference(path) -> tuple[str, dict[int, np.ndarray]]:
    """The robot-reported sphere positions: ``(cell_frame, {pose_index: (3,) m})``.

    The file is YAML::

        cell_frame: world           # the frame the positions are in (REP 105 name)
        unit: m                     # metres; anything else is refused
        positions:                  # pose_index of the capture -> sphere centre
          0: [1.2031, -0.4112, 0.9020]
          1: [...]

    Raises
    ------
    ValueError
        Unreadable file, missing or unknown keys, a unit other than ``m``, non-finite or
        absurd coordinates (beyond 100 m), or fewer than 3 positions; the key is named.
    """
    from galvoscan_common.yamlfile import read_yaml_mapping

    data = read_yaml_mapping(path, 'cell reference')
    unknown = set(data) - {'cell_frame', 'unit', 'positions'}
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
    return frame, out


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


def capture_steps(model, positions_v0, *, sphere_radius: float, frames: int = 40,
                  fraction: float = 0.7, frame_rate: float = 100.0):
    """One step per position: the sphere there, G1 aimed at it, G2 swept across it.

    ``positions_v0`` (n, 3) [m] are where the operator's current model expects the sphere
    (for a robot: its reported positions mapped by the nominal ``v0_T_cell``). The sweep
    covers ``fraction`` of the view's height at the sphere's distance.
    """
    from calibration_tools.placement import _aim, sphere_scene_yaml
    from calibration_tools.stages import CaptureStep
    from reconstructor.planning import view_sweep

    steps = []
    for k, centre in enumerate(_points(positions_v0, 'positions_v0')):
        aim = _aim(model, centre, f'sphere position {k}')
        distance = float(np.linalg.norm(centre)) - sphere_radius
        volts = view_sweep(model, float(aim[0]), float(aim[1]), distance, frames, fraction)
        steps.append(CaptureStep(k, sphere_scene_yaml(centre, sphere_radius), volts, True,
                                 frame_rate, note=f'sphere at position {k} (robot)'))
    return steps


def result_extra(solution: CellExtrinsic, cell_frame: str) -> dict:
    """What the calibration file keeps of a solution (plain floats)."""
    return {'cell_frame': cell_frame,
            'cell_T_v0': [[float(v) for v in row] for row in solution.cell_T_v0],
            'translation_std_m': [float(v) for v in solution.translation_std],
            'rotation_std_rad': [float(v) for v in solution.rotation_std],
            'rms_m': solution.rms}

