"""Physical rig simulator: the galvoscan rig as a library (no rclpy).

The simulator is the rig when there is no hardware: it is the driver's default backend,
the source of calibration data and the ground truth accuracy is measured against. It is
an independent physical model (docs/design.md section 5): mirrors are explicit planes with
their real imperfections, pixel rays and the laser fan are traced off them, and images
are formed with a sensor model.

Typical use::

    from galvoscan_sim import Simulator, load_rig, load_scene, patterns

    rig = load_rig('reference')            # or 'ideal', or a path to a rig YAML
    scene = load_scene('stair_block')      # or a path, or load_scene_text(yaml_text)
    sim = Simulator(rig, scene, seed=0)
    volts = patterns.synchronised(rig, [0.0], -0.2, steps=10, tilt_step=0.05)
    for frame in sim.scan(volts):          # SimFrame: .image (540, 720) uint8, .truth
        stripe = frame.truth.stripe        # per column: u, v, points_W, points_V0
    params = rig.true_model_parameters()   # intrinsics, l, d, theta0/k, pi0, n, P, k2
"""

from . import patterns
from .config import ConfigError
from .rig import ModelParameters, Rig, load_rig, load_rig_text, rig_from_dict, shipped_rigs
from .scene import Scene, load_scene, load_scene_text, scene_from_dict, shipped_scenes
from .simulator import FrameTruth, SimFrame, Simulator, StripeTruth

__all__ = [
    'ConfigError', 'FrameTruth', 'ModelParameters', 'Rig', 'Scene', 'SimFrame', 'Simulator',
    'StripeTruth', 'load_rig', 'load_rig_text', 'load_scene', 'load_scene_text', 'patterns',
    'rig_from_dict', 'scene_from_dict', 'shipped_rigs', 'shipped_scenes',
]
