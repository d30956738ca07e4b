"""The physical rig: camera, Galvanometer-1, Galvanometer-2 with the line laser, DAC.

Frames (docs/design.md section 2): C real camera (optical), G Galvanometer-1 head, G2
Galvanometer-2 head, V virtual camera (C seen through both G1 mirrors), V0 = V at
U1 = 0, W world (the scene's frame; the rig file fixes ``W_T_G``).

Everything here is physical: the virtual camera is the real camera reflected through the
two actual G1 mirror planes, pixel rays are traced off those planes, and the laser sheet is
the laser's fan traced off the two actual G2 mirror planes. Nothing is computed from the
reconstruction model; :meth:`Rig.true_model_parameters` only *reports* which model
parameters the physical description corresponds to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from galvoscan_common.stripe_layout import StripeLayout, stripe_layout

from .camera import CameraModel
from .config import ConfigError, Section
from .galvo import Dac, GalvoHead, MirrorDrive
from .readers import FileKind, as_rays, read_pose
from .spatial import (
    invert_transform,
    make_transform,
    reflection_transform,
    rotation_about,
    rotation_from_vector,
    rotation_vector,
    transform_plane,
    unit,
)

RIG_FORMAT_VERSION = 1
RIG_DIR = Path(__file__).resolve().parent / 'rigs'
RIG_FILES = FileKind(RIG_FORMAT_VERSION, RIG_DIR)

#: Output bit depths of the camera (Mono8, Mono10, Mono12, Mono16).
BIT_DEPTHS = (8, 10, 12, 16)

#: Fixed factor of docs/design.md: maps C to G before the mirrors, with l = 0 (added below).
_M0_ROT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class ImageFormation:
    """Sensor and image-formation settings.

    Attributes
    ----------
    exposure : float
        Exposure of laser frames [s].
    calibration_exposure : float
        Exposure of board (calibration) frames [s].
    full_well : float
        Saturation capacity [e-]; it maps to the top of the ADC range.
    bit_depth : int
        Output bit depth, one of :data:`BIT_DEPTHS`: 8 gives uint8 images (mono8), 10, 12
        and 16 give uint16 images (mono16) holding codes up to 2**bit_depth - 1, as a
        GenICam camera delivers Mono10/12/16 unpacked.
    black_level : float
        Output offset [DN] of the chosen format.
    shot_noise : bool
        Photon shot noise on/off.
    read_noise : float
        Read noise standard deviation [e-].
    speckle_contrast : float
        Std of the multiplicative per-pixel laser speckle factor, before optical blur [1].
    psf_sigma : float
        Gaussian optical blur [px].
    ambient_in_laser_frames : bool
        Whether room light also reaches laser frames (it always lights board frames).
    ambient_rate : float
        Ambient signal at albedo 1 [e-/s].
    light_direction : ndarray, shape (3,)
        Unit vector towards the room's main light, world frame.
    directional_fraction : float
        Share of the ambient light that is directional (Lambert) rather than uniform [1].
    """

    exposure: float
    calibration_exposure: float
    full_well: float
    bit_depth: int
    black_level: float
    shot_noise: bool
    read_noise: float
    speckle_contrast: float
    psf_sigma: float
    ambient_in_laser_frames: bool
    ambient_rate: float
    light_direction: np.ndarray
    directional_fraction: float

    @property
    def white_level(self) -> int:
        """The top output code [DN]: 2**bit_depth - 1."""
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> np.dtype:
        """Image element type: uint8 at 8 bits, uint16 (unpacked) above."""
        return np.dtype(np.uint8 if self.bit_depth <= 8 else np.uint16)

    @property
    def electrons_per_dn(self) -> float:
        """Conversion gain [e-/DN]: the full well maps to the top code."""
        return self.full_well / (self.white_level - self.black_level)

    @property
    def noisy(self) -> bool:
        return self.shot_noise or self.read_noise > 0.0


@dataclass(frozen=True)
class LaserSource:
    """The line laser in the G2 head frame (after its mounting error).

    Attributes
    ----------
    position : ndarray, shape (3,), metres
        Apex of the fan (the Powell lens' virtual source), G2 frame.
    direction : ndarray, shape (3,)
        Unit central beam direction, G2 frame.
    fan_normal : ndarray, shape (3,)
        Unit normal of the fan plane, G2 frame, perpendicular to ``direction``.
    fan_angle : float
        Full fan angle [rad].
    sigma : float
        Gaussian sigma of the sheet thickness [m] (line width / 4).
    peak_rate : float
        Peak signal at albedo 1, normal incidence and ``reference_distance`` [e-/s].
    reference_distance : float
        [m]
    """

    position: np.ndarray
    direction: np.ndarray
    fan_normal: np.ndarray
    fan_angle: float
    sigma: float
    peak_rate: float
    reference_distance: float

    @cached_property
    def spread_direction(self) -> np.ndarray:
        """Unit in-plane direction perpendicular to the central beam."""
        return np.cross(self.fan_normal, self.direction)


@dataclass(frozen=True)
class LaserSheet:
    """The laser light leaving G2, in one frame.

    All of the sheet's rays leave the last mirror as if they came from ``source`` (the
    laser's apex reflected through both mirror planes) inside the wedge of half angle
    ``half_angle`` about ``central``.

    Attributes
    ----------
    plane : ndarray, shape (4,)
        Centre plane of the sheet, unit normal.
    source : ndarray, shape (3,), metres
        Virtual apex.
    central : ndarray, shape (3,)
        Unit central ray direction.
    edge_normals : ndarray, shape (2, 3)
        In-plane unit normals of the wedge's two edges, pointing inwards.
    mirror_plane : ndarray, shape (4,)
        The last (tilt) mirror surface, unit normal; light leaves from it.
    half_angle : float
        [rad]
    """

    plane: np.ndarray
    source: np.ndarray
    central: np.ndarray
    edge_normals: np.ndarray
    mirror_plane: np.ndarray
    half_angle: float

    def transformed(self, A_T_F) -> LaserSheet:
        """The same sheet expressed in frame A (``A_T_F`` maps this frame to A, rigid)."""
        R, t = A_T_F[:3, :3], A_T_F[:3, 3]

        def plane(pi):
            n = R @ pi[:3]
            return np.append(n, pi[3] - n @ t)

        return LaserSheet(plane(self.plane), R @ self.source + t, R @ self.central,
                          self.edge_normals @ R.T, plane(self.mirror_plane), self.half_angle)


@dataclass(frozen=True)
class ModelParameters:
    """The reconstruction model's parameters that a rig corresponds to (docs/design.md sec. 2).

    For a rig without geometric imperfections they are exact: the model with these values
    reproduces the simulator's virtual camera poses and laser planes. With imperfections
    no value of the model's parameters is exact; these are the nominal values (l, d,
    intrinsics), the actual angle at 0 V, the least-squares linear gains over +-full scale,
    and the actual laser plane and G2 tilt axis at U2 = 0, which a calibration should
    approach but a model cannot fit everywhere.

    Attributes
    ----------
    fx, fy, cx, cy : float
        [px]
    distortion : ndarray, shape (5,)
        plumb_bob (k1, k2, p1, p2, k3).
    l, d : float
        [m]
    theta0_pan, theta0_tilt : float
        G1 mirror angles at 0 V [rad].
    k_pan, k_tilt : float
        G1 gains [rad/V].
    pi0 : ndarray, shape (4,)
        Laser plane at U2_tilt = 0 in V0 (unit normal).
    n : ndarray, shape (3,)
        Unit G2 tilt axis direction in V0 (the plane turns by +2 theta4 about it).
    P : ndarray, shape (3,), metres
        Point of the G2 tilt axis closest to the V0 origin, in V0.
    k2 : float
        G2 tilt gain [rad/V]; theta4 = k2 U2_tilt.
    u2_pan : float
        The G2 pan voltage these laser values hold for [V].
    W_T_V0 : ndarray, shape (4, 4)
        Pose of V0 in the world frame.
    exact : bool
        True when the rig has no geometric imperfection.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray
    l: float
    d: float
    theta0_pan: float
    k_pan: float
    theta0_tilt: float
    k_tilt: float
    pi0: np.ndarray
    n: np.ndarray
    P: np.ndarray
    k2: float
    u2_pan: float
    W_T_V0: np.ndarray
    exact: bool

    def as_dict(self) -> dict:
        out = {}
        for key, value in self.__dict__.items():
            out[key] = value.tolist() if isinstance(value, np.ndarray) else value
        return out


