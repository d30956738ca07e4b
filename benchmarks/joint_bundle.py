"""Would one bundle over camera and laser beat the staged calibration? Measured on the simulator.

Run: ``.venv/bin/python benchmarks/joint_bundle.py [--rigs 3] [--seed-start 0] [--reference]
[--max-nfev 100]``

Every parameter is asked for in one sparse least squares. The calibration estimates the
camera (intrinsics, dynamic camera) from circles, then the laser from stripe points placed in
V0 through that camera, and carries the camera's covariance into the laser's
(:mod:`reconstructor.uncertainty`). What the staged path leaves out is the stripes' own
information about the camera. This benchmark measures what that is worth.

Per rig (``galvoscan_sim.rig_family.draw_rig(seed)``, or ``--reference``: the reference rig
with simulator seed = seed), in this process: intrinsics, dynamic camera and laser plane are
calibrated on the simulator and the laser-axis views captured; then, from those same views,

- **staged**: the laser-axis stage as it runs in the product (staged fit, laser bundle);
- **joint**: one robust sparse least squares (scipy ``least_squares``, ``jac_sparsity``) over
  the laser-axis views' board features (px), every stripe point (its distance to the model's
  laser plane at its G2 voltage, through its pixel, its board's pose and the camera), with
  the camera (the intrinsics and dynamic camera's parameters), the laser
  (:class:`calibration_tools.laser_bundle.LaserParameters`) and every board's pose free. The
  circles of the earlier stages enter as the prior their fit left on the camera: the joint
  covariance of those stages (``parameter_covariance``). To first order that is the same as
  adding their circles and board poses to the problem (the boards' poses are not shared, so
  they marginalise into exactly that prior); the prior is the stages' cluster-robust
  covariance, the honest one, not the circles' raw information.

Scored as ``uncertainty_check`` scores the calibration's part: the simulator's exact stripe
pixels over a 9 x 9 grid of G1 views within +-8 V, on the rig without its galvos' frame
scatter, triangulated with each model; RMS error after the best rigid motion (shape).
One line per rig; the last line of stdout is one JSON object with the ratios joint / staged.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

EMPTY_SCENE = ('format_version: 1\nname: empty\nobjects:\n  - type: plane\n    name: floor\n'
               '    pose: {translation: [0.0, 0.0, 5.0]}\n    albedo: 0.1\n')
#: Robust loss scale of the joint problem, in the residuals' own sigmas (soft L1 beyond).
ROBUST_SIGMAS = 2.5


def staged_chain(rig, seed: int):
    """Intrinsics, dynamic camera and laser plane calibrated; the laser-axis views and the
    laser-axis stage's result on them: (calibration before it, views, its result)."""
    from calibration_tools import stage_runner
    from calibration_tools.registry import plan
    from calibration_tools.stages import apply_result
    from galvoscan.simulated_rig import execute_in_process, nominal_calibration
    from galvoscan_sim import Simulator, load_scene_text

    sim = Simulator(rig, load_scene_text(EMPTY_SCENE), seed=seed)
    cal = nominal_calibration(rig)
    for stage in ('intrinsics', 'dynamic_camera', 'laser_plane'):
        views, _ = execute_in_process(sim, plan(stage, cal))
        cal = apply_result(cal, stage_runner.compute(stage, views, cal),
                           [{'path': f'in-process {stage}', 'sha256': '0' * 64}])
    views, _ = execute_in_process(sim, plan('laser_axis', cal))
    return cal, views, stage_runner.compute('laser_axis', views, cal)


