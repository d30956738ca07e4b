"""Capture plans: what to place in front of the rig and which voltages to scan, per stage.

A plan is a list of :class:`CaptureStep`. Each step optionally replaces the scene (in the
simulator through ``sim/set_scene``; on real hardware the operator places the object the
step's note describes), then runs one custom scan of the step's voltages with the laser on
or off. A laser-off frame of a board and the laser-on frames of the same board placement
are two steps, the second with ``scene_yaml=None``.

Plans use only ``calibration.model``, the operator's current approximate model (the rig's
design values at first, then what earlier stages calibrated), to place the targets and aim
G1 at them; never the simulator's true parameters. The scene frame W of every scene is
taken to be the model's V0, as an operator measuring from the scanner would.

Plans adapt to the rig (any rig of the family, not one):

- the working depth is where the model's U2 = 0 laser sheet crosses the V0 optical axis
  (:func:`laser_crossing_depth`), and every placement is made relative to it and to the
  model's field of view there (the reference rig's figures below are for 650 mm and a
  60 x 45 mm view);
- the targets come from an operator's kit of standard sizes (:data:`CHECKERBOARD_SQUARES`,
  :data:`CIRCLE_GRID_PITCHES`, :data:`CIRCLE_BOARD_PITCHES`, :data:`SPHERE_RADII`): the
  largest that suits the view (:func:`choose_targets`, the one rule that both the plans and
  the solvers use, through :mod:`calibration_tools.registry`);
- every placement is checked before it becomes a step (:func:`check_view`: within G1
  reach, projected inside the image with a margin, in the focus range
  :data:`FOCUS_RANGE`, facing the camera and the laser, no other board of its scene
  between it and the camera or the laser); one that fails is replaced by the next
  candidate of a short search (other tilt, nearer the crossing, nearer the axis, a
  smaller G2 span) or dropped, and every replacement and drop is a line of the
  :class:`Plan`'s ``report``;
- a stage's plan fails (:class:`PlanError`) only when what is left cannot constrain the
  stage's parameters, and says which and why.

========================  ======================================  ===========  ============
stage                     targets (scene per step)                full plan    quick plan
========================  ======================================  ===========  ============
intrinsics                4 mm checkerboard at U1 = 0, tilted      30 views     8 views
                          ~34 deg in directions all around         30 steps     8 steps
dynamic_camera            740 mm circle board at 650 mm, centred  136 views     20 views
                          and at 4 placements 420 mm to the sides  5 steps      1 step
laser_plane               small circle grids on the U2 = 0 laser   8 boards,    4 boards,
                          plane, near and far (4 per scene)        16 frames    8 frames
laser_axis                rows of boards on the planes of 9 G2     36 boards,   6 boards,
                          voltages over +-4 V, lit at 4 voltages   36 planes,   3 planes,
                          within +-0.05 V (rows 2 V apart share    180 frames   12 frames
                          a scene)
joint_correction          10 mm sphere at 9 positions along x,     ~120-170     9 frames
                          G1 on a 0.1 V grid around each           frames,      (3 x 3)
                          (chained through shared nodes)           9 steps      1 step
========================  ======================================  ===========  ============

Several small boards share a scene: each is seen (and lit) at its own G1 voltages, with no
other board in that view, so a laser stage treats every (step pose, G1 voltages) pair as
its own board pose (see :mod:`calibration_tools.stage_runner`). No rclpy.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from calibration_tools.board_layout import Checkerboard, CircleBoard, CircleGrid
from calibration_tools.stages import CaptureStep

# ----------------------------------------------------------------------------- the kit
#: The operator's kit: checkerboard squares [m] (11 x 8 inner corners, 12 x 9 squares).
CHECKERBOARD_SQUARES = (0.00025, 0.0005, 0.001, 0.0015, 0.002, 0.003, 0.004, 0.005, 0.006,
                        0.008, 0.010, 0.015)
#: Circle-grid pitches [m] of the laser stages' grids (circles 5/9 of the pitch).
CIRCLE_GRID_PITCHES = (0.0003, 0.00045, 0.0006, 0.0009, 0.0015, 0.002, 0.0025, 0.003, 0.0045,
                       0.006, 0.009, 0.012, 0.018)
#: Circle-grid layouts (cols, rows) of the kit, most circles first. All are found by
#: OpenCV's symmetric-grid finder (``findCirclesGrid``), which never finds a 4 x 3 or a
#: 3-column grid (measured: 0 of 8 synthetic images); the smallest is 5 x 3.
CIRCLE_GRID_LAYOUTS = ((11, 8), (9, 6), (7, 5), (5, 4), (5, 3))
#: How far [m] stripe points keep (on the board) from the edges of a laser grid's circles at
#: the design working distance: the thickness of the reference laser line there (0.6 mm),
#: where the stripe's profile straddles an albedo edge and its centre is biased. A line
#: generator's thickness grows with its throw (a fixed fan-thickness divergence, refocused
#: for the distance), so the margin is scaled with the working depth
#: (:attr:`Targets.edge_margin`, passed to the laser stages' solvers).
LASER_EDGE_MARGIN = 0.0006
#: Smallest RMS spread [m] of one laser plane's stripe points across their main direction
#: at the design working distance (below it they are nearly one line, not a plane). The
#: boards, and so their stripes and the distances between them, shrink with the view, so
#: it is scaled with the working depth like the edge margin (:attr:`Targets.min_spread`);
#: a fixed 1 mm refused two good 7 mm boards 34 mm apart at 200 mm.
LASER_MIN_SPREAD = 0.001
#: Smallest pitch a laser grid should have, in edge margins: the gaps between the circles
#: must leave enough stripe points away from their edges (3 mm at 650 mm; 2 mm grids left
#: too few there). A view too small for an 11 x 8 grid at this pitch gets fewer circles.
MIN_LASER_PITCH_MARGINS = 5.0
#: Pitches [m] of the dynamic camera's 35 x 35 circle boards (the paper's board is 20 mm;
#: circles of 1/2 and 3/4 of the pitch).
CIRCLE_BOARD_PITCHES = (0.001, 0.0025, 0.005, 0.010, 0.020, 0.040)
#: Calibration sphere radii [m]: grade balls come in fine steps of diameter; a short-range
#: view (a few mm) needs the steps between 1 and 5 mm radius, or its sphere is left far
#: smaller than the view allows and the stripe draws too short an arc on it.
SPHERE_RADII = (0.0005, 0.00075, 0.001, 0.00125, 0.0015, 0.002, 0.0025, 0.003, 0.004,
                0.005, 0.0075, 0.010, 0.015, 0.020, 0.025)

#: How much of the view [1] each target may fill: a checkerboard's squares, a laser grid's
#: board, a circle board's pitch (at least this many pitches across the shorter side of
#: the view, so that a view shows a large circle's neighbourhood) and a sphere's diameter.
#: The reference rig's (60 x 45 mm view) kit: 4 mm squares, 4.5 mm grid, 20 mm board,
#: 10 mm sphere.
CHECKERBOARD_FILL = 0.85
LASER_BOARD_FILL = 0.92
CIRCLE_BOARD_PITCHES_PER_VIEW = 2.2
SPHERE_FILL = 0.34

#: Depths [1, relative to the working depth] within which targets are taken to be in
#: focus (the model has no depth of field; a fixed-focus lens at f/8).
FOCUS_RANGE = (0.8, 1.25)
#: Pixels a target's outline keeps from the image border.
IMAGE_MARGIN_PX = 4.0

#: Intrinsics target of the reference rig's kit: 12 x 9 checkerboard of 4 mm squares.
INTRINSICS_BOARD = Checkerboard(11, 8, 0.004)
#: Laser-stage target of the reference kit: 11 x 8 circles of 2.5 mm at 4.5 mm pitch.
LASER_BOARD = CircleGrid(cols=11, rows=8, pitch=0.0045, diameter=0.0025)
#: Dynamic-camera target of the reference kit: the paper's 740 mm circle board.
CIRCLE_BOARD = CircleBoard()
#: Joint-correction target of the reference kit: calibration sphere radius [m].
SPHERE_RADIUS = 0.01
#: Design working distance along the V0 optical axis [m] (the paper's 650 mm): the
#: working depth the plans' nominal figures are written for, and the fallback where the
#: model's laser sheet does not cross the optical axis.
WORKING_DISTANCE = 0.65
#: Largest |U| a plan commands [V] (the DAC's top code is just below +10 V).
MAX_ABS_VOLTAGE = 9.9
#: How precisely a person places a target by eye [m]: the half extents of the region an
#: instruction asks for (a target within about 10 cm of where it was asked is found by the
#: search). A plan keeps what it needs in reach anywhere within it.
REGION_HALF_EXTENT = 0.06

#: Big-board placements: centre offset (x, y) in V0 [m] at the design working distance
#: (scaled with the working depth), and the board's rotation vector [rad]. Pose 0 is in
#: front of the scanner; poses 1-4 reach the paper's +-10 V verification grid.
CIRCLE_BOARD_OFFSETS = ((0.0, 0.0), (0.42, 0.0), (-0.42, 0.0), (0.0, 0.42), (0.0, -0.42))
CIRCLE_BOARD_ROTATION = (0.05, -0.08, 0.0)
#: Fractions of a placement's offset tried, in order, when its large circles are out of
#: G1 reach.
CIRCLE_BOARD_SHRINK = (1.0, 0.85, 0.7, 0.55, 0.4)

#: Laser boards in a row on one laser plane: (x [views wide at the working depth], near
#: (0) or far (1) depth). Near and far boards alternate so that no board is in the view or
#: the laser path of another.
LASER_ROW = ((-1.75, 0), (-0.5833, 1), (0.5833, 0), (1.75, 1))
#: Near and far board depths relative to where the laser plane crosses the V0 axis [1, of
#: the working depth] (+-55 mm at 650 mm).
LASER_DEPTHS = (-0.055 / 0.65, 0.055 / 0.65)
#: The laser-axis rows (full plans): this many G2 voltages, evenly over the span of the
#: scans (:func:`_axis_rows`), in two interleaved scenes. The span matters: G2's response is
#: not linear, and its curvature fitted from +-4 V and extrapolated to the -7.4 V that the
#: top of G1's range needs put 0.3-0.7 mm into the laser planes of a drawn rig.
LASER_AXIS_ROW_COUNT = 9
#: A laser-axis row is placed where its plane meets the view axis at the working depth
#: within this fraction of G1's range.
LASER_AXIS_REACH = 0.9
#: The paper's model's rows [V] (its linear G2 response fitted over the scans' whole span
#: made a drawn rig's shape error 0.14 -> 0.22 mm: a straight line through a curve) and the
#: quick plan's, each at full span, and the span fractions tried when the outer rows are
#: out of G1 reach.
LASER_AXIS_PAPER_ROWS = (([-4.0, -2.0, 0.0, 2.0, 4.0], [-3.0, -1.0, 1.0, 3.0]))
LASER_AXIS_QUICK_ROWS = ([-2.0, 0.0, 2.0],)
LASER_AXIS_SPAN = (1.0, 0.8, 0.6, 0.45, 0.3)
#: Sphere positions along V0's x at the design working distance [m] (scaled with depth).
JOINT_LATERALS = (0.0, 0.02, -0.02, 0.04, -0.04, 0.06, -0.06, 0.08, -0.08)
#: Fractions of a sphere position's offset tried, in order, until its G1 grid shares a
#: node with the positions before it.
JOINT_LATERAL_SHRINK = (1.0, 0.85, 0.7, 0.55, 0.4)
#: Fewest G1 grid nodes a sphere position keeps.
MIN_SPHERE_NODES = 4


class PlanError(ValueError):
    """What is left of a plan cannot constrain the stage's parameters (message says which)."""