def _reflect_point(n, c, p):
    return p - 2.0 * (float(n @ p) - c) * n


def _reflect_dir(n, v):
    return v - 2.0 * float(n @ v) * n


def trace_off_planes(origins, directions, planes):
    """Trace rays off a sequence of mirror planes.

    Parameters
    ----------
    origins : ndarray, shape (n, 3), metres
    directions : ndarray, shape (n, 3)
        Unit ray directions.
    planes : list of (ndarray shape (3,), float)
        Mirror surfaces ``n . x = c`` in the order the light meets them.

    Returns
    -------
    tuple (ndarray shape (n, 3), ndarray shape (n, 3), ndarray shape (n,) bool)
        Hit points on the last mirror, reflected directions, and whether every mirror was
        met in front of the ray (t > 0).
    """
    o, d = as_rays(origins, directions)
    ok = np.ones(len(o), dtype=bool)
    for n, c in planes:
        dn = d @ n
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (c - o @ n) / dn
        ok &= t > 0.0
        o = o + t[:, None] * d
        d = d - 2.0 * dn[:, None] * n
    return o, d, ok


@dataclass(frozen=True)
class Rig:
    """A complete physical rig description (load one with :func:`load_rig`).

    Attributes
    ----------
    name, source : str
    camera : CameraModel
    image : ImageFormation
    l, d : float
        G1 geometry [m]: camera centre at (-l, 0, 0) in G, tilt axis through (0, d, 0).
    g1, g2 : GalvoHead
    G_T_C : ndarray, shape (4, 4)
        Real camera pose in G (docs/design.md's M0, times the camera mounting error).
    G_T_G2 : ndarray, shape (4, 4)
    laser : LaserSource
    dac : Dac
    W_T_G : ndarray, shape (4, 4)
    imperfections : dict
        The imperfection values as read (for reports).
    geometric_imperfection : bool
        True when any geometric imperfection is non-zero.
    """

    name: str
    source: str
    camera: CameraModel
    image: ImageFormation
    l: float
    d: float
    g1: GalvoHead
    g2: GalvoHead
    G_T_C: np.ndarray
    G_T_G2: np.ndarray
    laser: LaserSource
    dac: Dac
    W_T_G: np.ndarray
    imperfections: dict = field(default_factory=dict)
    geometric_imperfection: bool = False

    # ----------------------------------------------------------------- angles
    def applied_voltages(self, voltages) -> np.ndarray:
        """DAC output for commanded (U1_pan, U1_tilt, U2_pan, U2_tilt).

        Parameters
        ----------
        voltages : array_like, shape (4,), volts
        """
        U = np.asarray(voltages, dtype=np.float64)
        if U.shape != (4,):
            raise ValueError(f'voltages: expected shape (4,), got {U.shape}')
        return self.dac.quantize(U)

    def without_jitter(self) -> Rig:
        """The same rig with every galvo's per-frame angle noise set to zero: its repeatable
        geometry, which a calibration can know (scores split a model's error into that part
        and the frame noise)."""
        def quiet(head):
            return replace(head, pan_drive=replace(head.pan_drive, jitter=0.0),
                           tilt_drive=replace(head.tilt_drive, jitter=0.0))

        return replace(self, g1=quiet(self.g1), g2=quiet(self.g2))

    def mirror_angles(self, applied, jitter_draws=None) -> np.ndarray:
        """True mechanical angles (theta1..theta4) [rad] for applied voltages.

        Parameters
        ----------
        applied : array_like, shape (4,), volts
            (U1_pan, U1_tilt, U2_pan, U2_tilt) as output by the DAC.
        jitter_draws : array_like, shape (4,), optional
            Standard normal draws scaled by each channel's jitter; None for no jitter.
        """
        U = np.asarray(applied, dtype=np.float64)
        if U.shape != (4,):
            raise ValueError(f'applied: expected shape (4,), got {U.shape}')
        z = np.zeros(4) if jitter_draws is None else np.asarray(jitter_draws, np.float64)
        if z.shape != (4,):
            raise ValueError(f'jitter_draws: expected shape (4,), got {z.shape}')
        drives = (self.g1.pan_drive, self.g1.tilt_drive, self.g2.pan_drive,
                  self.g2.tilt_drive)
        return np.array([dr.angle(float(u), float(j)) for dr, u, j in zip(drives, U, z,
                                                                           strict=True)])

    # ------------------------------------------------------- dynamic camera
    def g1_planes(self, theta_pan: float, theta_tilt: float):
        """The two G1 mirror surfaces in G, in the order light from the camera meets them."""
        return [self.g1.pan.plane(theta_pan), self.g1.tilt.plane(theta_tilt)]

    def G_T_V(self, theta_pan: float, theta_tilt: float) -> np.ndarray:
        """Pose of the virtual camera in G: the camera reflected through both mirrors.

        Returns
        -------
        ndarray, shape (4, 4)
        """
        (n1, c1), (n2, c2) = self.g1_planes(theta_pan, theta_tilt)
        return reflection_transform(n2, c2) @ reflection_transform(n1, c1) @ self.G_T_C

    @cached_property
    def G_T_V0(self) -> np.ndarray:
        """Pose of V0 (both G1 channels at 0 V, no jitter) in G."""
        th = self.mirror_angles(np.zeros(4))
        return self.G_T_V(th[0], th[1])

    @cached_property
    def W_T_V0(self) -> np.ndarray:
        return self.W_T_G @ self.G_T_V0

    def V0_T_V(self, theta_pan: float, theta_tilt: float) -> np.ndarray:
        """Virtual camera pose at the given angles in V0 (4, 4)."""
        return invert_transform(self.G_T_V0) @ self.G_T_V(theta_pan, theta_tilt)

    def trace_camera_rays(self, xy, theta_pan: float, theta_tilt: float):
        """Trace pixel rays from the real camera off the two G1 mirrors.

        Parameters
        ----------
        xy : ndarray, shape (n, 2)
            Undistorted normalised pixel coordinates (ray (x, y, 1) in C).
        theta_pan, theta_tilt : float
            Mirror angles [rad].

        Returns
        -------
        tuple (ndarray shape (n, 3), ndarray shape (n, 3))
            Ray origins on the tilt mirror and unit directions into the scene, in G.
        """
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f'xy: expected shape (n, 2), got {xy.shape}')
        R = self.G_T_C[:3, :3]
        inv_norm = 1.0 / np.sqrt(xy[:, 0] ** 2 + xy[:, 1] ** 2 + 1.0)
        d = (xy[:, 0:1] * R[:, 0] + xy[:, 1:2] * R[:, 1] + R[:, 2]) * inv_norm[:, None]
        o = np.broadcast_to(self.G_T_C[:3, 3], d.shape)
        o, d, _ = trace_off_planes(o, d, self.g1_planes(theta_pan, theta_tilt))
        return o, d

    # -------------------------------------------------------- dynamic laser
    def laser_sheet_G(self, theta_pan2: float, theta_tilt2: float) -> LaserSheet:
        """The laser sheet leaving G2 at the given G2 mirror angles, in G.

        The fan's apex, central ray and edge rays are traced off the actual G2 pan and
        tilt mirror planes; the sheet is what leaves the tilt mirror.
        """
        L = self.laser
        planes = [self.g2.pan.plane(theta_pan2), self.g2.tilt.plane(theta_tilt2)]
        half = 0.5 * L.fan_angle
        e = L.spread_direction
        dirs = np.array([L.direction, math.cos(half) * L.direction + math.sin(half) * e,
                         math.cos(half) * L.direction - math.sin(half) * e])
        hits, out, ok = trace_off_planes(np.tile(L.position, (3, 1)), dirs, planes)
        if not ok[0]:
            raise ValueError(f'rig {self.name}: the laser beam misses a G2 mirror')
        src = L.position
        normal = L.fan_normal
        for n, c in planes:
            src = _reflect_point(n, c, src)
            normal = _reflect_dir(n, normal)
        central = out[0]
        edges = np.cross(normal, out[1:])
        edges /= np.linalg.norm(edges, axis=1)[:, None]
        edges *= np.sign(edges @ central)[:, None]
        n_t, c_t = planes[1]
        normal = normal / np.linalg.norm(normal)
        sheet = LaserSheet(np.append(normal, -float(normal @ src)), src, central, edges,
                           np.append(n_t, -c_t), half)
        return sheet.transformed(self.G_T_G2)

    # ----------------------------------------------------------- reporting
    def stripe_layout(self) -> StripeLayout:
        """The stripe's layout at the working point (``galvoscan_common.stripe_layout``),
        from the actual sheet at U2 = 0 (and 0.1 V for its sense) in the actual V0."""
        to_v0 = invert_transform(self.G_T_V0)
        planes = []
        for u in (0.0, 0.1):
            th = self.mirror_angles(self.applied_voltages(np.array([0.0, 0.0, 0.0, u])))
            planes.append(transform_plane(to_v0, self.laser_sheet_G(th[2], th[3]).plane))
        return stripe_layout(planes[0], self.camera.fx, self.camera.fy, plane_moved=planes[1])

    def true_model_parameters(self, u2_pan: float = 0.0) -> ModelParameters:
        """The model parameters this physical rig corresponds to (see ModelParameters).

        Parameters
        ----------
        u2_pan : float
            G2 pan voltage the laser values refer to [V] (quantised by the DAC).
        """
        applied = self.applied_voltages(np.array([0.0, 0.0, u2_pan, 0.0]))
        th = self.mirror_angles(applied)
        V0_T_G = invert_transform(self.G_T_V0)
        sheet = self.laser_sheet_G(th[2], th[3]).transformed(V0_T_G)
        R = V0_T_G[:3, :3] @ self.G_T_G2[:3, :3]
        n = unit(R @ self.g2.tilt.axis_direction)
        p = V0_T_G[:3, :3] @ (self.G_T_G2[:3, :3] @ self.g2.tilt.axis_point
                              + self.G_T_G2[:3, 3]) + V0_T_G[:3, 3]
        P = p - float(p @ n) * n
        t0p, kp = self.g1.pan_drive.best_linear_fit()
        t0t, kt = self.g1.tilt_drive.best_linear_fit()
        _, k2 = self.g2.tilt_drive.best_linear_fit()
        cam = self.camera
        return ModelParameters(
            cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion.copy(), self.l, self.d, t0p, kp,
            t0t, kt, sheet.plane, n, P, k2, float(applied[2]), self.W_T_V0.copy(),
            not self.geometric_imperfection)


    def physical_model_parameters(self, u2_pan: float = 0.0) -> dict:
        """This rig in the terms of the reconstruction's *physical* mirror model.

        Reporting only, like :meth:`true_model_parameters`: the mirrors' actual axes, surface
        offsets and responses re-expressed in that model's gauge (the G1 pan axis along -z
        through the origin, the common perpendicular of the two G1 axes along y), as a dict
        keyed like the model's ``to_dict()`` (``l``, ``d``, ``g1_pan``, ``g1_tilt``,
        ``g2_tilt`` responses, ``physical`` deviations) plus the laser parameters of
        :meth:`true_model_parameters`. That model reproduces this rig's ``V0_T_V`` and laser
        planes exactly (to round-off) when DAC quantisation and jitter are left out.
        """
        g1 = self.g1
        a1, p1 = g1.pan.axis_direction, g1.pan.axis_point
        a2, p2 = g1.tilt.axis_direction, g1.tilt.axis_point
        common = unit(np.cross(a1, a2), 'G1 axes common perpendicular')
        s, t, _ = np.linalg.solve(np.array([a1, -a2, -common]).T, p2 - p1)
        foot = p1 + s * a1
        y = p2 + t * a2 - foot
        d = float(np.linalg.norm(y))
        z = -a1
        y = y / d
        R = np.array([np.cross(y, z), y, z])  # rows: the model's G axes in this rig's G
        Gm_T_G = make_transform(R, -R @ foot)
        a2m = R @ a2
        beta = math.atan2(a2m[2], a2m[0])
        a1m = np.array([0.0, 0.0, -1.0])
        r1 = R @ g1.pan.reference_normal
        r2 = R @ g1.tilt.reference_normal
        perp2 = np.array([math.sin(beta), 0.0, -math.cos(beta)])
        G_T_C = Gm_T_G @ self.G_T_C
        rot = _M0_ROT.T @ G_T_C[:3, :3]
        centre = G_T_C[:3, 3]
        tp = self.true_model_parameters(u2_pan)
        # the G2 tilt mirror at U2 = 0, in V0
        applied = self.applied_voltages(np.array([0.0, 0.0, u2_pan, 0.0]))
        th = self.mirror_angles(applied)
        V0_T_G2 = invert_transform(self.G_T_V0) @ self.G_T_G2
        m0 = V0_T_G2[:3, :3] @ self.g2.tilt.normal(th[3])
        n = tp.n
        u = unit(tp.pi0[:3] - float(tp.pi0[:3] @ n) * n, 'laser normal across the axis')
        v = np.cross(n, u)
        return {
            'l': float(-centre[0]), 'd': d,
            'g1_pan': _response(g1.pan_drive, _angle_about(a1m, np.array([1.0, 0.0, 0.0]), r1)),
            'g1_tilt': _response(g1.tilt_drive, _angle_about(a2m, perp2, r2)),
            'g2_tilt': _response(self.g2.tilt_drive, 0.0),
            'laser_plane_v0': tp.pi0.tolist(), 'laser_axis_dir': n.tolist(),
            'laser_axis_point': tp.P.tolist(),
            'physical': {
                'camera_rotation': rotation_vector(rot).tolist(),
                'camera_offset': [float(centre[1]), float(centre[2])],
                'g1_axes_angle': beta,
                'g1_pan_surface_offset': g1.pan.surface_offset,
                'g1_pan_normal_tilt': math.asin(float(np.clip(r1 @ a1m, -1.0, 1.0))),
                'g1_tilt_surface_offset': g1.tilt.surface_offset,
                'g1_tilt_normal_tilt': math.asin(float(np.clip(r2 @ a2m, -1.0, 1.0))),
                'g2_tilt_surface_offset': self.g2.tilt.surface_offset,
                'g2_tilt_normal_tilt': math.asin(float(np.clip(m0 @ n, -1.0, 1.0))),
                'g2_tilt_normal_angle': math.atan2(float(m0 @ v), float(m0 @ u)),
            },
        }


