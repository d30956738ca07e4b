"""Benchmark: triangulate the 720 stripe points of one frame on one core.

Times ``reconstructor.model.triangulate`` (undistortion, laser plane in V, ray-plane
intersection and the V0 transform) and, in the same run, a plain ``cv2.undistortPoints`` on the
same pixels. The rig is the nominal example (not a calibration) with an illustrative plumb_bob
distortion. Prints the figures; the last stdout line is one JSON object with
``triangulation_us_per_frame``, ``undistort_us_per_frame`` (medians, microseconds) and
``ratio`` (triangulation / cv2 undistortion). The same frame through the physical mirror
model (the reference rig's order of deviations) is timed in the same blocks:
``physical_us_per_frame`` and ``physical_ratio`` (physical / paper model). Goal: both
medians <= 100 us.

Usage: python benchmarks/triangulation.py [--repeats N]
"""

import os

for _var in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import brentq  # noqa: E402

from reconstructor.model import (  # noqa: E402
    PhysicalGeometry,
    laser_plane_v,
    nominal_example_rig,
    project_points,
    triangulate,
)

# Illustrative distortion for a long-focus lens (k1, k2, p1, p2, k3); not a calibration.
DIST = (-0.25, 2.0, 1.0e-4, -1.0e-4, -20.0)
U1 = (1.5, -2.0)  # U1_pan, U1_tilt of the benchmark frame, volts


def stripe_frame(model, u1_pan, u1_tilt, depth=0.65):
    """Voltages and stripe pixels (one per image column) of a wall facing the virtual camera.

    The wall is the plane Z_V = depth; U2_tilt is chosen so that the laser plane crosses the
    view centre on it. Pixels come from projecting the plane/wall intersection line.
    """
    intr = model.intrinsics
    centre = np.array([0.0, 0.0, depth, 1.0])
    u2 = brentq(lambda u: laser_plane_v(model, u1_pan, u1_tilt, u) @ centre, -10.0, 10.0)
    a, b, c, e = laser_plane_v(model, u1_pan, u1_tilt, u2)
    # Line a x + b y + c + e / depth = 0 in undistorted normalised coordinates.
    xs = np.linspace(-0.08, 0.08, 20001)
    ys = -(a * xs + c + e / depth) / b
    pix = project_points(intr, depth * np.column_stack([xs, ys, np.ones_like(xs)]))
    cols = np.arange(intr.width, dtype=np.float64) + 0.5
    rows = np.interp(cols, pix[:, 0], pix[:, 1])
    return (u1_pan, u1_tilt, u2), np.column_stack([cols, rows])


def median_us(fn, repeats):
    times = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times[i] = time.perf_counter_ns() - t0
    return float(np.median(times)) / 1e3, float(times.min()) / 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5000)
    args = parser.parse_args()
    cv2.setNumThreads(1)

    model = nominal_example_rig(dist=DIST)
    VOLTAGES, uv = stripe_frame(model, *U1)
    res = triangulate(model, uv, *VOLTAGES)
    if not (
        res.valid.all()
        and np.all((uv >= 0) & (uv <= [model.intrinsics.width, model.intrinsics.height]))
    ):
        raise SystemExit(f"benchmark frame has {res.n_invalid} invalid points")
    K = model.intrinsics.matrix()
    D = np.array(model.intrinsics.dist)
    uv_cv = np.ascontiguousarray(uv.reshape(-1, 1, 2))
    plan = model.intrinsics._plan
    # the same rig with mirror deviations of the reference rig's order (illustrative)
    physical = dataclasses.replace(model, physical=PhysicalGeometry(
        camera_rotation=(2e-4, -1e-3, 6e-4), camera_offset=(2e-5, -2e-5), g1_axes_angle=-2e-4,
        g1_pan_surface_offset=1.5e-4, g1_tilt_surface_offset=-1e-4,
        g2_tilt_surface_offset=1.5e-4))
    if triangulate(physical, uv, *VOLTAGES).n_invalid:
        raise SystemExit("benchmark frame is invalid under the physical model")

    def run_tri():
        triangulate(model, uv, *VOLTAGES)

    def run_phys():
        triangulate(physical, uv, *VOLTAGES)

    def run_cv():
        cv2.undistortPoints(uv_cv, K, D)

    for _ in range(200):  # warm-up
        run_tri()
        run_cv()
        run_phys()
    # Interleave them in blocks so machine load affects all alike.
    tri, cv, phys = [], [], []
    block = max(1, args.repeats // 10)
    for _ in range(10):
        tri.append(median_us(run_tri, block))
        cv.append(median_us(run_cv, block))
        phys.append(median_us(run_phys, block))
    tri_med = float(np.median([t[0] for t in tri]))
    cv_med = float(np.median([c[0] for c in cv]))
    phys_med = float(np.median([p[0] for p in phys]))
    print(f"points per frame: {uv.shape[0]}, distortion {DIST}, voltages {VOLTAGES}")
    print(
        f"stripe rows {uv[:, 1].min():.1f}..{uv[:, 1].max():.1f} px, depth "
        f"{res.p_v[:, 2].min():.4f}..{res.p_v[:, 2].max():.4f} m"
    )
    print(
        f"undistortion plan: start={'series guess' if plan.use_guess else 'xd'}, "
        f"steps={plan.n_fast}, last-step tol={plan.fast_tol:.2e}"
    )
    print(
        f"triangulate:         median {tri_med:8.1f} us (best block min "
        f"{min(t[1] for t in tri):.1f} us)"
    )
    print(
        f"cv2.undistortPoints: median {cv_med:8.1f} us (best block min "
        f"{min(c[1] for c in cv):.1f} us)"
    )
    print(
        f"triangulate, physical mirror model: median {phys_med:8.1f} us "
        f"(x{phys_med / tri_med:.2f} the paper model)"
    )
    print(f"goal <= 100 us: {'met' if max(tri_med, phys_med) <= 100.0 else 'NOT met'}")
    print(
        json.dumps(
            {
                "triangulation_us_per_frame": round(tri_med, 2),
                "undistort_us_per_frame": round(cv_med, 2),
                "ratio": round(tri_med / cv_med, 3),
                "physical_us_per_frame": round(phys_med, 2),
                "physical_ratio": round(phys_med / tri_med, 3),
            }
        )
    )


if __name__ == "__main__":
    main()
