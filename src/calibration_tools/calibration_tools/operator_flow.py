"""Calibrating with an operator who places the targets (no rclpy).

A capture plan (:mod:`calibration_tools.capture_plans`) says where each target of the kit
should go and which views to take of it. On a real rig nobody can put a 48 x 36 mm board
inside a 60 x 45 mm view at 650 mm by eye, so the plan becomes a list of
:class:`Placement` requests: a target, a region (centre and extents in V0, with a depth), a
tilt with its tolerance, whether to put it on the visible laser line and whether to hold it
still. After the operator says "placed", the scanner finds the target itself:

1. :func:`search_voltages`: G1 looks at the requested centre, then around it on square
   spirals of whole views, out to the region's extents and well beyond;
2. :func:`locate`: target detection on every search view, partial views included (the
   bright board or sphere against the dark room: its visible part says where to look
   next); a fully detected board gives its pose by PnP with the current model, the
   circle board its pose from its identified circles, the sphere its centre from its
   outline and known radius. Nothing but the target's own detections enters the pose;
3. :func:`check_pose`: the measured pose is within G1 reach, in focus, tilted as asked and
   (for laser targets) on the laser line, or an instruction says what to change and in
   which direction (:class:`Move`);
4. :func:`views_for`: the stage's views planned around the measured pose (G1 aimed with
   the current model), as capture steps;
5. :func:`feature_shift_px`: the views are gated: a check view at the end must show the
   target where the first view did, or the placement is taken again.

The calibration node runs this loop against the ``calibration/instruction`` topic and the
``calibration/operator`` service; a person, a robot program or the application's simulated
operator answers it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import yaml

from calibration_tools import capture_plans as cp
from calibration_tools.board_layout import Checkerboard, CircleBoard, CircleGrid
from calibration_tools.stages import CaptureStep

#: The half extents of the region asked for [m] (:data:`capture_plans.REGION_HALF_EXTENT`).
REGION_HALF_EXTENT = cp.REGION_HALF_EXTENT
#: How precisely a target is put on a visible laser line [m] (across the line).
LASER_LINE_HALF_EXTENT = 0.01
#: Accepted deviation of a target's tilt from the tilt asked for [rad] (a person's +-8 deg
#: with a margin).
TILT_TOLERANCE = math.radians(12.0)
#: The search: G1 aims on a square spiral around the requested centre, whole views apart
#: (the target's bright outline shows in any view that holds part of it, and the part
#: says where its centre is), first one ring, then :data:`WIDE_RINGS` (+-4 views, +-240
#: mm at 650 mm).
SEARCH_STEP_VIEWS = 1.0
SEARCH_RINGS = 1
WIDE_RINGS = 4
#: Search rounds that re-centre on partial views of the target (each one view).
SEARCH_ROUNDS = 4
#: A target has moved between two views of the same G1 voltages when its features shifted
#: more than this [px] (the detections' own scatter is ~0.05 px).
MOVED_PX = 0.75
#: How far [m] the joint correction's sphere may be from the centre asked for: its G1 grid
#: (+-0.1 V, about +-5 mm at 650 mm) must hold the node of the placement before it, so the
#: scanner tells the operator how far to move it until it is this close.
SPHERE_MAX_OFFSET = 0.004
#: A region's depth extent keeps this far [m] inside the focus range, and is at least
#: :data:`MIN_DEPTH_EXTENT` (a person judges depth to about a centimetre).
FOCUS_MARGIN = 0.005
MIN_DEPTH_EXTENT = 0.01
#: Largest |U1| the scanner aims at [V].
MAX_ABS_VOLTAGE = cp.MAX_ABS_VOLTAGE


#: A row's boards must also stand at both ends of its plan along the stripe: each plane is
#: fitted from its own boards first, and its turn about the depth axis is pinned by how far
#: apart along the stripe they stand: a plan's neighbours leave it looser than its two ends,
#: and at G2's end rows that turn shows as a twist of the surface's far corners. A planned
#: board within this fraction of its row's extent from an end stands at that end.
ROW_END_FRACTION = 0.1
#: A person puts a board within about 60 mm along the laser line, which on its own would
#: often bring a row's two ends a third of its extent together: a board at an end that
#: stands more than this fraction of its row's extent in from where it was asked is asked
#: to move out (standing out beyond the end helps).
ROW_END_SLACK = 0.2


# ----------------------------------------------------------------------------- requests
@dataclass
class Placement:
    """One target placement a stage asks for.

    Attributes
    ----------
    stage : str
    index : int
        Placement number within the stage (its views' pose_index).
    kind : str
        ``checkerboard``, ``circle_grid``, ``circle_board`` or ``sphere``.
    target : Checkerboard, CircleGrid, CircleBoard or float
        The kit's target (the sphere's radius [m]).
    V0_T_target : ndarray, shape (4, 4), metres
        Where the plan wants it: its centre and orientation (z into its face).
    views : list of (ndarray shape (n, 4), bool, float)
        The plan's (voltages, laser on, frame rate) of it, for its G2 voltages and counts.
    on_laser_line : bool
        Its centre must lie on the laser sheet (the laser stages, the sphere).
    backdrop_gap : float or None, metres
        The sphere's backdrop this far behind its back (None: none).
    by_robot : bool
        A robot puts it where asked (the cell and hand-eye stages: their robot-reported
        positions are the stage's input), so the plan's own views are taken.
    max_offset : float, metres
        How far from the centre asked for it may be (the joint correction's sphere: its G1
        grid must hold U1 = 0 and share nodes with the positions before it).
    plan_steps : list of CaptureStep
        The plan's steps of it (scene text dropped), taken as they are for ``by_robot``.
    across : int
        The V0 axis across the laser line (1: y, the laser below or above the camera; 0: x,
        beside it; ``reconstructor.planning.stripe_layout``): an ``on_laser_line`` target's
        tight tolerance.
    row_end : tuple or None
        A laser-axis board at an end of its row along the stripe: which end (0 or 1), the
        V0 unit vector towards the row's middle and how far [m] in from its position it may
        stand (:data:`ROW_END_SLACK`); None between the ends (:func:`row_ends`).
    """

    stage: str
    index: int
    kind: str
    target: object
    V0_T_target: np.ndarray
    views: list = field(default_factory=list)
    on_laser_line: bool = False
    backdrop_gap: float | None = None
    by_robot: bool = False
    max_offset: float = math.inf
    plan_steps: list = field(default_factory=list)
    #: depths [m] the target is in focus between (None: not limited)
    focus: tuple | None = None
    across: int = 1
    row_end: tuple | None = None

    @property
    def centre(self) -> np.ndarray:
        return self.V0_T_target[:3, 3].copy()

    @property
    def size(self) -> float:
        """The target's largest dimension [m]."""
        if self.kind == 'sphere':
            return 2.0 * float(self.target)
        if self.kind == 'spheres':
            return 2.0 * float(self.target[0])
        b = self.target
        pitch = b.square if isinstance(b, Checkerboard) else b.pitch
        return float(max(b.cols + 2, b.rows + 2) * pitch)

    def outline(self) -> tuple[float, float]:
        """Width and height [m] of the target as it shows against the room (the board with
        its margins, the sphere's diameter)."""
        b = self.target
        if self.kind in ('sphere', 'spheres'):
            return (self.size, self.size)
        if isinstance(b, Checkerboard):
            return ((b.cols + 3) * b.square, (b.rows + 3) * b.square)
        return ((b.cols + 1) * b.pitch, (b.rows + 1) * b.pitch)

    def spec(self) -> dict:
        """The target's dimensions [m], as the instruction's ``target_spec`` carries them."""
        b = self.target
        if self.kind == 'spheres':
            return {'radius': float(b[0]), 'centres': np.round(b[1], 9).tolist()}
        if self.kind == 'sphere':
            out = {'radius': float(b)}
            if self.backdrop_gap is not None:
                out['backdrop_gap'] = float(self.backdrop_gap)
            return out
        if self.kind == 'checkerboard':
            return {'cols': b.cols, 'rows': b.rows, 'square': float(b.square)}
        if self.kind == 'circle_grid':
            return {'cols': b.cols, 'rows': b.rows, 'pitch': float(b.pitch),
                    'diameter': float(b.diameter)}
        return {'cols': b.cols, 'rows': b.rows, 'pitch': float(b.pitch),
                'sub_pattern': b.sub_pattern, 'small_diameter': float(b.small_diameter),
                'large_diameter': float(b.large_diameter)}

    def extents(self) -> np.ndarray:
        """Half extents of the region along V0 x, y, z [m]."""
        e = np.full(3, REGION_HALF_EXTENT)
        if self.on_laser_line:
            e[self.across] = LASER_LINE_HALF_EXTENT
        if self.focus is not None:  # in depth no farther than the focus range allows
            z = float(self.centre[2])
            room = min(z - self.focus[0], self.focus[1] - z) - FOCUS_MARGIN
            e[2] = min(e[2], max(room, MIN_DEPTH_EXTENT))
        return e

    def tilt(self) -> float:
        """Angle between the wanted normal and the direction to the scanner [rad]."""
        c = self.centre
        n = -self.V0_T_target[:3, 2]
        return float(math.acos(np.clip(n @ (-c / np.linalg.norm(c)), -1.0, 1.0)))


def target_from_spec(kind: str, spec: dict):
    """The kit target an instruction names (``target`` and ``target_spec``).

    Raises
    ------
    ValueError
        An unknown kind or missing dimensions.
    """
    try:
        if kind == 'checkerboard':
            return Checkerboard(int(spec['cols']), int(spec['rows']), float(spec['square']))
        if kind == 'circle_grid':
            return CircleGrid(cols=int(spec['cols']), rows=int(spec['rows']),
                              pitch=float(spec['pitch']), diameter=float(spec['diameter']))
        if kind == 'circle_board':
            return CircleBoard(rows=int(spec['rows']), cols=int(spec['cols']),
                               pitch=float(spec['pitch']),
                               sub_pattern=int(spec['sub_pattern']),
                               small_diameter=float(spec['small_diameter']),
                               large_diameter=float(spec['large_diameter']))
        if kind == 'sphere':
            return float(spec['radius'])
        if kind == 'spheres':
            return float(spec['radius']), np.asarray(spec['centres'], dtype=np.float64)
    except (KeyError, TypeError) as exc:
        raise ValueError(f'target_spec of a {kind}: {exc!r} missing or malformed') from None
    raise ValueError(f"unknown target '{kind}'; one of checkerboard, circle_grid, "
                     'circle_board, sphere')


def _pose(obj) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(obj['pose']['rotation_vector']).as_matrix()
    T[:3, 3] = obj['pose']['translation']
    return T


def _target_of(obj):
    """(kind, target) of a plan's scene object, or None for a backdrop."""
    t = obj['type']
    if t == 'checkerboard':
        nx, ny = obj['squares']
        return 'checkerboard', Checkerboard(int(nx) - 1, int(ny) - 1, float(obj['square_size']))
    if t == 'circle_board':
        cols, rows = obj['grid']
        if int(obj.get('sub_pattern', 1)) == 1:
            return 'circle_grid', CircleGrid(cols=int(cols), rows=int(rows),
                                             pitch=float(obj['pitch']),
                                             diameter=float(obj['small_diameter']))
        return 'circle_board', CircleBoard(rows=int(rows), cols=int(cols),
                                           pitch=float(obj['pitch']),
                                           sub_pattern=int(obj['sub_pattern']),
                                           small_diameter=float(obj['small_diameter']),
                                           large_diameter=float(obj['big_diameter']))
    if t == 'sphere':
        return 'sphere', float(obj['radius'])
    return None


def placements(stage: str, steps, by_robot: bool = False, across: int = 1) -> list[Placement]:
    """The plan's steps as one placement per target (a scene of several boards becomes one
    placement per board, each with its own rows of the scene's scans).

    With ``by_robot`` (the cell and hand-eye stages) every scene is one placement of kind
    ``spheres``: the spheres' centres in the robot's frame, placed by the robot and taken
    with the plan's views. ``across``: the V0 axis across the laser line
    (:attr:`Placement.across`).

    Raises
    ------
    ValueError
        A step without a scene before it, or a scene the rows cannot be split over.
    """
    t = getattr(steps, 'targets', None)
    focus = None if t is None else tuple(f * t.depth for f in cp.FOCUS_RANGE)
    groups: list[tuple[str, list]] = []
    for s in steps:
        if s.scene_yaml is not None:
            groups.append((s.scene_yaml, []))
        elif not groups:
            raise ValueError(f'{stage}: the plan\'s first step places no target')
        groups[-1][1].append(s)
    out: list[Placement] = []
    for text, group in groups:
        objects = yaml.safe_load(text)['objects']
        plain = [dataclasses.replace(s, scene_yaml=None) for s in group]
        if by_robot:
            spheres = [o for o in objects if o['type'] == 'sphere']
            if not spheres:
                raise ValueError(f'{stage}: a scene of the plan holds no sphere')
            centres = np.array([o['pose']['translation'] for o in spheres], dtype=np.float64)
            T = np.eye(4)
            T[:3, 3] = centres.mean(axis=0)
            views = [(np.array(s.voltages), bool(s.laser_on), float(s.frame_rate))
                     for s in group]
            out.append(Placement(stage, len(out), 'spheres',
                                 (float(spheres[0]['radius']), centres), T, views,
                                 by_robot=True, plan_steps=plain))
            continue
        wall = next((o for o in objects if o['type'] == 'plane'), None)
        found = [(o, _target_of(o)) for o in objects]
        found = [(o, kt) for o, kt in found if kt is not None]
        k = len(found)
        for j, (obj, (kind, target)) in enumerate(found):
            views = []
            for s in group:
                n = len(s.voltages)
                if n % k:
                    raise ValueError(f'{stage}: a step of {n} rows cannot be split over '
                                     f'{k} targets')
                m = n // k
                rows = np.asarray(s.voltages)[j * m:(j + 1) * m] if k > 1 else s.voltages
                views.append((np.array(rows), bool(s.laser_on), float(s.frame_rate)))
            T = _pose(obj)
            gap = None
            if kind == 'sphere' and wall is not None:
                gap = float(wall['pose']['translation'][2] - T[2, 3] - target)
            lit = any(v[1] for v in views)
            out.append(Placement(stage, len(out), kind, target, T, views, lit, gap,
                                 max_offset=SPHERE_MAX_OFFSET if kind == 'sphere'
                                 else math.inf, focus=focus, across=across))
    for k, (end, inward, span) in row_ends(out).items():
        if end is not None:
            out[k].row_end = (end, inward, ROW_END_SLACK * span)
    return out


def lit_voltage(p: Placement) -> float | None:
    """The G2 voltage [V] a placement's laser views light it at (their median; None for a
    placement without lit views)."""
    rows = [float(r[3]) for v, lit, _ in p.views if lit for r in v]
    return float(np.median(rows)) if rows else None


def row_key(p: Placement) -> float | None:
    """The row (one plane of its stage's solver) a placement belongs to: its lit G2
    voltage, rounded; None for the placements of stages without rows
    (:attr:`calibration_tools.registry.Stage.rows`)."""
    from calibration_tools.registry import REGISTRY

    if not getattr(REGISTRY.get(p.stage), 'rows', False):
        return None
    u = lit_voltage(p)
    return None if u is None else round(u, 3)


def row_ends(places) -> dict:
    """Each laser-axis placement's end of its row along the stripe, keyed by placement
    index: ``(end, inward, span)`` with ``end`` 0 or 1 for the two ends (None between them,
    or for a row whose boards overlap along it), ``inward`` the V0 unit vector from
    its position towards the row's middle along the stripe and ``span`` [m] the row's
    extent along it (:data:`ROW_END_FRACTION`). The stripe runs along V0 x, or y for a
    laser beside the camera (:attr:`Placement.across`). Empty for the other stages."""
    by_row: dict = {}
    for p in places:
        key = row_key(p)
        if key is not None:
            by_row.setdefault(key, {})[p.index] = p
    out = {}
    for row in by_row.values():
        along = 1 - next(iter(row.values())).across
        t = np.array([q.V0_T_target[along, 3] for q in row.values()], dtype=np.float64)
        mid, span = 0.5 * (t.max() + t.min()), float(np.ptp(t))
        spread = span > min(q.outline()[along] for q in row.values())
        for k, tq in zip(row, t, strict=True):
            end = None
            if spread and tq <= t.min() + ROW_END_FRACTION * span:
                end = 0
            elif spread and tq >= t.max() - ROW_END_FRACTION * span:
                end = 1
            inward = np.zeros(3)
            if end is not None:
                inward[along] = np.sign(mid - tq)
            out[k] = (end, inward, span)
    return out


# ----------------------------------------------------------------------------- instructions
def describe(p: Placement, text_prefix: str = '') -> str:
    """The placement asked for, in words."""
    c = p.centre * 1e3
    if p.kind == 'spheres':
        return (f'{text_prefix}Robot: bring the {len(p.target[1])} sphere(s) of radius '
                f'{p.target[0] * 1e3:g} mm to the positions of target_spec (the robot\'s '
                f'frame, centred at {c[0]:+.0f}, {c[1]:+.0f}, {c[2]:+.0f} mm), hold still, '
                'then press placed.')
    e = p.extents() * 1e3
    b = p.target
    if p.kind == 'checkerboard':
        what = f'the {b.cols + 1} x {b.rows + 1} checkerboard ({b.square * 1e3:g} mm squares)'
    elif p.kind == 'circle_grid':
        what = f'the {b.cols} x {b.rows} circle grid ({b.pitch * 1e3:g} mm pitch)'
    elif p.kind == 'circle_board':
        what = f'the large circle board ({b.pitch * 1e3:g} mm pitch)'
    else:
        what = f'the {2e3 * float(b):g} mm calibration sphere'
    line = (f'{text_prefix}Place {what} with its centre at x {c[0]:+.0f}, y {c[1]:+.0f}, '
            f'depth {c[2]:.0f} mm (within {e[0]:.0f} / {e[1]:.0f} / {e[2]:.0f} mm), '
            f'facing the scanner tilted {math.degrees(p.tilt()):.0f} deg '
            f'(+-{math.degrees(TILT_TOLERANCE):.0f} deg)')
    if p.on_laser_line:
        line += ', its centre on the laser line'
    if p.kind == 'sphere' and p.backdrop_gap is not None:
        line += f', a matte backdrop {p.backdrop_gap * 1e3:.0f} mm behind it'
    return line + '; keep it still until the capture ends, then press placed.'


def instruction_fields(p: Placement, state: str, text: str, move=None, direction: str = ''):
    """The instruction message's placement fields as a dict (the node copies them)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(p.V0_T_target[:3, :3]).as_quat()  # x, y, z, w
    return {'stage': p.stage, 'state': state, 'placement': p.index, 'target': p.kind,
            'target_spec': yaml.safe_dump(p.spec(), default_flow_style=True).strip(),
            'centre': p.centre.tolist(), 'extents': p.extents().tolist(),
            'orientation': [float(x) for x in q], 'tilt': p.tilt(),
            'tilt_tolerance': TILT_TOLERANCE, 'on_laser_line': p.on_laser_line,
            'hold_still': True, 'by_robot': p.by_robot,
            'move': [0.0, 0.0, 0.0] if move is None else [float(x) for x in move],
            'direction': direction, 'text': text}


# ----------------------------------------------------------------------------- the search
def _view_size(model, depth: float) -> tuple[float, float]:
    intr = model.intrinsics
    return intr.width / intr.fx * depth, intr.height / intr.fy * depth


def search_voltages(model, p: Placement, centre=None, rings: int = SEARCH_RINGS,
                    step_views: float = SEARCH_STEP_VIEWS) -> np.ndarray:
    """G1 aims of a search around ``centre`` (default: the requested one), laser off.

    A square spiral on the plane of the requested depth, ``step_views`` views apart, nearest
    first (the large circle board: +-2 whole views first, then +-3 half views); aims out of
    G1 reach are left out (the large circle board, when none is left: the same search
    around a point nearer the axis, at 85, 70 or 55 % of its lateral offset).

    Returns
    -------
    ndarray, shape (n, 4), volts
    """
    from reconstructor.planning import aim_g1

    c = p.centre if centre is None else np.asarray(centre, dtype=np.float64)
    w, h = _view_size(model, float(c[2]))
    if p.kind == 'circle_board':
        # +-2 whole views hold a whole sub-pattern, so most often a large circle wholly in
        # one view; the next round's half-view steps leave none cut by every view's border
        rings, step_views = {0: (2, 1.0), SEARCH_RINGS: (3, 0.5)}.get(
            rings, (rings, step_views))
    step = step_views * np.array([w, h])
    cells = sorted(((i, j) for i in range(-rings, rings + 1) for j in range(-rings, rings + 1)),
                   key=lambda ij: (max(abs(ij[0]), abs(ij[1])), math.atan2(ij[1], ij[0])))
    # the large circle board reaches past G1's range where its plan put it at the edge (its
    # large circles in reach, its centre not): then its part nearer the axis is searched
    shrink = (1.0, 0.85, 0.7, 0.55) if p.kind == 'circle_board' else (1.0,)
    for f in shrink:
        at = np.array([c[0] * f, c[1] * f, c[2]])
        pts = np.array([at + np.array([i * step[0], j * step[1], 0.0]) for i, j in cells])
        u = aim_g1(model, pts, max_abs_u=MAX_ABS_VOLTAGE)
        u = u[np.isfinite(u).all(axis=1) & (np.abs(u) <= MAX_ABS_VOLTAGE).all(axis=1)]
        if len(u):
            break
    return np.column_stack([u, np.zeros((len(u), 2))])


@dataclass
class Located:
    """Where the search found the target.

    Attributes
    ----------
    V0_T_target : ndarray, shape (4, 4) or None
        Measured pose (centre and orientation; the sphere: its centre, axes of V0); None
        when only partial views were seen.
    look_at : ndarray, shape (3,) or None
        Where to look next (the partial views' estimate of its centre), metres.
    seen : int
        Search views that showed (part of) the target.
    note : str
    check_voltages : ndarray, shape (4,) or None
        The search view the pose came from: the motion gate looks there again after the
        capture and compares ``features``.
    features : ndarray, shape (n, 2) or None
        The target's features in that view, pixels.
    stamp : float or None
        That view's image stamp [s] (what ``features`` were detected in).
    """

    V0_T_target: np.ndarray | None
    look_at: np.ndarray | None
    seen: int
    note: str
    check_voltages: np.ndarray | None = None
    features: np.ndarray | None = None
    stamp: float | None = None


def _bright_blob(img, min_area: int = 400, half_px=None):
    """The largest bright region of a laser-off frame (a target against the room, or the
    sphere against its darker backdrop): (centre (u, v), area px, touches the border,
    radius px of its outline's enclosing circle, centroid (u, v) of the region) or None. A
    region cut by the border has its centre extrapolated with the target's half size
    ``half_px`` (u, v) when given.

    Otsu's threshold splits the frame in two; a region counts only when the two sides
    differ clearly (their means 1.5 x apart and 25 grey levels): an empty view is noise.
    """
    import cv2

    from calibration_tools.small_board import as_uint8_image

    g = cv2.GaussianBlur(as_uint8_image(np.asarray(img)), (5, 5), 0)
    level, mask = cv2.threshold(g, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    hi, lo = g[mask > 0], g[mask == 0]
    if hi.size < min_area or lo.size == 0:
        return None
    m_hi, m_lo = float(hi.mean()), float(lo.mean())
    if m_hi < 1.5 * m_lo or m_hi - m_lo < 25.0:
        return None
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask)
    if n < 2:
        return None
    i = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    area = int(stats[i, cv2.CC_STAT_AREA])
    if area < min_area:
        return None
    x, y, bw, bh = (int(stats[i, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    H, W = g.shape
    border = x <= 1 or y <= 1 or x + bw >= W - 1 or y + bh >= H - 1
    contours, _ = cv2.findContours((labels == i).astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    (cx, cy), r = cv2.minEnclosingCircle(max(contours, key=len))
    centroid = np.array(cents[i], dtype=np.float64)
    centre = np.array([cx, cy]) if not border else centroid
    if border:  # where the whole outline's centre lies, from the sides it shows
        centre = _extrapolated_centre(centroid, (x, y, bw, bh), (W, H), half_px)
    return centre, area, border, float(r), centroid


def _extrapolated_centre(centroid, box, size, half_px):
    """The centre of a target cut by the image border: along an axis where the visible part
    touches one border only, half the target's size [px] in from its far side, and at least
    15 % of the image beyond the middle towards that border (a turned target shows taller
    than its size: the next look must still move towards the part not seen)."""
    out = np.array(centroid, dtype=np.float64)
    for k in range(2):
        lo, extent, n = box[k], box[k + 2], size[k]
        at_lo, at_hi = lo <= 1, lo + extent >= n - 1
        if at_lo and not at_hi:
            if half_px is not None:
                out[k] = lo + extent - half_px[k]
            out[k] = min(out[k], 0.35 * n)
        elif at_hi and not at_lo:
            if half_px is not None:
                out[k] = lo + half_px[k]
            out[k] = max(out[k], 0.65 * n)
    return out


def _ray_point(model, u, uv, depth: float) -> np.ndarray:
    """The V0 point at ``depth`` on the ray of pixel ``uv`` seen at G1 voltages ``u``."""
    import cv2

    from reconstructor.model import v0_T_v

    intr = model.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    xy = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(1, 1, 2), K,
                             np.asarray(intr.dist, np.float64)).reshape(2)
    T = np.asarray(v0_T_v(model, float(u[0]), float(u[1])))
    o, d = T[:3, 3], T[:3, :3] @ np.array([xy[0], xy[1], 1.0])
    s = (depth - o[2]) / d[2] if abs(d[2]) > 1e-9 else 0.0
    return o + s * d


def _board_pose(model, board, img, u):
    """V0_T_board (origin at the pattern's centre, z into the board) of a laser-off view
    with the whole pattern detected, and its features; None when not detected."""
    import cv2

    from calibration_tools.intrinsics import detect_target
    from reconstructor.model import v0_T_v

    pts = detect_target(img, board, fast=True)
    if pts is None:
        return None
    obj = board.object_points()
    obj = obj - obj.mean(axis=0)
    intr = model.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    ok, rvec, tvec = cv2.solvePnP(obj, pts.reshape(-1, 1, 2), K,
                                  np.asarray(intr.dist, np.float64),
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    V_T_B = np.eye(4)
    V_T_B[:3, :3] = cv2.Rodrigues(rvec)[0]
    V_T_B[:3, 3] = tvec.ravel()
    if V_T_B[2, 2] < 0:  # z into the board, away from the viewer: flip about x
        V_T_B[:3, :3] = V_T_B[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return np.asarray(v0_T_v(model, float(u[0]), float(u[1]))) @ V_T_B, pts


def _sphere_pose(model, radius, img, u):
    """V0_T_target (the sphere's centre, V0 axes) from its outline in a laser-off view, or
    None when it is cut by the image border."""
    blob = _bright_blob(img, min_area=50)
    if blob is None or blob[2]:
        return None
    uv, _, _, r_px, _ = blob
    intr = model.intrinsics
    depth_along = intr.fx * radius / max(r_px, 1e-6)
    from reconstructor.model import v0_T_v

    T = np.asarray(v0_T_v(model, float(u[0]), float(u[1])))
    ray = np.array([(uv[0] - intr.cx) / intr.fx, (uv[1] - intr.cy) / intr.fy, 1.0])
    p_v = ray / np.linalg.norm(ray) * math.hypot(depth_along, radius)
    out = np.eye(4)
    out[:3, 3] = T[:3, :3] @ p_v + T[:3, 3]
    return out


def locate(model, p: Placement, views) -> Located:
    """Find the target in search views (laser off): its measured pose, or where to look next.

    The target's bright outline against the room is found in every view (cheap); the full
    detection (corners, circles, the sphere's whole outline) runs on the two views whose
    outline is nearest the image centre. Views with only a part of it give where to look
    next: their outlines' centroids, weighted by area, at the requested depth.

    Parameters
    ----------
    model : RigModel
        The current model (aims and back-projection).
    p : Placement
    views : sequence of CaptureView
        The search's frames (their reported voltages are used).
    """
    views = [v for v in views if not v.laser_on]
    if p.kind == 'circle_board':
        return _locate_circle_board(model, p, views)
    intr = model.intrinsics
    centre_px = np.array([intr.width / 2.0, intr.height / 2.0])
    half = np.array(p.outline()) / 2.0 / float(p.centre[2])
    blobs = []
    for v in views:
        blob = _bright_blob(v.image, min_area=50 if p.kind == 'sphere' else 400,
                            half_px=(half[0] * intr.fx, half[1] * intr.fy))
        if blob is not None:
            blobs.append((float(np.linalg.norm(blob[0] - centre_px)), v, blob))
    if not blobs:
        return Located(None, None, 0, 'not seen in any search view')
    blobs.sort(key=lambda b: b[0])
    for _, v, blob in blobs[:2]:
        u = np.asarray(v.voltages, dtype=np.float64)
        if p.kind == 'sphere':
            T = _sphere_pose(model, float(p.target), v.image, u[:2])
            if T is not None:
                return Located(T, None, len(blobs), 'sphere outline seen whole', u,
                               blob[4][None], float(v.stamp))
            continue
        got = _board_pose(model, p.target, v.image, u[:2])
        if got is not None:
            return Located(got[0], None, len(blobs), 'whole pattern detected', u, got[1],
                           float(v.stamp))
    w = np.array([b[2][1] for b in blobs], dtype=np.float64)
    pts = np.array([_ray_point(model, np.asarray(v.voltages)[:2], b[0], float(p.centre[2]))
                    for _, v, b in blobs])
    look = (w[:, None] * pts).sum(axis=0) / w.sum()
    return Located(None, look, len(blobs), f'{len(blobs)} partial view(s) of it')


def _locate_circle_board(model, p: Placement, views) -> Located:
    """The large circle board's pose from its identified circles (its large circles fix its
    lattice position; the request only seeds the search, within half a sub-pattern)."""
    from calibration_tools.board_identify import identify_views
    from calibration_tools.circle_board import detect_circles
    from calibration_tools.small_board import as_uint8_image

    dets, U, stamps = [], [], []
    for v in views:
        d = detect_circles(as_uint8_image(np.asarray(v.image)), dark_circles=True)
        if len(d) >= 4:
            dets.append(d)
            U.append(np.asarray(v.voltages, dtype=np.float64)[:2])
            stamps.append(float(v.stamp))
    if len(dets) < 2:
        return Located(None, None, len(dets), f'{len(dets)} search view(s) show circles')
    try:
        ident = identify_views(dets, np.array(U), model, p.target, p.V0_T_target,
                               refine_mirrors=False, refine_theta0=False, max_rounds=2,
                               min_anchors=1)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        return Located(None, None, len(dets), f'circles seen but not identified: {exc}')
    ok = sum(v.accepted for v in ident.views)
    if ok < 2:
        return Located(None, None, len(dets), f'circles seen, {ok} view(s) identified')
    k = int(np.argmax([len(d) for d in dets]))
    return Located(np.asarray(ident.board_poses[0]), None, len(dets),
                   f'{ok} of {len(dets)} search views identified',
                   np.array([U[k][0], U[k][1], 0.0, 0.0]), dets[k].centres, stamps[k])


#: Sub-patterns the large circle board's edge probe (:func:`pin_board_lattice`) moves at
#: most, each way along each of its axes: a person puts it within about 60 mm of where asked,
#: two sub-patterns of the smallest board (7 x 5 mm).
PIN_PERIODS = 3


def _edge_reading(model, B, T, axis: int, side: float, view) -> tuple[str, int]:
    """What one view aimed between the board's last circles along an edge and the lattice
    sites past them (``axis`` 0: x, 1: y; ``side`` +-1), as the pose ``T`` puts them, shows:
    ``('edge', k)`` when the circles end inside the view (the next site would be whole in it
    and holds none), ``k`` whole sub-patterns past where ``T`` puts the edge; ``('beyond',
    0)`` when circles stand past the last ones (the board goes on); ``('none', 0)`` without
    circles (it ends sooner); ``('', 0)`` when unclear. Read on the board's plane through the
    model: its error moves the circles and the view's border alike, by far less than a
    pitch."""
    from calibration_tools.board_geometry import pixels_to_board
    from calibration_tools.circle_board import detect_circles
    from calibration_tools.small_board import as_uint8_image

    img = np.asarray(view.image)
    d = detect_circles(as_uint8_image(img), dark_circles=True)
    if len(d) == 0:
        return 'none', 0
    u = np.asarray(view.voltages, dtype=np.float64)
    h, w = img.shape[:2]
    border = np.array([[x, y] for x in np.linspace(0, w - 1, 9) for y in np.linspace(0, h - 1, 7)
                       if x in (0, w - 1) or y in (0, h - 1)])
    far = pixels_to_board(model, border, u[0], u[1], T)[:, axis] * side
    xy = pixels_to_board(model, d.centres, u[0], u[1], T)
    x = xy[np.isfinite(xy).all(axis=1), axis] * side
    if not len(x) or not np.isfinite(far).any():
        return '', 0
    last = ((B.cols if axis == 0 else B.rows) - 1) / 2.0 * B.pitch
    top = float(x.max())
    if top > last + 0.5 * B.pitch:
        return 'beyond', 0
    if top + B.pitch + B.large_diameter < float(np.nanmax(far)):
        return 'edge', int(round((top - last) / (B.sub_pattern * B.pitch)))
    return '', 0


def pin_board_lattice(model, p: Placement, T, look):
    """The large circle board's pose with its lattice pinned by its edges: ``(V0_T_target,
    note)``.

    Its large circles fix the circles' labels only modulo the sub-pattern (a placement
    farther than half a sub-pattern from where asked is read a whole number of sub-patterns
    off, and the views planned around it miss the board). The board's edges fix them: one
    view aimed half a pitch past the middle of an edge, as the pose puts it, shows circles
    past it (the board reaches further: the pose moves a sub-pattern out), none (it ends
    sooner: a sub-pattern in) or the edge. Along each axis the edge on the side nearer G1's
    centre is probed first, then the other; an axis whose edges no view shows keeps its pose
    (said in the note).

    ``look`` takes laser-off frames at G1 voltages (as for :func:`search`).
    """
    from reconstructor.planning import aim_g1

    B = p.target
    period = B.sub_pattern * B.pitch
    T = np.array(T, dtype=np.float64)
    notes = []
    for axis in (0, 1):
        half = ((B.cols if axis == 0 else B.rows) - 1) / 2.0 * B.pitch
        e = T[:3, axis]
        sides = sorted((1.0, -1.0), key=lambda s: float(np.linalg.norm(
            (T[:3, 3] + s * half * e)[:2])))
        moved, pinned = 0, False
        for side in sides:
            for _ in range(2 * PIN_PERIODS + 1):
                at = T[:3, 3] + side * (half + 0.5 * B.pitch) * e
                g1 = aim_g1(model, at, max_abs_u=MAX_ABS_VOLTAGE)
                if not np.all(np.isfinite(g1)) or np.abs(g1).max() > MAX_ABS_VOLTAGE:
                    break
                got = look(np.array([[g1[0], g1[1], 0.0, 0.0]]))
                reading, k = _edge_reading(model, B, T, axis, side, got[0]) if got else ('', 0)
                step = {'beyond': 1, 'none': -1, 'edge': k}.get(reading, 0)
                if reading and abs(moved + side * step) <= PIN_PERIODS:
                    T[:3, 3] += side * step * period * e
                    moved += int(side * step)
                    if reading == 'edge':
                        pinned = True
                        break
                else:
                    break
            if pinned:
                break
        if moved:
            notes.append(f'{"xy"[axis]} moved {moved:+d} sub-pattern(s) by its edge')
        if not pinned:
            notes.append(f'{"xy"[axis]} edge not seen')
    return T, '; '.join(notes)


def search(model, p: Placement, targets: cp.Targets, look, note=None, look_lit=None):
    """Find a placed target: ``(Located, None)`` when it can be captured, else
    ``(Located or None, Move)`` saying what the operator must change.

    One view at the centre asked for; while only parts of the target show, one view where
    they put its centre (:data:`SEARCH_ROUNDS` at most); when nothing shows, a ring of
    views around it, then :data:`WIDE_RINGS` rings (:func:`search_voltages`).

    Parameters
    ----------
    look : callable ``(voltages (n, 4)) -> list of CaptureView``
        Takes laser-off frames at G1 voltages (the node records them; tests run the
        simulator).
    note : callable ``(voltages, Located)``, optional
        Told every look's outcome (the node logs it).
    look_lit : callable ``(voltages (n, 4)) -> list of CaptureView``, optional
        Takes laser-on frames: a sphere found is then checked to carry the laser line
        (:func:`stripe_on_sphere`).
    """
    centre, rings = p.centre, 0
    widen = iter((SEARCH_RINGS, WIDE_RINGS))
    for _ in range(SEARCH_ROUNDS + 3):
        volts = search_voltages(model, p, centre, rings)
        if not len(volts):
            return None, reach_move(model, p, centre, 'no view of the search within G1 reach')
        loc = locate(model, p, look(volts))
        if loc.V0_T_target is not None and p.kind == 'circle_board':
            T, why = pin_board_lattice(model, p, loc.V0_T_target, look)
            loc = dataclasses.replace(loc, V0_T_target=T,
                                      note=loc.note + (f'; {why}' if why else ''))
        if note is not None:
            note(volts, loc)
        if loc.V0_T_target is not None:
            move = check_pose(model, p, loc.V0_T_target, targets)
            if move is None and p.kind == 'sphere' and look_lit is not None:
                off = look(loc.check_voltages[None])
                u = loc.check_voltages.copy()
                u[3] = float(np.median([r[3] for v, lit, _ in p.views if lit for r in v]))
                move = stripe_on_sphere(model, p, loc.V0_T_target, off[0].image,
                                        look_lit(u[None])[0].image)
            return loc, move
        if loc.look_at is not None:
            move = reach_move(model, p, loc.look_at)
            if move is not None:
                return loc, move
            centre, rings = loc.look_at, 0
        else:
            rings = next(widen, None)
            if rings is None:
                break
    return None, not_found(p)


# ----------------------------------------------------------------------------- checks
def stripe_on_sphere(model, p: Placement, T, off_image, lit_image) -> Move | None:
    """None when the laser line crosses the sphere's middle in a lit frame (its stripe
    pixels reach within half a radius of the outline's centre), else the move onto the line:
    across the stripe (V0 y for a laser below or above the camera, x beside it) by where the
    stripe runs on the backdrop beside it (the sphere's own outline and the stripe; the
    model's laser plane gives only the stripe's direction and the sheet's slope)."""
    blob = _bright_blob(off_image, min_area=50)
    if blob is None:
        return not_found(p)
    (cu, cv), r = blob[4], blob[3]
    lit = np.asarray(lit_image, np.float64)  # a laser frame: the stripe on a dark scene
    level = max(30.0, 0.5 * float(lit.max()))
    vs, us = np.nonzero(lit > level)
    if vs.size == 0:
        return Move('off_laser_line', np.zeros(3), 'the laser line is not on the sphere or '
                    'the backdrop in view: put the sphere on the laser line')
    d = np.hypot(us - cu, vs - cv)
    if np.count_nonzero(d < 0.5 * r) >= 5:
        return None
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import stripe_layout

    # the line runs dy [m] across the stripe from the sphere's centre (below it for a stripe
    # along the rows); it must cross the sphere where it was asked for, so the sphere goes
    # nearer or farther along the sheet's slope
    k = stripe_layout(model).across
    f = model.intrinsics.fy if k == 1 else model.intrinsics.fx
    dy = (float(np.median(vs if k == 1 else us)) - (cv if k == 1 else cu)) * float(T[2, 3]) / f
    u2 = float(np.median([r[3] for v, lit, _ in p.views if lit for r in v]))
    plane = np.asarray(laser_plane_v0(model, u2), dtype=np.float64)
    b, c = plane[k], plane[2]
    slope = -c / b if abs(b) > 1e-9 else 0.0  # d(across)/dz of the sheet along the stripe
    move = np.zeros(3)
    if abs(slope) > 0.2:
        move[2] = -dy / slope
    else:
        move[k] = dy
    return Move('off_laser_line', move, 'the laser line misses the sphere\'s middle: '
                + _direction_words(move))



@dataclass
class Move:
    """What the operator must change: ``reason`` (not_found, out_of_reach, too_near,
    too_far, off_centre, off_row_end, too_tilted, off_laser_line), the displacement [m] in
    V0 and the words."""

    reason: str
    move: np.ndarray
    words: str


def _direction_words(d) -> str:
    """A V0 displacement in words (x right and y down as the scanner sees it, z away)."""
    names = (('right (+x)', 'left (-x)'), ('down (+y)', 'up (-y)'), ('away (+z)', 'nearer (-z)'))
    parts = [f'{abs(v) * 1e3:.0f} mm {names[k][0 if v > 0 else 1]}'
             for k, v in enumerate(d) if abs(v) >= 0.001]
    return 'move it ' + ' and '.join(parts) if parts else 'move it slightly'


def check_pose(model, p: Placement, T, targets: cp.Targets) -> Move | None:
    """None when the measured pose ``T`` can be captured for ``p``, else what to change."""
    from reconstructor.planning import aim_g1

    c = T[:3, 3]
    lo, hi = (f * targets.depth for f in cp.FOCUS_RANGE)
    if c[2] < lo:
        d = np.array([0.0, 0.0, p.centre[2] - c[2]])
        return Move('too_near', d, f'too near ({c[2] * 1e3:.0f} mm, focus from '
                                   f'{lo * 1e3:.0f} mm): ' + _direction_words(d))
    if c[2] > hi:
        d = np.array([0.0, 0.0, p.centre[2] - c[2]])
        return Move('too_far', d, f'too far ({c[2] * 1e3:.0f} mm, focus to '
                                  f'{hi * 1e3:.0f} mm): ' + _direction_words(d))
    if p.kind == 'circle_board':  # in reach where its views can be identified: as planned
        from calibration_tools.dynamic_camera import anchor_voltages

        reach = len(anchor_voltages(model, p.target, T, max_abs_u=MAX_ABS_VOLTAGE)) >= 2
    else:
        g1 = aim_g1(model, c, max_abs_u=MAX_ABS_VOLTAGE)
        reach = bool(np.all(np.isfinite(g1))) and np.abs(g1).max() <= MAX_ABS_VOLTAGE
    if not reach:
        d = p.centre - c
        return Move('out_of_reach', d, 'out of G1 reach: ' + _direction_words(d))
    off = c - p.centre
    if np.linalg.norm(off[:2]) > p.max_offset:
        d = np.array([-off[0], -off[1], 0.0])
        return Move('off_centre', d, f'{np.linalg.norm(off[:2]) * 1e3:.0f} mm from the '
                    f'position asked for (within {p.max_offset * 1e3:.0f} mm): '
                    + _direction_words(d))
    if p.row_end is not None:
        _, inward, slack = p.row_end
        short = float(off @ inward)
        if short > slack:
            d = -short * inward
            return Move('off_row_end', d, f'{short * 1e3:.0f} mm in from the end of the '
                        f'laser line asked for (within {slack * 1e3:.0f} mm): '
                        + _direction_words(d))
    if p.kind != 'sphere':
        n = -T[:3, 2]
        want = -p.V0_T_target[:3, 2]
        ang = math.acos(float(np.clip(n @ want, -1.0, 1.0)))
        if ang > TILT_TOLERANCE and p.kind != 'circle_board':
            return Move('too_tilted', np.zeros(3),
                        f'turned {math.degrees(ang):.0f} deg from the tilt asked for '
                        f'(+-{math.degrees(TILT_TOLERANCE):.0f} deg): turn it to face the '
                        'scanner as asked')
    # the sphere: the position asked for is on the sheet, and it is kept within millimetres
    # of it (its depth from its outline is too coarse for this check)
    if p.on_laser_line and p.kind != 'sphere':
        miss = _laser_miss(model, p, T)
        if miss is not None:
            return Move('off_laser_line', miss, 'not on the laser line: '
                        + _direction_words(miss))
    return None


def _laser_rows(p: Placement) -> list[float]:
    return sorted({round(float(r[3]), 6) for v, lit, _ in p.views if lit for r in v})


def _laser_miss(model, p: Placement, T) -> np.ndarray | None:
    """The move onto the laser line [m] when the stripe of the placement's G2 voltages
    misses the measured board's middle (a quarter of its smaller side)."""
    from reconstructor.model import laser_plane_v0

    rows = _laser_rows(p)
    if not rows:
        return None
    u = float(np.mean(rows))
    pi = np.asarray(laser_plane_v0(model, u), dtype=np.float64)
    c = T[:3, 3].copy()
    b = p.target
    tol = 0.25 * min(b.cols, b.rows) * (b.square if isinstance(b, Checkerboard) else b.pitch)
    dist = float(pi[:3] @ c + pi[3]) / float(np.linalg.norm(pi[:3]))
    if abs(dist) <= tol:
        return None
    # move across the laser line (V0 y, or x for a laser beside the camera) onto the sheet
    k = p.across
    ny = pi[k] / np.linalg.norm(pi[:3])
    move = np.zeros(3)
    move[k] = -dist / ny if abs(ny) > 0.2 else 0.0
    return move


# ----------------------------------------------------------------------------- views
def views_for(model, p: Placement, T, targets: cp.Targets, seed: int = 0) -> list[CaptureStep]:
    """The stage's capture steps for the target measured at ``T``, G1 aimed with ``model``.

    - a small board (intrinsics, laser stages): G1 at its centre, laser off, then lit at the
      plan's G2 voltages;
    - the circle board: the reachable large circles, then random points within 16.5 pitches
      of its centre, as many views as the plan's;
    - the sphere: the plan's G1 grid nodes (they chain the positions' corrections), lit at
      the plan's G2 voltage; nodes whose view would cut the measured sphere dropped.

    Raises
    ------
    ValueError
        Nothing of it can be viewed within G1 reach.
    """
    from reconstructor.planning import aim_g1

    c = T[:3, 3]
    pose = p.index
    if p.kind in ('checkerboard', 'circle_grid'):
        g1 = aim_g1(model, c, max_abs_u=MAX_ABS_VOLTAGE)
        if not np.all(np.isfinite(g1)):
            raise ValueError('its centre is out of G1 reach')
        out = []
        for volts, lit, rate in p.views:
            V = np.array(volts, dtype=np.float64)
            V[:, 0], V[:, 1] = g1[0], g1[1]
            out.append(CaptureStep(pose, None, V, lit, frame_rate=rate,
                                   note=f'{p.stage}: placement {pose}, measured at '
                                        f'{cp._mm(c)}' + (', lit' if lit else '')))
        return out
    if p.kind == 'circle_board':
        from calibration_tools.dynamic_camera import anchor_voltages

        n = sum(len(v) for v, _, _ in p.views)
        B = p.target
        aims = anchor_voltages(model, B, T, max_abs_u=MAX_ABS_VOLTAGE)[:3]
        rng = np.random.default_rng(seed + pose)
        reach = 16.5 * B.pitch
        pts = np.column_stack([rng.uniform(-reach, reach, (6 * n, 2)), np.zeros(6 * n)])
        more = aim_g1(model, pts @ T[:3, :3].T + T[:3, 3], max_abs_u=MAX_ABS_VOLTAGE)
        more = more[np.isfinite(more).all(axis=1)][: max(n - len(aims), 0)]
        u = np.vstack([aims.reshape(-1, 2), more])
        if len(u) < 3:
            raise ValueError('fewer than 3 views of it within G1 reach')
        return [CaptureStep(pose, None, np.column_stack([u, np.zeros((len(u), 2))]), False,
                            note=f'{p.stage}: circle board placement {pose} measured at '
                                 f'{cp._mm(c)}, {len(u)} G1 positions')]
    # the sphere: the plan's G1 grid nodes (one global grid, chosen so that neighbouring
    # positions share nodes and their corrections chain), kept where the sphere measured
    # within SPHERE_MAX_OFFSET of its position asked for is wholly in view
    V = np.vstack([v for v, lit, _ in p.views if lit])
    rate = next(r for _, lit, r in p.views if lit)
    r_px = model.intrinsics.fx * float(p.target) / max(float(c[2]), 1e-6)
    keep = np.array([cp.check_view(model, targets, c[None], centre=c, g1=v[:2],
                                   radius_px=r_px) is None for v in V], dtype=bool)
    if keep.sum() < cp.MIN_SPHERE_NODES:
        raise ValueError(f'{int(keep.sum())} G1 grid node(s) see the whole sphere, '
                         f'{cp.MIN_SPHERE_NODES} needed')
    return [CaptureStep(pose, None, V[keep], True, frame_rate=rate,
                        note=f'{p.stage}: sphere placement {pose} measured at {cp._mm(c)}, '
                             f'{int(keep.sum())} of the plan\'s {len(V)} G1 grid nodes')]


def check_step(p: Placement, voltages) -> CaptureStep:
    """One laser-off frame at ``voltages`` (the search view the pose came from), taken
    after the placement's views: the gate that catches a target moved during capture
    (:func:`feature_shift_px` against that search view's features)."""
    v = np.asarray(voltages, dtype=np.float64).reshape(4).copy()
    v[2:] = 0.0
    return CaptureStep(p.index, None, v[None], False, frame_rate=50.0,
                       note=f'{p.stage}: placement {p.index}, check view')


def features(p: Placement, image) -> np.ndarray | None:
    """The target's features in a laser-off view (pixels, shape (n, 2)), for the motion
    gate: the board's pattern, the circles, the sphere's outline centre."""
    from calibration_tools.circle_board import detect_circles
    from calibration_tools.small_board import as_uint8_image

    if p.kind in ('checkerboard', 'circle_grid'):
        from calibration_tools.intrinsics import detect_target

        return detect_target(image, p.target, fast=True)
    if p.kind == 'circle_board':
        d = detect_circles(as_uint8_image(np.asarray(image)), dark_circles=True)
        return d.centres if len(d) >= 4 else None
    blob = _bright_blob(image, min_area=50)
    return None if blob is None else blob[4][None]


#: The reprojection gate: a board view whose detected pattern, fitted by its own pose with
#: the current model's camera, leaves an RMS above this [px] is rejected (the intrinsics
#: stage's own limit for a view, ``calibrate_intrinsics(max_view_rms_px)``): a corner
#: detected on the wrong square, a warped or partly covered board.
REPROJECTION_MAX_PX = 1.0
#: The motion-blur gate: a view whose target edges spread over more than this many times
#: those of the still check view taken after it (same target, same depth, laser off) is
#: rejected: the target moved during the exposure (an optical blur is the same in both).
#: The small boards only, seen whole at the check view's depth: the large circle board's
#: raster views see parts of it up to ~0.2 m nearer or farther than the check view does
#: (740 mm tilted by tens of degrees), and focus alone spreads their edges by up to this
#: ratio (a drawn rig's side placement: 0.91-1.52 x over its 24 still views); there the
#: motion gate and the stage's own fit of every circle judge.
BLUR_RATIO_MAX = 1.5
#: The targets the motion-blur gate applies to.
BLUR_GATED = ('checkerboard', 'circle_grid')


def reprojection_rms_px(model, p: Placement, pts) -> float:
    """RMS [px] of a board view's detected pattern ``pts`` about its own best pose (PnP with
    the model's camera); NaN for targets without an identified pattern in one view (the
    circle board, the sphere)."""
    import cv2

    if p.kind not in ('checkerboard', 'circle_grid') or pts is None or len(pts) < 6:
        return math.nan
    obj = p.target.object_points()
    if len(obj) != len(pts):
        return math.nan
    intr = model.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    dist = np.asarray(intr.dist, np.float64)
    img = np.asarray(pts, np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return math.inf
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((proj - img.reshape(-1, 2)) ** 2, axis=1))))


def edge_spread_px(image, pts=None) -> float:
    """How many pixels the target's edges spread over: its contrast over the steepest
    gradients (the 99th percentile) within the box around ``pts`` (the whole frame when
    None), the larger of the two image directions (a motion widens the edges across it
    only). A still, focused target: about 2 px."""
    g = np.asarray(image, dtype=np.float64)
    if pts is not None and len(pts):
        q = np.asarray(pts, np.float64).reshape(-1, 2)
        pad = 10
        x0, y0 = (max(int(v) - pad, 0) for v in q.min(axis=0))
        x1, y1 = (int(v) + pad for v in q.max(axis=0))
        g = g[y0:y1 + 1, x0:x1 + 1]
    if g.shape[0] < 3 or g.shape[1] < 3:
        return math.nan
    contrast = float(np.percentile(g, 98) - np.percentile(g, 2))
    spread = 0.0
    for grad in np.gradient(g):  # along rows and columns: a motion blurs the edges across it
        steep = float(np.percentile(np.abs(grad), 99))
        spread = max(spread, contrast / steep if steep > 0 else math.inf)
    return spread


def gate_view(model, p: Placement, image, still_spread: float):
    """The gates of one laser-off view of a placement: ``(features, reason, rms)`` with
    reason '' when kept, else ``reprojection_outlier`` or ``motion_blur`` (``not_detected``
    when the target's features are not found in it); ``rms`` is the board's reprojection
    RMS [px] (NaN for the circle board and the sphere)."""
    pts = features(p, image)
    if pts is None or len(pts) == 0:
        return None, 'not_detected', math.nan
    rms = reprojection_rms_px(model, p, pts)
    if rms > REPROJECTION_MAX_PX:
        return pts, 'reprojection_outlier', rms
    if p.kind in BLUR_GATED and math.isfinite(still_spread) and still_spread > 0:
        if edge_spread_px(image, pts) > BLUR_RATIO_MAX * still_spread:
            return pts, 'motion_blur', rms
    return pts, '', rms


def feature_shift_px(a, b) -> float:
    """Median shift [px] between two feature sets of one target seen at the same voltages
    (nearest neighbours); inf when either is missing."""
    if a is None or b is None or len(a) == 0 or len(b) == 0:
        return math.inf
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2).min(axis=1)
    return float(np.median(d))


def reach_move(model, p: Placement, seen_at, why: str = '') -> Move | None:
    """The move that brings a target seen (in part) at ``seen_at`` back within G1 reach,
    towards the centre asked for; None when ``seen_at`` is within reach (and ``why`` empty)."""
    from reconstructor.planning import aim_g1

    c = np.asarray(seen_at, dtype=np.float64)
    g1 = aim_g1(model, c, max_abs_u=MAX_ABS_VOLTAGE)
    if not why and np.all(np.isfinite(g1)) and np.abs(g1).max() <= MAX_ABS_VOLTAGE:
        return None
    d = p.centre - c
    d[2] = 0.0
    return Move('out_of_reach', d, (why or 'out of G1 reach') + ': ' + _direction_words(d))


def not_found(p: Placement) -> Move:
    """The instruction when no search view showed the target."""
    return Move('not_found', np.zeros(3),
                'not found in the region asked for: check that it is there, faces the '
                'scanner and is lit, then press placed again')


#: Where the calibration node writes the measured target poses of a capture, beside its
#: bags (``{pose_index: V0_T_target}``), for the stages that use them (dynamic_camera).
MEASURED_POSES = 'measured_poses.yaml'


def write_measured_poses(path, poses: dict) -> None:
    """Write ``{pose_index: V0_T_target (4, 4)}`` as YAML."""
    from pathlib import Path

    text = yaml.safe_dump({'frame': 'v0', 'unit': 'm', 'note': 'target poses measured from '
                           'their own detections during capture (V0_T_target)',
                           'poses': {int(k): np.asarray(v, dtype=np.float64).tolist()
                                     for k, v in poses.items()}}, sort_keys=False)
    Path(path).write_text(text)


def read_measured_poses(bags) -> dict | None:
    """The measured poses written beside ``bags`` (all of one run folder), or None."""
    from calibration_tools.stage_runner import expand_bag_dirs

    folders = {b.parent for b in expand_bag_dirs(bags)}
    found = [f / MEASURED_POSES for f in folders if (f / MEASURED_POSES).is_file()]
    if len(found) != 1 or len(folders) != 1:
        return None
    data = yaml.safe_load(found[0].read_text()) or {}
    try:
        out = {int(k): np.asarray(v, dtype=np.float64).reshape(4, 4)
               for k, v in (data.get('poses') or {}).items()}
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{found[0]}: malformed poses ({exc})') from None
    for k, T in out.items():
        if not np.all(np.isfinite(T)):
            raise ValueError(f'{found[0]}: pose {k} is not finite')
    return out or None


def new_stats(planned: int) -> dict:
    """A capture's operator figures (the node fills them in)."""
    return {'planned': int(planned), 'placed': 0, 'skipped': 0, 'undone': 0,
            'instructions': 0, 'views': 0, 'search_scans': 0, 'search_views': 0,
            'refused': {}, 'rejected': {}, 'seconds': 0.0, 'done_early': False,
            'placements_max': int(planned), 'targets_met': False}


def stats_line(stats: dict) -> str:
    """One line of a capture's operator figures."""
    ref = ', '.join(f'{k} {v}' for k, v in stats['refused'].items()) or 'none'
    rej = ', '.join(f'{k} {v}' for k, v in stats['rejected'].items()) or 'none'
    return (f"{stats['placed']}/{stats['planned']} placements kept, {stats['skipped']} "
            f"skipped, {stats['instructions']} instructions, {stats['search_views']} search "
            f"views; placements refused: {ref}; views rejected: {rej}; standard errors "
            f"{'met' if stats.get('targets_met') else 'not all met'} (at most "
            f"{stats.get('placements_max', stats['planned'])} placements)")