class JointProblem:
    """The laser-axis views' features and stripes, the camera under its prior, the laser."""

    def __init__(self, before, views, staged_model, sigma_stripe_m: float) -> None:
        from calibration_tools.board_geometry import project_circle_centres
        from calibration_tools.laser_bundle import LaserParameters
        from calibration_tools.laser_plane import BoardPoses, board_stripe_points
        from calibration_tools.registry import board_views, stage_options
        from reconstructor.model import v0_T_v
        from reconstructor.uncertainty import parameter_covariance, parameter_value

        self.project = project_circle_centres
        opts = stage_options('laser_axis', before)
        board = opts['board']
        bv = board_views(views)
        coll = board_stripe_points(bv, before.model, board, edge_margin=opts['edge_margin'])
        self.obj = board.object_points()
        zero = np.zeros(len(self.obj))
        intr = before.model.intrinsics
        poses = BoardPoses(bv, board, before.model, 0.5)  # as the stage found them
        boards: dict = {}
        self.stripes = []
        for s in coll.stripes:  # each stripe's board: the laser-off view it was measured on
            pose, corners, _ = poses.for_view(s.view_index)
            if pose is None:
                continue
            key = id(pose)
            if key not in boards:
                boards[key] = {'T': pose.V_T_B,
                               'corners': np.asarray(corners, float).reshape(-1, 2),
                               'index': len(boards)}
            T = v0_T_v(before.model, *s.u1)
            p_v = (s.points_v0 - T[:3, 3]) @ T[:3, :3]  # back to V; its pixels, as measured
            uv = project_circle_centres(intr, np.eye(4), p_v, np.zeros(len(p_v)))
            self.stripes.append({'uv': uv, 'u1': s.u1, 'u2': s.u2_tilt,
                                 'board': boards[key]['index']})
        self.boards = sorted(boards.values(), key=lambda b: b['index'])
        rms = [np.mean(np.sum((project_circle_centres(intr, b['T'], self.obj, zero)
                               - b['corners']) ** 2, axis=1)) for b in self.boards]
        self.sigma_feature_px = float(np.sqrt(np.mean(rms) / 2.0))
        self.sigma_stripe_m = float(sigma_stripe_m)
        pc = parameter_covariance(before)
        self.cam = [n for n in pc.names if n.startswith(
            ('intrinsics.', 'physical.camera', 'physical.g1', 'g1_')) or n in ('l', 'd')]
        ix = [pc.names.index(n) for n in self.cam]
        C = np.asarray(pc.matrix, dtype=np.float64)[np.ix_(ix, ix)]
        self.sd = np.sqrt(np.diag(C))
        w, V = np.linalg.eigh(C / np.outer(self.sd, self.sd))
        keep = w > 1e-10 * w.max()
        self.whiten = (V[:, keep] / np.sqrt(w[keep])).T
        self.model0 = staged_model
        self.start = {n: parameter_value(staged_model, n) for n in self.cam}
        self.laser = LaserParameters(staged_model, 3)
        self.nc, self.nl = len(self.cam), self.laser.size
        self.scale = np.concatenate([self.sd, self.laser.scale,
                                     np.tile([1e-4] * 3 + [1e-5] * 3, len(self.boards))])

    def unpack(self, z):
        from calibration_tools.board_fit import rodrigues
        from reconstructor.model import RigModel
        from reconstructor.uncertainty import with_parameters

        x = z * self.scale
        m = with_parameters(self.model0, dict(zip(self.cam, x[:self.nc], strict=True)))
        v = self.laser.values(x[self.nc:self.nc + self.nl])
        data = m.to_dict()
        for k in ('laser_plane_v0', 'laser_axis_dir', 'laser_axis_point'):
            data[k] = [float(a) for a in v[k]]
        data['g2_tilt'] = {**data['g2_tilt'], 'k': float(v['g2_tilt']['k']),
                           'poly': [float(a) for a in v['g2_tilt']['poly']]}
        m = RigModel.from_dict(data, correction=self.model0.correction)
        Ts = []
        for j, b in enumerate(self.boards):
            d = x[self.nc + self.nl + 6 * j: self.nc + self.nl + 6 * j + 6]
            T = np.eye(4)
            T[:3, :3] = rodrigues(d[:3]) @ b['T'][:3, :3]
            T[:3, 3] = b['T'][:3, 3] + d[3:]
            Ts.append(T)
        return m, Ts

    def fun(self, z):
        from reconstructor.model import laser_plane_v0, undistort_points, v0_T_v

        m, Ts = self.unpack(z)
        out = [self.whiten @ z[:self.nc]]
        zero = np.zeros(len(self.obj))
        for b, T in zip(self.boards, Ts, strict=True):
            out.append(((self.project(m.intrinsics, T, self.obj, zero) - b['corners'])
                        / self.sigma_feature_px).ravel())
        planes = laser_plane_v0(m, np.array([s['u2'] for s in self.stripes]))
        for s, pl in zip(self.stripes, planes, strict=True):
            T = Ts[s['board']]
            ray = np.column_stack([undistort_points(m.intrinsics, s['uv']),
                                   np.ones(len(s['uv']))])
            n = T[:3, 2]
            p = ray * ((n @ T[:3, 3]) / (ray @ n))[:, None]
            M = v0_T_v(m, *s['u1'])
            q = p @ M[:3, :3].T + M[:3, 3]
            out.append((q @ pl[:3] + pl[3]) / self.sigma_stripe_m / np.sqrt(len(q)))
        return np.concatenate(out)

    def sparsity(self):
        from scipy.sparse import lil_matrix

        nf = [2 * len(b['corners']) for b in self.boards]
        ns = [len(s['uv']) for s in self.stripes]
        n_rows = len(self.whiten) + sum(nf) + sum(ns)
        first = self.nc + self.nl
        S = lil_matrix((n_rows, first + 6 * len(self.boards)), dtype=np.int8)
        S[:len(self.whiten), :self.nc] = 1
        r = len(self.whiten)
        intr = [k for k, n in enumerate(self.cam) if n.startswith('intrinsics.')]
        for j, k in enumerate(nf):
            for c in intr:
                S[r:r + k, c] = 1
            S[r:r + k, first + 6 * j: first + 6 * j + 6] = 1
            r += k
        for s, k in zip(self.stripes, ns, strict=True):
            S[r:r + k, :first] = 1
            S[r:r + k, first + 6 * s['board']: first + 6 * s['board'] + 6] = 1
            r += k
        return S