def _response(drive: MirrorDrive, delta: float) -> dict:
    """A drive as the model's polynomial response, its angle measured ``delta`` further on."""
    fs = drive.full_scale
    c2, c3 = drive.nonlinearity
    return {'theta0': drive.theta0 + drive.zero_offset + delta,
            'k': drive.gain * (1.0 + drive.gain_error), 'poly': [c2 / fs**2, c3 / fs**3]}


def _angle_about(axis, a, b) -> float:
    """Signed angle from ``a`` to ``b`` about ``axis``, both taken across the axis [rad]."""
    a = a - float(a @ axis) * axis
    b = b - float(b @ axis) * axis
    return math.atan2(float(np.cross(a, b) @ axis), float(a @ b))


# ====================================================================== loading

def _pose(sec: Section, name: str) -> np.ndarray:
    return read_pose(sec.section(name), 20.0)


def _drive(sec: Section, name: str, imp: Section | None, full_scale: float) -> MirrorDrive:
    s = sec.section(name)
    theta0 = s.number('theta0', -math.pi, math.pi, 'rad', hint='radians expected')
    gain = s.number('gain', -0.2, 0.2, 'rad/V', hint='radians per volt expected')
    s.finish()
    if gain == 0.0:
        raise s.error('gain', 'a non-zero gain in rad/V', gain)
    if imp is None:
        return MirrorDrive(theta0, gain, full_scale=full_scale)
    zero = imp.number('zero_offset', -0.02, 0.02, 'rad')
    gain_err = imp.number('gain_error', -0.05, 0.05, '(relative)')
    nl = imp.vector('nonlinearity', 2, -0.01, 0.01, 'rad')
    jitter = imp.number('jitter', 0.0, 1e-3, 'rad')
    return MirrorDrive(theta0, gain, zero, gain_err, (float(nl[0]), float(nl[1])), jitter,
                       full_scale)


