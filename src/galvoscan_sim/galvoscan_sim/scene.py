"""Scenes: objects with poses and albedo, ray intersection, textures and laser curves.

Every object has a pose ``W_T_O`` in the world frame W and an albedo. In an object's own
frame its front faces -z, so an object with the identity rotation faces a camera on the
world's -z side looking along +z (the rig's nominal V0).

Object types (YAML ``type``):

``plane``         the plane z = 0, infinite or ``size`` [sx, sy]; two-sided.
``box``           ``size`` [sx, sy, sz] centred on the origin.
``stair_block``   footprint ``size`` [sx, sy] x base height ``size[2]``, resting on z = 0
                  and rising towards -z; the half x >= 0 is ``step_height`` higher. The two
                  top faces are parallel, ``step_height`` apart (the paper's 30 mm block).
``sphere``        ``radius`` about the origin (the calibration sphere).
``flat_plate``    ``size`` [sx, sy], front face z = 0, ``thickness`` behind it (+z).
``checkerboard``  a flat plate with ``squares`` [nx, ny] of ``square_size``.
``circle_board``  the paper's 740 x 740 mm board: 35 x 35 circles at 20 mm pitch, in 7 x 7
                  sub-patterns whose centre circle is 15 mm, the others 10 mm.

Any object may name a ``material`` (:mod:`galvoscan_sim.materials`): a glossy lobe, the
reflections it throws, subsurface scattering. Its ``albedo`` is then optional (the
material's diffuse reflectance by default). Without one the object is Lambertian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import materials as mt
from . import raykernels as rk
from .config import ConfigError, Section
from .readers import MM_HINT, FileKind, as_rays, read_pose
from .spatial import invert_transform

SCENE_FORMAT_VERSION = 1
SCENE_DIR = Path(__file__).resolve().parent / 'scenes'
SCENE_FILES = FileKind(SCENE_FORMAT_VERSION, SCENE_DIR)
OBJECT_TYPES = ('plane', 'box', 'stair_block', 'sphere', 'flat_plate', 'checkerboard',
                'circle_board')
#: Rays start this far [m] beyond their origin when testing for hits (self-intersection).
EPS = 1e-7


@dataclass(frozen=True)
class _Box:
    lo: np.ndarray
    hi: np.ndarray


@dataclass(frozen=True)
class _Sphere:
    center: np.ndarray
    radius: float


@dataclass(frozen=True)
class _Rect:
    half: np.ndarray  # (2,), may be inf


@dataclass
class SceneObject:
    """One object of a scene.

    Attributes
    ----------
    type, name : str
    W_T_O : ndarray, shape (4, 4)
        Object pose in the world frame.
    albedo : float
        Diffuse reflectance of the object (of the light parts of a board) [1].
    params : dict
        Type-specific parameters as read (SI).
    material : Material or None
        Surface material; None is Lambertian with ``albedo``.
    """

    type: str
    name: str
    W_T_O: np.ndarray
    albedo: float
    params: dict
    prims: list = field(default_factory=list)
    material: mt.Material | None = None

    def __post_init__(self):
        self.O_T_W = invert_transform(self.W_T_O)

    # ------------------------------------------------------------ textures
    def albedo_local(self, p, footprint):
        """Albedo at local points ``p`` (n, 3) seen with a pixel ``footprint`` (n,) [m]."""
        a = np.full(len(p), self.albedo)
        if self.type not in ('checkerboard', 'circle_board'):
            return a
        front = np.abs(p[:, 2]) < 1e-6
        if not np.any(front):
            return a
        x, y, w = p[front, 0], p[front, 1], np.maximum(footprint[front], 1e-9)
        if self.type == 'checkerboard':
            dark = self._checker_dark(x, y, w)
            other = self.params['dark_albedo']
        else:
            dark = self._circle_cover(x, y, w)
            other = self.params['circle_albedo']
        a[front] = self.albedo + (other - self.albedo) * dark
        return a

    def _checker_dark(self, x, y, w):
        """Box-filtered (pixel footprint w) share of dark squares around (x, y)."""
        nx, ny = self.params['squares']
        s = self.params['square_size']

        def axis(t, n):
            # t from the pattern's edge; +1/-1 for even/odd cells, box-filtered across the
            # internal lines only, and the fraction of the footprint inside the pattern
            k = np.clip(np.floor(t / s), 0, n - 1)
            sign = 1.0 - 2.0 * np.mod(k, 2.0)
            lo_edge = np.where(k > 0, t - k * s, np.inf)
            hi_edge = np.where(k < n - 1, (k + 1) * s - t, np.inf)
            wave = sign * np.minimum(1.0, np.minimum(lo_edge, hi_edge) / (0.5 * w))
            inside = np.clip(0.5 + np.minimum(t, n * s - t) / w, 0.0, 1.0)
            return wave, inside

        wx, ix = axis(x + 0.5 * nx * s, nx)
        wy, iy = axis(y + 0.5 * ny * s, ny)
        return ix * iy * (0.5 + 0.5 * wx * wy)

    def _circle_cover(self, x, y, w):
        pr = self.params
        nx, ny = pr['grid']
        pitch = pr['pitch']
        i = np.clip(np.rint(x / pitch + 0.5 * (nx - 1)), 0, nx - 1)
        j = np.clip(np.rint(y / pitch + 0.5 * (ny - 1)), 0, ny - 1)
        cx = (i - 0.5 * (nx - 1)) * pitch
        cy = (j - 0.5 * (ny - 1)) * pitch
        c = pr['sub_pattern'] // 2
        big = (np.mod(i, pr['sub_pattern']) == c) & (np.mod(j, pr['sub_pattern']) == c)
        r = np.where(big, 0.5 * pr['big_diameter'], 0.5 * pr['small_diameter'])
        sd = r - np.hypot(x - cx, y - cy)
        return np.clip(0.5 + sd / w, 0.0, 1.0)

    # ------------------------------------------------------ feature points
    def feature_points(self) -> dict | None:
        """Calibration features of a board, or None for other objects.

        Returns
        -------
        dict
            ``object_points`` (n, 3) [m] in the object frame (z = 0), ``world_points``
            (n, 3) [m], ``ids`` (n, 2) int grid indices (column, row); circle boards add
            ``big`` (n,) bool and ``diameters`` (n,) [m].
        """
        pr = self.params
        if self.type == 'checkerboard':
            nx, ny = pr['squares']
            s = pr['square_size']
            ii, jj = np.meshgrid(np.arange(1, nx), np.arange(1, ny))
            ids = np.stack([ii.ravel(), jj.ravel()], axis=1)
            pts = np.zeros((len(ids), 3))
            pts[:, 0] = (ids[:, 0] - 0.5 * nx) * s
            pts[:, 1] = (ids[:, 1] - 0.5 * ny) * s
            out = {'ids': ids - 1}
        elif self.type == 'circle_board':
            nx, ny = pr['grid']
            ii, jj = np.meshgrid(np.arange(nx), np.arange(ny))
            ids = np.stack([ii.ravel(), jj.ravel()], axis=1)
            pts = np.zeros((len(ids), 3))
            pts[:, 0] = (ids[:, 0] - 0.5 * (nx - 1)) * pr['pitch']
            pts[:, 1] = (ids[:, 1] - 0.5 * (ny - 1)) * pr['pitch']
            c = pr['sub_pattern'] // 2
            big = (ids[:, 0] % pr['sub_pattern'] == c) & (ids[:, 1] % pr['sub_pattern'] == c)
            out = {'ids': ids, 'big': big,
                   'diameters': np.where(big, pr['big_diameter'], pr['small_diameter'])}
        else:
            return None
        out['object_points'] = pts
        out['world_points'] = pts @ self.W_T_O[:3, :3].T + self.W_T_O[:3, 3]
        return out


@dataclass
class Hits:
    """Closest hits of a bundle of rays (world frame).

    Attributes
    ----------
    t : ndarray, shape (n,)
        Distance along the (unit) ray [m]; inf where nothing is hit.
    obj : ndarray, shape (n,), int
        Index of the object hit, -1 for none.
    normal : ndarray, shape (n, 3)
        Unit surface normal facing the ray's origin.
    points : ndarray, shape (n, 3)
        Hit points [m] (undefined where obj = -1).
    """

    t: np.ndarray
    obj: np.ndarray
    normal: np.ndarray
    points: np.ndarray


def _box_slabs(o, d, box: _Box):
    """Slab test of rays (o, d) (n, 3) with the box: (t_in, t_out), each (n,), and the
    per-axis entry parameters tn (n, 3)."""
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / d
        t1 = (box.lo - o) * inv
        t2 = (box.hi - o) * inv
    tn = np.minimum(t1, t2)
    tf = np.maximum(t1, t2)
    t_in = np.maximum(np.maximum(tn[:, 0], tn[:, 1]), tn[:, 2])
    t_out = np.minimum(np.minimum(tf[:, 0], tf[:, 1]), tf[:, 2])
    return t_in, t_out, tn


def _box_hit(o, d, box: _Box):
    t_in, t_out, tn = _box_slabs(o, d, box)
    hit = (t_in <= t_out) & (t_in > EPS)
    return np.where(hit, t_in, np.inf), tn


def _box_blocks(o, d, box: _Box, t_max):
    """Segments that pass through the box's interior before t_max (a segment that starts
    on the box's surface and goes into it counts; one that leaves it does not)."""
    t_in, t_out, _ = _box_slabs(o, d, box)
    return (t_in <= t_out) & (t_out > EPS) & (t_in < t_max)


