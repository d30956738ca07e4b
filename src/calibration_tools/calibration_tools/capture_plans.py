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

========================  ======================================  ===========  ============
stage                     targets (scene per step)                full plan    quick plan
========================  ======================================  ===========  ============
intrinsics                4 mm checkerboard at U1 = 0, tilted      30 views     8 views
                          ~34 deg in directions all around         30 steps     8 steps
dynamic_camera            740 mm circle board at 650 mm, centred   88 views     20 views
                          and at 4 placements 420 mm to the sides  5 steps      1 step
laser_plane               small circle grids on the U2 = 0 laser   8 boards,    4 boards,
                          plane, near and far (4 per scene)        16 frames    8 frames
laser_axis                rows of boards on the planes of 9 G2     36 boards,   6 boards,
                          voltages over +-4 V, lit at +-0.05 V     18 planes,   3 planes,
                          (rows 2 V apart share a scene)           108 frames   12 frames
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

import numpy as np

from calibration_tools.board_layout import PAPER_CIRCLE_BOARD, Checkerboard, CircleGrid
from calibration_tools.stages import CaptureStep

#: Intrinsics target: the simulator's 12 x 9 checkerboard of 4 mm squares (inner corners).
INTRINSICS_BOARD = Checkerboard(11, 8, 0.004)
#: Laser-stage target: 11 x 8 circles of 2.5 mm at 4.5 mm pitch (54 x 40.5 mm board).
LASER_BOARD = CircleGrid(cols=11, rows=8, pitch=0.0045, diameter=0.0025)
#: Dynamic-camera target: the paper's 740 mm circle board.
CIRCLE_BOARD = PAPER_CIRCLE_BOARD
#: Joint-correction target: calibration sphere radius [m].
SPHERE_RADIUS = 0.01
#: Design working distance along the V0 optical axis [m] (the paper's 650 mm).
WORKING_DISTANCE = 0.65
#: Largest |U| a plan commands [V] (the DAC's top code is just below +10 V).
MAX_ABS_VOLTAGE = 9.9

#: Big-board placements: centre offset (x, y) in V0 [m] at the working distance, and the
#: board's rotation vector [rad]. Pose 0 is in front of the scanner; poses 1-4 reach the
#: paper's +-10 V verification grid.
CIRCLE_BOARD_OFFSETS = ((0.0, 0.0), (0.42, 0.0), (-0.42, 0.0), (0.0, 0.42), (0.0, -0.42))
CIRCLE_BOARD_ROTATION = (0.05, -0.08, 0.0)

