"""Scenes of the evaluation (the paper's test objects), as simulator scene YAML (no rclpy).

The world frame W of these scenes is the rig's nominal V0 (x right, y down, z away from
the scanner). Each function returns the YAML text and what the evaluation needs to know
about the object (its pose ``W_T_O`` and dimensions): the experimenter's knowledge of
where they put it.

Objects are placed around the evaluated rig's working point (:class:`Site`), where its
laser sheet crosses its optical axis, not at a fixed depth: the same evaluation runs on a
rig set up for 100 mm or for 1000 mm. The sizes of the plate and the sphere scale with the
working point's depth (the field of view at a given lens grows in proportion to depth);
lateral placements too, but never further out, relative to the rig's own G1 reach at that
depth, than on the reference rig. The paper's values are those at :data:`REFERENCE_DEPTH`.
The stair block is the paper's standard component and keeps its size at every distance
(its 30 mm step is what is measured).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

STAIR_SIZE = (0.12, 0.10, 0.02)   # footprint x, y and base height [m]
STAIR_STEP = 0.03                 # the paper's 30 mm step [m]
#: Rotation vector [rad] that shows the riser to a laser below the camera (the block's step
#: runs along x, across a stripe along the image rows); :func:`stair` turns the block with
#: the rig's stripe layout for a laser elsewhere.
STAIR_TILT = (0.12, -0.35, 0.0)
SPHERE_RADIUS = 0.0254            # 2 inch calibration sphere [m]
PLATE_SIZE = 0.74                 # [m]
#: Plate raster (:func:`plate_raster`): neighbouring views of a row overlap by this
#: fraction of a view's width.
PLATE_VIEW_OVERLAP = 0.1
#: Plate coverage (:func:`plate_coverage`) is counted in this many cells per side of
#: the plate: 20 mm cells on the paper's 740 mm plate (its calibration board's pitch).
PLATE_CELLS = 37
REFERENCE_DEPTH = 0.65            # depth along V0 of the paper's scenes [m]
STAIR_GRID_HALF = (0.38, 0.33)    # stair positions over +-x, +-y at the reference depth [m]
#: G1's reach on the reference rig at the reference depth, x and y [m]: where the view axis
#: meets the plane 650 mm deep at +-VOLTAGE_LIMIT, rounded down to 1 mm (pinned by a
#: test). Lateral placements are never further out, relative to a rig's own reach, than
#: on the reference rig.
REFERENCE_REACH = (0.476, 0.455)
#: How far the stair block's outermost aim can lie beyond its position [m]: the +-30 mm
#: face aims plus up to 17 mm from the block's tilt (its faces 20 and 50 mm up).
STAIR_AIM_EXTENT = 0.05
PLATE_POSES = ((0.08, 0.12, 0.0), (-0.10, 0.05, 0.0), (0.03, -0.15, 0.10))  # rotvecs [rad]


@dataclass(frozen=True)
class Site:
    """Where an evaluation puts its objects: around a rig's working point.

    Attributes
    ----------
    centre_W : ndarray, shape (3,), metres
        The working point in W (the sheet at U2 = 0 crossing the optical axis at U1 = 0).
    scale : float
        Object size factor: the working point's depth over :data:`REFERENCE_DEPTH`, rounded
        to 0.01 (objects come in sizes; 1 for a rig set up as the paper's).
    lateral : tuple of float
        Placement factors along x and y: ``scale``, or less where G1's reach at the working
        depth is smaller than ``scale`` times :data:`REFERENCE_REACH` (rounded to 0.01).
    reach : tuple of float
        G1's reach at the working depth along x and y [m] (:func:`g1_reach`).
    exit_m : float
        Distance from W's origin to the G1 exit mirror along the axis [m]: a stand-off D
        (working distance, as :func:`galvoscan_sim.rig_family.working_distance` defines it)
        lies ``exit_m + D`` from W's origin.
    """

    centre_W: np.ndarray
    scale: float
    lateral: tuple
    reach: tuple
    exit_m: float

    @property
    def depth(self) -> float:
        """Depth of the working point along W's z [m]."""
        return float(self.centre_W[2])

    def offset(self, shift) -> np.ndarray:
        """The working point moved by ``shift`` (3,) [m], a shift at the reference depth on
        the reference rig: x and y times ``lateral``, z times ``scale``."""
        f = np.array([self.lateral[0], self.lateral[1], self.scale])
        return self.centre_W + f * np.asarray(shift, dtype=np.float64)

    def at_standoff(self, distance: float) -> np.ndarray:
        """The point on the line from W's origin through the working point at stand-off
        ``distance`` [m] from the G1 exit mirror, shape (3,) [m]."""
        u = self.centre_W / np.linalg.norm(self.centre_W)
        return u * (self.exit_m + float(distance))

    def stair_grid(self, n_x: int, n_y: int, spread: float = 1.0) -> list:
        """n_x x n_y stair positions (3,) [m] over the range at the working point's depth,
        row by row (x fastest).

        The grid spans ``spread`` times :data:`STAIR_GRID_HALF` times ``lateral``, narrowed
        where the block's outermost aim (:data:`STAIR_AIM_EXTENT` beyond a position; the
        block keeps its size) would lie further out in G1's reach than on the reference rig.
        """
        half = []
        for i in (0, 1):
            ref = (STAIR_GRID_HALF[i] + STAIR_AIM_EXTENT) / REFERENCE_REACH[i]
            h = min(STAIR_GRID_HALF[i] * self.lateral[i],
                    ref * self.reach[i] - STAIR_AIM_EXTENT)
            half.append(spread * max(h, 0.0))
        xs = np.linspace(-half[0], half[0], n_x) if n_x > 1 else [0.0]
        ys = np.linspace(-half[1], half[1], n_y) if n_y > 1 else [0.0]
        return [self.centre_W + np.array([x, y, 0.0]) for y in ys for x in xs]


def g1_reach(rig, depth: float) -> np.ndarray:
    """How far G1 can turn the view at ``depth`` [m]: where the view axis meets the plane
    z = depth (V0) at +-VOLTAGE_LIMIT on each G1 axis, the nearer side, shape (2,) [m]
    (x, y). ``rig`` is a ``galvoscan_sim.Rig`` (its physics, not the model)."""
    from galvoscan_common.frame import VOLTAGE_LIMIT

    out = []
    for axis in (0, 1):
        side = []
        for sign in (-1.0, 1.0):
            u = np.zeros(4)
            u[axis] = sign * VOLTAGE_LIMIT
            th = rig.mirror_angles(rig.applied_voltages(u))
            T = rig.V0_T_V(th[0], th[1])
            ray, o = T[:3, 2], T[:3, 3]
            side.append(abs((o + (depth - o[2]) / ray[2] * ray)[axis]))
        out.append(min(side))
    return np.array(out)


def site_of(rig) -> Site:
    """The :class:`Site` of a rig (a ``galvoscan_sim.Rig`` or a rig description dict).

    Raises
    ------
    ValueError
        The rig's laser sheet does not cross its optical axis in front of the scanner.
    """
    from galvoscan_sim import Rig, rig_from_dict
    from galvoscan_sim.rig_family import working_distance, working_point

    if not isinstance(rig, Rig):
        rig = rig_from_dict(rig, '<rig description>')
    c = np.asarray(working_point(rig), dtype=np.float64)
    depth = float(np.linalg.norm(c))
    if not np.all(np.isfinite(c)) or c[2] <= 0:
        raise ValueError(f'rig: no working point in front of the scanner ({c})')
    scale = max(round(depth / REFERENCE_DEPTH, 2), 0.01)
    reach = g1_reach(rig, float(c[2]))
    lateral = tuple(max(round(min(scale, float(r)), 2), 0.01)
                    for r in reach / np.asarray(REFERENCE_REACH))
    return Site(c, scale, lateral, tuple(float(r) for r in reach),
                depth - float(working_distance(rig)))


#: The site of the paper's rig (working point on W's z axis at 650 mm, stand-off unknown).
PAPER_SITE = Site(np.array([0.0, 0.0, REFERENCE_DEPTH]), 1.0, (1.0, 1.0), REFERENCE_REACH,
                  0.0)


def _pose(R: Rotation, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    T[:3, 3] = t
    return T


def _fmt(v) -> str:
    return '[' + ', '.join(f'{float(x):.9g}' for x in v) + ']'


def facing(position, tilt=(0.0, 0.0, 0.0)) -> Rotation:
    """Rotation turning an object's -z axis toward the scanner (W origin), then ``tilt``."""
    d = -np.asarray(position, dtype=np.float64)
    d /= np.linalg.norm(d)
    R_face, _ = Rotation.align_vectors([d], [[0.0, 0.0, -1.0]])
    return R_face * Rotation.from_rotvec(tilt)


def _surface(material: str | None, albedo: float) -> str:
    """The scene-file lines of an object's surface: a named material (its own diffuse
    reflectance) or the Lambertian ``albedo``."""
    if material is None:
        return f'    albedo: {albedo}\n'
    return f'    material: {material}\n'


def stair(position, material: str | None = None, layout=None) -> tuple[str, dict]:
    """The 30 mm stair block with its upper face near ``position`` [m], facing the scanner.

    ``material``: a name of ``galvoscan_sim.materials.MATERIALS`` (default: Lambertian,
    albedo 0.6). ``layout``: the rig's stripe layout
    (``galvoscan_common.stripe_layout.StripeLayout``, e.g.
    ``reconstructor.planning.stripe_layout`` of its calibration; None: the paper's, the
    laser below the camera). The block is set up for a laser below (its step across the
    stripe, :data:`STAIR_TILT` showing the riser to the laser) and turned about the
    optical axis by ``layout.turn``: the stripe crosses the riser, and the riser faces the
    laser, wherever it sits. Returns the scene text and ``{'W_T_O', 'size',
    'step_height', 'aim_W'}``; ``aim_W`` is the middle of the riser, where the view should
    be centred.
    """
    p = np.asarray(position, dtype=np.float64)
    turn = Rotation.from_rotvec([0.0, 0.0, 0.0 if layout is None else float(layout.turn)])
    R = turn * facing(turn.inv().apply(p), STAIR_TILT)
    depth = STAIR_SIZE[2] + STAIR_STEP
    t = p + p / np.linalg.norm(p) * depth  # resting face behind the upper face
    W_T_O = _pose(R, t)
    aim = W_T_O[:3, :3] @ np.array([0.0, 0.0, -STAIR_SIZE[2] - STAIR_STEP / 2]) + t
    text = f"""format_version: 1
name: eval_stair
description: 30 mm stair block at {_fmt(p)} m
objects:
  - type: stair_block
    name: stair
    pose: {{translation: {_fmt(t)}, rotation_vector: {_fmt(R.as_rotvec())}}}
    size: {_fmt(STAIR_SIZE)}
    step_height: {STAIR_STEP}
{_surface(material, 0.6)}"""
    return text, {'W_T_O': W_T_O, 'size': STAIR_SIZE, 'step_height': STAIR_STEP, 'aim_W': aim}


def plate(index: int, site: Site = PAPER_SITE, *, grow: bool = False,
          material: str | None = None) -> tuple[str, dict]:
    """The flat plate centred at ``site``'s working point, in pose ``index`` of PLATE_POSES.

    By default it is the paper's 740 x 740 mm plate, a physical artefact like the stair
    block: it keeps its size at a longer working distance and shrinks with ``site.scale``
    only where the range is smaller (short range). With ``grow`` it is scaled with the
    working depth either way, so that it spans the same viewing angles as the paper's
    plate at 650 mm: a harder test at long range, where the model's angular errors grow in
    millimetres with the distance.

    Returns the scene text and ``{'W_T_O', 'size'}``: the plate's pose (4, 4) and its size
    (2,) [m]. The evaluation scans it edge to edge (:func:`plate_raster`).
    """
    R = Rotation.from_rotvec(PLATE_POSES[index % len(PLATE_POSES)])
    t = np.asarray(site.centre_W, dtype=np.float64)
    factor = site.scale if grow else min(1.0, site.scale)
    size = PLATE_SIZE * factor
    text = f"""format_version: 1
name: eval_plate_{index}
description: {size * 1e3:.0f} x {size * 1e3:.0f} mm flat plate, pose {index}
objects:
  - type: flat_plate
    name: plate
    pose: {{translation: {_fmt(t)}, rotation_vector: {_fmt(R.as_rotvec())}}}
    size: [{size:.9g}, {size:.9g}]
    thickness: 0.02
{_surface(material, 0.5)}"""
    return text, {'W_T_O': _pose(R, t), 'size': (size, size)}


def plate_raster(size: float, view, frames: int, max_spacing: float = 0.018,
                 skip: int = 1, across: int = 1) -> tuple[np.ndarray, np.ndarray, float]:
    """G1 views and stripe lines that scan a square plate edge to edge, row by row.

    The stripe lines (one frame each) are evenly spaced over the plate, at most
    ``max_spacing`` apart, the outermost half a spacing from the edges; ``frames``
    consecutive lines make one row of views, each view centred on its lines. The views of
    a row overlap by :data:`PLATE_VIEW_OVERLAP` of their width and the outermost ones reach
    past the plate's edges. Rows alternate in direction (a serpentine: G1 never jumps back
    across the plate between rows).

    Parameters
    ----------
    size : float
        The plate's side [m].
    view : (float, float)
        One view's width and height on the plate [m] (image size over focal length times
        the distance).
    frames : int
        Stripe lines (frames) per view, at least 1; fewer where they do not fit in 90 % of
        its height (a short-range view): ``lines`` says how many.
    max_spacing : float
        Largest line spacing [m]: below :data:`PLATE_CELLS`' cell size, every cell of the
        plate is crossed by a line.
    skip : int
        Keep every ``skip``-th row and column (centred): a decimated raster that no longer
        covers the whole plate (``--quick``).
    across : int
        The plate axis the stripe lines are spaced along: 1 (y: the lines run along x, a
        stripe along the image rows) or 0 (x: a stripe along the columns, the raster
        transposed; ``reconstructor.planning.stripe_layout``).

    Returns
    -------
    centres : ndarray, shape (n, 2)
        View centres (x, y) [m] in the plate's frame, in scan order.
    lines : ndarray, shape (n, frames)
        The plate y (x with ``across`` 0) [m] of each view's stripe lines.
    spacing : float
        Line spacing [m].

    Raises
    ------
    ValueError
        Bad arguments.
    """
    w, h = (float(v) for v in view)
    if frames < 1 or skip < 1 or not (w > 0 and h > 0 and size > 0 and max_spacing > 0) \
            or across not in (0, 1):
        raise ValueError(f'plate_raster: frames {frames}, skip {skip}, view {view}, '
                         f'size {size}, max_spacing {max_spacing}, across {across}')
    if across == 0:
        w, h = h, w
    while True:  # fewer lines a view where a short-range view cannot hold them all
        n_rows = max(1, math.ceil(size / (frames * max_spacing) - 1e-9))
        spacing = size / (n_rows * frames)
        if frames == 1 or (frames - 1) * spacing <= 0.9 * h:
            break
        frames -= 1
    col_step = (1.0 - PLATE_VIEW_OVERLAP) * w
    n_cols = max(1, math.ceil(max(size - w, 0.0) / col_step - 1e-9) + 1)

    def kept(n):
        idx = np.arange(0, n, skip)
        return idx + (n - 1 - idx[-1]) // 2

    rows = kept(n_rows)
    xs = (kept(n_cols) - (n_cols - 1) / 2.0) * col_step
    centres, lines = [], []
    for j, r in enumerate(rows):
        ys = -size / 2.0 + (r * frames + np.arange(frames) + 0.5) * spacing
        for x in xs if j % 2 == 0 else xs[::-1]:
            centres.append((x, float(ys.mean())))
            lines.append(ys)
    centres = np.array(centres, dtype=np.float64).reshape(-1, 2)
    if across == 0:
        centres = centres[:, ::-1].copy()
    return centres, np.array(lines, dtype=np.float64), float(spacing)


def plate_coverage(points_O, size: float, cells: int = PLATE_CELLS) -> float:
    """Fraction of a square plate's ``cells`` x ``cells`` cells that hold at least one of
    ``points_O`` (n, 2 or 3) [m], given in the plate's frame (centred, x and y along its
    sides)."""
    p = np.asarray(points_O, dtype=np.float64)
    if p.size == 0:
        return 0.0
    ij = np.floor((p[:, :2] + size / 2.0) / (size / cells)).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < cells), axis=1)
    return float(np.unique(ij[ok, 0] * cells + ij[ok, 1]).size) / cells ** 2