def run(seed: int, reference: bool, max_nfev: int, folder: Path) -> dict:
    from scipy.optimize import least_squares

    from calibration_tools.capture_plans import laser_crossing_depth
    from calibration_tools.stages import apply_result
    from galvoscan import sim_scores
    from galvoscan_sim import load_rig
    from galvoscan_sim.rig_family import draw_rig

    if reference:
        rig = load_rig('reference')
    else:
        path = folder / f'rig_{seed:03d}.yaml'
        path.write_text(yaml.safe_dump(draw_rig(seed), sort_keys=False))
        rig = load_rig(str(path))
    t0 = time.monotonic()
    before, views, result = staged_chain(rig, seed)
    staged = apply_result(before, result, [{'path': 'in-process laser_axis',
                                            'sha256': '0' * 64}])
    t_staged = time.monotonic() - t0
    prob = JointProblem(before, views, staged.model,
                        result.residuals.get('bundle_point_rms_m', 2e-5))
    t1 = time.monotonic()
    sol = least_squares(prob.fun, np.zeros(len(prob.scale)), jac_sparsity=prob.sparsity(),
                        loss='soft_l1', f_scale=ROBUST_SIGMAS, method='trf',
                        x_scale='jac', max_nfev=max_nfev)
    t_joint = time.monotonic() - t1
    joint, _ = prob.unpack(sol.x)
    quiet = rig.without_jitter()
    depth = laser_crossing_depth(staged.model)

    def shape(m):
        return sim_scores.reconstruction_errors(m, quiet, span=8.0, n=9,
                                                depth=depth)['aligned_rms_m'] * 1e3

    moved = np.abs(sol.x[:prob.nc])
    return {'seed': seed, 'depth_mm': depth * 1e3, 'staged_mm': shape(staged.model),
            'joint_mm': shape(joint), 'boards': len(prob.boards),
            'stripes': len(prob.stripes), 'camera_parameters': prob.nc,
            'camera_moved_max_sigma': float(moved.max()),
            'camera_moved_most': prob.cam[int(np.argmax(moved))],
            'nfev': int(sol.nfev), 'converged': bool(sol.status > 0),
            'staged_chain_s': t_staged, 'joint_s': t_joint}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rigs', type=int, default=3)
    p.add_argument('--seed-start', type=int, default=0)
    p.add_argument('--reference', action='store_true',
                   help='the reference rig with simulator seeds, not drawn rigs')
    p.add_argument('--max-nfev', type=int, default=100,
                   help='function evaluations of the joint solve (1..1000)')
    args = p.parse_args(argv)
    if not 1 <= args.rigs <= 50:
        p.error('--rigs must be 1..50')
    if not 1 <= args.max_nfev <= 1000:
        p.error('--max-nfev must be 1..1000')
    t0 = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory(prefix='galvoscan_joint_') as tmp:
        for i, seed in enumerate(range(args.seed_start, args.seed_start + args.rigs), 1):
            row = run(seed, args.reference, args.max_nfev, Path(tmp))
            rows.append(row)
            print(f"rig {i}/{args.rigs} seed {seed} ({row['depth_mm']:.0f} mm): staged "
                  f"{row['staged_mm']:.4f} mm, joint {row['joint_mm']:.4f} mm "
                  f"(x{row['joint_mm'] / row['staged_mm']:.3f}); camera moved at most "
                  f"{row['camera_moved_max_sigma']:.2f} sigma ({row['camera_moved_most']}); "
                  f"{row['boards']} boards, {row['stripes']} stripes; {row['nfev']} "
                  f"evaluations{'' if row['converged'] else ' (not converged)'} "
                  f"[chain {row['staged_chain_s']:.0f} s, joint {row['joint_s']:.0f} s]",
                  flush=True)
    ratios = np.array([r['joint_mm'] / r['staged_mm'] for r in rows])
    print(json.dumps({'rigs': len(rows), 'reference': args.reference,
                      'staged_mm': [r['staged_mm'] for r in rows],
                      'joint_mm': [r['joint_mm'] for r in rows],
                      'ratio_joint_to_staged': ratios.tolist(),
                      'ratio_median': float(np.median(ratios)),
                      'camera_moved_max_sigma': max(r['camera_moved_max_sigma'] for r in rows),
                      'wall_s': time.monotonic() - t0}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