#: Laser boards in a row on one laser plane: (x [m], near (0) or far (1) depth). Near and
#: far boards alternate so that no board is in the view or the laser path of another.
LASER_ROW = ((-0.105, 0), (-0.035, 1), (0.035, 0), (0.105, 1))
#: Near and far board depths relative to where the laser plane crosses the V0 axis [m].
LASER_DEPTHS = (-0.055, 0.055)


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

    The design working distance when the model's plane does not cross it between 0.2 and
    3 m (a plane nearly parallel to the axis).
    """
    a, b, c, e = model.laser_plane_v0
    if abs(c) > 1e-9:
        z = -e / c
        if 0.2 < z < 3.0:
            return float(z)
    return WORKING_DISTANCE


def _transform(rotvec, t) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _fmt(v) -> str:
    return '[' + ', '.join(f'{float(x):.10g}' for x in v) + ']'


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


def circle_board_pose(pose_index: int) -> np.ndarray:
    """Where the plan places the large circle board for ``pose_index``: ``V0_T_W``, metres.

    The placement is the operator's fixed bench setup (:data:`CIRCLE_BOARD_OFFSETS` at the
    design working distance), the board's prior pose for the dynamic-camera stage.
    """
    if not 0 <= int(pose_index) < len(CIRCLE_BOARD_OFFSETS):
        raise ValueError(f'pose_index must be in [0, {len(CIRCLE_BOARD_OFFSETS)}), '
                         f'got {pose_index}')
    ox, oy = CIRCLE_BOARD_OFFSETS[int(pose_index)]
    return _transform(CIRCLE_BOARD_ROTATION, [ox, oy, WORKING_DISTANCE])


# ----------------------------------------------------------------------------- stages
def intrinsics_steps(model, n_views: int, *, tilt: float = 0.6, seed: int = 0):
    """Checkerboard views at U1 = 0, tilted by ``tilt`` rad in directions all around.

    Each board is centred on the model's ray through the image centre at 640-720 mm and
    moved back until its pattern projects inside the image (model intrinsics) with 12 px to
    spare.
    """
    from calibration_tools.placement import board_scene_yaml
    from reconstructor.model import project_points

    rng = np.random.default_rng(seed)
    intr = model.intrinsics
    ray = np.array([(intr.width / 2 - intr.cx) / intr.fx, (intr.height / 2 - intr.cy) / intr.fy,
                    1.0])
    b = INTRINSICS_BOARD
    half = np.array([(b.cols + 1) * b.square / 2, (b.rows + 1) * b.square / 2])
    corners = np.array([[sx * half[0], sy * half[1], 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    steps = []
    for i in range(n_views):
        a = 2.0 * math.pi * i / n_views + rng.uniform(0.0, 0.3)
        rotvec = np.array([tilt * math.cos(a), tilt * math.sin(a), rng.uniform(-0.3, 0.3)])
        z = rng.uniform(0.64, 0.72)
        lateral = np.array([rng.uniform(-0.003, 0.003), rng.uniform(-0.002, 0.002), 0.0])
        T = _transform(rotvec, np.zeros(3))
        for _ in range(40):
            t = ray * z + lateral
            uv = project_points(intr, corners @ T[:3, :3].T + t)
            if np.all(np.isfinite(uv)) and uv[:, 0].min() > 12 and uv[:, 1].min() > 12 and \
                    uv[:, 0].max() < intr.width - 12 and uv[:, 1].max() < intr.height - 12:
                break
            z *= 1.02
        # The board frame's x runs along the pattern's columns; place its centre at t.
        steps.append(CaptureStep(i, board_scene_yaml(b, t, rotvec), np.zeros((1, 4)), False,
                                 note=f'intrinsics: checkerboard view {i} at U1 = 0, '
                                      f'{t[2] * 1e3:.0f} mm'))
    return steps


def dynamic_camera_steps(model, counts, *, seed: int = 0):
    """Circle-board views: per placement, 3 views centred on large circles, the rest at
    random points of the board, all aimed with the model.

    Parameters
    ----------
    counts : sequence of int
        Views per placement (pose_index = position in the sequence, see
        :func:`circle_board_pose`).
    """
    from calibration_tools.dynamic_camera import anchor_voltages
    from reconstructor.planning import aim_g1

    rng = np.random.default_rng(seed)
    steps = []
    for p, n in enumerate(counts):
        if n < 3:
            raise ValueError(f'counts[{p}] must be >= 3 (identification needs anchors)')
        T = circle_board_pose(p)
        aims = anchor_voltages(model, CIRCLE_BOARD, T, max_abs_u=MAX_ABS_VOLTAGE)[:3]
        if len(aims) < 2:
            raise ValueError(f'placement {p}: fewer than 2 large circles within reach of G1 '
                             f'under the model')
        pts = np.column_stack([rng.uniform(-0.33, 0.33, (6 * n, 2)), np.zeros(6 * n)])
        more = aim_g1(model, pts @ T[:3, :3].T + T[:3, 3], max_abs_u=MAX_ABS_VOLTAGE)
        more = more[np.isfinite(more).all(axis=1)][: n - len(aims)]
        u = np.vstack([aims, more])
        volts = np.column_stack([u, np.zeros((len(u), 2))])
        ox, oy = CIRCLE_BOARD_OFFSETS[p]
        steps.append(CaptureStep(p, circle_board_scene_yaml(T), volts, False,
                                 note=f'dynamic camera: circle board at ({ox * 1e3:+.0f}, '
                                      f'{oy * 1e3:+.0f}, {WORKING_DISTANCE * 1e3:.0f}) mm, '
                                      f'{len(u)} G1 positions'))
    return steps


def laser_row_steps(model, rows, *, offsets=(0.0,), boards=LASER_ROW, depth_shift=0.0,
                    mirror_x: bool = False, pose_index: int = 0, seed: int = 0,
                    label: str = 'laser'):
    """One scene of small circle-grid boards lying on the model's laser planes, and its two
    steps: the boards with the laser off, then lit.

    Parameters
    ----------
    model : RigModel
    rows : sequence of float, volts
        G2 tilt voltages; one row of ``boards`` on each of their laser planes.
    offsets : sequence of float, volts
        The laser-on frames of a board are at its row's voltage plus each offset.
    boards : sequence of (float, int)
        (x [m], near 0 / far 1) of the boards of a row (:data:`LASER_ROW`).
    depth_shift : float, metres
        Added to both board depths.
    mirror_x : bool
        Use -x for every board.
    """
    from calibration_tools.placement import board_rotation_on_laser, boards_scene_yaml
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import aim_g1

    rng = np.random.default_rng(seed)
    z0 = laser_crossing_depth(model)
    placements, off_volts, on_volts = [], [], []
    for u in rows:
        pi = laser_plane_v0(model, float(u))
        if abs(pi[1]) < 0.2:
            raise ValueError(f'the laser plane at U2 = {u} V is too steep to place boards on')
        for x, far in boards:
            x = -x if mirror_x else x
            z = z0 + LASER_DEPTHS[far] + depth_shift
            p = np.array([x, -(pi[0] * x + pi[2] * z + pi[3]) / pi[1], z])
            R = board_rotation_on_laser(model, p, rng.choice([-1.0, 1.0]) * 0.4,
                                        rng.uniform(-0.1, 0.1))
            placements.append((LASER_BOARD, p, R))
            g1 = aim_g1(model, p)
            if not np.all(np.abs(g1) <= MAX_ABS_VOLTAGE):
                raise ValueError(f'a board at U2 = {u} V is out of G1 reach under the model')
            off_volts.append([g1[0], g1[1], 0.0, 0.0])
            on_volts += [[g1[0], g1[1], 0.0, float(u) + o] for o in offsets]
    text = boards_scene_yaml(placements, name=f"cal_{label.replace(' ', '_')}_boards")
    n = len(placements)
    return [
        CaptureStep(pose_index, text, np.array(off_volts), False,
                    note=f'{label}: {n} circle-grid boards on the laser planes of U2 = '
                         f'{_fmt(rows)} V, laser off'),
        CaptureStep(pose_index, None, np.array(on_volts), True, frame_rate=100.0,
                    note=f'{label}: the same {n} boards lit ({len(offsets)} G2 voltage(s) '
                         f'each)'),
    ]


def laser_plane_steps(model, scenes: int):
    """Boards on the U2 = 0 laser plane: ``scenes`` scenes of 4 boards (near and far)."""
    steps = []
    for k in range(scenes):
        steps += laser_row_steps(model, [0.0], depth_shift=0.01 * k, mirror_x=bool(k % 2),
                                 pose_index=k, seed=k, label='laser plane')
    return steps


def laser_axis_steps(model, quick: bool):
    """Boards on the laser planes of several G2 voltages (rows 2 V apart share a scene)."""
    if quick:
        return laser_row_steps(model, [-2.0, 0.0, 2.0], boards=((-0.035, 0), (0.035, 1)),
                               label='laser axis')
    steps = []
    for k, rows in enumerate(([-4.0, -2.0, 0.0, 2.0, 4.0], [-3.0, -1.0, 1.0, 3.0])):
        steps += laser_row_steps(model, rows, offsets=(-0.05, 0.05), mirror_x=bool(k),
                                 pose_index=k, seed=10 + k, label='laser axis')
    return steps


def joint_correction_steps(model, laterals, *, reach=(0.3, 0.1), step: float = 0.1,
                           u2_tilt: float = 0.0):
    """The sphere at positions along V0's x, G1 stepped over a global ``step`` V grid.

    Each position is one scene: the sphere's front on the model's laser plane at
    ``u2_tilt`` at the working distance, a wall right behind it, and the G1 grid nodes
    within ``reach`` of the voltages aimed at its centre (the first position's grid holds
    U1 = 0, the correction's reference; neighbouring positions share nodes, so their
    corrections chain).
    """
    from calibration_tools.placement import sphere_grid_steps

    z0 = laser_crossing_depth(model)
    steps = []
    for pose, x in enumerate(laterals):
        s, _, _ = sphere_grid_steps(model, u2_tilt, SPHERE_RADIUS, None, None, depth=z0,
                                    lateral=x, grid_step=step, reach=reach, pose_index=pose)
        steps += s
    return steps

