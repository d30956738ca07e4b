"""Placing calibration targets: scene texts and capture steps that play the operator (no rclpy).

They place a small board (or the calibration sphere) in the scene and aim G1 at it with the
*current* (approximate) model a real operator would have, never with the simulator's true
parameters. The scene frame W is taken to be the model's V0. On a simulated rig the scene
text goes to ``sim/set_scene``; on a real rig the operator places what the step's note
describes. :mod:`calibration_tools.capture_plans` builds the stages' plans from these;
running them on the simulator is the application's job (``galvoscan.simulated_rig``).
"""

from __future__ import annotations

import numpy as np

from calibration_tools.stages import CaptureStep

_BOARD_OBJECT = """  - type: {kind}
    name: {name}
    pose: {{translation: {t}, rotation_vector: {r}}}
    size: [{sx}, {sy}]
    thickness: 0.003
    albedo: 0.85
{pattern}"""
_CHECKER = """    squares: [{nx}, {ny}]
    square_size: {sq}
    dark_albedo: 0.05
"""
_CIRCLES = """    grid: [{nx}, {ny}]
    pitch: {p}
    sub_pattern: 1
    small_diameter: {d}
    big_diameter: {d}
    circle_albedo: 0.05
"""


def _aim(model, point_v0, what: str) -> np.ndarray:
    """G1 voltages centring ``point_v0`` under ``model`` (:func:`reconstructor.planning.aim_g1`).

    Raises
    ------
    ValueError
        The point is out of G1 reach under the model.
    """
    from reconstructor.planning import aim_g1

    g1 = aim_g1(model, point_v0)
    if not np.all(np.isfinite(g1)):
        raise ValueError(f'{what} at {np.round(point_v0, 4).tolist()} m is out of G1 reach '
                         'under the model')
    return g1


def _board_object(board, translation, rotation_vector, name: str) -> str:
    from calibration_tools.board_layout import Checkerboard, CircleGrid

    t = [float(v) for v in np.asarray(translation, dtype=np.float64).reshape(3)]
    r = [float(v) for v in np.asarray(rotation_vector, dtype=np.float64).reshape(3)]
    if isinstance(board, Checkerboard):
        # cols x rows inner corners: (cols + 1) x (rows + 1) squares, one square of margin.
        nx, ny, sq = board.cols + 1, board.rows + 1, board.square
        return _BOARD_OBJECT.format(kind='checkerboard', name=name, t=t, r=r,
                                    sx=(nx + 2) * sq, sy=(ny + 2) * sq,
                                    pattern=_CHECKER.format(nx=nx, ny=ny, sq=sq))
    if not isinstance(board, CircleGrid):
        raise ValueError(f'board must be a Checkerboard or CircleGrid, got '
                         f'{type(board).__name__}')
    p = board.pitch
    return _BOARD_OBJECT.format(kind='circle_board', name=name, t=t, r=r,
                                sx=(board.cols + 1) * p, sy=(board.rows + 1) * p,
                                pattern=_CIRCLES.format(nx=board.cols, ny=board.rows, p=p,
                                                        d=board.diameter))


def board_scene_yaml(board, translation, rotation_vector) -> str:
    """Simulator scene text with one small board (Checkerboard or CircleGrid) at a pose.

    Parameters
    ----------
    board : board_layout.Checkerboard or board_layout.CircleGrid
    translation : array_like, shape (3,), metres
        Board centre in the scene frame W.
    rotation_vector : array_like, shape (3,), radians
        Board orientation in W (the board's z axis points into the board).
    """
    return ('format_version: 1\nname: cal_board\nobjects:\n'
            + _board_object(board, translation, rotation_vector, 'board'))


def boards_scene_yaml(placements, name: str = 'cal_boards') -> str:
    """Simulator scene text with several small boards.

    Parameters
    ----------
    placements : sequence of (board, translation, rotation)
        ``board`` a Checkerboard or CircleGrid; ``translation`` shape (3,), metres, its
        centre in W; ``rotation`` a rotation vector shape (3,), radians, or a rotation
        matrix shape (3, 3).
    name : str
    """
    if not placements:
        raise ValueError('placements must hold at least one board')
    objects = []
    for k, (board, t, rot) in enumerate(placements):
        rot = np.asarray(rot, dtype=np.float64)
        objects.append(_board_object(board, t, _rotvec(rot) if rot.shape == (3, 3) else rot,
                                     f'board{k}'))
    return f'format_version: 1\nname: {name}\nobjects:\n' + ''.join(objects)


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def board_rotation_on_laser(model, p_v0, tilt_y: float, roll: float,
                            along: int = 0) -> np.ndarray:
    """Orientation (3 x 3) of a board at ``p_v0`` facing the bisector of the directions to
    the camera and to the model's laser axis, its x along V0's axis ``along`` (the stripe's
    direction, ``reconstructor.planning.stripe_layout``), turned by ``tilt_y`` about its own
    y and ``roll`` about its normal (radians)."""
    from scipy.spatial.transform import Rotation

    p_v0 = np.asarray(p_v0, dtype=np.float64)
    to_cam = -p_v0 / np.linalg.norm(p_v0)
    to_laser = model.laser_axis_point - p_v0
    to_laser -= (to_laser @ model.laser_axis_dir) * model.laser_axis_dir
    to_laser /= np.linalg.norm(to_laser)
    facing = to_cam + to_laser
    facing /= np.linalg.norm(facing)
    # Board z axis points into the board (away from the viewer): -facing.
    z = -facing
    x = np.eye(3)[along] - z[along] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    return R @ Rotation.from_euler('yz', [tilt_y, roll]).as_matrix()


