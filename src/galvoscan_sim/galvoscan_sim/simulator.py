"""Image formation and ground truth: the rig looking at a scene.

One frame, for voltages (U1_pan, U1_tilt, U2_pan, U2_tilt):

1. The DAC quantises the voltages; each mirror's true angle follows its (possibly
   nonlinear) response plus a per-frame jitter draw.
2. The laser sheet is the laser's fan traced off the two actual G2 mirrors.
3. Ground-truth stripe: the sheet's centre plane is cut with every face and sphere of the
   scene; for each image column the points of those curves that project exactly onto the
   column (sub-pixel v, projection = reflection through the two actual G1 mirror planes,
   which is exact for plane mirrors) are kept if the camera sees them (facing, not inside a
   solid, nothing on the segment to the G1 tilt mirror) and the laser reaches them (facing,
   inside the fan, nothing on the segment to the G2 tilt mirror).
4. Only a window of rows around each such point is ray-traced at full resolution: pixel
   rays are traced off the G1 mirror planes into the scene, and each hit is lit by the
   sheet with a Gaussian profile in its distance from the sheet's centre plane, times
   albedo, the cosine of the laser's incidence, 1/distance from the fan apex and a speckle
   factor, if the segment to the G2 mirror is free.
5. Room light (ambient plus a directional share) lights every surface: in board frames at
   full resolution with anti-aliased textures; in laser frames, if enabled, from a coarse
   grid of traced pixels, bilinearly upsampled (the background is dim and smooth there).
6. Optical blur, full-well clipping, shot and read noise, 8-bit quantisation.

Steps 3 and 4 work column by column (a window of rows around each column's stripe point).
A stripe along the image columns (a laser beside the camera, ``Rig.stripe_layout``) is
rendered with the camera described transposed: the same camera with its u and v (x and
y; fx and fy, cx and cy, width and height, p1 and p2) exchanged, which sees exactly the same
light; its image and its stripe truth are transposed back, so that every output is the
camera's own.

Noise uses a pool of standard normal draws made once per simulator from its seed; each
frame reads it at a random offset (independent within a frame; two frames may share
raster-shifted noise values). ``exact_noise=True`` draws fresh values every frame.
Everything is deterministic for a given seed and frame index.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from . import raykernels as rk
from .rig import LaserSheet, ModelParameters, Rig
from .scene import Hits, Scene
from .spatial import invert_transform, normalize_plane, transform_plane

_NEAR = 0.01  # [m] nearest depth considered in front of the virtual camera
#: Exchanges a camera's x and y axes (C' to C): the transposed camera's frame.
_SWAP_XY = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


def _transposed(rig: Rig) -> Rig:
    """The rig with its camera described transposed (u and v exchanged): the same camera."""
    from dataclasses import replace

    cam = rig.camera
    k1, k2, p1, p2, k3 = (float(v) for v in cam.distortion)
    cam_t = replace(cam, width=cam.height, height=cam.width, fx=cam.fy, fy=cam.fx, cx=cam.cy,
                    cy=cam.cx, distortion=np.array([k1, k2, p2, p1, k3]))
    return replace(rig, camera=cam_t, G_T_C=rig.G_T_C @ _SWAP_XY)


@lru_cache(maxsize=4)
def _pixel_grid(camera, step: int) -> np.ndarray:
    """Undistorted normalised coordinates of the pixel grid (read-only, cached)."""
    grid = camera.normalized_grid(step)
    grid.flags.writeable = False
    return grid


@lru_cache(maxsize=2)
def _noise_pool(seed: int) -> np.ndarray:
    """2**22 standard normal draws for a seed (read-only, cached)."""
    pool = np.random.default_rng([seed, 0x5EED]).standard_normal(1 << 22, dtype=np.float32)
    pool.flags.writeable = False
    return pool


def _reflection(n, c):
    """4x4 reflection through the plane n . x = c (n unit; no checks, hot path)."""
    T = np.eye(4)
    T[:3, :3] -= 2.0 * np.outer(n, n)
    T[:3, 3] = 2.0 * c * n
    return T


@dataclass
class StripeTruth:
    """Ground-truth stripe of one frame: one entry per (column, stripe branch).

    For image column ``column``, the entry is the point on the *actual* laser sheet's
    centre plane and on an object's surface whose projection has u == column exactly; it
    is seen by the camera and reached by the laser.

    Attributes
    ----------
    column : ndarray, shape (n,), int
    u, v : ndarray, shape (n,), px
        Exact sub-pixel projection (u equals column to ~1e-9 px).
    points_W, points_V0 : ndarray, shape (n, 3), metres
    normals_W : ndarray, shape (n, 3)
        Surface normal at the point, facing the camera.
    object_index : ndarray, shape (n,), int
        Index into the scene's objects.
    """

    column: np.ndarray
    u: np.ndarray
    v: np.ndarray
    points_W: np.ndarray
    points_V0: np.ndarray
    normals_W: np.ndarray
    object_index: np.ndarray

    @staticmethod
    def empty() -> StripeTruth:
        z3 = np.zeros((0, 3))
        return StripeTruth(np.zeros(0, int), np.zeros(0), np.zeros(0), z3, z3.copy(),
                           z3.copy(), np.zeros(0, int))

    def __len__(self):
        return len(self.column)


@dataclass
class FrameTruth:
    """Everything true about one simulated frame.

    Attributes
    ----------
    index : int
        Frame index (seeds the frame's random draws).
    voltages_commanded, voltages_applied : ndarray, shape (4,), volts
        (U1_pan, U1_tilt, U2_pan, U2_tilt) asked for and output by the DAC.
    angles : ndarray, shape (4,), radians
        True mechanical mirror angles theta1..theta4, jitter included.
    W_T_V, V0_T_V, W_T_V0 : ndarray, shape (4, 4)
        Virtual camera poses.
    laser_on : bool
    laser_plane_W, laser_plane_V0 : ndarray, shape (4,)
        Centre plane of the actual sheet (unit normal); NaN when the laser is off.
    laser_source_W : ndarray, shape (3,), metres
        Virtual apex of the fan after both G2 mirrors.
    exposure : float
        [s]
    stripe : StripeTruth
    rig_name, scene_name : str
    model_parameters : ModelParameters or None
        The rig's true model-equivalent parameters (``Rig.true_model_parameters()`` at
        U2_pan = 0), shared by all frames of a simulator.
    reflection : StripeTruth
        Where the stripe thrown by specular faces (one bounce) lands: per column the point
        on the mirrored sheet's centre plane seen by the camera (see
        :meth:`Simulator.reflection_truth`); empty in scenes without specular materials.
    """

    index: int
    voltages_commanded: np.ndarray
    voltages_applied: np.ndarray
    angles: np.ndarray
    W_T_V: np.ndarray
    V0_T_V: np.ndarray
    W_T_V0: np.ndarray
    laser_on: bool
    laser_plane_W: np.ndarray
    laser_plane_V0: np.ndarray
    laser_source_W: np.ndarray
    exposure: float
    stripe: StripeTruth
    rig_name: str = ''
    scene_name: str = ''
    model_parameters: ModelParameters | None = None
    reflection: StripeTruth = field(default_factory=StripeTruth.empty)

    def as_dict(self) -> dict:
        """Plain dict (arrays kept as numpy arrays), e.g. for a driver Frame's truth."""
        out = {k: v for k, v in self.__dict__.items()
               if k not in ('stripe', 'model_parameters', 'reflection')}
        out['stripe'] = dict(self.stripe.__dict__)
        out['reflection'] = dict(self.reflection.__dict__)
        if self.model_parameters is not None:
            out['model_parameters'] = self.model_parameters.as_dict()
        return out


