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

No rclpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The fewest robot poses accepted.
MIN_POSES = 5
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
    """

    flange_T_v0: np.ndarray
    base_T_target: np.ndarray
    translation_rms: float
    rotation_rms: float
    closed_form_step: tuple


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


def _refine(base_T_flange, v0_T_target, X0) -> np.ndarray:
    """``flange_T_v0`` and ``base_T_target`` that make every pose agree (least squares)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def unpack(q):
        X, Y = np.eye(4), np.eye(4)
        X[:3, :3], X[:3, 3] = Rotation.from_rotvec(q[:3]).as_matrix(), q[3:6]
        Y[:3, :3], Y[:3, 3] = Rotation.from_rotvec(q[6:9]).as_matrix(), q[9:12]
        return X, Y

    def residuals(q):
        X, Y = unpack(q)
        out = []
        for T, C in zip(base_T_flange, v0_T_target, strict=True):
            D = np.linalg.inv(Y) @ T @ X @ C
            out += [D[:3, 3], LEVER_M * _rotvec(D[:3, :3])]
        return np.concatenate(out)

    Y0 = _mean_pose(base_T_flange @ X0 @ v0_T_target)
    q0 = np.concatenate([_rotvec(X0[:3, :3]), X0[:3, 3], _rotvec(Y0[:3, :3]), Y0[:3, 3]])
    return unpack(least_squares(residuals, q0, method='lm', xtol=1e-15, ftol=1e-15).x)[0]


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
    X = _refine(A, B, X0)
    targets = A @ X @ B
    mean = _mean_pose(targets)
    dt = targets[:, :3, 3] - mean[:3, 3]
    dr = np.array([_rotvec(mean[:3, :3].T @ T[:3, :3]) for T in targets])
    step = (float(np.linalg.norm(X0[:3, 3] - X[:3, 3])),
            float(np.linalg.norm(_rotvec(X[:3, :3].T @ X0[:3, :3]))))
    return HandEye(flange_T_v0=X, base_T_target=mean,
                   translation_rms=float(np.sqrt(np.mean(np.sum(dt ** 2, axis=1)))),
                   rotation_rms=float(np.sqrt(np.mean(np.sum(dr ** 2, axis=1)))),
                   closed_form_step=step)


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
