"""Rigid transforms, rotations, mirror reflections and planes (numpy only).

Conventions (docs/design.md section 2): ``A_T_B`` is a 4x4 array mapping B coordinates to A
coordinates, ``p_A = A_T_B @ p_B``. A plane is a 4-vector ``(a, b, c, e)`` with
``a x + b y + c z + e = 0``; if ``p_A = A_T_B p_B`` then ``pi_B = A_T_B.T @ pi_A``.
"""

from __future__ import annotations

import math

import numpy as np


def _vec3(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f'{name}: expected shape (3,), got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name}: contains non-finite values')
    return arr


def unit(vector, name: str = 'vector') -> np.ndarray:
    """Return ``vector`` scaled to unit length.

    Parameters
    ----------
    vector : array_like, shape (3,)
    """
    v = _vec3(vector, name)
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise ValueError(f'{name}: zero-length vector')
    return v / norm


def rotation_about(axis, angle: float) -> np.ndarray:
    """Rotation matrix for a right-handed rotation by ``angle`` [rad] about ``axis``.

    Parameters
    ----------
    axis : array_like, shape (3,)
        Rotation axis; need not be unit length.
    """
    a = unit(axis, 'axis')
    c, s = math.cos(angle), math.sin(angle)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return c * np.eye(3) + s * K + (1.0 - c) * np.outer(a, a)


def rotation_from_vector(rotvec) -> np.ndarray:
    """Rotation matrix from a rotation vector (axis times angle) [rad].

    Parameters
    ----------
    rotvec : array_like, shape (3,), radians
    """
    r = _vec3(rotvec, 'rotvec')
    angle = float(np.linalg.norm(r))
    if angle < 1e-300:
        return np.eye(3)
    return rotation_about(r / angle, angle)


def rotation_vector(R) -> np.ndarray:
    """Rotation vector (axis times angle) [rad] of a rotation matrix; the inverse of
    :func:`rotation_from_vector` for angles below pi.

    Parameters
    ----------
    R : array_like, shape (3, 3)
    """
    R = np.asarray(R, dtype=np.float64)
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0)))
    if angle < 1e-15:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * (angle / (2.0 * math.sin(angle)))


def make_transform(rotation, translation) -> np.ndarray:
    """4x4 rigid transform from a rotation matrix and a translation [m].

    Parameters
    ----------
    rotation : array_like, shape (3, 3)
    translation : array_like, shape (3,), metres
    """
    R = np.asarray(rotation, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f'rotation: expected shape (3, 3), got {R.shape}')
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = _vec3(translation, 'translation')
    return T


def invert_transform(T) -> np.ndarray:
    """Inverse of a 4x4 rigid (or reflection) transform whose 3x3 block is orthogonal.

    Parameters
    ----------
    T : array_like, shape (4, 4)
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f'T: expected shape (4, 4), got {T.shape}')
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def reflection_transform(normal, offset: float) -> np.ndarray:
    """4x4 transform reflecting points through the plane ``normal . x = offset``.

    Parameters
    ----------
    normal : array_like, shape (3,)
        Plane normal; must be unit length.
    offset : float
        Signed plane offset [m].

    Returns
    -------
    ndarray, shape (4, 4)
        ``[[I - 2 n n^T, 2 offset n], [0, 1]]``; determinant -1.
    """
    n = _vec3(normal, 'normal')
    if abs(float(n @ n) - 1.0) > 1e-9:
        raise ValueError('normal: must be a unit vector')
    T = np.eye(4)
    T[:3, :3] -= 2.0 * np.outer(n, n)
    T[:3, 3] = 2.0 * offset * n
    return T


def transform_points(A_T_B, points_B) -> np.ndarray:
    """Map points from frame B to frame A.

    Parameters
    ----------
    A_T_B : array_like, shape (4, 4)
    points_B : array_like, shape (n, 3), metres

    Returns
    -------
    ndarray, shape (n, 3), metres
    """
    T = np.asarray(A_T_B, dtype=np.float64)
    P = np.asarray(points_B, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f'A_T_B: expected shape (4, 4), got {T.shape}')
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'points_B: expected shape (n, 3), got {P.shape}')
    return P @ T[:3, :3].T + T[:3, 3]


def transform_plane(A_T_B, plane_B) -> np.ndarray:
    """Express a plane given in frame B in frame A: ``pi_A = inv(A_T_B).T @ pi_B``.

    Parameters
    ----------
    A_T_B : array_like, shape (4, 4)
    plane_B : array_like, shape (4,)
        ``(a, b, c, e)`` with ``a x + b y + c z + e = 0`` in B.
    """
    T = np.asarray(A_T_B, dtype=np.float64)
    pi = np.asarray(plane_B, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f'A_T_B: expected shape (4, 4), got {T.shape}')
    if pi.shape != (4,):
        raise ValueError(f'plane_B: expected shape (4,), got {pi.shape}')
    return invert_transform(T).T @ pi


def plane_from_point_normal(point, normal) -> np.ndarray:
    """Unit-normal plane 4-vector through ``point`` with ``normal``.

    Parameters
    ----------
    point : array_like, shape (3,), metres
    normal : array_like, shape (3,)
    """
    n = unit(normal, 'normal')
    return np.append(n, -float(n @ _vec3(point, 'point')))


def normalize_plane(plane) -> np.ndarray:
    """Scale a plane 4-vector so that its normal has unit length.

    Parameters
    ----------
    plane : array_like, shape (4,)
    """
    pi = np.asarray(plane, dtype=np.float64)
    if pi.shape != (4,):
        raise ValueError(f'plane: expected shape (4,), got {pi.shape}')
    norm = float(np.linalg.norm(pi[:3]))
    if norm < 1e-300:
        raise ValueError('plane: zero normal')
    return pi / norm