def _mirror_imperfection(imp: Section, name: str):
    s = imp.section(name)
    offset = s.number('surface_offset', -0.005, 0.005, 'm',
                      hint='metres expected, not millimetres')
    tilt = s.vector('axis_tilt', 2, -0.05, 0.05, 'rad')
    return s, offset, tilt


def _galvo_head(sec: Section, d: float, pan_imp, tilt_imp, full_scale: float) -> GalvoHead:
    """Pan and tilt drives of a head section with their mirrors' imperfections (as read by
    :func:`_mirror_imperfection`), pan axis to tilt axis ``d`` [m]."""
    pan_s, pan_off, pan_tilt = pan_imp
    tilt_s, tilt_off, tilt_tilt = tilt_imp
    return GalvoHead.build(d, _drive(sec, 'pan', pan_s, full_scale),
                           _drive(sec, 'tilt', tilt_s, full_scale), pan_off, pan_tilt,
                           tilt_off, tilt_tilt)


def _read_camera(top: Section) -> tuple[tuple, tuple]:
    """The ``camera`` section: (the :class:`CameraModel` arguments before ``distortion``,
    the :class:`ImageFormation` arguments up to ``black_level``)."""
    cam = top.section('camera')
    width = cam.integer('width', 16, 20000, 'px')
    height = cam.integer('height', 16, 20000, 'px')
    pixel_size = cam.number('pixel_size', 5e-7, 5e-5, 'm', hint='metres expected, not µm')
    fx = cam.number('fx', 10.0, 1e6, 'px')
    fy = cam.number('fy', 10.0, 1e6, 'px')
    cx = cam.number('cx', -width, 2.0 * width, 'px')
    cy = cam.number('cy', -height, 2.0 * height, 'px')
    exposure = cam.number('exposure', 1e-6, 1.0, 's', hint='seconds expected, not µs/ms')
    cal_exposure = cam.number('calibration_exposure', 1e-6, 1.0, 's',
                              hint='seconds expected, not ms')
    full_well = cam.number('full_well', 100.0, 1e7, 'e-')
    bit_depth = cam.integer('bit_depth', BIT_DEPTHS[0], BIT_DEPTHS[-1], 'bit')
    if bit_depth not in BIT_DEPTHS:
        raise cam.error('bit_depth', f'one of {", ".join(map(str, BIT_DEPTHS))} bit',
                        bit_depth)
    # a quarter of the range at most: an offset that lifts read noise off code 0, not one
    # that eats the signal's range (64 DN at 8 bits)
    black_level = cam.number('black_level', 0.0, float(1 << (bit_depth - 2)), 'DN')
    cam.finish()
    return ((width, height, pixel_size, fx, fy, cx, cy),
            (exposure, cal_exposure, full_well, bit_depth, black_level))