class Plan(list):
    """A stage's capture steps (a list of :class:`CaptureStep`) with the plan's report.

    Attributes
    ----------
    report : list of str
        One line per step that was replaced or dropped, and why.
    targets : Targets or None
        The kit's targets the plan uses.
    """

    def __init__(self, steps=(), report=(), targets=None):
        super().__init__(steps)
        self.report = list(report)
        self.targets = targets


@dataclass(frozen=True)
class Targets:
    """The targets of the operator's kit that suit a model's view (:func:`choose_targets`).

    Attributes
    ----------
    depth : float, metres
        Working depth along the V0 optical axis.
    view : (float, float), metres
        Width and height of the view at ``depth``.
    checkerboard : Checkerboard
    laser_board : CircleGrid
    circle_board : CircleBoard
    sphere_radius : float, metres
    edge_margin : float, metres
        How far the laser stages keep stripe points from the laser grid's circle edges
        (:data:`LASER_EDGE_MARGIN` scaled with ``depth``).
    min_spread : float, metres
        The laser stages' smallest accepted spread of a plane's stripe points
        (:data:`LASER_MIN_SPREAD` scaled with ``depth``).
    """

    depth: float
    view: tuple
    checkerboard: Checkerboard
    laser_board: CircleGrid
    circle_board: CircleBoard
    sphere_radius: float
    edge_margin: float = LASER_EDGE_MARGIN
    min_spread: float = LASER_MIN_SPREAD


