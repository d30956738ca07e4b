"""Write the example images of docs/ (``python -m galvoscan_sim.examples [out_dir]``).

- ``sim_stair.png``: the 30 mm stair block (turned to show its riser), stripe on both
  faces and the riser, room light on;
- ``sim_stair_laser_frame.png``: the same as a real 500 us laser frame (dark image);
- ``sim_sphere.png``: the calibration sphere with the stripe;
- ``sim_circle_board.png``: one G1 view of the 740 mm circle board with the stripe;
- ``sim_v_groove.png``: a laser frame of the machined-aluminium V-groove, each face
  throwing the stripe onto the other (4x the rig's laser power: the exposure auto
  exposure gives this part).

All with the reference rig (every imperfection on) and a fixed seed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from .rig import load_rig
from .scene import load_scene
from .simulator import Simulator


def save_examples(out_dir) -> list[Path]:
    """Render the example frames into ``out_dir``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig = load_rig('reference')
    lit = dict(background='full', exposure=0.004, laser_power=0.125)
    jobs = [
        ('sim_stair.png', 'stair_block_turned', [0.0, 0.0, 0.0, 0.0], lit),
        ('sim_stair_laser_frame.png', 'stair_block_turned', [0.0, 0.0, 0.0, 0.0], {}),
        ('sim_sphere.png', 'sphere', [0.0, -0.2, 0.0, -0.1], lit),
        ('sim_circle_board.png', 'circle_board', [0.3, -0.2, 0.0, 0.05],
         dict(background='full', exposure=0.006, laser_power=0.1)),
        ('sim_v_groove.png', 'v_groove_machined_aluminium', [0.0, 0.0, 0.0, -0.12],
         dict(laser_power=4.0)),
    ]
    written = []
    for name, scene, volts, kwargs in jobs:
        sim = Simulator(rig, load_scene(scene), seed=2024)
        frame = sim.render(np.array(volts), **kwargs)
        path = out / name
        cv2.imwrite(str(path), frame.image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(path)
    return written


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    for path in save_examples(argv[0] if argv else 'docs'):
        print(path)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