def _read_dac(top: Section) -> Dac:
    dac_s = top.section('dac')
    dac = Dac(dac_s.integer('bits', 8, 24, 'bit'),
              dac_s.number('full_scale', 0.1, 100.0, 'V'))
    dac_s.finish()
    return dac


@dataclass
class _Imperfections:
    """The ``imperfections`` section of a rig file; ``section`` and the mirrors' sections
    (``mirrors[key] = (section, surface offset, axis tilt)``) are finished later, once the
    heads have read their drive errors from them."""

    section: Section
    distortion: np.ndarray
    mount: np.ndarray
    fan_roll: float
    fan_offset: float
    mirrors: dict
    #: the ``image`` subsection as :class:`ImageFormation` takes it: shot noise, read
    #: noise, speckle contrast, psf sigma, ambient light in laser frames
    image: tuple


def _read_imperfections(top: Section) -> _Imperfections:
    imp = top.section('imperfections')
    distortion = imp.vector('lens_distortion', 5, -50.0, 50.0, '(plumb_bob k1 k2 p1 p2 k3)')
    mount = imp.vector('camera_mount_rotation', 3, -0.05, 0.05, 'rad')
    fan_roll = imp.number('laser_fan_roll', -0.1, 0.1, 'rad')
    fan_offset = imp.number('laser_fan_offset', -0.01, 0.01, 'm',
                            hint='metres expected, not millimetres')
    mirrors = {}
    for key in ('g1_pan', 'g1_tilt', 'g2_pan', 'g2_tilt'):
        mirrors[key] = _mirror_imperfection(imp, key)
    img = imp.section('image')
    shot = img.boolean('shot_noise')
    read_noise = img.number('read_noise', 0.0, 1000.0, 'e-')
    speckle = img.number('speckle_contrast', 0.0, 1.0, '(relative)')
    psf = img.number('psf_sigma', 0.0, 10.0, 'px')
    ambient_laser = img.boolean('ambient_in_laser_frames')
    img.finish()
    return _Imperfections(imp, distortion, mount, fan_roll, fan_offset, mirrors,
                          (shot, read_noise, speckle, psf, ambient_laser))


