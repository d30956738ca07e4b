"""Run-time joint-correction table (docs/design.md §3 step 5, the paper's Algorithm 1).

The joint calibration stores, for G1 voltages on a rectangular grid, rigid transforms
``V0c_T_V0`` that map points triangulated by the model (frame V0) into the corrected output
frame V0c. At run time :class:`CorrectionTable` interpolates them:

- translation: bilinear in (U1_pan, U1_tilt);
- rotation: bilinear in the tangent space of one fixed reference rotation ``R_ref`` (the
  mean of the stored rotations). With ``r_k = log(R_ref.T @ R_k)`` the rotation vectors of
  the four cell corners, ``R(u) = R_ref @ exp(sum_k w_k(u) r_k)``. This is exact at the
  nodes, continuous everywhere (one tangent space for the whole grid), always a proper
  rotation, and never interpolates matrix elements one by one.

Outside the grid the voltages are clamped to the grid's range, so the correction of the
nearest edge (or corner) is used; it is not extrapolated. Grid nodes whose correction could
not be measured are stored with ``valid: false``; interpolation then uses the valid corners of
the cell with their bilinear weights renormalised, and a cell with no valid corner uses the
valid node nearest to the query in voltage space.

A grid axis may hold a single voltage; the correction is then constant along that axis.

File layout (the calibration file's top-level ``joint_correction`` section, SI units)::

    joint_correction:
      format: g1_grid_rigid
      format_version: 1
      u1_pan: [-0.2, 0.0, 0.2]          # V, strictly increasing
      u1_tilt: [-0.1, 0.0, 0.1]         # V, strictly increasing
      rotation_vector: [[[rx, ry, rz], ...], ...]   # rad, shape (n_pan, n_tilt, 3)
      translation: [[[tx, ty, tz], ...], ...]       # m, shape (n_pan, n_tilt, 3)
      valid: [[true, ...], ...]                     # shape (n_pan, n_tilt)

``rotation_vector`` and ``translation`` give the node's ``V0c_T_V0``: ``p_V0c = R p_V0 + t``
with ``R = exp(rotation_vector)``. No rclpy here.
"""

from __future__ import annotations

import bisect
import math
from types import SimpleNamespace

import numpy as np

from reconstructor.geometry.checks import check_keys

FORMAT = 'g1_grid_rigid'
FORMAT_VERSION = 1
_KEYS = ('format', 'format_version', 'u1_pan', 'u1_tilt', 'rotation_vector', 'translation',
         'valid')

#: Largest accepted voltage magnitude on a grid axis, V (the galvos take +-10 V).
MAX_ABS_VOLTAGE = 15.0
#: Largest accepted correction translation, m; larger is a likely unit mistake (millimetres).
MAX_TRANSLATION_M = 0.1
#: Largest accepted correction rotation, rad.
MAX_ROTATION_RAD = 0.5


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rotation matrices from rotation vectors (Rodrigues).

    Parameters
    ----------
    rotvec : ndarray, shape (..., 3), radians

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    r = np.asarray(rotvec, dtype=np.float64)
    if r.ndim < 1 or r.shape[-1] != 3:
        raise ValueError(f'rotvec must have shape (..., 3), got {r.shape}')
    theta2 = np.sum(r * r, axis=-1)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    # sin(t)/t and (1 - cos(t))/t^2 with their series near 0.
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1] = -r[..., 2]
    K[..., 0, 2] = r[..., 1]
    K[..., 1, 0] = r[..., 2]
    K[..., 1, 2] = -r[..., 0]
    K[..., 2, 0] = -r[..., 1]
    K[..., 2, 1] = r[..., 0]
    out = a[..., None, None] * K + b[..., None, None] * (K @ K)
    out[..., 0, 0] += 1.0
    out[..., 1, 1] += 1.0
    out[..., 2, 2] += 1.0
    return out


def matrix_to_rotvec(R) -> np.ndarray:
    """Rotation vectors (log map) of rotation matrices.

    Parameters
    ----------
    R : ndarray, shape (..., 3, 3)
        Proper rotations.

    Returns
    -------
    ndarray, shape (..., 3), radians (angle in [0, pi])
    """
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f'R must have shape (..., 3, 3), got {R.shape}')
    flat = R.reshape(-1, 3, 3)
    if flat.shape[0] == 0:
        return np.zeros(R.shape[:-2] + (3,))
    return Rotation.from_matrix(flat).as_rotvec().reshape(R.shape[:-2] + (3,))


