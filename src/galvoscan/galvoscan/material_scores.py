"""Accuracy per surface material: the scan plans and the scores, for the materials benchmark
(in process) and ``galvoscan evaluate --materials`` (through the graph).

No rclpy here. Points are in V0 [m]; the truth (the scene, ``W_T_V0``) comes from the
simulator and is used only to score.

- stair error: measured minus true step of the stair block [mm] (``metrics.stair_step``
  on the points within 5 mm of the true surface);
- plate flatness: RMSE of the plate's points about a RANSAC plane [mm];
- outlier fraction: the share of points farther than :data:`OUTLIER_M` from the true
  surface;
- coverage: points per true stripe column (in process), or per point of the same scan of
  the matte part (through the graph, where the true columns are not known).
"""

from __future__ import annotations

import numpy as np

from galvoscan import metrics
from reconstructor.planning import aim_camera, view_sweep

#: A point farther than this from the true surface is an outlier [m].
OUTLIER_M = 0.5e-3
#: Points within this of the true surface are the stair's (``metrics.stair_step``) [m].
STAIR_BAND_M = 5e-3


def materials() -> tuple[str, ...]:
    """The named materials scored: every one of ``galvoscan_sim.materials`` but the
    near-mirror test material."""
    from galvoscan_sim.materials import MATERIAL_NAMES

    return tuple(m for m in MATERIAL_NAMES if m != 'polished_aluminium')


def faces_v0(scene, V0_T_W) -> list:
    """The scene's finite rectangular faces in V0, (centre, e1, e2, half) each: the part's
    nominal shape and pose (its CAD, where the operator put it)."""
    F = scene.faces
    R, t = V0_T_W[:3, :3], V0_T_W[:3, 3]
    return [(R @ F.center[k] + t, R @ F.e1[k], R @ F.e2[k], F.half[k])
            for k in range(len(F.obj)) if np.all(np.isfinite(F.half[k]))]


def stair_sweeps(model, V0_T_W, info, frames) -> list:
    """Three views of the stair block (its lower face, the step, its upper face), each a
    sweep of ``frames`` rows [V]."""
    W_T_O, sz, step = info['W_T_O'], info['size'][2], info['step_height']
    sweeps = []
    for x, z in ((-0.03, -sz), (0.0, -sz - step / 2), (0.03, -sz - step)):
        aim_V0 = (V0_T_W @ W_T_O @ np.array([x, 0.0, z, 1.0]))[:3]
        u1 = aim_camera(model, aim_V0)
        sweeps.append(view_sweep(model, *u1, distance=float(np.linalg.norm(aim_V0)),
                                 frames=frames))
    return sweeps


def aimed_sweep(model, V0_T_W, aim_W, frames) -> list:
    """One view aimed at ``aim_W`` (3,) [m, world], a sweep of ``frames`` rows [V]."""
    aim_V0 = (V0_T_W @ np.append(aim_W, 1.0))[:3]
    u1 = aim_camera(model, aim_V0)
    return [view_sweep(model, *u1, distance=float(np.linalg.norm(aim_V0)), frames=frames)]


def surface_offsets(scene, W_T_V0, points_v0) -> np.ndarray:
    """Distance of each point to the scene's true surface [m]: to the nearest point of any
    of its planar faces (rectangles, or planes where unbounded), (n,)."""
    p = np.asarray(points_v0, np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(0)
    p_w = p @ W_T_V0[:3, :3].T + W_T_V0[:3, 3]
    F = scene.faces
    best = np.full(len(p), np.inf)
    for k in range(len(F.obj)):
        d = p_w - F.center[k]
        x, y, z = d @ F.e1[k], d @ F.e2[k], d @ F.normal[k]
        dx = np.maximum(np.abs(x) - F.half[k][0], 0.0)
        dy = np.maximum(np.abs(y) - F.half[k][1], 0.0)
        best = np.minimum(best, np.sqrt(dx * dx + dy * dy + z * z))
    return best


def outlier_fraction(offsets) -> float:
    """Share of points farther than :data:`OUTLIER_M` from the true surface (NaN: none)."""
    o = np.asarray(offsets, np.float64)
    return float(np.mean(~(np.abs(o) <= OUTLIER_M))) if o.size else float('nan')


def stair_error_mm(W_T_V0, info, points_v0, offsets) -> float:
    """Measured minus true step of the stair block [mm], from its points in V0 and their
    offsets from the true surface [m].

    Raises
    ------
    ValueError
        Too few points on a face (``metrics.stair_step``).
    """
    O_T_V0 = np.linalg.inv(info['W_T_O']) @ W_T_V0
    pts = metrics.to_frame(O_T_V0, np.asarray(points_v0, np.float64).reshape(-1, 3))
    keep = np.abs(np.asarray(offsets)) <= STAIR_BAND_M
    return metrics.stair_step(pts[keep], info['size'], info['step_height']).error * 1e3


def flatness_mm(points_v0) -> float:
    """RMSE of the points about a RANSAC plane [mm] (NaN under 100 points)."""
    p = np.asarray(points_v0, np.float64).reshape(-1, 3)
    if len(p) < 100:
        return float('nan')
    plane, inl = metrics.ransac_plane(p, threshold=2e-3, iterations=500, seed=0)
    return float(np.sqrt(np.mean((p[inl] @ plane[:3] + plane[3]) ** 2))) * 1e3


def _cell(value, fmt: str) -> str:
    return 'n/a' if value is None or not np.isfinite(value) else format(value, fmt)


def table_markdown(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """A Markdown table: ``columns`` are (key, heading, format) of each row's values."""
    out = ['| ' + ' | '.join(h for _, h, _ in columns) + ' |',
           '|' + '---|' * len(columns)]
    for r in rows:
        out.append('| ' + ' | '.join(
            str(r[k]) if f == 's' else _cell(r.get(k), f) for k, _, f in columns) + ' |')
    return '\n'.join(out)