def _read_heads(top: Section, imp: _Imperfections, dac: Dac):
    """The ``g1`` and ``g2`` sections: (l, d, g1, G_T_G2, g2); finishes the mirrors'
    imperfection sections."""
    mirrors = imp.mirrors
    g1s = top.section('g1')
    l = g1s.number('l', 0.005, 1.0, 'm', hint='metres expected; 83.45 mm is 0.08345')
    d = g1s.number('d', 0.002, 0.5, 'm', hint='metres expected; 22.14 mm is 0.02214')
    g1 = _galvo_head(g1s, d, mirrors['g1_pan'], mirrors['g1_tilt'], dac.full_scale)
    g1s.finish()

    g2s = top.section('g2')
    d2 = g2s.number('d', 0.002, 0.5, 'm', hint='metres expected, not millimetres')
    G_T_G2 = _pose(g2s, 'pose_in_g1')
    g2 = _galvo_head(g2s, d2, mirrors['g2_pan'], mirrors['g2_tilt'], dac.full_scale)
    g2s.finish()
    for s, _, _ in mirrors.values():
        s.finish()
    return l, d, g1, G_T_G2, g2


def _read_laser(top: Section, imp: _Imperfections) -> LaserSource:
    """The ``laser`` section, with the fan's roll and offset imperfections applied."""
    las = top.section('laser')
    position = las.vector('source_position', 3, -1.0, 1.0, 'm',
                          hint='metres expected, not millimetres')
    direction = unit(las.vector('direction', 3, -1.0, 1.0, '(unit vector)'))
    fan_normal = unit(las.vector('fan_normal', 3, -1.0, 1.0, '(unit vector)'))
    if abs(float(direction @ fan_normal)) > 1e-6:
        raise las.error('fan_normal', 'a vector perpendicular to laser.direction',
                        fan_normal.tolist())
    fan_angle = las.number('fan_angle', 0.01, 2.6, 'rad', hint='radians expected')
    line_width = las.number('line_width', 1e-6, 0.01, 'm', hint='metres expected')
    peak_rate = las.number('peak_rate', 0.0, 1e12, 'e-/s')
    ref_dist = las.number('reference_distance', 0.05, 20.0, 'm')
    las.finish()
    rolled = rotation_about(direction, imp.fan_roll) @ fan_normal
    return LaserSource(position + imp.fan_offset * fan_normal, direction, rolled, fan_angle,
                       line_width / 4.0, peak_rate, ref_dist)