def board_laser_steps(model, u2_tilts, depths, board, *, offsets=(0.0,), tilt_y: float = 0.4,
                      seed: int = 0, pose_start: int = 0) -> list[CaptureStep]:
    """Steps imaging one board per pose, lit by the laser, seen at the G1 voltages that
    centre it.

    For every centre voltage ``u`` in ``u2_tilts`` and every depth ``z`` in ``depths``, a
    board is placed (in a scene of its own) with its centre on the laser plane of ``model``
    at ``U2_tilt = u``, near V0's optical axis at depth z, facing between the camera and the
    laser, turned by +-``tilt_y`` about its own y. G1 is aimed at its centre. Per pose: a
    laser-off step of one frame (with the scene), then a laser-on step with one frame per
    ``u + offset``.

    Parameters
    ----------
    model : reconstructor.model.RigModel
        The operator's approximate model (aiming and placement only).
    u2_tilts : sequence of float, volts
    depths : sequence of float, metres
    board : board_layout.Checkerboard or board_layout.CircleGrid
    offsets : sequence of float, volts
        G2 tilt offsets of the laser-on frames around each centre voltage.
    tilt_y : float, radians
    seed : int
    pose_start : int
        pose_index of the first pose.

    Returns
    -------
    list of CaptureStep
    """
    from reconstructor.model import laser_plane_v0

    rng = np.random.default_rng(seed)
    steps = []
    pose = int(pose_start)
    for u in u2_tilts:
        u = float(u)
        pi = laser_plane_v0(model, u)
        for z in depths:
            x = rng.uniform(-0.003, 0.003)
            p = np.array([x, -(pi[0] * x + pi[2] * z + pi[3]) / pi[1], z])
            R = board_rotation_on_laser(model, p, rng.choice([-1.0, 1.0]) * tilt_y,
                                        rng.uniform(-0.1, 0.1))
            g1 = _aim(model, p, 'a board')
            steps.append(CaptureStep(pose, board_scene_yaml(board, p, _rotvec(R)),
                                     [[g1[0], g1[1], 0.0, 0.0]], False,
                                     note=f'board on the U2 = {u:g} V plane at {z:.4f} m'))
            steps.append(CaptureStep(pose, None,
                                     [[g1[0], g1[1], 0.0, u + off] for off in offsets], True,
                                     note='the same board lit'))
            pose += 1
    return steps


def sphere_scene_yaml(centre, radius: float, wall_z: float | None = None,
                      occluder=None) -> str:
    """Simulator scene text: the calibration sphere, optionally a wall behind it and a box.

    Parameters
    ----------
    centre : array_like, shape (3,), metres
        Sphere centre in the scene frame W.
    radius : float, metres
    wall_z : float, metres, optional
        A wall (plane z = wall_z, facing the camera) behind the sphere.
    occluder : (array_like shape (3,), array_like shape (3,)), optional
        Centre and size [m] of a box standing in front of the sphere.
    """
    def pose(t):
        return f'{{translation: {[float(v) for v in t]}, rotation_vector: [0.0, 0.0, 0.0]}}'

    objects = [f'  - type: sphere\n    name: sphere\n    pose: {pose(centre)}\n'
               f'    radius: {float(radius)}\n    albedo: 0.75\n']
    if wall_z is not None:
        objects.append(f'  - type: plane\n    name: wall\n    pose: {pose([0, 0, wall_z])}\n'
                       f'    albedo: 0.3\n')
    if occluder is not None:
        oc, size = occluder
        objects.append(f'  - type: box\n    name: occluder\n    pose: {pose(oc)}\n'
                       f'    size: {[float(v) for v in size]}\n    albedo: 0.5\n')
    return 'format_version: 1\nname: cal_sphere\nobjects:\n' + ''.join(objects)