@dataclass
class SimFrame:
    """One simulated camera image with its ground truth.

    Attributes
    ----------
    image : ndarray, shape (height, width), uint8 (8-bit rigs) or uint16 (10, 12, 16 bits)
    truth : FrameTruth
    """

    image: np.ndarray
    truth: FrameTruth


@dataclass
class _Geometry:
    angles: np.ndarray
    W_T_V: np.ndarray
    V_T_W: np.ndarray
    W_T_G: np.ndarray
    center: np.ndarray           # virtual camera centre, W
    cam_mirror: np.ndarray       # G1 tilt mirror plane, W
    sheet: LaserSheet | None = None
    extra: dict = field(default_factory=dict)


class Simulator:
    """The rig (:class:`~galvoscan_sim.rig.Rig`) scanning a scene.

    Parameters
    ----------
    rig : Rig
    scene : Scene
    seed : int
        Seeds every random draw (jitter, noise, speckle); same seed, same frames.
    exact_noise : bool
        Draw fresh normal deviates for every frame instead of reading the seeded pool.
    coarse_step : int
        Pixel step of the traced grid for the room-light background of laser frames.
    """

    def __init__(self, rig: Rig, scene: Scene, seed: int = 0, *, exact_noise: bool = False,
                 coarse_step: int = 10):
        self.rig = rig
        self.scene = scene
        self.seed = int(seed)
        self.exact_noise = exact_noise
        #: Whether the camera is worked with transposed (a stripe along the columns).
        self.transposed = rig.stripe_layout().orientation == 'vertical'
        self._outer = rig
        rig = _transposed(rig) if self.transposed else rig
        self._r = rig
        cam = rig.camera
        self.coarse_step = int(coarse_step)
        self._grid = _pixel_grid(cam, 1)
        self._coarse = _pixel_grid(cam, self.coarse_step).reshape(-1, 2)
        gx, gy = self._grid[..., 0], self._grid[..., 1]
        mx, my = 2.0 / cam.fx, 2.0 / cam.fy  # two pixels of margin around the image
        self._bounds = (float(gx.min()) - mx, float(gx.max()) + mx, float(gy.min()) - my,
                        float(gy.max()) + my)
        self._pool = None
        if rig.image.noisy and not exact_noise:
            self._pool = _noise_pool(self.seed)
        self._next_index = 0
        self._intr = self._intrinsics()
        def mirror(m):
            return np.concatenate((m.axis_point, m.reference_normal, m._binormal,
                                   (m.surface_offset,)))

        L = rig.laser
        self._g2_pack = (mirror(rig.g2.pan), mirror(rig.g2.tilt),
                         np.concatenate((L.position, L.direction, L.fan_normal,
                                         L.spread_direction)),
                         np.ascontiguousarray(rig.W_T_G @ rig.G_T_G2))
        self._cam_const = np.concatenate((rig.G_T_C[:3, :3].ravel(), rig.G_T_C[:3, 3],
                                          rig.W_T_G[:3, :3].ravel(), rig.W_T_G[:3, 3]))
        #: The rig's true model-equivalent parameters (see Rig.true_model_parameters).
        self.model_parameters = self._outer.true_model_parameters()
        self.W_T_V0 = self._outer.W_T_V0
        self.V0_T_W = invert_transform(self.W_T_V0)

    # ------------------------------------------------------------- helpers
    def set_scene(self, scene: Scene) -> None:
        """Replace the scene (the rig and the seed stay)."""
        self.scene = scene

    def _rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(index)])

    def geometry(self, angles, laser_on: bool = True) -> _Geometry:
        """Camera and laser geometry for true mirror angles (4,) [rad] (with
        :attr:`transposed`, the virtual camera's x and y axes are exchanged in ``W_T_V``
        and ``V_T_W``: the frame the rendering works in)."""
        rig = self._r
        th = np.asarray(angles, dtype=np.float64)
        if th.shape != (4,):
            raise ValueError(f'angles: expected shape (4,), got {th.shape}')
        (n1, c1), (n2, c2) = rig.g1_planes(th[0], th[1])
        G_T_V = _reflection(n2, c2) @ (_reflection(n1, c1) @ rig.G_T_C)
        W_T_G = rig.W_T_G
        W_T_V = W_T_G @ G_T_V
        V_T_W = np.eye(4)
        V_T_W[:3, :3] = W_T_V[:3, :3].T
        V_T_W[:3, 3] = -W_T_V[:3, :3].T @ W_T_V[:3, 3]
        # the G1 tilt mirror n2 . x = c2 in W (W_T_G is rigid)
        nW = W_T_G[:3, :3] @ n2
        cam_mirror = np.array([nW[0], nW[1], nW[2], float(nW @ W_T_G[:3, 3]) - c2])
        center = W_T_V[:3, 3].copy()
        geo = _Geometry(th, W_T_V, V_T_W, W_T_G, center, cam_mirror)
        geo.extra['cam'] = np.concatenate((self._cam_const[:12], n1, (c1,), n2, (c2,),
                                           self._cam_const[12:], center))
        if laser_on:
            pack = np.empty(20)
            pan, tilt, laser, W_T_G2 = self._g2_pack
            if not rk.laser_sheet(pan, tilt, laser, 0.5 * rig.laser.fan_angle, W_T_G2,
                                  float(th[2]), float(th[3]), pack):
                raise ValueError(f'rig {rig.name}: the laser beam misses a G2 mirror at '
                                 f'angles {th[2:]}')
            geo.sheet = LaserSheet(pack[0:4], pack[4:7], pack[17:20], pack[7:13].reshape(2, 3),
                                   pack[13:17], 0.5 * rig.laser.fan_angle)
            geo.extra['sheet'] = pack[:17]
        return geo

    def project_points(self, points_W, angles) -> np.ndarray:
        """Pixel coordinates of world points seen through the G1 mirrors.

        Parameters
        ----------
        points_W : array_like, shape (n, 3), metres
        angles : array_like, shape (4,), radians
            True mirror angles (only theta1, theta2 matter).

        Returns
        -------
        ndarray, shape (n, 2), px (NaN behind the virtual camera)
        """
        P = np.asarray(points_W, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3:
            raise ValueError(f'points_W: expected shape (n, 3), got {P.shape}')
        geo = self.geometry(angles, laser_on=False)
        uv = self._r.camera.project(P @ geo.V_T_W[:3, :3].T + geo.V_T_W[:3, 3])
        return uv[:, ::-1].copy() if self.transposed else uv

    def trace_pixels(self, uv, angles) -> Hits:
        """Trace pixel rays off the G1 mirrors into the scene.

        Parameters
        ----------
        uv : array_like, shape (n, 2), px
        angles : array_like, shape (4,), radians

        Returns
        -------
        Hits
            World-frame hits.
        """
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f'uv: expected shape (n, 2), got {uv.shape}')
        th = np.asarray(angles, dtype=np.float64)
        if th.shape != (4,):
            raise ValueError(f'angles: expected shape (4,), got {th.shape}')
        if self.transposed:
            uv = uv[:, ::-1]
        xy = self._r.camera.pixel_to_normalized(uv)
        return self._trace_xy(xy, th)

    def _trace_xy(self, xy, th) -> Hits:
        rig = self._r
        o, d = rig.trace_camera_rays(xy, th[0], th[1])
        R, t = rig.W_T_G[:3, :3], rig.W_T_G[:3, 3]
        return self.scene.intersect(o @ R.T + t, d @ R.T)

    # ------------------------------------------------------ stripe truth
    def _half_spaces(self, geo: _Geometry) -> np.ndarray:
        R = geo.W_T_V[:3, :3]
        C = geo.center
        x0, x1, y0, y1 = self._bounds
        hs = [(C, R @ np.array([1.0, 0.0, -x0])), (C, R @ np.array([-1.0, 0.0, x1])),
              (C, R @ np.array([0.0, 1.0, -y0])), (C, R @ np.array([0.0, -1.0, y1])),
              (C + _NEAR * R[:, 2], R[:, 2])]
        sh = geo.sheet
        hs += [(sh.source, sh.edge_normals[0]), (sh.source, sh.edge_normals[1])]
        return np.array([np.array(h) for h in hs])

    def _intrinsics(self) -> np.ndarray:
        cam = self._r.camera
        return np.concatenate([[cam.fx, cam.fy, cam.cx, cam.cy], cam.distortion,
                               [cam.width, cam.height]]).astype(np.float64)

    def _stripe_crossings(self, geo: _Geometry):
        """True stripe points (see StripeTruth), sorted by column then v, or None."""
        sheet = geo.sheet
        cam = self._r.camera
        hs = self._half_spaces(geo)
        A, B, nrm, obj, two = self.scene.sheet_segments(sheet.plane, hs, geo.center,
                                                        sheet.source)
        circles = self.scene.sheet_circles(sheet.plane)
        cap = (len(A) + 2 * len(circles)) * cam.width + 16
        X = np.empty((cap, 3))
        N = np.empty((cap, 3))
        ob = np.empty(cap, np.int64)
        cl = np.empty(cap, np.int64)
        u = np.empty(cap)
        v = np.empty(cap)
        ptype, _, R, T, prm = self.scene.packed()
        intr = self._intr
        psheet = geo.extra['sheet']
        VTW = np.ascontiguousarray(geo.V_T_W)
        m = 0
        if len(A):
            m = rk.segment_crossings(ptype, R, T, prm, VTW, intr, geo.center, geo.cam_mirror,
                                     psheet, A, B, nrm, two, obj.astype(np.int64), _NEAR, X,
                                     N, ob, cl, u, v)
        for k, cc, rho, e1, e2, sc, _ in circles:
            dist = float(np.linalg.norm(cc - geo.center))
            samples = int(np.clip(2 * np.pi * rho * cam.fx / max(dist, 1e-3) / 4, 64, 4096))
            m += rk.circle_crossings(ptype, R, T, prm, VTW, intr, geo.center, geo.cam_mirror,
                                     psheet, cc, rho, e1, e2, sc, samples, k, _NEAR, X[m:],
                                     N[m:], ob[m:], cl[m:], u[m:], v[m:])
        if m == 0:
            return None
        X, N, ob, cl, u, v = X[:m], N[:m], ob[:m], cl[:m], u[:m], v[:m]
        order = np.lexsort((v, cl))
        X, N, ob, cl, u, v = X[order], N[order], ob[order], cl[order], u[order], v[order]
        dup = np.zeros(m, bool)
        dup[1:] = (cl[1:] == cl[:-1]) & (np.abs(np.diff(v)) < 1e-6)
        if np.any(dup):
            keep = ~dup
            X, N, ob, cl, u, v = X[keep], N[keep], ob[keep], cl[keep], u[keep], v[keep]
        return X, N, ob, cl, u, v

    def stripe_truth(self, geo: _Geometry) -> StripeTruth:
        """Ground-truth stripe for a frame geometry (see :class:`StripeTruth`)."""
        if geo.sheet is None:
            return StripeTruth.empty()
        res = self._stripe_crossings(geo)
        if res is None:
            return StripeTruth.empty()
        return self._stripe_truth(res)

    def _stripe_truth(self, res) -> StripeTruth:
        """Stripe truth from crossings, in the camera's own pixels (transposed back: one
        entry per row, ``column`` then holding the row)."""
        X, N, ob, cl, u, v = res
        R, t = self.V0_T_W[:3, :3], self.V0_T_W[:3, 3]
        if self.transposed:
            u, v = v, u
        return StripeTruth(cl, u, v, X, X @ R.T + t, N, ob)

    # ------------------------------------------------------------ images
    def _background(self, geo, exposure, full: bool) -> np.ndarray:
        """Room-light signal [e-]: every pixel (full) or the coarse grid, float32."""
        rig, cam = self._r, self._r.camera
        im = rig.image
        step = 1 if full else self.coarse_step
        xy = self._grid.reshape(-1, 2) if full else self._coarse
        ptype, pobj, R, T, prm = self.scene.packed()
        tex, oR, oT = self.scene.texture_table
        out = np.empty(len(xy), np.float32)
        rk.ambient_pixels(ptype, R, T, prm, pobj, geo.extra['cam'], xy, step / cam.fx,
                          geo.center, self.scene.albedo_table, tex, oR, oT,
                          im.ambient_rate * exposure, im.light_direction,
                          im.directional_fraction, out)
        return out.reshape(cam.height // step, cam.width // step)

    def _window_sigma(self, obj) -> np.ndarray:
        """Stripe sigma [m] each direct window is sized for: the sheet's, widened on
        translucent objects by their subsurface spread and shift."""
        sigma = self._r.laser.sigma
        mats = self.scene.material_table[obj]
        ell = np.where(mats[:, 5] > 0, mats[:, 4], 0.0)
        return np.where(ell > 0, np.sqrt(sigma * sigma + ell * ell) + ell, sigma)

    def _laser_layer(self, geo, crossings, energy, rng, reflections=()):
        """The laser stripe (electrons) in windows around the true points, and the stripes
        the specular faces throw (``reflections``, see :meth:`_reflection_crossings`).

        Returns
        -------
        tuple (ndarray shape (rows, width) float32, int)
            The band of image rows holding the stripe and its first row.
        """
        rig, cam, sheet = self._r, self._r.camera, geo.sheet
        sigma = rig.laser.sigma
        starts, ends = [], []
        if crossings is not None:
            X, N, ob, col, _, v = crossings
            half = np.empty(len(col), np.int64)
            rk.window_halves(X, N, col, v, np.ascontiguousarray(geo.W_T_V[:3, :3]),
                             geo.center, sheet.plane, self._window_sigma(ob),
                             rig.image.psf_sigma, self._intr, half)
            v0 = np.rint(v).astype(np.int64)
            starts.append(v0 - half)
            ends.append(v0 + half)
        for r in reflections:
            starts.append(r['v0'] - r['half'])
            ends.append(r['v0'] + r['half'])
        lo_all, hi_all = np.concatenate(starts), np.concatenate(ends)
        psf = rig.image.psf_sigma
        pad = int(np.ceil(3 * psf)) + 1 if psf > 0 else 0
        b0 = max(int(lo_all.min()) - pad, 0)
        b1 = min(int(hi_all.max()) + 1 + pad, cam.height)
        if b1 <= b0:
            return np.zeros((0, cam.width), np.float32), 0
        band = np.zeros((b1 - b0, cam.width), np.float32)
        ptype, pobj, Rp, Tp, prm = self.scene.packed()
        tex, oR, oT = self.scene.texture_table
        mats = self.scene.material_table
        scale = energy * rig.laser.reference_distance
        if crossings is not None:
            c = rig.image.speckle_contrast
            if c > 0 and self._pool is not None:
                z, zoff = self._pool, int(rng.integers(0, len(self._pool)))
            elif c > 0:
                z, zoff = rng.standard_normal(int(np.sum(2 * half + 1))), 0
            else:
                z, zoff = np.zeros(1, np.float32), 0
            rk.laser_windows(ptype, Rp, Tp, prm, pobj, self.scene.albedo_table, tex, oR, oT,
                             mats, geo.extra['cam'], self._grid, col, v0, half,
                             geo.extra['sheet'], sigma, scale, c, z, zoff, band, b0,
                             1.0 / cam.fx)
        for r in reflections:
            layer = np.zeros_like(band)
            rk.reflection_windows(ptype, Rp, Tp, prm, pobj, self.scene.albedo_table, mats,
                                  geo.extra['cam'], self._grid, r['col'], r['v0'], r['half'],
                                  r['vsheet'], r['face'], r['fmat'], geo.extra['sheet'], sigma,
                                  scale, layer, b0)
            band += layer
        if psf > 0:
            # blur each cluster of window rows on its own: the rows between clusters are
            # empty and farther apart than the kernel, so this equals blurring the band
            order = np.argsort(lo_all)
            lo = lo_all[order] - pad - b0
            hi = np.maximum.accumulate(hi_all[order] + 1 + pad - b0)
            cut = np.flatnonzero(lo[1:] > hi[:-1] + pad) + 1
            for a, b in zip(np.r_[0, cut], np.r_[cut, len(lo)], strict=True):
                self._blur_rows(band, lo[a], hi[b - 1], psf)
        return band, b0

    # ------------------------------------------------------- reflections
    def _specular_faces(self, geo):
        """Planar faces of specular objects that face the laser's apex: (index, outward
        normal (3,)) pairs (two-sided faces turned towards the apex)."""
        F = self.scene.faces
        mats = self.scene.material_table
        src = geo.sheet.source
        out = []
        for f in range(len(F.obj)):
            if mats[F.obj[f], 6] <= 0:
                continue
            n = F.normal[f].copy()
            side = float(n @ (src - F.center[f]))
            if F.two_sided[f] and side < 0:
                n, side = -n, -side
            if side > 0:
                out.append((f, n))
        return out

    def _reflection_crossings(self, geo) -> list:
        """The stripes thrown by the specular faces (one bounce): per face, its true
        points, the window specification and the packed mirrored sheet (list of dicts)."""
        F = self.scene.faces
        sheet = geo.sheet
        cam = self._r.camera
        out = []
        base_hs = self._half_spaces(geo)[:5]
        ptype, _, R, T, prm = self.scene.packed()
        VTW = np.ascontiguousarray(geo.V_T_W)
        for f, nA in self._specular_faces(geo):
            cA = F.center[f]
            dA = float(nA @ cA)
            H = np.eye(3) - 2.0 * np.outer(nA, nA)
            apex = sheet.source - 2.0 * (float(nA @ sheet.source) - dA) * nA
            Nv = H @ sheet.plane[:3]
            e_v = -float(Nv @ apex)
            edges = [H @ en for en in sheet.edge_normals]
            vpack = np.concatenate((Nv, (e_v,), apex, edges[0], edges[1], nA, (-dA,)))
            hs = np.concatenate((base_hs, np.array([(apex, edges[0]), (apex, edges[1]),
                                                     (cA, nA)])))
            A, B, nrm, obj, two = self.scene.sheet_segments(np.r_[Nv, e_v], hs, geo.center,
                                                            apex)
            if not len(A):
                continue
            cap = len(A) * cam.width + 16
            X, N = np.empty((cap, 3)), np.empty((cap, 3))
            ob, cl = np.empty(cap, np.int64), np.empty(cap, np.int64)
            u, v = np.empty(cap), np.empty(cap)
            m = rk.segment_crossings(ptype, R, T, prm, VTW, self._intr, geo.center,
                                     geo.cam_mirror, vpack, A, B, nrm, two,
                                     obj.astype(np.int64), _NEAR, X, N, ob, cl, u, v)
            if m == 0:
                continue
            X, N, ob, cl, u, v = X[:m], N[:m], ob[:m], cl[:m], u[:m], v[:m]
            # the ray back towards the mirrored apex must cross the face inside it, and the
            # laser must reach that point of the face
            d = apex - X
            dist = np.linalg.norm(d, axis=1)
            d /= dist[:, None]
            den = d @ nA
            with np.errstate(divide='ignore', invalid='ignore'):
                L = (dA - X @ nA) / den
            Z = X + L[:, None] * d
            q = Z - cA
            inside = ((den < 0) & (L > 0) & (L < dist)
                      & (np.abs(q @ F.e1[f]) <= F.half[f, 0])
                      & (np.abs(q @ F.e2[f]) <= F.half[f, 1]))
            w = sheet.source - Z
            wd = np.linalg.norm(w, axis=1)
            w /= wd[:, None]
            mirror = sheet.mirror_plane
            with np.errstate(divide='ignore', invalid='ignore'):
                tm = -(Z @ mirror[:3] + mirror[3]) / (w @ mirror[:3])
            tm = np.where((tm > 0) & (tm < wd), tm, wd)
            keep = inside & ~self.scene.occluded(Z, w, tm)
            if not np.any(keep):
                continue
            X, N, ob, cl, u, v, L = X[keep], N[keep], ob[keep], cl[keep], u[keep], v[keep], \
                L[keep]
            fmat = self.scene.material_table[F.obj[f]]
            sig_r = np.sqrt(self._r.laser.sigma ** 2 + 2.0 * fmat[1] ** 2 * L ** 2)
            half = np.empty(len(cl), np.int64)
            rk.window_halves(X, N, cl, v, np.ascontiguousarray(geo.W_T_V[:3, :3]),
                             geo.center, vpack[:4], sig_r, self._r.image.psf_sigma,
                             self._intr, half)
            face = np.concatenate((cA, F.e1[f], F.e2[f], F.half[f], nA))
            out.append({'X': X, 'N': N, 'obj': ob, 'col': cl, 'u': u, 'v': v,
                        'v0': np.rint(v).astype(np.int64), 'half': half, 'vsheet': vpack,
                        'face': face, 'fmat': np.ascontiguousarray(fmat)})
        return out

    def _reflection_truth(self, reflections) -> StripeTruth:
        if not reflections:
            return StripeTruth.empty()
        cat = {k: np.concatenate([r[k] for r in reflections]) for k in
               ('col', 'u', 'v', 'X', 'N', 'obj')}
        order = np.lexsort((cat['v'], cat['col']))
        X = cat['X'][order]
        R, t = self.V0_T_W[:3, :3], self.V0_T_W[:3, 3]
        u, v = cat['u'][order], cat['v'][order]
        if self.transposed:
            u, v = v, u
        return StripeTruth(cat['col'][order], u, v, X,
                           X @ R.T + t, cat['N'][order], cat['obj'][order])

    def reflection_truth(self, geo: _Geometry) -> StripeTruth:
        """Where the specular faces throw the stripe (one bounce) for a frame geometry:
        per column, the points on the mirrored sheets' centre planes the camera sees."""
        if geo.sheet is None or not self.scene.specular:
            return StripeTruth.empty()
        return self._reflection_truth(self._reflection_crossings(geo))

    @staticmethod
    def _blur_rows(band, start, end, psf):
        start, end = max(int(start), 0), min(int(end), band.shape[0])
        if end > start:
            band[start:end] = cv2.GaussianBlur(band[start:end], (0, 0), psf,
                                               borderType=cv2.BORDER_CONSTANT)

    def _sensor(self, bg, band, b0, rng) -> np.ndarray:
        """Background (None, coarse or full) + stripe band -> noisy image in the camera's
        output format (uint8 at 8 bits, uint16 above)."""
        im, cam = self._r.image, self._r.camera
        n = cam.width * cam.height
        if im.noisy:
            if self._pool is not None:
                off = int(rng.integers(0, len(self._pool) - n))
                z = self._pool[off:off + n]
            else:
                z = rng.standard_normal(n, dtype=np.float32)
        else:
            z = np.zeros(0, np.float32)
        if bg is None:
            bg = np.zeros((0, 0), np.float32)
        elif bg.shape != (cam.height, cam.width):
            bg = cv2.resize(bg, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR)
        out = np.empty((cam.height, cam.width), im.dtype)
        rk.sensor(bg, band, b0, z, float(im.full_well), bool(im.shot_noise),
                  float(im.read_noise ** 2), 1.0 / im.electrons_per_dn, float(im.black_level),
                  float(im.white_level), out)
        return out

    def render(self, voltages, *, laser_on: bool = True, background: str = 'coarse',
               exposure: float | None = None, laser_power: float = 1.0,
               frame_index: int | None = None) -> SimFrame:
        """Simulate one camera frame.

        Parameters
        ----------
        voltages : array_like, shape (4,), volts
            Commanded (U1_pan, U1_tilt, U2_pan, U2_tilt).
        laser_on : bool
        background : {'coarse', 'full'}
            Room light from a coarse traced grid (laser frames) or every pixel with
            anti-aliased textures (board frames).
        exposure : float, optional
            [s]; the rig's laser-frame exposure by default.
        laser_power : float
            Laser power relative to the rig's [1].
        frame_index : int, optional
            Seeds this frame's draws; by default the next index of this simulator.

        Returns
        -------
        SimFrame
        """
        if background not in ('coarse', 'full'):
            raise ValueError(f"background: expected 'coarse' or 'full', got {background!r}")
        if not laser_power >= 0:
            raise ValueError(f'laser_power: expected >= 0, got {laser_power}')
        rig = self._r
        U = np.asarray(voltages, dtype=np.float64)
        if U.shape != (4,):
            raise ValueError(f'voltages: expected shape (4,), got {U.shape}')
        applied = rig.applied_voltages(U)
        if frame_index is None:
            frame_index = self._next_index
        self._next_index = int(frame_index) + 1
        rng = self._rng(frame_index)
        angles = rig.mirror_angles(applied, rng.standard_normal(4))
        exposure = rig.image.exposure if exposure is None else float(exposure)
        if not exposure > 0:
            raise ValueError(f'exposure: expected > 0 s, got {exposure}')
        geo = self.geometry(angles, laser_on)
        full = background == 'full'
        ambient = full or not laser_on or rig.image.ambient_in_laser_frames
        bg = None
        if ambient:
            bg = self._background(geo, exposure, full)
            if full and rig.image.psf_sigma > 0:
                bg = cv2.GaussianBlur(bg, (0, 0), rig.image.psf_sigma)
        stripe = StripeTruth.empty()
        reflection = StripeTruth.empty()
        band, b0 = np.zeros((0, rig.camera.width), np.float32), 0
        if laser_on:
            res = self._stripe_crossings(geo)
            refl = self._reflection_crossings(geo) if self.scene.specular else []
            if res is not None or refl:
                energy = rig.laser.peak_rate * exposure * laser_power
                band, b0 = self._laser_layer(geo, res, energy, rng, refl)
            if res is not None:
                stripe = self._stripe_truth(res)
            reflection = self._reflection_truth(refl)
        image = self._sensor(bg, band, b0, rng)
        W_T_V = geo.W_T_V
        if self.transposed:
            image = np.ascontiguousarray(image.T)
            W_T_V = W_T_V @ _SWAP_XY
        nan4 = np.full(4, np.nan)
        plane_W = geo.sheet.plane if laser_on else nan4
        truth = FrameTruth(
            int(frame_index), U.copy(), applied, angles, W_T_V,
            self.V0_T_W @ W_T_V, self.W_T_V0.copy(), laser_on, plane_W,
            normalize_plane(transform_plane(self.V0_T_W, plane_W)) if laser_on else nan4,
            geo.sheet.source if laser_on else np.full(3, np.nan), exposure, stripe,
            rig.name, self.scene.name, self.model_parameters, reflection)
        return SimFrame(image, truth)

    def calibration_frame(self, voltages, *, laser_on: bool = False,
                          exposure: float | None = None, laser_power: float | None = None,
                          frame_index: int | None = None) -> SimFrame:
        """A fully textured board frame under room light, optionally with the stripe.

        The exposure defaults to the rig's ``calibration_exposure``; the laser power
        defaults to the value that gives the stripe the same signal as in a laser frame.
        """
        rig = self._r
        exposure = rig.image.calibration_exposure if exposure is None else exposure
        if laser_power is None:
            laser_power = rig.image.exposure / exposure
        return self.render(voltages, laser_on=laser_on, background='full', exposure=exposure,
                           laser_power=laser_power, frame_index=frame_index)

    def scan(self, voltages: Iterable, **render_kwargs) -> Iterator[SimFrame]:
        """Frames for a list of voltages, produced one by one.

        Parameters
        ----------
        voltages : array_like, shape (n, 4), volts
        **render_kwargs
            Passed to :meth:`render` (not ``frame_index``).
        """
        U = np.asarray(voltages, dtype=np.float64)
        if U.ndim != 2 or U.shape[1] != 4:
            raise ValueError(f'voltages: expected shape (n, 4), got {U.shape}')
        self.rig.dac.quantize(U)  # range check before the first frame
        for row in U:
            yield self.render(row, **render_kwargs)