def total_frames(steps) -> int:
    """Frames of a whole plan."""
    return sum(s.frames for s in steps)


# ----------------------------------------------------------------------------- helpers
def current_model(calibration):
    """The model a plan is made with: the calibration's (or the RigModel), without correction."""
    from reconstructor.model import RigModel

    model = getattr(calibration, 'model', calibration)
    if not isinstance(model, RigModel):
        raise ValueError('calibration must be a Calibration (or a RigModel), got '
                         f'{type(calibration).__name__}')
    # Targets are placed in the model's V0, before any joint correction.
    return dataclasses.replace(model, correction=None)


def laser_crossing_depth(model) -> float:
    """Depth where the model's U2 = 0 laser plane crosses the V0 optical axis [m].

    The design working distance when the model's plane does not cross it between the G1
    exit mirror (l + d) and 3 m (a plane nearly parallel to the axis).
    """
    a, b, c, e = model.laser_plane_v0
    if abs(c) > 1e-9:
        z = -e / c
        if float(model.l + model.d) + 0.02 < z < 3.0:
            return float(z)
    return WORKING_DISTANCE


def _largest(catalogue, fits):
    """The largest entry of a catalogue that ``fits``; the smallest when none does."""
    ok = [x for x in catalogue if fits(x)]
    return max(ok) if ok else min(catalogue)


def choose_targets(model) -> Targets:
    """The kit's targets for a model: the largest of each kind that suits its view.

    The one rule plans and solvers share (:mod:`calibration_tools.registry` passes the same
    targets to a stage's solver as to its plan).

    Parameters
    ----------
    model : reconstructor.model.RigModel
        The operator's current model.

    Returns
    -------
    Targets
    """
    from reconstructor.planning import stripe_layout

    z = laser_crossing_depth(model)
    intr = model.intrinsics
    w, h = intr.width / intr.fx * z, intr.height / intr.fy * z
    sq = _largest(CHECKERBOARD_SQUARES, lambda s: 12 * s <= CHECKERBOARD_FILL * w
                  and 9 * s <= CHECKERBOARD_FILL * h)
    # a laser grid's columns run along the stripe (:func:`laser_row_steps`)
    wa, ha = (w, h) if stripe_layout(model).along == 0 else (h, w)
    grids = [(_largest(CIRCLE_GRID_PITCHES, lambda p, c=c, r=r: (c + 1) * p <= LASER_BOARD_FILL
                       * wa and (r + 1) * p <= LASER_BOARD_FILL * ha), c, r)
             for c, r in CIRCLE_GRID_LAYOUTS]
    margin = LASER_EDGE_MARGIN * z / WORKING_DISTANCE
    pg, gc, gr = next((g for g in grids if g[0] >= MIN_LASER_PITCH_MARGINS * margin - 1e-12),
                      max(grids))
    pb = _largest(CIRCLE_BOARD_PITCHES,
                  lambda p: min(w, h) / p >= CIRCLE_BOARD_PITCHES_PER_VIEW)
    # the sphere's G1 grid is widest along the stripe: its arc must stay in view there
    r = _largest(SPHERE_RADII, lambda r: 2 * r <= SPHERE_FILL * wa)
    return Targets(
        depth=z, view=(float(w), float(h)),
        checkerboard=Checkerboard(11, 8, sq),
        laser_board=CircleGrid(cols=gc, rows=gr, pitch=pg, diameter=round(pg * 5 / 9, 7)),
        circle_board=CircleBoard(pitch=pb, small_diameter=pb / 2, large_diameter=pb * 0.75),
        sphere_radius=r, edge_margin=float(margin),
        min_spread=float(LASER_MIN_SPREAD * z / WORKING_DISTANCE))


def _transform(rotvec, t) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _fmt(v) -> str:
    return '[' + ', '.join(f'{float(x):.10g}' for x in v) + ']'


def _mm(p) -> str:
    return '(' + ', '.join(f'{float(x) * 1e3:+.0f}' for x in p) + ') mm'


# ----------------------------------------------------------------------------- checks
def _viewpoint(model, g1) -> np.ndarray:
    """The virtual camera's centre in V0 at G1 voltages ``g1`` [m], shape (3,)."""
    from reconstructor.model import v0_T_v

    return np.asarray(v0_T_v(model, float(g1[0]), float(g1[1])))[:3, 3]


def _segment_hits(a, b, rect) -> bool:
    """Whether segment a-b crosses a rectangle ``(T, half_x, half_y)`` (pose, metres)."""
    T, hx, hy = rect
    n, c = T[:3, 2], T[:3, 3]
    da, db = (a - c) @ n, (b - c) @ n
    if da * db >= 0.0:
        return False
    q = a + (b - a) * (da / (da - db)) - c
    return abs(q @ T[:3, 0]) <= hx and abs(q @ T[:3, 1]) <= hy


