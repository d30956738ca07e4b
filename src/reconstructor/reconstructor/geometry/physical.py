"""The physical mirror model: each galvo mirror as a plane turning about its axis.

The paper's model (docs/design.md §2) idealises Galvanometer-1 as two mirrors whose surfaces
contain their rotation axes, the pan axis along G's z, the tilt axis along G's x through
(0, d, 0), and the camera looking along G's x from (-l, 0, 0) with the fixed orientation M0;
the laser plane turns rigidly about the G2 tilt axis. Real mirrors are glued some tenths of a
millimetre in front of their axes, a little off square to them, the two G1 axes are not
exactly perpendicular, and the camera is mounted with small errors. :class:`PhysicalGeometry`
holds exactly those deviations. With all of them zero the physical model *is* the paper's
(``tests``: equal to 1e-12).

Galvanometer-1, in G (the frame the axes define; its gauge is fixed as follows):

- pan mirror: axis the line through the origin along ``a1 = (0, 0, -1)``; normal at angle θ
  ``n1(θ) = Rot(a1, θ) r1`` with ``r1 = cos γ1 (1, 0, 0) + sin γ1 a1``; surface
  ``n1 · x = -s1`` (s1 in front of the axis, towards the arriving light; the normals point
  away from it, as the paper's Pan factor has them);
- tilt mirror: axis through ``(0, d, 0)`` along ``a2 = (cos β, 0, sin β)`` (y is the common
  perpendicular of the two axes, the origin its foot on the pan axis); normal
  ``n2(θ) = Rot(a2, θ) r2`` with ``r2 = cos γ2 (sin β, 0, -cos β) + sin γ2 a2``; surface
  ``n2 · x = n2 · (0, d, 0) - s2``;
- camera: ``G_R_C = M0 · exp([ω]x)`` and centre ``(-l, 0, 0) + M0 (tx, ty, 0)``.

``G_T_V(θ1, θ2) = H(n2, c2) · H(n1, c1) · G_T_C`` with ``H(n, c)`` the reflection about the
plane ``n · x = c``; ``V0_T_V = inv(G_T_V(θ(0))) · G_T_V(θ(U))`` as in the paper's model. θ is
the same voltage→angle polynomial (:class:`~.galvo.MirrorParams`) in both models.

Galvanometer-2 tilt, in V0: the mirror turns about the model's axis (unit n through P) by
``Δθ = θ4(U) - θ4(0)``; its normal at U2 = 0 is ``m0 = cos γ4 (cos ψ4 u + sin ψ4 v) + sin γ4 n``
(``u`` the U2 = 0 laser-plane normal made perpendicular to n, ``v = n × u``) and its surface
lies ``s4`` in front of the axis. The sheet arriving from the G2 pan mirror is fixed (G2 pan
holds its voltage while scanning), so the plane at U2 is the U2 = 0 plane reflected back
through the mirror at U2 = 0 and forward through the mirror at U2. With s4 = γ4 = 0 the
two reflections make the paper's rigid rotation by 2Δθ about the axis, whatever ψ4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np

from ..correction import rotvec_to_matrix
from .checks import check_keys, finite_scalar, finite_vector
from .galvo import broadcast_angles

#: M0's rotation: maps camera axes (x right, y down, z forward) to G (docs/design.md §2).
M0_ROT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class PhysicalGeometry:
    """Deviations of a real rig from the paper's ideal mirrors (SI units, see the module).

    Parameters
    ----------
    camera_rotation : array_like, shape (3,), radians
        Rotation vector ω of the camera mount, in C: ``G_R_C = M0 exp([ω]x)``.
    camera_offset : array_like, shape (2,), metres
        Offset (tx, ty) of the camera centre across its optical axis, in C (along it is l).
    g1_axes_angle : float, radians
        β: the G1 tilt axis' angle from perpendicular to the pan axis.
    g1_pan_surface_offset, g1_tilt_surface_offset, g2_tilt_surface_offset : float, metres
        Distance of each mirror's reflective surface in front of its rotation axis.
    g1_pan_normal_tilt, g1_tilt_normal_tilt, g2_tilt_normal_tilt : float, radians
        Angle of each mirror's normal from perpendicular to its axis (mirror glued off square).
    g2_tilt_normal_angle : float, radians
        ψ4: the G2 tilt mirror's normal at U2 = 0 about its axis, from the laser plane's
        normal (matters only with a surface offset or a normal tilt).
    """

    camera_rotation: tuple = (0.0, 0.0, 0.0)
    camera_offset: tuple = (0.0, 0.0)
    g1_axes_angle: float = 0.0
    g1_pan_surface_offset: float = 0.0
    g1_pan_normal_tilt: float = 0.0
    g1_tilt_surface_offset: float = 0.0
    g1_tilt_normal_tilt: float = 0.0
    g2_tilt_surface_offset: float = 0.0
    g2_tilt_normal_tilt: float = 0.0
    g2_tilt_normal_angle: float = math.pi / 4

    def __post_init__(self):
        rot = finite_vector(self.camera_rotation, "physical.camera_rotation", 3)
        off = finite_vector(self.camera_offset, "physical.camera_offset", 2)
        object.__setattr__(self, "camera_rotation", tuple(float(v) for v in rot))
        object.__setattr__(self, "camera_offset", tuple(float(v) for v in off))
        for f in fields(self)[2:]:
            value = finite_scalar(getattr(self, f.name), f"physical.{f.name}")
            object.__setattr__(self, f.name, value)
        for name, limit in _LIMITS.items():
            value = getattr(self, name)
            size = float(np.max(np.abs(value)))
            if size > limit:
                raise ValueError(
                    f"physical.{name} = {value} is beyond {limit:g} "
                    f"({_LIMIT_UNITS[name]}): not a small mounting deviation (wrong unit?)")

    def to_dict(self) -> dict:
        """Plain floats and lists, SI units."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else float(value)
        return out

    @classmethod
    def from_dict(cls, data) -> PhysicalGeometry:
        """Build from :meth:`to_dict` output; ValueError names the key that is wrong."""
        names = tuple(f.name for f in fields(cls))
        check_keys(data, names, "physical.")
        return cls(**{k: data[k] for k in names})

    def value(self, name: str) -> float:
        """One deviation by name, a list entry as ``'camera_rotation[2]'``."""
        field_name, j = _split(name)
        value = getattr(self, field_name)
        return float(value if j is None else value[j])

    def replaced(self, values: dict) -> PhysicalGeometry:
        """A copy with the named deviations (as :meth:`value` names them) set."""
        data = self.to_dict()
        for name, v in values.items():
            field_name, j = _split(name)
            if j is None:
                data[field_name] = float(v)
            else:
                data[field_name][j] = float(v)
        return PhysicalGeometry.from_dict(data)