#: The V-groove (:func:`v_groove`): an inside corner of two faces, each this wide [m]
#: across the groove and ``GROOVE_LENGTH`` along it, meeting at ``GROOVE_ANGLE`` [rad].
GROOVE_FACE = 0.04
GROOVE_LENGTH = 0.08
GROOVE_ANGLE = math.pi / 2
GROOVE_THICKNESS = 0.01


def v_groove(position, material: str | None = 'machined_aluminium',
             wall_distance: float = 0.05, layout=None) -> tuple[str, dict]:
    """An inside corner: two faces meeting along a line through ``position`` [m] (the
    groove's bottom, its axis across the stripe), opening towards the scanner, and a matt
    wall ``wall_distance`` [m] behind. A specular material throws the stripe from each face
    onto the other.

    ``layout``: the rig's stripe layout, as for :func:`stair` (None: a laser below, the
    axis along W's y); the groove is turned about the optical axis by ``layout.turn``, so
    that the stripe crosses both faces.

    Returns the scene text and ``{'faces': [(n (3,), point (3,))] * 2, 'axis_W'}``: the
    faces' planes (outward unit normal and a point) in W and the groove's bottom point.
    """
    p = np.asarray(position, dtype=np.float64)
    turn = Rotation.from_rotvec([0.0, 0.0, 0.0 if layout is None else float(layout.turn)])
    half = GROOVE_ANGLE / 2.0
    faces, objects = [], []
    for sign, name in ((-1.0, 'left'), (1.0, 'right')):
        # the face runs from the axis out to x = sign * ..., towards the scanner (-z), for
        # a laser below; turned to the laser's side
        out = turn.apply([sign * math.sin(half), 0.0, -math.cos(half)])   # along the face
        n = turn.apply([-sign * math.cos(half), 0.0, -math.sin(half)])    # outward normal
        R = Rotation.align_vectors([n, out], [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])[0]
        centre = p + out * GROOVE_FACE / 2 - n * GROOVE_THICKNESS / 2
        faces.append((n, p.copy()))
        objects.append(f"""  - type: box
    name: {name}_face
    pose: {{translation: {_fmt(centre)}, rotation_vector: {_fmt(R.as_rotvec())}}}
    size: [{GROOVE_FACE:.9g}, {GROOVE_LENGTH:.9g}, {GROOVE_THICKNESS:.9g}]
{_surface(material, 0.6)}""")
    text = f"""format_version: 1
name: eval_v_groove
description: inside corner ({math.degrees(GROOVE_ANGLE):.0f} deg) at {_fmt(p)} m
objects:
{''.join(objects)}  - type: plane
    name: wall
    pose: {{translation: [0, 0, {p[2] + wall_distance:.9g}], rotation_vector: [0, 0, 0]}}
    size: [2.0, 2.0]
    albedo: 0.35
"""
    return text, {'faces': faces, 'axis_W': p}