def check_view(model, targets: Targets, outline_v0, *, centre=None, normal=None,
               lit: bool = False, others=(), g1=None, radius_px: float = 0.0,
               margin_px: float = IMAGE_MARGIN_PX):
    """Check a target placement before capture: None when it can be captured, else why.

    Parameters
    ----------
    model : RigModel
        The operator's model (no correction).
    targets : Targets
        For the working depth (focus range).
    outline_v0 : array_like, shape (n, 3), metres
        Points that must be seen: a board's outline corners, a sphere's centre.
    centre : array_like, shape (3,), metres, optional
        The target's centre, G1 is aimed at it (default: the mean of ``outline_v0``).
    normal : array_like, shape (3,), optional
        The target's facing direction (towards its viewer); checked against the camera
        and, with ``lit``, the laser.
    lit : bool
        The laser must reach the target (no other target between it and the laser).
    others : sequence of (ndarray shape (4, 4), float, float)
        Other boards of the same scene as (V0_T_board, half width, half height), metres.
    g1 : array_like, shape (2,), volts, optional
        View voltages (default: aimed at ``centre``).
    radius_px : float
        Extra margin [px] the outline points need (a sphere's apparent radius).
    margin_px : float
        Pixels kept from the image border.

    Returns
    -------
    str or None
    """
    from reconstructor.model import predict_pixels
    from reconstructor.planning import aim_g1

    P = np.asarray(outline_v0, dtype=np.float64).reshape(-1, 3)
    c = P.mean(axis=0) if centre is None else np.asarray(centre, dtype=np.float64)
    lo, hi = (f * targets.depth for f in FOCUS_RANGE)
    if not lo <= c[2] <= hi:
        return (f'at {c[2] * 1e3:.0f} mm, outside the focus range {lo * 1e3:.0f}-'
                f'{hi * 1e3:.0f} mm')
    if g1 is None:
        g1 = aim_g1(model, c, max_abs_u=MAX_ABS_VOLTAGE)
    g1 = np.asarray(g1, dtype=np.float64)
    if not np.all(np.isfinite(g1)) or np.abs(g1).max() > MAX_ABS_VOLTAGE:
        return f'at {_mm(c)} out of G1 reach (|U1| <= {MAX_ABS_VOLTAGE} V) under the model'
    uv, front = predict_pixels(model, P, g1[0], g1[1])
    intr = model.intrinsics
    m = margin_px + radius_px
    if not (np.all(front) and np.all(np.isfinite(uv)) and uv[:, 0].min() >= m
            and uv[:, 1].min() >= m and uv[:, 0].max() <= intr.width - 1 - m
            and uv[:, 1].max() <= intr.height - 1 - m):
        return f'at {_mm(c)} not inside the image at U1 = {_fmt(np.round(g1, 3))} V'
    eye = _viewpoint(model, g1)
    source = None
    if lit:
        ax = np.asarray(model.laser_axis_dir, dtype=np.float64)
        source = model.laser_axis_point + ((c - model.laser_axis_point) @ ax) * ax
    if normal is not None:
        nrm = np.asarray(normal, dtype=np.float64)
        if (eye - c) @ nrm <= 0 or (source is not None and (source - c) @ nrm <= 0):
            return f'at {_mm(c)} turned away from the camera or the laser'
    for rect in others:
        if _segment_hits(c, eye, rect) or (source is not None
                                           and _segment_hits(c, source, rect)):
            return f'at {_mm(c)} hidden by another board of its scene'
    return None


def _rect(T, board) -> tuple:
    """(V0_T_board, half width, half height) of a small board's outline (with margin)."""
    pitch = board.square if isinstance(board, Checkerboard) else board.pitch
    n = 2 if isinstance(board, Checkerboard) else 1
    return T, (board.cols + n) * pitch / 2, (board.rows + n) * pitch / 2


