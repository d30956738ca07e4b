"""Scenes of the evaluation (the paper's test objects), as simulator scene YAML (no rclpy).

The world frame W of these scenes is the rig's nominal V0 (x right, y down, z away from
the scanner). Each function returns the YAML text and what the evaluation needs to know
about the object (its pose ``W_T_O`` and dimensions): the experimenter's knowledge of
where they put it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

STAIR_SIZE = (0.12, 0.10, 0.02)   # footprint x, y and base height [m]
STAIR_STEP = 0.03                 # the paper's 30 mm step [m]
STAIR_TILT = (0.12, -0.35, 0.0)   # rotation vector [rad] that shows the riser to the laser
SPHERE_RADIUS = 0.0254            # 2 inch calibration sphere [m]
PLATE_SIZE = 0.74                 # [m]
PLATE_POSES = ((0.08, 0.12, 0.0), (-0.10, 0.05, 0.0), (0.03, -0.15, 0.10))  # rotvecs [rad]


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


def stair(position) -> tuple[str, dict]:
    """The 30 mm stair block with its upper face near ``position`` [m], facing the scanner.

    Returns the scene text and ``{'W_T_O', 'size', 'step_height', 'aim_W'}``; ``aim_W`` is
    the middle of the riser, where the view should be centred.
    """
    p = np.asarray(position, dtype=np.float64)
    R = facing(p, STAIR_TILT)
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
    albedo: 0.6
"""
    return text, {'W_T_O': W_T_O, 'size': STAIR_SIZE, 'step_height': STAIR_STEP, 'aim_W': aim}


def plate(index: int, distance: float = 0.65) -> tuple[str, dict]:
    """The 740 x 740 mm flat plate at ``distance`` [m], in pose ``index`` of PLATE_POSES."""
    R = Rotation.from_rotvec(PLATE_POSES[index % len(PLATE_POSES)])
    t = np.array([0.0, 0.0, distance])
    text = f"""format_version: 1
name: eval_plate_{index}
description: 740 x 740 mm flat plate, pose {index}
objects:
  - type: flat_plate
    name: plate
    pose: {{translation: {_fmt(t)}, rotation_vector: {_fmt(R.as_rotvec())}}}
    size: [{PLATE_SIZE}, {PLATE_SIZE}]
    thickness: 0.02
    albedo: 0.5
"""
    return text, {'W_T_O': _pose(R, t), 'size': (PLATE_SIZE, PLATE_SIZE)}


def sphere(position) -> tuple[str, dict]:
    """The calibration sphere with its front at ``position`` [m]."""
    p = np.asarray(position, dtype=np.float64)
    centre = p + p / np.linalg.norm(p) * SPHERE_RADIUS
    text = f"""format_version: 1
name: eval_sphere
description: 50.8 mm calibration sphere
objects:
  - type: sphere
    name: sphere
    pose: {{translation: {_fmt(centre)}, rotation_vector: [0, 0, 0]}}
    radius: {SPHERE_RADIUS}
    albedo: 0.75
"""
    return text, {'centre_W': centre, 'radius': SPHERE_RADIUS, 'aim_W': p}


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
#: nominal V0 [m]: over the range at 650 mm, not on one line or plane.
CELL_POSITIONS = ((0.0, 0.0, 0.65), (0.25, 0.15, 0.6), (-0.25, 0.15, 0.7),
                  (0.22, -0.15, 0.72), (-0.22, -0.16, 0.58), (0.04, 0.18, 0.66))


def cell_reference(nominal_W_T_V0, cell_frame: str = 'world') -> tuple[str, np.ndarray]:
    """The cell stage's reference file text, with W as the cell frame.

    The robot is programmed with the scanner's designed mounting ``nominal_W_T_V0``
    (4, 4): it reports the positions it moved the sphere to, in W, and the file carries the
    designed mounting as ``nominal_cell_T_v0`` (to aim G1). Returns the text and the
    positions (n, 3) [m] in W.
    """
    T = np.asarray(nominal_W_T_V0, dtype=np.float64)
    p = np.asarray(CELL_POSITIONS) @ T[:3, :3].T + T[:3, 3]
    lines = [f'cell_frame: {cell_frame}', 'unit: m', 'positions:']
    lines += [f'  {k}: {_fmt(q)}' for k, q in enumerate(p)]
    lines += ['nominal_cell_T_v0:'] + [f'  - {_fmt(row)}' for row in T]
    return '\n'.join(lines) + '\n', p