def _axis(values, key: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1 or a.shape[0] < 1:
        raise ValueError(f'{key} must be a non-empty list of voltages, got shape {a.shape}')
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{key} must be finite, got {a.tolist()}')
    if np.any(np.abs(a) > MAX_ABS_VOLTAGE):
        raise ValueError(f'{key} must lie within +-{MAX_ABS_VOLTAGE:g} V, got {a.tolist()}')
    if a.shape[0] > 1 and not np.all(np.diff(a) > 0.0):
        raise ValueError(f'{key} must be strictly increasing, got {a.tolist()}')
    return a


class CorrectionTable:
    """Joint-correction transforms ``V0c_T_V0`` on a grid of G1 voltages.

    Implements the ``JointCorrection`` protocol of :mod:`reconstructor.geometry.rig`.

    Parameters
    ----------
    u1_pan : array_like, shape (n_pan,), volts
        Grid voltages of the G1 pan mirror, strictly increasing.
    u1_tilt : array_like, shape (n_tilt,), volts
        Grid voltages of the G1 tilt mirror, strictly increasing.
    transforms : array_like, shape (n_pan, n_tilt, 4, 4)
        ``V0c_T_V0`` at each node (rigid; the rotation block is re-orthonormalised).
        Entries of invalid nodes are ignored (may be NaN).
    valid : array_like of bool, shape (n_pan, n_tilt), optional
        Which nodes hold a measured correction (default: all). At least one must.

    Raises
    ------
    ValueError
        Naming the argument: wrong shapes, non-increasing axes, non-finite or non-rigid
        transforms, implausible magnitudes, or rotations too far apart to interpolate.
    """

    def __init__(self, u1_pan, u1_tilt, transforms, valid=None):
        pan = _axis(u1_pan, 'u1_pan')
        tilt = _axis(u1_tilt, 'u1_tilt')
        shape = (pan.shape[0], tilt.shape[0])
        T = np.asarray(transforms, dtype=np.float64)
        if T.shape != shape + (4, 4):
            raise ValueError(f'transforms must have shape {shape + (4, 4)}, got {T.shape}')
        if valid is None:
            ok = np.ones(shape, dtype=bool)
        else:
            ok = np.asarray(valid)
            if ok.shape != shape or ok.dtype != bool:
                raise ValueError(f'valid must be a bool array of shape {shape}, got '
                                 f'{ok.dtype} {ok.shape}')
            ok = ok.copy()
        if not ok.any():
            raise ValueError('valid: at least one node must hold a correction')
        rot = np.zeros(shape + (3,))
        trans = np.zeros(shape + (3,))
        for i, j in np.argwhere(ok):
            Tij = T[i, j]
            if not np.all(np.isfinite(Tij)):
                raise ValueError(f'transforms[{i}][{j}] must be finite')
            if not np.allclose(Tij[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
                raise ValueError(f'transforms[{i}][{j}] last row must be (0, 0, 0, 1)')
            R = Tij[:3, :3]
            if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
                raise ValueError(f'transforms[{i}][{j}] rotation block is not a proper '
                                 f'rotation')
            rot[i, j] = matrix_to_rotvec(R)
            trans[i, j] = Tij[:3, 3]
        self._init(pan, tilt, rot, trans, ok)

    @classmethod
    def from_rotvecs(cls, u1_pan, u1_tilt, rotation_vector, translation, valid=None):
        """Build from rotation vectors and translations.

        Parameters
        ----------
        u1_pan, u1_tilt : array_like, shapes (n_pan,), (n_tilt,), volts
        rotation_vector : array_like, shape (n_pan, n_tilt, 3), radians
        translation : array_like, shape (n_pan, n_tilt, 3), metres
        valid : array_like of bool, shape (n_pan, n_tilt), optional
        """
        pan = _axis(u1_pan, 'u1_pan')
        tilt = _axis(u1_tilt, 'u1_tilt')
        shape = (pan.shape[0], tilt.shape[0], 3)
        rv = np.asarray(rotation_vector, dtype=np.float64)
        tr = np.asarray(translation, dtype=np.float64)
        for name, arr in (('rotation_vector', rv), ('translation', tr)):
            if arr.shape != shape:
                raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
        T = np.zeros(shape[:2] + (4, 4))
        T[..., :3, :3] = rotvec_to_matrix(np.nan_to_num(rv))
        T[..., :3, 3] = tr
        T[..., 3, 3] = 1.0
        return cls(pan, tilt, T, valid)

    def _init(self, pan, tilt, rot, trans, ok):
        for (i, j), t in np.ndenumerate(np.linalg.norm(trans, axis=-1)):
            if ok[i, j] and not t <= MAX_TRANSLATION_M:
                raise ValueError(f'translation[{i}][{j}] is {t:g} m, more than '
                                 f'{MAX_TRANSLATION_M:g} m; it looks like millimetres')
        for (i, j), a in np.ndenumerate(np.linalg.norm(rot, axis=-1)):
            if ok[i, j] and not a <= MAX_ROTATION_RAD:
                raise ValueError(f'rotation_vector[{i}][{j}] is {a:g} rad, more than '
                                 f'{MAX_ROTATION_RAD:g} rad; it looks like degrees')
        self._pan = pan
        self._tilt = tilt
        self._rot = rot
        self._trans = trans
        self._valid = ok
        # Reference rotation: mean of the valid node rotations (one tangent space for the grid).
        from scipy.spatial.transform import Rotation

        R_nodes = rotvec_to_matrix(rot)
        R_ref = Rotation.from_rotvec(rot[ok]).mean().as_matrix()
        rel = np.zeros_like(rot)
        rel[ok] = matrix_to_rotvec(np.swapaxes(R_ref, -1, -2) @ R_nodes[ok])
        self._R_ref = R_ref
        self._rel = rel
        self._R_nodes = R_nodes
        self._nodes_v = np.stack(np.meshgrid(pan, tilt, indexing='ij'), axis=-1)[ok]
        self._valid_idx = np.argwhere(ok)
        self._fast = SimpleNamespace(pan=tuple(pan.tolist()), tilt=tuple(tilt.tolist()),
                                     rel=rel.tolist(), trans=trans.tolist(),
                                     valid=ok.tolist())
        for arr in (self._pan, self._tilt, self._rot, self._trans, self._valid, self._rel):
            arr.flags.writeable = False

    # ------------------------------------------------------------------ properties
    @property
    def u1_pan(self) -> np.ndarray:
        """Grid voltages of G1 pan, shape (n_pan,), volts (read-only)."""
        return self._pan

    @property
    def u1_tilt(self) -> np.ndarray:
        """Grid voltages of G1 tilt, shape (n_tilt,), volts (read-only)."""
        return self._tilt

    @property
    def valid(self) -> np.ndarray:
        """Which nodes hold a correction, shape (n_pan, n_tilt) (read-only)."""
        return self._valid

    def node_transform(self, i: int, j: int) -> np.ndarray:
        """The stored ``V0c_T_V0`` of node (i, j), shape (4, 4); ValueError if not valid."""
        if not (0 <= i < self._pan.shape[0] and 0 <= j < self._tilt.shape[0]):
            raise ValueError(f'node ({i}, {j}) is outside the grid')
        if not self._valid[i, j]:
            raise ValueError(f'node ({i}, {j}) holds no correction (valid is false)')
        T = np.eye(4)
        T[:3, :3] = self._R_nodes[i, j]
        T[:3, 3] = self._trans[i, j]
        return T

    # ------------------------------------------------------------------ evaluation
    @staticmethod
    def _locate(grid: np.ndarray, u: np.ndarray):
        """Cell index and fraction along one axis, with clamping; u shape (n,)."""
        if grid.shape[0] == 1:
            return np.zeros(u.shape, dtype=np.intp), np.zeros(u.shape)
        uc = np.clip(u, grid[0], grid[-1])
        i = np.clip(np.searchsorted(grid, uc, side='right') - 1, 0, grid.shape[0] - 2)
        frac = (uc - grid[i]) / (grid[i + 1] - grid[i])
        return i, frac

    def V0c_T_V0(self, u1_pan, u1_tilt) -> np.ndarray:  # noqa: N802
        """Interpolated correction for G1 voltages.

        Parameters
        ----------
        u1_pan, u1_tilt : float or array_like, broadcastable shapes (...), volts
            Voltages outside the grid are clamped to it. Non-finite voltages give NaN.

        Returns
        -------
        ndarray, shape (..., 4, 4)
            Rigid transforms from the model's V0 to the corrected V0c.
        """
        if isinstance(u1_pan, float) and isinstance(u1_tilt, float):
            return self._scalar(u1_pan, u1_tilt)
        up = np.asarray(u1_pan, dtype=np.float64)
        ut = np.asarray(u1_tilt, dtype=np.float64)
        try:
            shape = np.broadcast_shapes(up.shape, ut.shape)
        except ValueError:
            raise ValueError(f'u1_pan shape {up.shape} and u1_tilt shape {ut.shape} do not '
                             f'broadcast') from None
        up = np.broadcast_to(up, shape).reshape(-1)
        ut = np.broadcast_to(ut, shape).reshape(-1)
        finite = np.isfinite(up) & np.isfinite(ut)
        upf = np.where(finite, up, self._pan[0])
        utf = np.where(finite, ut, self._tilt[0])
        i, a = self._locate(self._pan, upf)
        j, b = self._locate(self._tilt, utf)
        i1 = np.minimum(i + 1, self._pan.shape[0] - 1)
        j1 = np.minimum(j + 1, self._tilt.shape[0] - 1)
        ci = np.stack([i, i1, i, i1], axis=-1)  # (n, 4)
        cj = np.stack([j, j, j1, j1], axis=-1)
        w = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], axis=-1)
        w = w * self._valid[ci, cj]
        wsum = w.sum(axis=-1)
        empty = wsum <= 0.0
        if empty.any():
            # No valid corner in the cell: nearest valid node in voltage space.
            q = np.stack([upf[empty], utf[empty]], axis=-1)
            d2 = ((q[:, None, :] - self._nodes_v[None, :, :]) ** 2).sum(axis=-1)
            k = self._valid_idx[np.argmin(d2, axis=1)]
            ci[empty, 0], cj[empty, 0] = k[:, 0], k[:, 1]
            w[empty] = 0.0
            w[empty, 0] = 1.0
            wsum = np.where(empty, 1.0, wsum)
        w = w / wsum[:, None]
        rv = np.einsum('nk,nkd->nd', w, self._rel[ci, cj])
        t = np.einsum('nk,nkd->nd', w, self._trans[ci, cj])
        out = np.zeros((up.shape[0], 4, 4))
        out[:, :3, :3] = self._R_ref @ rotvec_to_matrix(rv)
        out[:, :3, 3] = t
        out[:, 3, 3] = 1.0
        out[~finite] = np.nan
        return out.reshape(shape + (4, 4))

    @staticmethod
    def _locate_scalar(grid: tuple, u: float):
        n = len(grid)
        if n == 1:
            return 0, 0, 0.0
        u = min(max(u, grid[0]), grid[-1])
        i = min(max(bisect.bisect_right(grid, u) - 1, 0), n - 2)
        return i, i + 1, (u - grid[i]) / (grid[i + 1] - grid[i])

    def _scalar(self, up: float, ut: float) -> np.ndarray:
        """``V0c_T_V0`` for two floats (single-frame fast path), shape (4, 4)."""
        if not (math.isfinite(up) and math.isfinite(ut)):
            return np.full((4, 4), np.nan)
        s = self._fast
        i, i1, a = self._locate_scalar(s.pan, up)
        j, j1, b = self._locate_scalar(s.tilt, ut)
        corners = ((i, j, (1 - a) * (1 - b)), (i1, j, a * (1 - b)), (i, j1, (1 - a) * b),
                   (i1, j1, a * b))
        rv = [0.0, 0.0, 0.0]
        t = [0.0, 0.0, 0.0]
        wsum = 0.0
        for ci, cj, w in corners:
            if w > 0.0 and s.valid[ci][cj]:
                wsum += w
                r, tr = s.rel[ci][cj], s.trans[ci][cj]
                for k in range(3):
                    rv[k] += w * r[k]
                    t[k] += w * tr[k]
        if wsum <= 0.0:
            return self.V0c_T_V0(np.array(up), np.array(ut))
        rx, ry, rz = rv[0] / wsum, rv[1] / wsum, rv[2] / wsum
        th2 = rx * rx + ry * ry + rz * rz
        if th2 < 1e-12:
            ca, cb = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
        else:
            th = math.sqrt(th2)
            ca, cb = math.sin(th) / th, (1.0 - math.cos(th)) / th2
        R = np.array([
            [1.0 - cb * (ry * ry + rz * rz), -ca * rz + cb * rx * ry, ca * ry + cb * rx * rz],
            [ca * rz + cb * rx * ry, 1.0 - cb * (rx * rx + rz * rz), -ca * rx + cb * ry * rz],
            [-ca * ry + cb * rx * rz, ca * rx + cb * ry * rz, 1.0 - cb * (rx * rx + ry * ry)],
        ])
        out = np.eye(4)
        out[:3, :3] = self._R_ref @ R
        out[0, 3], out[1, 3], out[2, 3] = t[0] / wsum, t[1] / wsum, t[2] / wsum
        return out

    # ------------------------------------------------------------------ dict form
    def to_dict(self) -> dict:
        """Plain lists and floats for the calibration file's ``joint_correction`` section."""
        rot = np.where(self._valid[..., None], self._rot, 0.0)
        trans = np.where(self._valid[..., None], self._trans, 0.0)
        return {
            'format': FORMAT,
            'format_version': FORMAT_VERSION,
            'u1_pan': [float(v) for v in self._pan],
            'u1_tilt': [float(v) for v in self._tilt],
            'rotation_vector': rot.tolist(),
            'translation': trans.tolist(),
            'valid': self._valid.tolist(),
        }

    @classmethod
    def from_dict(cls, data) -> CorrectionTable:
        """Build a table from :meth:`to_dict` output (e.g. the parsed YAML section).

        Raises
        ------
        ValueError
            Naming the key (e.g. ``translation[1][0][2]``): missing, unknown, wrong type,
            shape or version, non-finite, or implausible magnitude.
        """
        check_keys(data, _KEYS, name='joint_correction')
        if data['format'] != FORMAT:
            raise ValueError(f'format must be {FORMAT!r}, got {data["format"]!r}')
        if data['format_version'] != FORMAT_VERSION:
            raise ValueError(f'format_version is {data["format_version"]!r}; this software '
                             f'reads version {FORMAT_VERSION}')
        pan = _axis(_numbers(data['u1_pan'], 'u1_pan', 1), 'u1_pan')
        tilt = _axis(_numbers(data['u1_tilt'], 'u1_tilt', 1), 'u1_tilt')
        shape = (pan.shape[0], tilt.shape[0])
        rv = _numbers(data['rotation_vector'], 'rotation_vector', 3, shape + (3,))
        tr = _numbers(data['translation'], 'translation', 3, shape + (3,))
        valid = data['valid']
        ok = np.zeros(shape, dtype=bool)
        if not isinstance(valid, list) or len(valid) != shape[0]:
            raise ValueError(f'valid must be a list of {shape[0]} lists of {shape[1]} booleans')
        for i, row in enumerate(valid):
            if not isinstance(row, list) or len(row) != shape[1]:
                raise ValueError(f'valid[{i}] must be a list of {shape[1]} booleans')
            for j, v in enumerate(row):
                if not isinstance(v, bool):
                    raise ValueError(f'valid[{i}][{j}] must be true or false, got {v!r}')
                ok[i, j] = v
        return cls.from_rotvecs(pan, tilt, rv, tr, ok)


def _numbers(value, key: str, depth: int, shape=None) -> np.ndarray:
    """Nested lists of real numbers -> float array; errors name the exact element."""

    def walk(v, path, level):
        if level == 0:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f'{path} must be a number, got {v!r}')
            if not math.isfinite(float(v)):
                raise ValueError(f'{path} must be finite, got {v!r}')
            return float(v)
        if not isinstance(v, (list, tuple)):
            raise ValueError(f'{path} must be a list, got {v!r}')
        return [walk(x, f'{path}[{i}]', level - 1) for i, x in enumerate(v)]

    nested = walk(value, key, depth if shape is None else len(shape))
    try:
        arr = np.array(nested, dtype=np.float64)
    except ValueError:
        raise ValueError(f'{key} must have shape {shape} (a regular nested list)') from None
    if shape is not None and arr.shape != tuple(shape):
        raise ValueError(f'{key} must have shape {tuple(shape)}, got {arr.shape}')
    return arr