def _read_world_and_light(top: Section):
    """The ``world`` and ``illumination`` sections: (W_T_G, the :class:`ImageFormation`
    arguments from ``ambient_rate`` on)."""
    world = top.section('world')
    W_T_G = _pose(world, 'pose_g1')
    world.finish()

    ill = top.section('illumination')
    ambient_rate = ill.number('ambient_rate', 0.0, 1e12, 'e-/s')
    light_dir = unit(ill.vector('light_direction', 3, -1.0, 1.0, '(unit vector, world)'))
    directional = ill.number('directional_fraction', 0.0, 1.0, '(fraction)')
    ill.finish()
    return W_T_G, (ambient_rate, light_dir, directional)


def _is_geometric(imp: _Imperfections, g1: GalvoHead, g2: GalvoHead) -> bool:
    """Whether any geometric imperfection (mount, fan, mirrors, drives) is non-zero."""
    mirrors, mount = imp.mirrors, imp.mount
    return bool(
        np.any(mount != 0.0) or imp.fan_roll != 0.0 or imp.fan_offset != 0.0
        or any(off != 0.0 or np.any(tl != 0.0) for _, off, tl in mirrors.values())
        or any(dr.zero_offset != 0.0 or dr.gain_error != 0.0 or any(dr.nonlinearity)
               for dr in (g1.pan_drive, g1.tilt_drive, g2.pan_drive, g2.tilt_drive)))


