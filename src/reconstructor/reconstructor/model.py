"""Geometric model of the rig: dynamic camera, dynamic laser, camera, triangulation.

Public entry point of the pure-numpy model library (no rclpy). See docs/design.md sections 2-4 for
the mathematics and notation; the implementation lives in ``reconstructor.geometry``.
"""

from reconstructor.geometry.camera import (
    UNDISTORT_MAX_ITER,
    UNDISTORT_STEP_TOL,
    UNDISTORT_TARGET_ERROR,
    CameraIntrinsics,
    distort_normalised,
    project_points,
    undistort_points,
)
from reconstructor.geometry.galvo import (
    MirrorParams,
    g_T_v,
    m0_factor,
    pan_factor,
    rigid_inverse,
    tilt_factor,
)
from reconstructor.geometry.laser import laser_plane_v, laser_plane_v0, transform_plane
from reconstructor.geometry.physical import PhysicalGeometry
from reconstructor.geometry.rig import (
    MODEL_KINDS,
    JointCorrection,
    RigModel,
    nominal_example_rig,
    v0_T_v,
)
from reconstructor.geometry.triangulation import (
    DEFAULT_MIN_RAY_PLANE_ANGLE,
    TriangulationResult,
    predict_pixels,
    triangulate,
    triangulate_batch,
)

__all__ = [
    "DEFAULT_MIN_RAY_PLANE_ANGLE",
    "UNDISTORT_MAX_ITER",
    "UNDISTORT_STEP_TOL",
    "UNDISTORT_TARGET_ERROR",
    "CameraIntrinsics",
    "JointCorrection",
    "MODEL_KINDS",
    "MirrorParams",
    "PhysicalGeometry",
    "RigModel",
    "TriangulationResult",
    "distort_normalised",
    "g_T_v",
    "laser_plane_v",
    "laser_plane_v0",
    "m0_factor",
    "nominal_example_rig",
    "pan_factor",
    "predict_pixels",
    "project_points",
    "rigid_inverse",
    "tilt_factor",
    "transform_plane",
    "triangulate",
    "triangulate_batch",
    "undistort_points",
    "v0_T_v",
]