def _split(name: str):
    """``'camera_rotation[2]'`` -> ('camera_rotation', 2); ``'g1_axes_angle'`` -> (.., None)."""
    if name.endswith("]"):
        field_name, j = name[:-1].split("[")
        return field_name, int(j)
    return name, None


#: Largest plausible size of each deviation (a mounting error, not a redesign), and its unit.
_LIMITS = {
    "camera_rotation": 0.1, "camera_offset": 0.01, "g1_axes_angle": 0.1,
    "g1_pan_surface_offset": 0.01, "g1_pan_normal_tilt": 0.1,
    "g1_tilt_surface_offset": 0.01, "g1_tilt_normal_tilt": 0.1,
    "g2_tilt_surface_offset": 0.01, "g2_tilt_normal_tilt": 0.1,
}
_LIMIT_UNITS = {k: ("m" if "offset" in k else "rad") for k in _LIMITS}


def _turned(axis, ref, theta) -> np.ndarray:
    """``Rot(axis, θ) ref`` for angles of any shape (...): returns (..., 3)."""
    c = np.cos(theta)[..., None]
    s = np.sin(theta)[..., None]
    return c * ref + s * np.cross(axis, ref) + (1.0 - c) * float(axis @ ref) * axis


def _turn_terms(axis, ref) -> tuple:
    """``(ref, axis x ref, (axis . ref) axis)`` as float tuples, for :func:`_turned_scalar`."""
    cross = np.cross(axis, ref)
    along = float(axis @ ref) * axis
    return tuple(float(v) for v in ref), tuple(float(v) for v in cross), \
        tuple(float(v) for v in along)


