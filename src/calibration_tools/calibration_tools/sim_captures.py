"""Calibration II captures from the rig simulator (``galvo_driver.sim``), for tests and demos.

These helpers play the operator: they place a small board (or the calibration sphere) in the
simulated scene, aim G1 at it and record laser-off and laser-on frames as
:class:`~calibration_tools.stages.CaptureView`. They aim with the *current* (approximate)
model a real operator would have, never with the simulator's true parameters, and every
commanded voltage is a DAC code (so the voltages stored with a view are exactly the ones the
galvos received). No rclpy.

Each function returns ``(views, truths)``: ``truths[i]`` is the simulator's
``FrameTruth`` of ``views[i]``, for scoring only.
"""

from __future__ import annotations

import numpy as np

from calibration_tools.stages import CaptureView

_BOARD_YAML = """
format_version: 1
name: cal2_board
objects:
  - type: {kind}
    name: board
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
    from calibration_tools.board_layout import Checkerboard

    t = [float(v) for v in translation]
    r = [float(v) for v in rotation_vector]
    if isinstance(board, Checkerboard):
        # cols x rows inner corners: (cols + 1) x (rows + 1) squares, one square of margin.
        nx, ny, sq = board.cols + 1, board.rows + 1, board.square
        return _BOARD_YAML.format(kind='checkerboard', t=t, r=r, sx=(nx + 2) * sq,
                                  sy=(ny + 2) * sq,
                                  pattern=_CHECKER.format(nx=nx, ny=ny, sq=sq))
    p = board.pitch
    return _BOARD_YAML.format(kind='circle_board', t=t, r=r, sx=(board.cols + 1) * p,
                              sy=(board.rows + 1) * p,
                              pattern=_CIRCLES.format(nx=board.cols, ny=board.rows, p=p,
                                                      d=board.diameter))

def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _quantize(sim, volts) -> np.ndarray:
    return sim.rig.dac.quantize(np.asarray(volts, dtype=np.float64))


def aim_g1(model, point_v0, start=(0.0, 0.0), *, max_iter: int = 30) -> np.ndarray:
    """G1 voltages that bring a V0 point to the image centre under ``model`` (Newton).

    Parameters
    ----------
    model : reconstructor.model.RigModel
    point_v0 : array_like, shape (3,), metres
    start : (float, float), volts

    Returns
    -------
    ndarray, shape (2,), volts (U1_pan, U1_tilt)
    """
    from reconstructor.model import predict_pixels

    p = np.asarray(point_v0, dtype=np.float64).reshape(1, 3)
    u = np.array(start, dtype=np.float64)
    centre = np.array([model.intrinsics.cx, model.intrinsics.cy])
    h = 1e-4
    for _ in range(max_iter):
        uv = predict_pixels(model, p, u[0], u[1])[0][0]
        J = np.empty((2, 2))
        for k in range(2):
            du = u.copy()
            du[k] += h
            J[:, k] = (predict_pixels(model, p, du[0], du[1])[0][0] - uv) / h
        step = np.linalg.solve(J, centre - uv)
        u += step
        if np.abs(step).max() < 1e-10:
            break
    return u


def _board_rotation(model, p_v0, tilt_y: float, roll: float) -> np.ndarray:
    """Board orientation in V0: facing the bisector of the camera and laser directions."""
    to_cam = -p_v0 / np.linalg.norm(p_v0)
    to_laser = model.laser_axis_point - p_v0
    to_laser -= (to_laser @ model.laser_axis_dir) * model.laser_axis_dir
    to_laser /= np.linalg.norm(to_laser)
    facing = to_cam + to_laser
    facing /= np.linalg.norm(facing)
    # Board z axis points into the board (away from the viewer): -facing.
    z = -facing
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    from scipy.spatial.transform import Rotation

    return R @ Rotation.from_euler('yz', [tilt_y, roll]).as_matrix()


def board_poses_on_laser(sim, model, u2_tilts, depths, board, *,
                         offsets=(0.0,), tilt_y: float = 0.4, seed: int = 0):
    """Board poses lit by the laser, each seen at the G1 voltages that centre it.

    For every centre voltage ``u`` in ``u2_tilts`` and every depth ``z`` in ``depths``, a
    checkerboard is placed (in a scene of its own) with its centre on the laser plane of
    ``model`` at ``U2_tilt = u``, at depth z on the V0 optical axis's side, facing between the
    camera and the laser, turned by +-``tilt_y`` about its own y. G1 is aimed at its centre.
    One laser-off board frame, then one laser-on frame per ``u + offset``.

    Parameters
    ----------
    sim : galvo_driver.sim.simulator.Simulator
        Its scene is replaced.
    model : reconstructor.model.RigModel
        The operator's approximate model (aiming and placement only).
    u2_tilts : sequence of float, volts
    depths : sequence of float, metres
    board : board_layout.Checkerboard or board_layout.CircleGrid
    offsets : sequence of float, volts
        G2 tilt offsets of the laser-on frames around each centre voltage.
    tilt_y : float, radians
    seed : int

    Returns
    -------
    views : list of CaptureView
    truths : list of FrameTruth
    """
    from galvo_driver.sim.scene import load_scene_text
    from reconstructor.model import laser_plane_v0

    rng = np.random.default_rng(seed)
    views, truths = [], []
    pose = 0
    for u in u2_tilts:
        u = float(_quantize(sim, u))
        pi = laser_plane_v0(model, u)
        for z in depths:
            x = rng.uniform(-0.003, 0.003)
            p = np.array([x, -(pi[0] * x + pi[2] * z + pi[3]) / pi[1], z])
            R = _board_rotation(model, p, rng.choice([-1.0, 1.0]) * tilt_y,
                                rng.uniform(-0.1, 0.1))
            # The scene frame W is the rig's nominal V0: place the board there directly.
            sim.set_scene(load_scene_text(board_scene_yaml(board, p, _rotvec(R))))
            g1 = aim_g1(model, p)
            volts = _quantize(sim, [g1[0], g1[1], 0.0, 0.0])
            frame = sim.calibration_frame(volts)
            views.append(CaptureView(frame.image, volts, False, pose))
            truths.append(frame.truth)
            for off in offsets:
                volts = _quantize(sim, [g1[0], g1[1], 0.0, u + off])
                frame = sim.render(volts)
                views.append(CaptureView(frame.image, volts, True, pose))
                truths.append(frame.truth)
            pose += 1
    return views, truths


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
    return 'format_version: 1\nname: cal2_sphere\nobjects:\n' + ''.join(objects)


def sphere_g1_grid(sim, model, u2_tilt: float, radius: float, pans, tilts, *,
                   depth: float = 0.65, lateral: float = 0.0, absolute: bool = False,
                   wall_gap: float | None = 0.0, occluder=None, occluded_nodes=(),
                   pose_index: int = 0):
    """Laser-on frames of a sphere with G2 fixed and G1 stepped over a grid.

    The sphere is placed with its front on ``model``'s laser plane at ``u2_tilt``, at depth
    ``depth`` and ``lateral`` along V0's x; G1 is aimed at its centre, then offset by every
    (pan, tilt) of the grid (or set to them, with ``absolute``).

    Parameters
    ----------
    sim : galvo_driver.sim.simulator.Simulator
        Its scene is replaced.
    model : reconstructor.model.RigModel
        The operator's approximate model (placement and aiming only).
    u2_tilt : float, volts
    radius : float, metres
    pans, tilts : sequence of float, volts
        G1 offsets from the aimed voltages (the grid), or the grid's voltages themselves
        with ``absolute``.
    depth : float, metres
    lateral : float, metres
    absolute : bool
    wall_gap : float or None, metres
        Wall this far behind the sphere's back (None: no wall).
    occluder : (offset, size), optional
        A box (offset of its centre from the sphere centre, size; metres) present only in
        the frames of ``occluded_nodes`` (someone's hand in front of the sphere).
    occluded_nodes : sequence of (int, int)
        (pan index, tilt index) of the frames that see the occluder.
    pose_index : int

    Returns
    -------
    views : list of CaptureView
    truths : list of FrameTruth
    centre : ndarray, shape (3,), metres
        Where the sphere was placed (scene frame).
    aim : ndarray, shape (2,), volts
        The G1 voltages aimed at the sphere (grid origin).
    """
    from galvo_driver.sim.scene import load_scene_text
    from reconstructor.model import laser_plane_v0

    u2 = float(_quantize(sim, u2_tilt))
    pi = laser_plane_v0(model, u2)
    front = np.array([lateral, -(pi[0] * lateral + pi[2] * depth + pi[3]) / pi[1], depth])
    centre = front + np.array([0.0, 0.0, radius])
    wall = None if wall_gap is None else centre[2] + radius + wall_gap
    plain = load_scene_text(sphere_scene_yaml(centre, radius, wall))
    blocked = plain
    if occluder is not None:
        box = (centre + np.asarray(occluder[0], dtype=np.float64), occluder[1])
        blocked = load_scene_text(sphere_scene_yaml(centre, radius, wall, box))
    aim = aim_g1(model, centre)
    origin = np.zeros(2) if absolute else aim
    views, truths = [], []
    for a, dp in enumerate(pans):
        for b, dt in enumerate(tilts):
            sim.set_scene(blocked if (a, b) in set(map(tuple, occluded_nodes)) else plain)
            volts = _quantize(sim, [origin[0] + dp, origin[1] + dt, 0.0, u2])
            frame = sim.render(volts)
            views.append(CaptureView(frame.image, volts, True, pose_index))
            truths.append(frame.truth)
    return views, truths, centre, aim
