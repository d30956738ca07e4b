"""The simulator's true parameters as a RigModel / calibration file (no rclpy).

FOR TESTS AND COMPARISONS ONLY. A calibration made this way is not a calibration: it is
labelled ``source: simulator_truth`` in the file, and the reconstructor says so when it
loads one. Accuracy figures come from calibrating the simulated rig, never from this.
"""

from __future__ import annotations

import math

from reconstructor.calibration_file import Calibration
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel


def truth_model(rig, u2_pan: float = 0.0) -> RigModel:
    """The RigModel equivalent of a simulated rig (exact for a rig without imperfections)."""
    p = rig.true_model_parameters(u2_pan)
    cam = rig.camera
    return RigModel(
        intrinsics=CameraIntrinsics(fx=p.fx, fy=p.fy, cx=p.cx, cy=p.cy,
                                    dist=tuple(float(x) for x in p.distortion),
                                    width=cam.width, height=cam.height),
        g1_pan=MirrorParams(theta0=p.theta0_pan, k=p.k_pan),
        g1_tilt=MirrorParams(theta0=p.theta0_tilt, k=p.k_tilt),
        l=p.l, d=p.d,
        laser_plane_v0=p.pi0, laser_axis_dir=p.n, laser_axis_point=p.P,
        # the sim's theta4 = k2 * U2_tilt; only differences of theta4 enter the model
        g2_tilt=MirrorParams(theta0=math.pi / 4, k=p.k2),
    )


def truth_calibration(rig, u2_pan: float = 0.0) -> Calibration:
    """A calibration file object holding the simulator's truth, labelled as such."""
    return Calibration(model=truth_model(rig, u2_pan), source='simulator_truth',
                       stages={'simulator_truth': {'rig': rig.name,
                                                   'note': 'true parameters, tests only'}})