def sphere(position, radius: float = SPHERE_RADIUS) -> tuple[str, dict]:
    """The calibration sphere of ``radius`` [m] with its front at ``position`` (3,) [m]."""
    p = np.asarray(position, dtype=np.float64)
    centre = p + p / np.linalg.norm(p) * radius
    text = f"""format_version: 1
name: eval_sphere
description: {2e3 * radius:.1f} mm calibration sphere
objects:
  - type: sphere
    name: sphere
    pose: {{translation: {_fmt(centre)}, rotation_vector: [0, 0, 0]}}
    radius: {radius:.9g}
    albedo: 0.75
"""
    return text, {'centre_W': centre, 'radius': radius, 'aim_W': p}


def sphere_radius(site: Site) -> float:
    """The evaluation sphere's radius at ``site`` [m]: the 2 inch sphere, smaller at short
    range in proportion to the field of view (never larger: it must fit the views)."""
    return SPHERE_RADIUS * min(1.0, site.scale)


def wall(distance: float = 0.65) -> tuple[str, dict]:
    """A 3 x 3 m matt wall facing the scanner at ``distance`` [m] (range measurement)."""
    text = f"""format_version: 1
name: eval_wall
description: wall at {distance} m
objects:
  - type: plane
    name: wall
    pose: {{translation: [0, 0, {distance}], rotation_vector: [0, 0, 0]}}
    size: [3.0, 3.0]
    albedo: 0.5
"""
    return text, {'distance': distance}


