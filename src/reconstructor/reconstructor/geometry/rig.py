"""The whole-rig model (``RigModel``), its dict form, and the dynamic-camera map ``V0_T_V``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from types import SimpleNamespace
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .camera import CameraIntrinsics
from .checks import as_float_array, check_keys, finite_scalar, finite_vector, unit_vector
from .galvo import MirrorParams, g_T_v, g_T_v_scalar, rigid_inverse
from .physical import G1Geometry, G2TiltGeometry, PhysicalGeometry

#: The two forms of the model: the paper's (l, d, ideal mirrors) and the physical one.
MODEL_KINDS = ("paper", "physical")


@runtime_checkable
class JointCorrection(Protocol):
    """Interface of the joint-correction table (docs/design.md §3 step 5), applied after V0_T_V.

    ``V0c_T_V0(u1_pan, u1_tilt)`` takes G1 voltages (floats, or arrays of one shape (...),
    volts) and returns rigid transforms of shape (..., 4, 4) from the model's V0 to the
    corrected V0 output frame.
    """

    def V0c_T_V0(self, u1_pan, u1_tilt) -> np.ndarray: ...  # noqa: N802


@dataclass(frozen=True, eq=False)
class RigModel:
    """Geometric model of the rig, all in SI units (m, rad, V).

    Parameters
    ----------
    intrinsics : CameraIntrinsics
        Real camera C (pixels, plumb_bob distortion).
    g1_pan, g1_tilt : MirrorParams
        G1 mirror responses θ1(U1_pan), θ2(U1_tilt); ``angle(0)`` defines V0 (pi/4 nominal).
    l, d : float, metres
        Dynamic-camera lengths of Eq. 2.
    laser_plane_v0 : array_like, shape (4,)
        Laser plane pi0 = (a, b, c, e) in V0 at U2_tilt = 0; stored with a unit normal
        (the whole 4-vector is divided by the norm of its normal).
    laser_axis_dir : array_like, shape (3,)
        Direction n of the G2 tilt axis in V0; stored as a unit vector. Its sign fixes the
        sense of rotation (right hand about n for increasing θ4).
    laser_axis_point : array_like, shape (3,), metres
        A point P on the G2 tilt axis, in V0.
    g2_tilt : MirrorParams
        G2 tilt mirror response θ4(U2_tilt). The laser plane is pi0 rotated rigidly about the
        axis (n, P) by ``2 * (θ4(U) - θ4(0))``.
    correction : JointCorrection or None
        Optional joint-correction table; when set, triangulated V0 points are mapped through
        ``correction.V0c_T_V0(u1_pan, u1_tilt)``. Not serialised by :meth:`to_dict`.
    physical : PhysicalGeometry or None
        None: the paper's model. Set: the physical mirror model (:mod:`.physical`), whose
        deviations from the paper's ideal mirrors these are; l, d, the mirror responses and
        the laser parameters keep their meaning.
    """

    intrinsics: CameraIntrinsics
    g1_pan: MirrorParams
    g1_tilt: MirrorParams
    l: float
    d: float
    laser_plane_v0: np.ndarray
    laser_axis_dir: np.ndarray
    laser_axis_point: np.ndarray
    g2_tilt: MirrorParams
    correction: Any = None
    physical: Any = None

    @property
    def kind(self) -> str:
        """``'paper'`` or ``'physical'``."""
        return "paper" if self.physical is None else "physical"

    def __post_init__(self):
        if not isinstance(self.intrinsics, CameraIntrinsics):
            raise ValueError("intrinsics must be a CameraIntrinsics")
        for name in ("g1_pan", "g1_tilt", "g2_tilt"):
            if not isinstance(getattr(self, name), MirrorParams):
                raise ValueError(f"{name} must be a MirrorParams")
        object.__setattr__(self, "l", finite_scalar(self.l, "l"))
        object.__setattr__(self, "d", finite_scalar(self.d, "d"))
        object.__setattr__(self, "laser_plane_v0", unit_vector(
            self.laser_plane_v0, "laser_plane_v0", 4, "normal (a, b, c)"))
        object.__setattr__(self, "laser_axis_dir", unit_vector(
            self.laser_axis_dir, "laser_axis_dir", 3, "direction"))
        point = finite_vector(self.laser_axis_point, "laser_axis_point", 3)
        object.__setattr__(self, "laser_axis_point", point)
        if self.correction is not None and not callable(
            getattr(self.correction, "V0c_T_V0", None)
        ):
            raise ValueError("correction must be None or have a V0c_T_V0(u1_pan, u1_tilt) method")
        if self.physical is not None and not isinstance(self.physical, PhysicalGeometry):
            raise ValueError("physical must be None or a PhysicalGeometry")

    @cached_property
    def _pre(self) -> SimpleNamespace:
        """Quantities that depend on the model only (computed once, model is immutable)."""
        g1 = g2 = None
        if self.physical is not None:
            g1 = G1Geometry.build(self.physical, self.l, self.d)
            g2 = G2TiltGeometry.build(self.physical, self.laser_plane_v0, self.laser_axis_dir,
                                      self.laser_axis_point)
            g0 = g1.g_T_v_scalar(self.g1_pan.theta0, self.g1_tilt.theta0)
        else:
            g0 = g_T_v_scalar(self.g1_pan.theta0, self.g1_tilt.theta0, self.l, self.d)
        n0 = self.laser_plane_v0[:3]
        e0 = float(self.laser_plane_v0[3])
        n = self.laser_axis_dir
        P = self.laser_axis_point
        m = np.cross(n, n0)
        q = float(n @ n0) * n
        return SimpleNamespace(
            g1=g1,
            g2=g2,
            g0_inv=rigid_inverse(g0),
            n0=n0,
            m=m,
            q=q,
            e0=e0,
            n0P=float(n0 @ P),
            mP=float(m @ P),
            qP=float(q @ P),
            n0_t=tuple(float(v) for v in n0),
            m_t=tuple(float(v) for v in m),
            q_t=tuple(float(v) for v in q),
        )

    # ----------------------------------------------------------------- dict form
    def to_dict(self) -> dict:
        """Plain floats and lists in SI units, suitable for YAML. ``correction`` is omitted.

        A physical model adds ``model: physical`` and its ``physical`` section; a paper model
        has neither (files written before the physical model read unchanged).
        """
        i = self.intrinsics
        out = {
            "intrinsics": {
                "fx": i.fx,
                "fy": i.fy,
                "cx": i.cx,
                "cy": i.cy,
                "dist": list(i.dist),
                "width": i.width,
                "height": i.height,
            },
            "g1_pan": self.g1_pan.to_dict(),
            "g1_tilt": self.g1_tilt.to_dict(),
            "l": self.l,
            "d": self.d,
            "laser_plane_v0": [float(v) for v in self.laser_plane_v0],
            "laser_axis_dir": [float(v) for v in self.laser_axis_dir],
            "laser_axis_point": [float(v) for v in self.laser_axis_point],
            "g2_tilt": self.g2_tilt.to_dict(),
        }
        if self.physical is not None:
            out["model"] = "physical"
            out["physical"] = self.physical.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict, correction=None) -> RigModel:
        """Build a model from :meth:`to_dict` output.

        Raises
        ------
        ValueError
            Naming the key (dotted path, e.g. ``intrinsics.fx``) that is missing, unknown,
            non-finite or of the wrong shape.
        """
        if not isinstance(data, dict):
            raise ValueError(f"model must be a mapping, got {type(data).__name__}")
        kind = data.get("model", "paper")
        if kind not in MODEL_KINDS:
            raise ValueError(f"model.model must be one of {', '.join(MODEL_KINDS)}, "
                             f"got {kind!r}")
        check_keys({k: v for k, v in data.items() if k != "model"},
                   _TOP_KEYS + (("physical",) if kind == "physical" else ()), "")
        physical = None
        if kind == "physical":
            physical = PhysicalGeometry.from_dict(data["physical"])
        intr = data["intrinsics"]
        check_keys(intr, _INTR_KEYS, "intrinsics.")
        intr_values = {key: _num(intr[key], f"intrinsics.{key}") for key in _INTR_KEYS[:4]}
        intr_values["dist"] = _vec(intr["dist"], "intrinsics.dist", 5)
        intr_values["width"] = _num(intr["width"], "intrinsics.width")
        intr_values["height"] = _num(intr["height"], "intrinsics.height")
        intrinsics = _wrap("intrinsics", lambda: CameraIntrinsics(**intr_values))
        mirrors = {name: _mirror_from_dict(data[name], name) for name in _MIRROR_NAMES}
        return cls(
            intrinsics=intrinsics,
            l=_num(data["l"], "l"),
            d=_num(data["d"], "d"),
            laser_plane_v0=_vec(data["laser_plane_v0"], "laser_plane_v0", 4),
            laser_axis_dir=_vec(data["laser_axis_dir"], "laser_axis_dir", 3),
            laser_axis_point=_vec(data["laser_axis_point"], "laser_axis_point", 3),
            correction=correction,
            physical=physical,
            **mirrors,
        )


_TOP_KEYS = (
    "intrinsics",
    "g1_pan",
    "g1_tilt",
    "l",
    "d",
    "laser_plane_v0",
    "laser_axis_dir",
    "laser_axis_point",
    "g2_tilt",
)
_INTR_KEYS = ("fx", "fy", "cx", "cy", "dist", "width", "height")
_MIRROR_KEYS = ("theta0", "k", "poly")
_MIRROR_NAMES = ("g1_pan", "g1_tilt", "g2_tilt")


def _num(value, key) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{key} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{key} must be finite, got {v}")
    return v


def _vec(value, key, length) -> list[float]:
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != length:
        raise ValueError(f"{key} must be a list of {length} numbers, got {value!r}")
    return [_num(v, f"{key}[{i}]") for i, v in enumerate(value)]


def _mirror_from_dict(data, name) -> MirrorParams:
    check_keys(data, _MIRROR_KEYS, f"{name}.")
    poly = data["poly"]
    if not isinstance(poly, (list, tuple)):
        raise ValueError(f"{name}.poly must be a list of numbers, got {poly!r}")
    theta0 = _num(data["theta0"], f"{name}.theta0")
    k = _num(data["k"], f"{name}.k")
    coeffs = tuple(_num(c, f"{name}.poly[{i}]") for i, c in enumerate(poly))
    return _wrap(name, lambda: MirrorParams(theta0=theta0, k=k, poly=coeffs))


def _wrap(prefix, build):
    """Run a constructor; prefix its ValueError with the dict section it came from."""
    try:
        return build()
    except ValueError as exc:
        raise ValueError(f"{prefix}.{exc}") from None


# --------------------------------------------------------------------- dynamic camera
def v0_T_v(model: RigModel, u1_pan, u1_tilt) -> np.ndarray:
    """Map from the current virtual camera V to V0: ``inv(G_T_V(θ⁰)) @ G_T_V(θ)``.

    Parameters
    ----------
    model : RigModel
    u1_pan, u1_tilt : float or array_like, broadcastable shapes (...), volts
        G1 pan and tilt voltages.

    Returns
    -------
    ndarray, shape (..., 4, 4)
        ``V0_T_V`` (identity at U1 = 0). The joint correction is not included.
    """
    up = as_float_array(u1_pan, "u1_pan")
    ut = as_float_array(u1_tilt, "u1_tilt")
    pre = model._pre
    if pre.g1 is not None:
        return pre.g0_inv @ pre.g1.g_T_v(model.g1_pan.angle(up), model.g1_tilt.angle(ut))
    return pre.g0_inv @ g_T_v(
        model.g1_pan.angle(up), model.g1_tilt.angle(ut), model.l, model.d
    )


def v0_T_v_scalar(model: RigModel, u1_pan: float, u1_tilt: float) -> np.ndarray:
    """``v0_T_v`` for float voltages (single-frame fast path), shape (4, 4)."""
    pre = model._pre
    if pre.g1 is not None:
        G = pre.g1.g_T_v_scalar(model.g1_pan.angle(u1_pan), model.g1_tilt.angle(u1_tilt))
    else:
        G = g_T_v_scalar(model.g1_pan.angle(u1_pan), model.g1_tilt.angle(u1_tilt), model.l,
                         model.d)
    return pre.g0_inv @ G


def nominal_example_rig(dist=(0.0, 0.0, 0.0, 0.0, 0.0), standoff: float = 0.65) -> RigModel:
    """An example rig close to the paper's. NOT a calibration: for tests and demos only.

    Taken from the paper (Chen et al., section IV): intrinsics fx 7801.38, fy 7798.24,
    cx 359.51, cy 269.54 px; l = 83.45 mm, d = 22.14 mm; G2 axis roughly along V0 x through
    (y, z) = (-195.93, 257.97) mm. Nominal, not from the paper: galvo gain 20° per 10 V
    (mechanical) for all mirrors, θ0 = 45°, no nonlinearity, a 720 x 540 image, and a laser
    plane at U2 = 0 that contains the axis and the V0 optical axis point at ``standoff`` m.

    Parameters
    ----------
    dist : sequence of 5 float
        Plumb_bob coefficients (zero by default).
    standoff : float, metres
        Depth along the V0 optical axis where the U2 = 0 laser plane crosses it.
    """
    k = math.radians(20.0) / 10.0
    axis_point = np.array([0.0, -0.19593, 0.25797])
    axis_dir = np.array([1.0, 0.0, 0.0])
    target = np.array([0.0, 0.0, finite_scalar(standoff, "standoff")])
    normal = np.cross(axis_dir, target - axis_point)
    normal /= np.linalg.norm(normal)
    plane = np.append(normal, -normal @ axis_point)
    return RigModel(
        intrinsics=CameraIntrinsics(
            fx=7801.38, fy=7798.24, cx=359.51, cy=269.54, dist=tuple(dist), width=720, height=540
        ),
        g1_pan=MirrorParams(theta0=math.pi / 4, k=k),
        g1_tilt=MirrorParams(theta0=math.pi / 4, k=k),
        l=0.08345,
        d=0.02214,
        laser_plane_v0=plane,
        laser_axis_dir=axis_dir,
        laser_axis_point=axis_point,
        g2_tilt=MirrorParams(theta0=math.pi / 4, k=k),
    )