def _sphere_blocks(o, d, s: _Sphere, t_max):
    oc = o - s.center
    b = np.einsum('ij,ij->i', oc, d)
    c = np.einsum('ij,ij->i', oc, oc) - s.radius * s.radius
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    return (disc > 0.0) & (-b + root > EPS) & (-b - root < t_max)


def _box_normal(d, tn, t):
    axis = np.argmax(tn, axis=1)
    n = np.zeros_like(d)
    rows = np.arange(len(d))
    n[rows, axis] = -np.sign(d[rows, axis])
    return n


def _sphere_hit(o, d, s: _Sphere):
    oc = o - s.center
    b = np.einsum('ij,ij->i', oc, d)
    c = np.einsum('ij,ij->i', oc, oc) - s.radius * s.radius
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t = -b - root
    return np.where((disc >= 0.0) & (t > EPS), t, np.inf)


def _rect_hit(o, d, r: _Rect):
    with np.errstate(divide='ignore', invalid='ignore'):
        t = -o[:, 2] / d[:, 2]
    x = o[:, 0] + t * d[:, 0]
    y = o[:, 1] + t * d[:, 1]
    hit = (t > EPS) & (np.abs(x) <= r.half[0]) & (np.abs(y) <= r.half[1])
    return np.where(hit, t, np.inf)


