"""The simulated camera's lens: pinhole intrinsics plus plumb_bob distortion.

Pixel convention (OpenCV): pixel centres sit at integer (u, v); u runs right along a row,
v down a column. A point ``(X, Y, Z)`` in the optical frame (z forward, x right, y down)
projects to the normalised ``(x, y) = (X/Z, Y/Z)``, is distorted with
``(k1, k2, p1, p2, k3)`` and mapped by ``u = fx x_d + cx``, ``v = fy y_d + cy``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of the real camera C (shared by every virtual camera V).

    Attributes
    ----------
    width, height : int
        Image size [px].
    pixel_size : float
        Pixel pitch [m].
    fx, fy, cx, cy : float
        Focal lengths and principal point [px].
    distortion : ndarray, shape (5,)
        plumb_bob ``(k1, k2, p1, p2, k3)`` [1].
    """

    width: int
    height: int
    pixel_size: float
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray

    def _key(self):
        return (self.width, self.height, self.pixel_size, self.fx, self.fy, self.cx, self.cy,
                tuple(float(v) for v in self.distortion))

    def __hash__(self):
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, CameraModel) and self._key() == other._key()

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix [px]."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    def distort(self, x, y):
        """Apply plumb_bob distortion to normalised coordinates.

        Parameters
        ----------
        x, y : ndarray, shape (n,)
            Undistorted normalised coordinates [1].

        Returns
        -------
        tuple of ndarray, shape (n,)
            Distorted normalised coordinates.
        """
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * x * y
        xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
        return xd, yd

    def project(self, points) -> np.ndarray:
        """Project points given in the camera's optical frame to pixels.

        Parameters
        ----------
        points : array_like, shape (n, 3), metres
            Points in the optical frame of the (virtual) camera.

        Returns
        -------
        ndarray, shape (n, 2), px
            (u, v); NaN for points with z <= 0.
        """
        P = np.asarray(points, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3:
            raise ValueError(f'points: expected shape (n, 3), got {P.shape}')
        z = P[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            x = np.where(z > 0.0, P[:, 0] / z, np.nan)
            y = np.where(z > 0.0, P[:, 1] / z, np.nan)
        if self.has_distortion:
            x, y = self.distort(x, y)
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)

    def undistort_normalized(self, xd, yd, iterations: int = 20):
        """Invert :meth:`distort` by Newton's method (to ~1e-15).

        Parameters
        ----------
        xd, yd : ndarray, shape (n,)
            Distorted normalised coordinates [1].

        Returns
        -------
        tuple of ndarray, shape (n,)
        """
        xd = np.asarray(xd, dtype=np.float64)
        yd = np.asarray(yd, dtype=np.float64)
        if not self.has_distortion:
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            fx_, fy_ = self.distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dR = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            a = radial + 2.0 * x * x * dR + 2.0 * p1 * y + 6.0 * p2 * x
            b = 2.0 * x * y * dR + 2.0 * p1 * x + 2.0 * p2 * y
            c = 2.0 * x * y * dR + 2.0 * p1 * x + 2.0 * p2 * y
            d = radial + 2.0 * y * y * dR + 6.0 * p1 * y + 2.0 * p2 * x
            det = a * d - b * c
            x = x - (d * ex - b * ey) / det
            y = y - (-c * ex + a * ey) / det
            if float(np.max(np.abs(ex), initial=0.0)) < 1e-16 and float(
                    np.max(np.abs(ey), initial=0.0)) < 1e-16:
                break
        return x, y

    def pixel_to_normalized(self, uv) -> np.ndarray:
        """Undistorted normalised ray coordinates of pixels.

        Parameters
        ----------
        uv : array_like, shape (n, 2), px

        Returns
        -------
        ndarray, shape (n, 2)
            ``(x, y)`` such that the ray is ``(x, y, 1)`` in the optical frame.
        """
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f'uv: expected shape (n, 2), got {uv.shape}')
        xd = (uv[:, 0] - self.cx) / self.fx
        yd = (uv[:, 1] - self.cy) / self.fy
        x, y = self.undistort_normalized(xd, yd)
        return np.stack([x, y], axis=1)

    def normalized_grid(self, step: int = 1) -> np.ndarray:
        """Undistorted normalised coordinates of a regular pixel grid.

        With ``step`` s the grid samples pixel centres ``(s j + (s-1)/2, s i + (s-1)/2)``,
        which is what ``cv2.resize`` assumes when it scales an (H/s, W/s) image by s.

        Returns
        -------
        ndarray, shape (height // step, width // step, 2)
        """
        if step < 1 or self.width % step or self.height % step:
            raise ValueError(f'step: must divide {self.width} and {self.height}, got {step}')
        off = (step - 1) / 2.0
        us = np.arange(self.width // step) * step + off
        vs = np.arange(self.height // step) * step + off
        uu, vv = np.meshgrid(us, vs)
        xy = self.pixel_to_normalized(np.stack([uu.ravel(), vv.ravel()], axis=1))
        return xy.reshape(len(vs), len(us), 2)