def _turned_scalar(terms, theta: float) -> tuple:
    """``Rot(axis, θ) ref`` for one float angle, from :func:`_turn_terms`."""
    ref, cross, along = terms
    c, s = math.cos(theta), math.sin(theta)
    w = 1.0 - c
    return (c * ref[0] + s * cross[0] + w * along[0], c * ref[1] + s * cross[1] + w * along[1],
            c * ref[2] + s * cross[2] + w * along[2])


def _reflection_scalar(n, c: float) -> np.ndarray:
    """One reflection about ``n . x = c`` (n a float triple), shape (4, 4)."""
    a, b, e = n
    return np.array([[1.0 - 2.0 * a * a, -2.0 * a * b, -2.0 * a * e, 2.0 * c * a],
                     [-2.0 * a * b, 1.0 - 2.0 * b * b, -2.0 * b * e, 2.0 * c * b],
                     [-2.0 * a * e, -2.0 * b * e, 1.0 - 2.0 * e * e, 2.0 * c * e],
                     [0.0, 0.0, 0.0, 1.0]])


def _reflection(n, c) -> np.ndarray:
    """Reflections about planes ``n · x = c``: n (..., 3), c (...) -> (..., 4, 4)."""
    out = np.zeros(n.shape[:-1] + (4, 4))
    out[..., :3, :3] = np.eye(3) - 2.0 * n[..., :, None] * n[..., None, :]
    out[..., :3, 3] = 2.0 * c[..., None] * n
    out[..., 3, 3] = 1.0
    return out


@dataclass(frozen=True, eq=False)
class G1Geometry:
    """Galvanometer-1 of a physical model, ready to evaluate (built once per model)."""

    G_T_C: np.ndarray
    a1: np.ndarray
    r1: np.ndarray
    s1: float
    a2: np.ndarray
    r2: np.ndarray
    p2: np.ndarray
    s2: float

    @classmethod
    def build(cls, phys: PhysicalGeometry, l: float, d: float) -> G1Geometry:
        G_T_C = np.eye(4)
        G_T_C[:3, :3] = M0_ROT @ rotvec_to_matrix(phys.camera_rotation)
        tx, ty = phys.camera_offset
        G_T_C[:3, 3] = np.array([-l, 0.0, 0.0]) + M0_ROT @ np.array([tx, ty, 0.0])
        a1 = np.array([0.0, 0.0, -1.0])
        g1 = phys.g1_pan_normal_tilt
        r1 = math.cos(g1) * np.array([1.0, 0.0, 0.0]) + math.sin(g1) * a1
        b = phys.g1_axes_angle
        a2 = np.array([math.cos(b), 0.0, math.sin(b)])
        g2 = phys.g1_tilt_normal_tilt
        r2 = math.cos(g2) * np.array([math.sin(b), 0.0, -math.cos(b)]) + math.sin(g2) * a2
        return cls(G_T_C, a1, r1, phys.g1_pan_surface_offset, a2, r2,
                   np.array([0.0, d, 0.0]), phys.g1_tilt_surface_offset)

    def g_T_v(self, theta_pan, theta_tilt) -> np.ndarray:
        """``G_T_V`` for mirror angles of broadcastable shapes (...): (..., 4, 4)."""
        tp, tt = broadcast_angles(theta_pan, theta_tilt)
        n1 = _turned(self.a1, self.r1, tp)
        n2 = _turned(self.a2, self.r2, tt)
        c1 = np.full(tp.shape, -self.s1)
        c2 = n2 @ self.p2 - self.s2
        return _reflection(n2, c2) @ _reflection(n1, c1) @ self.G_T_C

    def g_T_v_scalar(self, theta_pan: float, theta_tilt: float) -> np.ndarray:
        """``g_T_v`` for two float angles (single-frame path), shape (4, 4): the same
        formulas on plain floats (numpy's per-call cost dominates at this size)."""
        n1 = _turned_scalar(self._t1, theta_pan)
        n2 = _turned_scalar(self._t2, theta_tilt)
        c2 = n2[0] * self.p2[0] + n2[1] * self.p2[1] + n2[2] * self.p2[2] - self.s2
        H = _reflection_scalar(n2, c2) @ _reflection_scalar(n1, -self.s1)
        return H @ self.G_T_C

    @cached_property
    def _t1(self):
        return _turn_terms(self.a1, self.r1)

    @cached_property
    def _t2(self):
        return _turn_terms(self.a2, self.r2)


