"""Physical galvanometer mirrors: explicit planes that rotate about (possibly tilted) axes.

A galvo head has a *pan* mirror and a *tilt* mirror. In the head's own frame (G for
Galvanometer-1, G2 for Galvanometer-2, docs/design.md section 2):

- the pan axis is the z axis through the origin, and the pan mirror's normal at angle
  theta is ``(cos theta, -sin theta, 0)``, i.e. the reference normal (1, 0, 0) turned by
  theta about -z;
- the tilt axis is parallel to x through (0, d, 0), and the tilt mirror's normal at angle
  theta is ``(0, sin theta, -cos theta)``, i.e. the reference normal (0, 0, -1) turned by
  theta about +x.

With these normals the reflection ``I - 2 n n^T`` about the pan plane is exactly
docs/design.md's ``Pan`` matrix and the reflection about the tilt plane (through (0, d, 0)) is
exactly its ``Tilt`` matrix, so the camera ray along +x is sent along +y by the pan mirror
and along +z by the tilt mirror at theta = 45 deg. The normals point *away* from the side
the light arrives from.

Real mirrors deviate (docs/design.md §5, the mirror surfaces off their axes): the reflective
surface sits ``surface_offset`` [m] in front of the rotation axis (towards the incoming light),
and the axis (with the mirror on it) is tilted by two small angles. Both are explicit here;
nothing is linearised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .spatial import rotation_from_vector, unit


@dataclass(frozen=True)
class Mirror:
    """One galvo mirror as a rotating plane.

    Attributes
    ----------
    axis_point : ndarray, shape (3,), metres
        A point on the rotation axis (head frame).
    axis_direction : ndarray, shape (3,)
        Unit rotation axis; the normal turns right-handedly about it as theta grows.
    reference_normal : ndarray, shape (3,)
        Unit mirror normal at theta = 0, perpendicular to the axis.
    surface_offset : float
        Distance of the reflective surface from the axis towards the incoming light [m].
    """

    axis_point: np.ndarray
    axis_direction: np.ndarray
    reference_normal: np.ndarray
    surface_offset: float = 0.0

    @staticmethod
    def build(axis_point, axis_direction, reference_normal, surface_offset=0.0,
              axis_tilt=(0.0, 0.0)) -> Mirror:
        """Mirror from its nominal axis and normal plus mechanical deviations.

        Parameters
        ----------
        axis_point : array_like, shape (3,), metres
        axis_direction, reference_normal : array_like, shape (3,)
            Nominal axis and theta = 0 normal (orthogonal).
        surface_offset : float
            [m], see the class doc.
        axis_tilt : array_like, shape (2,), radians
            Rotations of the whole mirror assembly about the nominal reference normal and
            about ``axis x reference_normal``; (0, 0) is a perfect axis.
        """
        a = unit(axis_direction, 'axis_direction')
        r = unit(reference_normal, 'reference_normal')
        if abs(float(a @ r)) > 1e-9:
            raise ValueError('reference_normal: must be perpendicular to axis_direction')
        tilt = np.asarray(axis_tilt, dtype=np.float64)
        if tilt.shape != (2,):
            raise ValueError(f'axis_tilt: expected shape (2,), got {tilt.shape}')
        R = rotation_from_vector(tilt[0] * r + tilt[1] * np.cross(a, r))
        return Mirror(np.asarray(axis_point, dtype=np.float64).copy(), R @ a, R @ r,
                      float(surface_offset))

    def __post_init__(self):
        object.__setattr__(self, '_binormal', np.cross(self.axis_direction,
                                                       self.reference_normal))

    def normal(self, theta: float) -> np.ndarray:
        """Unit mirror normal at angle ``theta`` [rad] (points away from the light)."""
        return self.reference_normal * math.cos(theta) + self._binormal * math.sin(theta)

    def plane(self, theta: float):
        """The reflective surface at angle ``theta`` [rad] as ``(n, c)``: ``n . x = c``.

        Returns
        -------
        tuple (ndarray shape (3,), float)
        """
        n = self.normal(theta)
        return n, float(n @ self.axis_point) - self.surface_offset


@dataclass(frozen=True)
class MirrorDrive:
    """Voltage-to-angle response of one galvo channel.

    ``theta(U) = theta0 + zero_offset + gain (1 + gain_error) U
    + c2 (U/U_fs)^2 + c3 (U/U_fs)^3 + jitter * N(0, 1)``

    Attributes
    ----------
    theta0 : float
        Nominal angle at U = 0 [rad].
    gain : float
        Nominal gain [rad/V].
    zero_offset : float
        Actual minus nominal angle at 0 V [rad] (mounting).
    gain_error : float
        Relative gain error [1].
    nonlinearity : ndarray, shape (2,)
        ``(c2, c3)`` [rad] of the quadratic and cubic terms in the normalised voltage.
    jitter : float
        Standard deviation of the per-frame angle noise [rad].
    full_scale : float
        U_fs [V].
    """

    theta0: float
    gain: float
    zero_offset: float = 0.0
    gain_error: float = 0.0
    nonlinearity: tuple = (0.0, 0.0)
    jitter: float = 0.0
    full_scale: float = 10.0

    def angle(self, voltage: float, jitter_draw: float = 0.0) -> float:
        """True mirror angle [rad] for an applied voltage [V] and a N(0, 1) draw."""
        u = voltage / self.full_scale
        c2, c3 = self.nonlinearity
        return (self.theta0 + self.zero_offset + self.gain * (1.0 + self.gain_error) * voltage
                + c2 * u * u + c3 * u * u * u + self.jitter * jitter_draw)

    def best_linear_fit(self, samples: int = 2001):
        """Least-squares ``theta ~ a + b U`` over the full range, without jitter.

        Returns
        -------
        tuple (float, float)
            (a [rad], b [rad/V]). Exact (theta0 and gain) when the response is linear.
        """
        U = np.linspace(-self.full_scale, self.full_scale, samples)
        theta = np.array([self.angle(float(x)) for x in U])
        c2, c3 = self.nonlinearity
        if c2 == 0.0 and c3 == 0.0:
            return self.theta0 + self.zero_offset, self.gain * (1.0 + self.gain_error)
        b, a = np.polyfit(U, theta, 1)
        return float(a), float(b)


@dataclass(frozen=True)
class GalvoHead:
    """A pan + tilt mirror pair in its head frame (see module doc)."""

    d: float
    pan: Mirror
    tilt: Mirror
    pan_drive: MirrorDrive
    tilt_drive: MirrorDrive

    @staticmethod
    def build(d: float, pan_drive: MirrorDrive, tilt_drive: MirrorDrive,
              pan_offset: float = 0.0, pan_axis_tilt=(0.0, 0.0), tilt_offset: float = 0.0,
              tilt_axis_tilt=(0.0, 0.0)) -> GalvoHead:
        pan = Mirror.build((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), pan_offset,
                           pan_axis_tilt)
        tilt = Mirror.build((0.0, d, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0), tilt_offset,
                            tilt_axis_tilt)
        return GalvoHead(float(d), pan, tilt, pan_drive, tilt_drive)


@dataclass(frozen=True)
class Dac:
    """Bipolar two's-complement DAC: ``2**bits`` codes over [-full_scale, full_scale).

    0 V is exactly representable; one code is ``2 full_scale / 2**bits`` volts.
    """

    bits: int = 16
    full_scale: float = 10.0

    @property
    def lsb(self) -> float:
        """Voltage step of one code [V]."""
        return 2.0 * self.full_scale / (1 << self.bits)

    def quantize(self, voltages) -> np.ndarray:
        """Voltages the DAC actually outputs for the commanded ones.

        Parameters
        ----------
        voltages : array_like, shape (...), volts
            Commands within [-full_scale, full_scale].

        Returns
        -------
        ndarray, same shape, volts
        """
        U = np.asarray(voltages, dtype=np.float64)
        if not np.all(np.isfinite(U)):
            raise ValueError('voltages: contains non-finite values')
        if np.any(np.abs(U) > self.full_scale * (1.0 + 1e-12)):
            raise ValueError(f'voltages: |U| exceeds the DAC range of +-{self.full_scale} V')
        half = 1 << (self.bits - 1)
        codes = np.clip(np.round(U / self.lsb), -half, half - 1)
        return codes * self.lsb