def _grid_axis(centre: float, reach: float, step: float) -> np.ndarray:
    lo = np.ceil((centre - reach) / step - 1e-9)
    hi = np.floor((centre + reach) / step + 1e-9)
    return np.round(np.arange(lo, hi + 1)) * step


def sphere_grid_steps(model, u2_tilt: float, radius: float, pans, tilts, *,
                      depth: float = 0.65, lateral: float = 0.0, absolute: bool = False,
                      grid_step: float | None = None, reach=(0.3, 0.3),
                      wall_gap: float | None = 0.0, occluder=None, occluded_nodes=(),
                      pose_index: int = 0, frame_rate: float = 100.0):
    """Steps of laser-on frames of a sphere with G2 fixed and G1 stepped over a grid.

    The sphere is placed with its front on ``model``'s laser plane at ``u2_tilt``, at depth
    ``depth`` and ``lateral`` along the stripe; G1 is aimed at its centre, then offset by every
    (pan, tilt) of the grid (or set to them, with ``absolute``). With ``grid_step`` the grid
    is instead every multiple of ``grid_step`` volts within ``reach`` of the aimed voltages
    (one global grid for all positions, so that positions share nodes).

    Parameters
    ----------
    model : reconstructor.model.RigModel
        The operator's approximate model (placement and aiming only).
    u2_tilt : float, volts
    radius : float, metres
    pans, tilts : sequence of float, volts, or None with ``grid_step``
        G1 offsets from the aimed voltages (the grid), or the grid's voltages themselves
        with ``absolute``.
    depth : float, metres
    lateral : float, metres
        Along the stripe's own V0 axis (x for a laser below or above the camera, y beside
        it: ``reconstructor.planning.stripe_layout``).
    absolute : bool
    grid_step : float, volts, optional
    reach : (float, float), volts
        Half widths of the ``grid_step`` grid in pan and tilt.
    wall_gap : float or None, metres
        Wall this far behind the sphere's back (None: no wall).
    occluder : (offset, size), optional
        A box (offset of its centre from the sphere centre, size; metres) present only in
        the frames of ``occluded_nodes`` (someone's hand in front of the sphere).
    occluded_nodes : sequence of (int, int)
        (pan index, tilt index) of the frames that see the occluder.
    pose_index : int
    frame_rate : float, Hz

    Returns
    -------
    steps : list of CaptureStep
        Frames in (pan, tilt) order; a new step wherever the scene changes.
    centre : ndarray, shape (3,), metres
        Where the sphere is placed (scene frame).
    aim : ndarray, shape (2,), volts
        The G1 voltages aimed at the sphere (grid origin).
    """
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import stripe_layout

    u2 = float(u2_tilt)
    pi = laser_plane_v0(model, u2)
    front = stripe_layout(model).point_on_plane(pi, lateral, depth)
    centre = front + np.array([0.0, 0.0, radius])
    wall = None if wall_gap is None else centre[2] + radius + wall_gap
    plain = sphere_scene_yaml(centre, radius, wall)
    blocked = plain
    if occluder is not None:
        box = (centre + np.asarray(occluder[0], dtype=np.float64), occluder[1])
        blocked = sphere_scene_yaml(centre, radius, wall, box)
    aim = _aim(model, centre, 'the sphere')
    if grid_step is not None:
        if not grid_step > 0:
            raise ValueError(f'grid_step must be > 0 V, got {grid_step}')
        pans = _grid_axis(aim[0], reach[0], grid_step)
        tilts = _grid_axis(aim[1], reach[1], grid_step)
        absolute = True
    if pans is None or tilts is None or len(pans) == 0 or len(tilts) == 0:
        raise ValueError('pans and tilts must be non-empty (or give grid_step)')
    origin = np.zeros(2) if absolute else aim
    occluded = set(map(tuple, occluded_nodes))
    steps: list[CaptureStep] = []
    rows, scene = [], None
    for a, dp in enumerate(pans):
        for b, dt in enumerate(tilts):
            text = blocked if (a, b) in occluded else plain
            if text is not scene and rows:
                steps.append(_sphere_step(pose_index, scene, rows, steps, frame_rate))
                rows = []
            scene = text
            rows.append([origin[0] + dp, origin[1] + dt, 0.0, u2])
    steps.append(_sphere_step(pose_index, scene, rows, steps, frame_rate))
    return steps, centre, aim


def _sphere_step(pose_index, scene, rows, steps, frame_rate):
    previous = next((s.scene_yaml for s in reversed(steps) if s.scene_yaml), None)
    return CaptureStep(pose_index, None if scene is previous else scene, rows, True,
                       frame_rate=frame_rate, note=f'sphere, {len(rows)} G1 grid nodes')