@dataclass
class Faces:
    """All planar faces of a scene, world frame (for laser-sheet curves)."""

    center: np.ndarray  # (f, 3)
    e1: np.ndarray      # (f, 3)
    e2: np.ndarray      # (f, 3)
    half: np.ndarray    # (f, 2), may be inf
    normal: np.ndarray  # (f, 3) outward (front for two-sided)
    obj: np.ndarray     # (f,)
    two_sided: np.ndarray  # (f,) bool


class Scene:
    """A set of objects in the world frame (load one with :func:`load_scene`).

    Attributes
    ----------
    name, source : str
    objects : list of SceneObject
    """

    def __init__(self, name: str, source: str, objects: list[SceneObject]):
        self.name = name
        self.source = source
        self.objects = list(objects)
        self._packed = None
        self.faces = self._collect_faces()
        self.albedo_table = np.array([o.albedo for o in self.objects], dtype=np.float64)
        self.textured = np.array([o.type in ('checkerboard', 'circle_board')
                                  for o in self.objects], dtype=np.bool_)
        tex = np.zeros((len(self.objects), 8))
        for k, o in enumerate(self.objects):
            pr = o.params
            if o.type == 'checkerboard':
                tex[k, :5] = (rk.TEX_CHECKER, *pr['squares'], pr['square_size'],
                              pr['dark_albedo'])
            elif o.type == 'circle_board':
                tex[k] = (rk.TEX_CIRCLES, *pr['grid'], pr['pitch'], pr['sub_pattern'],
                          pr['small_diameter'], pr['big_diameter'], pr['circle_albedo'])
        #: Texture table for the compiled tracer: (tex (K, 8), W_R_O (K, 3, 3), W_t_O (K, 3)).
        self.texture_table = (tex, np.ascontiguousarray([o.W_T_O[:3, :3] for o in self.objects]),
                              np.ascontiguousarray([o.W_T_O[:3, 3] for o in self.objects]))
        #: Packed materials (K, materials.PACK_WIDTH); all zeros for Lambertian objects.
        self.material_table = mt.pack([o.material for o in self.objects])
        #: Whether any object throws reflections / scatters under its surface.
        self.specular = bool(np.any(self.material_table[:, 6] > 0))
        self.subsurface = bool(np.any(self.material_table[:, 5] > 0))
        self.spheres = [(k, o.W_T_O[:3, :3] @ p.center + o.W_T_O[:3, 3], p.radius)
                        for k, o in enumerate(self.objects) for p in o.prims
                        if isinstance(p, _Sphere)]

    def __len__(self):
        return len(self.objects)

    def packed(self):
        """Flat primitive arrays for the compiled tracer (see ``raykernels``).

        Returns
        -------
        tuple
            ``(ptype (P,), pobj (P,), R (P, 3, 3), T (P, 3), prm (P, 8))``.
        """
        if self._packed is None:
            types, objs, Rs, Ts, prms = [], [], [], [], []
            for k, o in enumerate(self.objects):
                for p in o.prims:
                    prm = np.zeros(8)
                    prm[6] = float(np.array_equal(o.W_T_O[:3, :3], np.eye(3)))
                    if isinstance(p, _Box):
                        types.append(0)
                        prm[:3], prm[3:6] = p.lo, p.hi
                    elif isinstance(p, _Sphere):
                        types.append(1)
                        prm[:3], prm[3] = p.center, p.radius
                    else:
                        types.append(2)
                        prm[:2] = p.half
                    objs.append(k)
                    Rs.append(o.W_T_O[:3, :3])
                    Ts.append(o.W_T_O[:3, 3])
                    prms.append(prm)
            self._packed = (np.array(types, dtype=np.int64), np.array(objs, dtype=np.int64),
                            np.ascontiguousarray(Rs, dtype=np.float64),
                            np.ascontiguousarray(Ts, dtype=np.float64),
                            np.ascontiguousarray(prms, dtype=np.float64))
        return self._packed

    def object_index(self, name: str) -> int:
        for k, o in enumerate(self.objects):
            if o.name == name:
                return k
        raise KeyError(f'scene {self.name}: no object named {name!r}')

    def _collect_faces(self) -> Faces:
        rows = []
        for k, o in enumerate(self.objects):
            R, t = o.W_T_O[:3, :3], o.W_T_O[:3, 3]
            for p in o.prims:
                if isinstance(p, _Box):
                    c = 0.5 * (p.lo + p.hi)
                    h = 0.5 * (p.hi - p.lo)
                    for ax in range(3):
                        a1, a2 = (ax + 1) % 3, (ax + 2) % 3
                        for sgn in (-1.0, 1.0):
                            fc = c.copy()
                            fc[ax] += sgn * h[ax]
                            n = np.zeros(3)
                            n[ax] = sgn
                            rows.append((R @ fc + t, R[:, a1], R[:, a2], (h[a1], h[a2]),
                                         R @ n, k, False))
                elif isinstance(p, _Rect):
                    rows.append((t.copy(), R[:, 0], R[:, 1], tuple(p.half), -R[:, 2], k,
                                 True))
        if not rows:
            z = np.zeros((0, 3))
            return Faces(z, z, z, np.zeros((0, 2)), z, np.zeros(0, np.int64),
                         np.zeros(0, np.bool_))
        cols = list(zip(*rows, strict=True))
        return Faces(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]),
                     np.array(cols[3], dtype=np.float64), np.array(cols[4]),
                     np.array(cols[5], dtype=np.int64), np.array(cols[6], dtype=np.bool_))

    # ------------------------------------------------------------ tracing
    def intersect(self, origins, directions) -> Hits:
        """Closest intersection of each ray with the scene.

        Parameters
        ----------
        origins : ndarray, shape (n, 3), metres, world frame
        directions : ndarray, shape (n, 3)
            Unit directions.
        """
        o, d = as_rays(origins, directions)
        n = len(o)
        best = np.full(n, np.inf)
        obj = np.full(n, -1, dtype=int)
        normal = np.zeros((n, 3))
        for k, ob in enumerate(self.objects):
            R, tr = ob.W_T_O[:3, :3], ob.W_T_O[:3, 3]
            ol = (o - tr) @ R
            dl = d @ R
            for p in ob.prims:
                if isinstance(p, _Box):
                    t, tn = _box_hit(ol, dl, p)
                    closer = t < best
                    if np.any(closer):
                        nl = _box_normal(dl[closer], tn[closer], t[closer])
                elif isinstance(p, _Sphere):
                    t = _sphere_hit(ol, dl, p)
                    closer = t < best
                    if np.any(closer):
                        nl = (ol[closer] + t[closer, None] * dl[closer] - p.center) / p.radius
                else:
                    t = _rect_hit(ol, dl, p)
                    closer = t < best
                    if np.any(closer):
                        nl = np.zeros((int(closer.sum()), 3))
                        nl[:, 2] = -np.sign(dl[closer, 2])
                if np.any(closer):
                    best[closer] = t[closer]
                    obj[closer] = k
                    normal[closer] = nl @ R.T
        pts = o + np.where(np.isfinite(best), best, 0.0)[:, None] * d
        return Hits(best, obj, normal, pts)

    def occluded(self, origins, directions, t_max) -> np.ndarray:
        """Whether a surface or a solid's interior lies on ``origin + t dir``, 0 < t < t_max.

        Surfaces touching the origin (within EPS) do not count unless the segment enters
        the solid behind them, so a point on an object's face is not blocked by that face
        but a point on a wall is blocked by a block resting on the wall.

        Parameters
        ----------
        origins : ndarray, shape (n, 3), metres
        directions : ndarray, shape (n, 3)
            Unit directions.
        t_max : ndarray, shape (n,), metres

        Returns
        -------
        ndarray, shape (n,), bool
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        tm = np.asarray(t_max, dtype=np.float64) - EPS
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape or tm.shape != (len(o),):
            raise ValueError('origins, directions, t_max: expected shapes (n, 3), (n, 3), (n,)')
        blocked = np.zeros(len(o), dtype=bool)
        for ob in self.objects:
            R, tr = ob.W_T_O[:3, :3], ob.W_T_O[:3, 3]
            ol = (o - tr) @ R
            dl = d @ R
            for p in ob.prims:
                if isinstance(p, _Box):
                    blocked |= _box_blocks(ol, dl, p, tm)
                elif isinstance(p, _Sphere):
                    blocked |= _sphere_blocks(ol, dl, p, tm)
                else:
                    blocked |= _rect_hit(ol, dl, p) < tm
        return blocked

    def inside_solid(self, points, tol: float = 1e-9) -> np.ndarray:
        """Whether points lie strictly inside a box or sphere (by more than ``tol`` [m]).

        Parameters
        ----------
        points : ndarray, shape (n, 3), metres, world frame
        """
        P = np.asarray(points, dtype=np.float64)
        inside = np.zeros(len(P), dtype=bool)
        for ob in self.objects:
            pl = (P - ob.W_T_O[:3, 3]) @ ob.W_T_O[:3, :3]
            for p in ob.prims:
                if isinstance(p, _Box):
                    inside |= np.all((pl > p.lo + tol) & (pl < p.hi - tol), axis=1)
                elif isinstance(p, _Sphere):
                    inside |= np.linalg.norm(pl - p.center, axis=1) < p.radius - tol
        return inside

    def albedo(self, points, obj, footprint) -> np.ndarray:
        """Albedo at world points on the objects ``obj`` (-1: 0).

        Parameters
        ----------
        points : ndarray, shape (n, 3), metres
        obj : ndarray, shape (n,), int
        footprint : ndarray, shape (n,), metres
            Size of one pixel on the surface, for anti-aliased textures.
        """
        obj = np.asarray(obj)
        out = np.where(obj >= 0, self.albedo_table[np.maximum(obj, 0)], 0.0)
        for k in np.flatnonzero(self.textured):
            m = obj == k
            if not np.any(m):
                continue
            ob = self.objects[k]
            pl = (points[m] - ob.W_T_O[:3, 3]) @ ob.W_T_O[:3, :3]
            out[m] = ob.albedo_local(pl, footprint[m])
        return out

    # ----------------------------------------------- laser-sheet curves
    def sheet_segments(self, plane, half_spaces, viewer, source, max_length: float = 100.0):
        """Intersections of a plane with every planar face, clipped to half-spaces.

        Parameters
        ----------
        plane : ndarray, shape (4,)
            Unit-normal plane (world).
        half_spaces : ndarray, shape (k, 2, 3)
            Each ``(q, w)`` keeps points with ``(x - q) . w >= 0``.
        viewer, source : ndarray, shape (3,)
            Faces whose front side faces away from the viewer (camera centre) or the light
            source are skipped (two-sided faces: when the two are on different sides).

        Returns
        -------
        tuple
            ``(A, B, normal, obj, two_sided)``: segment ends (m, 3), outward face normal
            (m, 3), object index (m,), two-sidedness (m,).
        """
        F = self.faces
        n = len(F.obj)
        A = np.empty((n, 3))
        B = np.empty((n, 3))
        N = np.empty((n, 3))
        obj = np.empty(n, np.int64)
        two = np.empty(n, np.bool_)
        hs = np.ascontiguousarray(half_spaces, dtype=np.float64).reshape(-1, 2, 3)
        m = rk.sheet_segments(F.center, F.e1, F.e2, F.half, F.normal, F.obj, F.two_sided,
                              np.asarray(plane, np.float64), hs,
                              np.asarray(viewer, np.float64), np.asarray(source, np.float64),
                              float(max_length), A, B, N, obj, two)
        return A[:m], B[:m], N[:m], obj[:m], two[:m]

    def sheet_circles(self, plane):
        """Circles where a plane cuts the spheres.

        Returns
        -------
        list of tuple
            ``(obj, centre (3,), radius, e1 (3,), e2 (3,), sphere_centre (3,), r)``.
        """
        N, e = plane[:3], plane[3]
        out = []
        for k, c, r in self.spheres:
            dist = float(N @ c + e)
            if abs(dist) >= r:
                continue
            cc = c - dist * N
            rho = math.sqrt(r * r - dist * dist)
            a = np.array([1.0, 0.0, 0.0]) if abs(N[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            e1 = np.cross(N, a)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(N, e1)
            out.append((k, cc, rho, e1, e2, c, r))
        return out


# ====================================================================== loading

def _pose(sec: Section) -> np.ndarray:
    return read_pose(sec.section('pose'), 50.0, default=[0, 0, 0])


_MM = MM_HINT


def _object(sec: Section, index: int, names: set) -> SceneObject:
    typ = sec.string('type', OBJECT_TYPES)
    name = sec.string('name', default=f'{typ}_{index}')
    if name in names:
        raise sec.error('name', 'a name unique within the scene', name)
    names.add(name)
    W_T_O = _pose(sec)
    mat = None
    if sec.has('material'):
        mat = mt.MATERIALS.get(sec.string('material', mt.MATERIAL_NAMES))
    albedo = sec.number('albedo', 0.0, 1.0, '(reflectance)',
                        **({'default': mat.albedo} if mat is not None else {}))
    params: dict = {}
    prims: list = []
    if typ == 'plane':
        if sec.has('size'):
            size = sec.vector('size', 2, 1e-4, 1000.0, 'm', hint=_MM)
        else:
            size = np.array([np.inf, np.inf])
        params['size'] = size
        prims.append(_Rect(0.5 * size))
    elif typ == 'box':
        size = sec.vector('size', 3, 1e-4, 100.0, 'm', hint=_MM)
        params['size'] = size
        prims.append(_Box(-0.5 * size, 0.5 * size))
    elif typ == 'stair_block':
        size = sec.vector('size', 3, 1e-4, 10.0, 'm', hint=_MM)
        step = sec.number('step_height', 1e-4, 10.0, 'm', hint=_MM)
        params.update(size=size, step_height=step)
        sx, sy, sz = size
        prims.append(_Box(np.array([-sx / 2, -sy / 2, -sz]), np.array([sx / 2, sy / 2, 0.0])))
        prims.append(_Box(np.array([0.0, -sy / 2, -sz - step]),
                          np.array([sx / 2, sy / 2, 0.0])))
    elif typ == 'sphere':
        radius = sec.number('radius', 1e-4, 10.0, 'm', hint=_MM)
        params['radius'] = radius
        prims.append(_Sphere(np.zeros(3), radius))
    else:  # boards and plates
        size = sec.vector('size', 2, 1e-3, 10.0, 'm', hint=_MM)
        thickness = sec.number('thickness', 1e-4, 1.0, 'm', hint=_MM)
        params.update(size=size, thickness=thickness)
        prims.append(_Box(np.array([-size[0] / 2, -size[1] / 2, 0.0]),
                          np.array([size[0] / 2, size[1] / 2, thickness])))
        if typ == 'checkerboard':
            sq = sec.raw('squares', 'a list of 2 integers [nx, ny] >= 2')
            if (not isinstance(sq, list) or len(sq) != 2
                    or not all(isinstance(v, int) and 2 <= v <= 1000 for v in sq)):
                raise sec.error('squares', 'a list of 2 integers [nx, ny] >= 2', sq)
            params['squares'] = (sq[0], sq[1])
            params['square_size'] = sec.number('square_size', 1e-4, 1.0, 'm', hint=_MM)
            params['dark_albedo'] = sec.number('dark_albedo', 0.0, 1.0, '(reflectance)')
            if sq[0] * params['square_size'] > size[0] + 1e-9 or \
                    sq[1] * params['square_size'] > size[1] + 1e-9:
                raise sec.error('squares', 'a pattern that fits on the board (size)', sq)
        elif typ == 'circle_board':
            grid = sec.raw('grid', 'a list of 2 integers', [35, 35])
            if (not isinstance(grid, list) or len(grid) != 2
                    or not all(isinstance(v, int) and 1 <= v <= 1000 for v in grid)):
                raise sec.error('grid', 'a list of 2 integers [nx, ny]', grid)
            params['grid'] = (grid[0], grid[1])
            params['pitch'] = sec.number('pitch', 1e-4, 1.0, 'm', default=0.02, hint=_MM)
            params['sub_pattern'] = sec.integer('sub_pattern', 1, 1000, default=7)
            params['small_diameter'] = sec.number('small_diameter', 1e-4, 1.0, 'm',
                                                  default=0.010, hint=_MM)
            params['big_diameter'] = sec.number('big_diameter', 1e-4, 1.0, 'm',
                                                default=0.015, hint=_MM)
            params['circle_albedo'] = sec.number('circle_albedo', 0.0, 1.0, '(reflectance)')
            if params['big_diameter'] >= params['pitch']:
                raise sec.error('big_diameter', 'a diameter smaller than the pitch',
                                params['big_diameter'])
    sec.finish()
    return SceneObject(typ, name, W_T_O, albedo, params, prims, mat)


def scene_from_dict(data: dict, source: str) -> Scene:
    """Build a :class:`Scene` from a parsed scene file (see ``scenes/stair_block.yaml``).

    Raises
    ------
    ConfigError
        Naming ``source``, the key and what was expected.
    """
    top, name = SCENE_FILES.open(data, source)
    items = top.raw('objects', 'a list of objects')
    if not isinstance(items, list) or not items:
        raise top.error('objects', 'a non-empty list of objects', items)
    top.finish()
    objects, names = [], set()
    for k, item in enumerate(items):
        sec = Section(item, source, f'objects[{k}]')
        objects.append(_object(sec, k, names))
    return Scene(name, source, objects)


def load_scene(name_or_path) -> Scene:
    """Load a scene file.

    Parameters
    ----------
    name_or_path : str or Path
        A shipped scene name (see :func:`shipped_scenes`) or a path to a YAML file.
    """
    return scene_from_dict(*SCENE_FILES.read(name_or_path))


def load_scene_text(text: str, source: str = '<scene yaml>') -> Scene:
    """Load a scene from YAML text (e.g. the SetScene service's ``scene_yaml``)."""
    return scene_from_dict(*SCENE_FILES.read_text(text, source))


def shipped_scenes() -> list[str]:
    """Names of the scene files shipped with the package."""
    return SCENE_FILES.shipped()


__all__ = ['ConfigError', 'Hits', 'OBJECT_TYPES', 'Scene', 'SceneObject', 'load_scene',
           'load_scene_text', 'scene_from_dict', 'shipped_scenes']