#: Where the evaluation's "robot" puts the sphere for the cell extrinsic, in the rig's
#: nominal V0 [m], for a rig set up as the paper's (working point at 650 mm): over the
#: range there, not on one line or plane. Other rigs: offsets from the working point
#: scaled by the site's scale.
CELL_POSITIONS = ((0.0, 0.0, 0.65), (0.25, 0.15, 0.6), (-0.25, 0.15, 0.7),
                  (0.22, -0.15, 0.72), (-0.22, -0.16, 0.58), (0.04, 0.18, 0.66))


def cell_positions(nominal_W_T_V0, site: Site = PAPER_SITE) -> np.ndarray:
    """The robot's sphere positions (n, 3) [m] in W around ``site``'s working point."""
    T = np.asarray(nominal_W_T_V0, dtype=np.float64)
    offsets = np.asarray(CELL_POSITIONS) - np.array([0.0, 0.0, REFERENCE_DEPTH])
    f = np.array([site.lateral[0], site.lateral[1], site.scale])
    return site.centre_W + (f * offsets) @ T[:3, :3].T


def cell_reference(nominal_W_T_V0, site: Site = PAPER_SITE,
                   cell_frame: str = 'world') -> tuple[str, np.ndarray]:
    """The cell stage's reference file text, with W as the cell frame.

    The robot is programmed with the scanner's designed mounting ``nominal_W_T_V0``
    (4, 4): it reports the positions it moved the sphere to (:func:`cell_positions`), in
    W, and the file carries the designed mounting as ``nominal_cell_T_v0`` (to aim G1).
    Returns the text and the positions (n, 3) [m] in W.
    """
    T = np.asarray(nominal_W_T_V0, dtype=np.float64)
    p = cell_positions(T, site)
    lines = [f'cell_frame: {cell_frame}', 'unit: m', 'positions:']
    lines += [f'  {k}: {_fmt(q)}' for k, q in enumerate(p)]
    lines += ['nominal_cell_T_v0:'] + [f'  - {_fmt(row)}' for row in T]
    return '\n'.join(lines) + '\n', p