def _pattern_outline(T, board) -> np.ndarray:
    """The pattern's four outer corners in V0 (a board centred on T's origin), shape (4, 3)."""
    pitch = board.square if isinstance(board, Checkerboard) else board.pitch
    n = 1 if isinstance(board, Checkerboard) else 0
    hx, hy = (board.cols + n) * pitch / 2, (board.rows + n) * pitch / 2
    if isinstance(board, CircleGrid):
        hx, hy = hx - pitch / 2 + board.diameter / 2, hy - pitch / 2 + board.diameter / 2
    local = np.array([[sx * hx, sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    return local @ T[:3, :3].T + T[:3, 3]


def _require(stage: str, params: str, ok: bool, why: str, report) -> None:
    if not ok:
        tail = f'; {len(report)} placement(s) dropped or replaced: ' + '; '.join(report[:6]) \
            if report else ''
        raise PlanError(f'{stage}: the plan cannot constrain {params}: {why}{tail}')


def circle_board_scene_yaml(V0_T_W, board=CIRCLE_BOARD) -> str:
    """Simulator scene text with the large circle board at ``V0_T_W``.

    Parameters
    ----------
    V0_T_W : array_like, shape (4, 4), metres
        Board pose (its frame W: origin at the centre circle, z into the board).
    board : board_layout.CircleBoard
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(V0_T_W, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f'V0_T_W must have shape (4, 4), got {T.shape}')
    r = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    side_x, side_y = (board.cols + 2) * board.pitch, (board.rows + 2) * board.pitch  # margin
    return (f'format_version: 1\nname: cal_circle_board\n'
            f'description: {board.cols} x {board.rows} circle board for the dynamic camera\n'
            f'objects:\n  - type: circle_board\n    name: board\n'
            f'    pose: {{translation: {_fmt(T[:3, 3])}, rotation_vector: {_fmt(r)}}}\n'
            f'    size: {_fmt([side_x, side_y])}\n'
            f'    thickness: 0.01\n    grid: [{board.cols}, {board.rows}]\n'
            f'    pitch: {board.pitch!r}\n    sub_pattern: {board.sub_pattern}\n'
            f'    small_diameter: {board.small_diameter!r}\n'
            f'    big_diameter: {board.large_diameter!r}\n'
            f'    albedo: 0.85\n    circle_albedo: 0.05\n')


def _anchors_wherever_placed(model, board, T) -> int:
    """The fewest large circles of the board within G1 reach wherever a person puts it
    within the region asked for around ``T`` (each corner of the region, in x, y and depth,
    :data:`REGION_HALF_EXTENT`)."""
    from calibration_tools.dynamic_camera import anchor_voltages

    fewest = board.n_circles
    for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T:
        moved = T.copy()
        moved[:3, 3] += REGION_HALF_EXTENT * corner
        fewest = min(fewest, len(anchor_voltages(model, board, moved,
                                                 max_abs_u=MAX_ABS_VOLTAGE)))
    return fewest


def _circle_board_search(model, targets: Targets):
    """Placements of the circle board: ``[(placement index, V0_T_W, anchors)]`` and report.

    Each of :data:`CIRCLE_BOARD_OFFSETS` (scaled with the working depth) is tried at the
    fractions :data:`CIRCLE_BOARD_SHRINK` of its offset until at least 2 of its large
    circles are within G1 reach wherever within the region asked for a person puts it (the
    scanner refuses a board with fewer, :func:`operator_flow.check_pose`; a head with a
    narrow scan angle reaches only the inner part of a side placement, and a placement at
    the edge of that reach was refused for most of a person's placements). Where no
    fraction keeps that margin, the first with 2 large circles in reach as asked is taken;
    a placement where none has gets dropped.
    """
    from calibration_tools.dynamic_camera import anchor_voltages

    scale = targets.depth / WORKING_DISTANCE
    kept, report = [], []
    for i, (ox, oy) in enumerate(CIRCLE_BOARD_OFFSETS):
        tried = []
        for f in CIRCLE_BOARD_SHRINK:
            T = _transform(CIRCLE_BOARD_ROTATION, [ox * scale * f, oy * scale * f,
                                                   targets.depth])
            anchors = anchor_voltages(model, targets.circle_board, T,
                                      max_abs_u=MAX_ABS_VOLTAGE)[:3]
            if len(anchors) >= 2:
                tried.append((f, T, anchors))
                if _anchors_wherever_placed(model, targets.circle_board, T) >= 2:
                    break
        else:
            if not tried:
                report.append(f'dynamic camera: placement {i} at {_mm(T[:3, 3])} dropped: '
                              'fewer than 2 large circles within G1 reach at any offset '
                              'tried')
                continue
            f, T, anchors = tried[0]
            report.append(f'dynamic camera: placement {i} at {_mm(T[:3, 3])}: its large '
                          'circles leave G1 reach when the board is placed off the centre '
                          'asked for at every offset tried')
        if f != 1.0:
            report.append(f'dynamic camera: placement {i} moved in to {_mm(T[:3, 3])} '
                          f'({f:.0%} of its offset): its large circles were out of G1 reach')
        kept.append((i, T, anchors))
    return kept, report


def circle_board_poses(model, targets: Targets | None = None) -> list[np.ndarray]:
    """The circle board's placements ``V0_T_W`` (shape (4, 4), metres) by pose_index.

    What the dynamic-camera plan places and the solver takes as the board poses' priors
    (one function for both).
    """
    t = choose_targets(model) if targets is None else targets
    return [T for _, T, _ in _circle_board_search(model, t)[0]]


def circle_board_pose(pose_index: int, model=None) -> np.ndarray:
    """Where the plan places the circle board for ``pose_index``: ``V0_T_W``, metres.

    Parameters
    ----------
    pose_index : int
    model : RigModel, optional
        The operator's model (default: the design working distance's bench placement,
        :data:`CIRCLE_BOARD_OFFSETS`).
    """
    poses = ([_transform(CIRCLE_BOARD_ROTATION, [ox, oy, WORKING_DISTANCE])
              for ox, oy in CIRCLE_BOARD_OFFSETS] if model is None
             else circle_board_poses(model))
    if not 0 <= int(pose_index) < len(poses):
        raise ValueError(f'pose_index must be in [0, {len(poses)}), got {pose_index}')
    return poses[int(pose_index)]


# ----------------------------------------------------------------------------- stages
def intrinsics_steps(model, n_views: int, *, tilt: float = 0.6, seed: int = 0,
                     targets: Targets | None = None) -> Plan:
    """Checkerboard views at U1 = 0, tilted by ``tilt`` rad in directions all around.

    Each board is centred on the model's ray through the image centre at 0.98-1.11 of the
    working depth and moved back until its pattern projects inside the image (model
    intrinsics); a view that would leave the focus range is tried again less tilted
    (3/4, then 1/2 of ``tilt``), else dropped.
    """
    from calibration_tools.placement import board_scene_yaml

    t = choose_targets(model) if targets is None else targets
    rng = np.random.default_rng(seed)
    intr = model.intrinsics
    ray = np.array([(intr.width / 2 - intr.cx) / intr.fx, (intr.height / 2 - intr.cy) / intr.fy,
                    1.0])
    b, scale = t.checkerboard, t.depth / WORKING_DISTANCE
    steps, report = [], []
    for i in range(n_views):
        a = 2.0 * math.pi * i / n_views + rng.uniform(0.0, 0.3)
        spin = rng.uniform(-0.3, 0.3)
        z0 = rng.uniform(0.64, 0.72) * scale
        lateral = np.array([rng.uniform(-0.003, 0.003), rng.uniform(-0.002, 0.002),
                            0.0]) * scale
        placed, why = None, ''
        for f in (1.0, 0.75, 0.5):
            rotvec = np.array([tilt * f * math.cos(a), tilt * f * math.sin(a), spin])
            R, z = _transform(rotvec, np.zeros(3)), z0
            for _ in range(40):
                T = R.copy()
                T[:3, 3] = ray * z + lateral
                why = check_view(model, t, _pattern_outline(T, b), g1=(0.0, 0.0),
                                 margin_px=12.0)
                if why is None or 'focus' in why:
                    break
                z *= 1.02
            if why is None:
                placed = (T[:3, 3], rotvec, f)
                break
        if placed is None:
            report.append(f'intrinsics: view {i} dropped: {why}')
            continue
        if placed[2] != 1.0:
            report.append(f'intrinsics: view {i} tilted {placed[2]:.0%} of {tilt} rad to stay '
                          'in focus and in the image')
        # The board frame's x runs along the pattern's columns; place its centre at t.
        steps.append(CaptureStep(len(steps), board_scene_yaml(b, placed[0], placed[1]),
                                 np.zeros((1, 4)), False,
                                 note=f'intrinsics: {b.square * 1e3:g} mm checkerboard view '
                                      f'{i} at U1 = 0, {placed[0][2] * 1e3:.0f} mm'))
    _require('intrinsics', 'fx, fy, cx, cy and the distortion', len(steps) >= 4,
             f'{len(steps)} checkerboard view(s) left, at least 4 needed', report)
    return Plan(steps, report, t)


def dynamic_camera_steps(model, counts, *, seed: int = 0,
                         targets: Targets | None = None) -> Plan:
    """Circle-board views: per placement, 3 views centred on large circles, the rest at
    random points of the board, all aimed with the model.

    Parameters
    ----------
    counts : sequence of int
        Views per placement (:data:`CIRCLE_BOARD_OFFSETS` order); a placement that cannot
        be placed (:func:`circle_board_poses`) is dropped with its views.
    """
    from reconstructor.planning import aim_g1

    t = choose_targets(model) if targets is None else targets
    rng = np.random.default_rng(seed)
    kept, search_report = _circle_board_search(model, t)
    report = [r for r in search_report if int(r.split('placement ')[1].split()[0]) <
              len(counts)]
    B = t.circle_board
    reach = 16.5 * B.pitch  # random points: within 16.5 pitches of the centre circle
    steps = []
    for pose, (i, T, aims) in enumerate(kept):
        if i >= len(counts):
            continue
        n = counts[i]
        if n < 3:
            raise ValueError(f'counts[{i}] must be >= 3 (identification needs anchors)')
        pts = np.column_stack([rng.uniform(-reach, reach, (6 * n, 2)), np.zeros(6 * n)])
        more = aim_g1(model, pts @ T[:3, :3].T + T[:3, 3], max_abs_u=MAX_ABS_VOLTAGE)
        more = more[np.isfinite(more).all(axis=1)][: n - len(aims)]
        u = np.vstack([aims, more])
        volts = np.column_stack([u, np.zeros((len(u), 2))])
        steps.append(CaptureStep(pose, circle_board_scene_yaml(T, B), volts, False,
                                 note=f'dynamic camera: {B.pitch * 1e3:g} mm-pitch circle '
                                      f'board (placement {i}) at {_mm(T[:3, 3])}, '
                                      f'{len(u)} G1 positions'))
    _require('dynamic_camera', 'l, d and the G1 gains and zeros',
             bool(steps) and total_frames(steps) >= 6,
             f'{len(steps)} circle-board placement(s) with {total_frames(steps)} views left, '
             'at least one placement with 2 large circles in reach and 6 views needed', report)
    return Plan(steps, report, t)


def _laser_candidates(tilt_y: float, depth: float, x: float):
    """Replacement search for a laser board: (tilt about y, relative depth, x) in order."""
    return ((tilt_y, depth, x), (-tilt_y, depth, x), (tilt_y / 2, depth, x),
            (tilt_y, depth / 2, x), (-tilt_y, depth / 2, x), (0.0, 0.0, x * 0.8))


def _place_laser_board(model, t: Targets, pi, x, depth, tilt_y, roll, others, layout):
    """First candidate placement of a board on laser plane ``pi`` that passes the checks.

    The plane crosses the board between its two middle rows of circles: a board with an odd
    number of rows is moved half a pitch along its y, or the stripe would run along the
    middle row's circle edges and leave too few points away from them.

    Returns ``((p, R, g1), None)`` (``p`` the board's centre) or ``(None, why the first
    candidate failed)``.
    """
    from calibration_tools.placement import board_rotation_on_laser
    from reconstructor.planning import aim_g1

    b = t.laser_board
    shift = 0.5 * b.pitch if b.rows % 2 else 0.0
    first = None
    for ty, dz, xx in _laser_candidates(tilt_y, depth, x):
        z = t.depth * (1.0 + dz)
        p = layout.point_on_plane(pi, xx, z)          # xx along the stripe
        R = board_rotation_on_laser(model, p, ty, roll, along=layout.along)
        p = p - shift * R[:, 1]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p
        g1 = aim_g1(model, p, max_abs_u=MAX_ABS_VOLTAGE)
        why = check_view(model, t, _pattern_outline(T, t.laser_board), centre=p,
                         normal=-R[:, 2], lit=True, others=others, g1=g1)
        if why is None:
            return (p, R, g1, (ty, dz, xx) != (tilt_y, depth, x)), None
        first = first or why
    return None, first


#: The laser axis's lit frames of a board: at its row's voltage plus each of these [V]. Every
#: lit frame is one draw of the galvos' per-frame jitter, which moves its whole stripe off
#: the sheet at once, by far more than its points scatter about each other: a board's
#: stripes average it down, and four frames cost a few milliseconds. They keep within the
#: +-0.05 V the boards are placed for, so that the stripe stays on them.
LASER_AXIS_LIT_OFFSETS = (-0.05, -0.05 / 3, 0.05 / 3, 0.05)


def laser_row_steps(model, rows, *, offsets=(0.0,), boards=LASER_ROW, depth_shift=0.0,
                    mirror_x: bool = False, pose_index: int = 0, seed: int = 0,
                    label: str = 'laser', targets: Targets | None = None,
                    report: list | None = None):
    """One scene of small circle-grid boards lying on the model's laser planes, and its two
    steps: the boards with the laser off, then lit.

    Every board is checked (:func:`check_view`) before it is placed; one that fails is
    replaced by the first passing candidate of a short search (tilt flipped or halved,
    half as far from the crossing, nearer the axis) or dropped, with a line in ``report``.

    Parameters
    ----------
    model : RigModel
    rows : sequence of float, volts
        G2 tilt voltages; one row of ``boards`` on each of their laser planes.
    offsets : sequence of float, volts
        The laser-on frames of a board are at its row's voltage plus each offset.
    boards : sequence of (float, int)
        (position along the stripe [views at the working depth], near 0 / far 1) of a
        row's boards (:data:`LASER_ROW`); along V0's x for a laser below or above the
        camera, y beside it (``reconstructor.planning.stripe_layout``).
    depth_shift : float
        Added to both relative board depths [1, of the working depth].
    mirror_x : bool
        Use -x for every board.
    targets : Targets, optional
        Default: :func:`choose_targets` of the model.
    report : list, optional
        Receives a line per replaced or dropped board.

    Returns
    -------
    list of CaptureStep
        Empty when no board could be placed.
    """
    from calibration_tools.placement import boards_scene_yaml
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import stripe_layout

    t = choose_targets(model) if targets is None else targets
    report = [] if report is None else report
    rng = np.random.default_rng(seed)
    layout = stripe_layout(model)
    placements, rects, off_volts, on_volts = [], [], [], []
    for u in rows:
        pi = laser_plane_v0(model, float(u))
        for k, (x, far) in enumerate(boards):
            tilt_y, roll = rng.choice([-1.0, 1.0]) * 0.4, rng.uniform(-0.1, 0.1)
            if abs(pi[layout.across]) < 0.2:
                report.append(f'{label}: board {k} at U2 = {u:g} V dropped: the laser plane '
                              'is too steep to place boards on')
                continue
            x = (-x if mirror_x else x) * t.view[layout.along]    # views along the stripe
            got, why = _place_laser_board(model, t, pi, x, LASER_DEPTHS[far] + depth_shift,
                                          tilt_y, roll, rects, layout)
            if got is None:
                report.append(f'{label}: board {k} at U2 = {u:g} V dropped: {why}')
                continue
            p, R, g1, replaced = got
            if replaced:
                report.append(f'{label}: board {k} at U2 = {u:g} V replaced by one at '
                              f'{_mm(p)}: the planned one failed its check')
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, p
            rects.append(_rect(T, t.laser_board))
            placements.append((t.laser_board, p, R))
            off_volts.append([g1[0], g1[1], 0.0, 0.0])
            on_volts += [[g1[0], g1[1], 0.0, float(u) + o] for o in offsets]
    if not placements:
        return []
    text = boards_scene_yaml(placements, name=f"cal_{label.replace(' ', '_')}_boards")
    n, b = len(placements), t.laser_board
    return [
        CaptureStep(pose_index, text, np.array(off_volts), False,
                    note=f'{label}: {n} circle-grid boards ({b.pitch * 1e3:g} mm pitch) on the '
                         f'laser planes of U2 = {_fmt(rows)} V, laser off'),
        CaptureStep(pose_index, None, np.array(on_volts), True, frame_rate=100.0,
                    note=f'{label}: the same {n} boards lit ({len(offsets)} G2 voltage(s) '
                         f'each)'),
    ]


def _boards(steps) -> dict:
    """Lit boards of a laser plan: (pose_index, U1 pan, U1 tilt) -> mean U2 tilt [V]."""
    out: dict = {}
    for s in steps:
        if s.laser_on:
            for v in s.voltages:
                out.setdefault((s.pose_index, round(v[0], 6), round(v[1], 6)), []).append(v[3])
    return {k: float(np.mean(u)) for k, u in out.items()}


def laser_plane_steps(model, scenes: int, *, targets: Targets | None = None) -> Plan:
    """Boards on the U2 = 0 laser plane: ``scenes`` scenes of 4 boards (near and far)."""
    t = choose_targets(model) if targets is None else targets
    steps, report = [], []
    for k in range(scenes):
        steps += laser_row_steps(model, [0.0], depth_shift=0.01 / WORKING_DISTANCE * k,
                                 mirror_x=bool(k % 2), pose_index=k, seed=k,
                                 label='laser plane', targets=t, report=report)
    depths = {round(yaml_depth, 4) for yaml_depth in _board_depths(steps)}
    _require('laser_plane', 'the U2 = 0 laser plane', len(depths) >= 2,
             f'{len(_boards(steps))} board(s) at {len(depths)} depth(s) left, at least 2 '
             'boards at different depths needed', report)
    return Plan(steps, report, t)


def _board_depths(steps) -> list[float]:
    import yaml

    return [float(o['pose']['translation'][2]) for s in steps if s.scene_yaml
            for o in yaml.safe_load(s.scene_yaml)['objects']]


def _axis_reach(model, t: Targets, u: float) -> bool:
    """Whether the laser plane of G2 voltage ``u`` can take boards: it meets the view axis
    at the working depth within :data:`LASER_AXIS_REACH` of G1's range, and is not too steep."""
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import aim_g1, stripe_layout

    pi = laser_plane_v0(model, u)
    layout = stripe_layout(model)
    if abs(pi[layout.across]) < 0.2:
        return False
    p = layout.point_on_plane(pi, 0.0, t.depth)
    g1 = aim_g1(model, p, max_abs_u=MAX_ABS_VOLTAGE)
    return bool(np.all(np.abs(g1) <= LASER_AXIS_REACH * MAX_ABS_VOLTAGE))


def _axis_rows(model, t: Targets) -> tuple[list, list, str]:
    """The full plan's two interleaved sets of laser-axis rows [V]: :data:`LASER_AXIS_ROW_COUNT`
    voltages evenly between the outermost reachable G2 voltages on either side of 0
    (:func:`_axis_reach`, searched in 0.25 V steps up to 9.5 V), and a line saying so."""
    ends = []
    for sign in (-1.0, 1.0):
        end = 0.0
        for u in np.arange(0.25, 9.51, 0.25):
            if not _axis_reach(model, t, sign * float(u)):
                break
            end = sign * float(u)
        ends.append(end)
    rows = np.linspace(ends[0], ends[1], LASER_AXIS_ROW_COUNT)
    note = (f'laser axis: G2 rows over {ends[0]:+.2f}..{ends[1]:+.2f} V, where the laser meets '
            f'the view axis at the working depth within {LASER_AXIS_REACH:.0%} of G1 range')
    return [float(u) for u in rows[0::2]], [float(u) for u in rows[1::2]], note


def _axis_span(model, t: Targets, rows) -> float:
    """The largest fraction of :data:`LASER_AXIS_SPAN` whose outer rows are reachable.

    A row is reachable when the point of its laser plane on the view's axis at the working
    depth is within 85 % of G1's range and the plane is not too steep to place boards on.
    """
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import aim_g1, stripe_layout

    u_max = max(abs(u) for r in rows for u in r)
    layout = stripe_layout(model)
    for f in LASER_AXIS_SPAN:
        ok = True
        for u in (-u_max * f, u_max * f):
            pi = laser_plane_v0(model, u)
            if abs(pi[layout.across]) < 0.2:
                ok = False
                break
            p = layout.point_on_plane(pi, 0.0, t.depth)
            g1 = aim_g1(model, p, max_abs_u=MAX_ABS_VOLTAGE)
            ok = ok and bool(np.all(np.abs(g1) <= 0.85 * MAX_ABS_VOLTAGE))
        if ok:
            return f
    return LASER_AXIS_SPAN[-1]


def laser_axis_steps(model, quick: bool, *, targets: Targets | None = None) -> Plan:
    """Boards on the laser planes of several G2 voltages (rows 2 V apart share a scene).

    With the physical model the rows span the G2 voltages the scans need, as far as boards
    on their planes are in G1 reach (:func:`_axis_rows`); with the paper's, +-4 V
    (:data:`LASER_AXIS_PAPER_ROWS`); quick: +-2 V; both less where out of reach
    (:func:`_axis_span`). Boards are then checked one by one.
    """
    t = choose_targets(model) if targets is None else targets
    report: list[str] = []
    if quick:
        f = _axis_span(model, t, LASER_AXIS_QUICK_ROWS)
        if f != 1.0:
            report.append(f'laser axis: G2 rows narrowed to {f:.0%} of their span: the outer '
                          'rows are out of G1 reach under the model')
        steps = laser_row_steps(model, [u * f for u in LASER_AXIS_QUICK_ROWS[0]],
                                boards=((-0.5833, 0), (0.5833, 1)), label='laser axis',
                                targets=t, report=report)
    else:
        if model.kind == 'physical':
            *row_sets, note = _axis_rows(model, t)
            report.append(note)
        else:
            f = _axis_span(model, t, LASER_AXIS_PAPER_ROWS)
            row_sets = [[u * f for u in rows] for rows in LASER_AXIS_PAPER_ROWS]
            if f != 1.0:
                report.append(f'laser axis: G2 rows narrowed to {f:.0%} of their span: the '
                              'outer rows are out of G1 reach under the model')
        steps = []
        for k, rows in enumerate(row_sets):
            steps += laser_row_steps(model, rows, offsets=LASER_AXIS_LIT_OFFSETS,
                                     mirror_x=bool(k), pose_index=k, seed=10 + k,
                                     label='laser axis', targets=t, report=report)
    boards = _boards(steps)
    planes = {round(u, 2) for u in boards.values()}
    _require('laser_axis', 'the laser axis (G2 tilt gain and zero, axis direction and '
             'point)', len(planes) >= 2 and len(boards) >= 3,
             f'{len(boards)} lit board(s) on {len(planes)} G2 row(s) left, at least 3 boards '
             'on 2 rows needed', report)
    return Plan(steps, report, t)


def _sphere_nodes(model, t: Targets, centre, radius: float, volts) -> np.ndarray:
    """Which G1 grid nodes (rows of ``volts``, shape (n, 4)) see the whole sphere."""
    r_px = model.intrinsics.fx * radius / max(float(centre[2]), 1e-6)
    return np.array([check_view(model, t, centre[None], centre=centre, g1=v[:2],
                                radius_px=r_px) is None for v in volts], dtype=bool)


def _sphere_position(model, t: Targets, lateral, step, reach, u2_tilt, pose, seen):
    """One sphere position's step, checked: ``((step, kept nodes mask, node set), None)``
    or ``(None, why not)``."""
    from calibration_tools.placement import sphere_grid_steps

    try:
        s, centre, _ = sphere_grid_steps(model, u2_tilt, t.sphere_radius, None, None,
                                         depth=t.depth, lateral=lateral, grid_step=step,
                                         reach=reach, pose_index=pose)
    except ValueError as exc:
        return None, str(exc)
    volts = np.vstack([q.voltages for q in s])
    keep = _sphere_nodes(model, t, centre, t.sphere_radius, volts)
    nodes = {tuple(np.round(v[:2] / step).astype(int)) for v in volts[keep]}
    if keep.sum() < MIN_SPHERE_NODES:
        return None, (f'at {_mm(centre)}: {int(keep.sum())} G1 node(s) see the whole sphere, '
                      f'{MIN_SPHERE_NODES} needed')
    if seen and not nodes & seen:
        return None, f'at {_mm(centre)}: it shares no G1 node with the positions before it'
    note = (f'sphere (radius {t.sphere_radius * 1e3:g} mm) at {_mm(centre)}, '
            f'{int(keep.sum())} G1 grid nodes')
    return (dataclasses.replace(s[0], voltages=volts[keep], note=note), keep, nodes), None


def joint_correction_steps(model, laterals, *, reach=(0.3, 0.1), step: float = 0.1,
                           u2_tilt: float = 0.0, targets: Targets | None = None) -> Plan:
    """The sphere at positions along the stripe (V0's x for a laser below or above the
    camera, y beside it), G1 stepped over a global ``step`` V grid.

    Each position is one scene: the sphere's front on the model's laser plane at
    ``u2_tilt`` at the working depth, a wall right behind it, and the G1 grid nodes
    within ``reach`` of the voltages aimed at its centre (the first position's grid holds
    U1 = 0, the correction's reference; neighbouring positions share nodes, so their
    corrections chain). Nodes whose view would not hold the whole sphere are dropped; a
    position left with fewer than :data:`MIN_SPHERE_NODES` nodes, or sharing none with the
    positions before it, is dropped (each reported).

    Parameters
    ----------
    laterals : sequence of float, metres
        Sphere positions along the stripe at the design working distance (scaled with the
        depth).
    reach : (float, float), volts
        Half widths of each position's G1 grid along the stripe and across it.
    """
    from reconstructor.planning import stripe_layout

    t = choose_targets(model) if targets is None else targets
    # (along, across) to G1 (pan, tilt): G1's axis index is the V0 axis it moves the view on
    reach = tuple(reach) if stripe_layout(model).along == 0 else tuple(reach)[::-1]
    scale = t.depth / WORKING_DISTANCE
    steps, report, seen = [], [], set()
    for pose, x in enumerate(laterals):
        why = 'not tried'
        for f in JOINT_LATERAL_SHRINK if pose else (1.0,):
            got, why = _sphere_position(model, t, x * scale * f, step, reach, u2_tilt,
                                        len({q.pose_index for q in steps}), seen)
            if got is not None:
                break
        if got is None:
            report.append(f'joint correction: position {pose} dropped: {why}')
            continue
        step_, keep, nodes = got
        if f != 1.0:
            report.append(f'joint correction: position {pose} moved in to {f:.0%} of its '
                          'offset to share G1 nodes with the positions before it')
        if not keep.all():
            report.append(f'joint correction: position {pose}: {int((~keep).sum())} of '
                          f'{len(keep)} G1 nodes dropped (the sphere leaves the view)')
        seen |= nodes
        steps.append(step_)
    _require('joint_correction', 'the joint correction (its U1 = 0 reference and the '
             'chained grid)', bool(steps) and (0, 0) in {
                 tuple(np.round(v[:2] / step).astype(int)) for v in steps[0].voltages},
             'no sphere position keeps the U1 = 0 node' if steps else
             'no sphere position left', report)
    return Plan(steps, report, t)