def _check_laser_reaches_g2(rig: Rig, source: str) -> None:
    """The laser must actually reach both G2 mirrors at the rest position."""
    try:
        th = rig.mirror_angles(np.zeros(4))
        rig.laser_sheet_G(th[2], th[3])
    except ValueError as exc:
        raise ConfigError(source, 'laser', f'a laser that hits both G2 mirrors ({exc})') \
            from exc


def rig_from_dict(data: dict, source: str) -> Rig:
    """Build a :class:`Rig` from a parsed rig file (see ``rigs/reference.yaml``).

    Raises
    ------
    ConfigError
        Naming ``source``, the key and what was expected; also when the laser misses a
        G2 mirror at the rest position.
    """
    top, name = RIG_FILES.open(data, source)
    lens, sensor = _read_camera(top)
    dac = _read_dac(top)
    imp = _read_imperfections(top)
    l, d, g1, G_T_G2, g2 = _read_heads(top, imp, dac)
    laser = _read_laser(top, imp)
    W_T_G, light = _read_world_and_light(top)
    imp.section.finish()
    top.finish()

    image = ImageFormation(*sensor, *imp.image, *light)
    camera = CameraModel(*lens, imp.distortion)
    M0 = make_transform(_M0_ROT, (-l, 0.0, 0.0))
    G_T_C = M0 @ make_transform(rotation_from_vector(imp.mount), np.zeros(3))
    geometric = _is_geometric(imp, g1, g2)
    imperf = {k: v for k, v in data.get('imperfections', {}).items()}
    rig = Rig(name, source, camera, image, l, d, g1, g2, G_T_C, G_T_G2, laser, dac, W_T_G,
              imperf, geometric)
    _check_laser_reaches_g2(rig, source)
    return rig


def load_rig(name_or_path) -> Rig:
    """Load a rig file.

    Parameters
    ----------
    name_or_path : str or Path
        A shipped rig name (``'reference'``, ``'ideal'``) or a path to a YAML file.

    Raises
    ------
    ConfigError
        The file is missing, malformed, or has a missing/implausible/unknown key.
    """
    return rig_from_dict(*RIG_FILES.read(name_or_path))


def load_rig_text(text: str, source: str = '<rig yaml>') -> Rig:
    """Load a rig from YAML text."""
    return rig_from_dict(*RIG_FILES.read_text(text, source))


def shipped_rigs() -> list[str]:
    """Names of the rig files shipped with the package."""
    return RIG_FILES.shipped()