@dataclass(frozen=True, eq=False)
class G2TiltGeometry:
    """The G2 tilt mirror of a physical model, in V0 (built once per model)."""

    n: np.ndarray
    m0: np.ndarray
    P: np.ndarray
    s: float
    plane_in: np.ndarray  # the sheet arriving at the tilt mirror, (a, b, c, e) in V0

    @classmethod
    def build(cls, phys: PhysicalGeometry, plane0, axis_dir, axis_point) -> G2TiltGeometry:
        n = np.asarray(axis_dir, dtype=np.float64)
        n0 = np.asarray(plane0[:3], dtype=np.float64)
        u = n0 - float(n0 @ n) * n
        norm = float(np.linalg.norm(u))
        if norm < 1e-9:
            raise ValueError("physical model: the laser plane's normal is parallel to the G2 "
                             "tilt axis (the mirror would not sweep the sheet)")
        u = u / norm
        v = np.cross(n, u)
        g, psi = phys.g2_tilt_normal_tilt, phys.g2_tilt_normal_angle
        m0 = math.cos(g) * (math.cos(psi) * u + math.sin(psi) * v) + math.sin(g) * n
        P = np.asarray(axis_point, dtype=np.float64)
        s = phys.g2_tilt_surface_offset
        plane_in = _reflect_plane(m0, float(m0 @ P) - s, np.asarray(plane0, dtype=np.float64))
        return cls(n, m0, P, s, plane_in)

    @cached_property
    def _terms(self):
        return _turn_terms(self.n, self.m0), tuple(float(v) for v in self.P), \
            tuple(float(v) for v in self.plane_in)

    def plane_scalar(self, delta: float) -> tuple:
        """:meth:`plane` for one float turn, as a tuple (single-frame path)."""
        terms, P, pin = self._terms
        m = _turned_scalar(terms, delta)
        c = m[0] * P[0] + m[1] * P[1] + m[2] * P[2] - self.s
        dot = m[0] * pin[0] + m[1] * pin[1] + m[2] * pin[2]
        return (pin[0] - 2.0 * dot * m[0], pin[1] - 2.0 * dot * m[1],
                pin[2] - 2.0 * dot * m[2], pin[3] + 2.0 * c * dot)

    def plane(self, delta) -> np.ndarray:
        """Laser planes for mirror turns ``Δθ`` (...) from U2 = 0: (..., 4), unit normals."""
        m = _turned(self.n, self.m0, np.asarray(delta, dtype=np.float64))
        return _reflect_plane(m, m @ self.P - self.s, self.plane_in)


def _reflect_plane(m, c, plane) -> np.ndarray:
    """Planes reflected about mirrors ``m · x = c`` (m (..., 3), c (...)); plane (4,)."""
    dot = m @ plane[:3]
    out = np.empty(np.shape(dot) + (4,))
    out[..., :3] = plane[:3] - 2.0 * dot[..., None] * m
    out[..., 3] = plane[3] + 2.0 * c * dot
    return out
