"""Calibration II on the simulated rigs: laser plane, laser axis and the joint correction.

Run: ``.venv/bin/python benchmarks/calibration_laser.py [--seeds N] [--quick]``

For the ``ideal`` and the ``reference`` rig (``galvoscan_sim``), with the simulator as the
judge:

1. laser plane at U2 = 0 (16 circle-grid poses) -> normal and offset errors;
2. laser axis (36 poses, 18 G2 voltages over +-4 V) -> direction, distance, k errors;
3. joint correction with the model these stages produced (intrinsics and dynamic camera are
   the simulator's model-equivalent values, standing in for Calibration I):

   - *local*: the sphere in the middle, a 5 x 5 G1 grid of +-0.3 / +-0.2 V around it;
   - *wide*: the sphere moved to 5 x 3 positions (G2 moved with it), 0.1 V G1 grid nodes
     around each position, positions chained through shared nodes (the paper's M), covering
     about +-1 V of G1 pan and tilt.

   Reported: the paper's Error1 / Error3 before and Error2 after (and the same against the
   densified reference stripe), and the true RMS error of the reconstructed stripe points
   before and after the correction, at the nodes and at held-out voltages between them.

The paper's figures (4.928 / 5.475 mm before, 0.197 mm after) are printed beside ours for
comparison only. The last line of stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import time

import numpy as np

from calibration_tools.board_layout import CircleGrid
from calibration_tools.joint_correction import run_joint_correction
from calibration_tools.laser_axis import run_laser_axis
from calibration_tools.laser_plane import run_laser_plane
from calibration_tools.stages import apply_result
from galvoscan.sim_scores import stripe_point_errors
from galvoscan.simulated_rig import board_poses_on_laser, sphere_g1_grid
from galvoscan_sim.rig import load_rig
from galvoscan_sim.scene import load_scene
from galvoscan_sim.simulator import Simulator
from reconstructor import calibration_file as cf
from reconstructor.correction import CorrectionTable
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel

PAPER = {'error1_mm': 4.928, 'error3_mm': 5.475, 'error2_mm': 0.197}
BOARD = CircleGrid(cols=11, rows=8, pitch=0.0045, diameter=0.0025)
PLANE_DEPTHS = [0.585 + 0.0025 * i for i in range(8)] + [0.6975 + 0.0025 * i for i in range(8)]
AXIS_CENTRES = [-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0]
AXIS_DEPTHS = [0.59, 0.6, 0.7, 0.71]
RADIUS = 0.01


def operator_model(truth, rng):
    """Calibration I's results (the simulator's model-equivalent values) plus rough laser
    values such as a design drawing gives."""
    return RigModel(
        intrinsics=CameraIntrinsics(truth.fx, truth.fy, truth.cx, truth.cy,
                                    tuple(truth.distortion), 720, 540),
        g1_pan=MirrorParams(truth.theta0_pan, truth.k_pan),
        g1_tilt=MirrorParams(truth.theta0_tilt, truth.k_tilt),
        l=truth.l, d=truth.d,
        laser_plane_v0=truth.pi0 + np.r_[rng.normal(0, 0.002, 3), rng.normal(0, 5e-4)],
        laser_axis_dir=truth.n + rng.normal(0, 0.002, 3),
        laser_axis_point=truth.P + rng.normal(0, 0.002, 3),
        g2_tilt=MirrorParams(math.pi / 4, truth.k2 * (1 + rng.normal(0, 0.002))))


def angle_deg(a, b):
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def dist_to_line(q, p, n):
    w = q - p
    return float(np.linalg.norm(w - (w @ n) * n))


def plane_stage(rig, model, seed):
    sim = Simulator(rig, load_scene('checkerboard'), seed=seed)
    views, _ = board_poses_on_laser(sim, model, [0.0], PLANE_DEPTHS, BOARD, seed=seed)
    cal = cf.Calibration(model=model)
    res = run_laser_plane(views, cal, board=BOARD)
    truth = rig.true_model_parameters()
    plane = np.array(res.updates['laser_plane_v0'])
    true = truth.pi0 if truth.pi0[:3] @ plane[:3] > 0 else -truth.pi0
    work = np.array([0.0, 0.0, 0.65])
    figs = {'normal_error_deg': angle_deg(plane[:3], true[:3]),
            'offset_error_mm': abs(plane[3] - true[3]) * 1e3,
            'error_at_650mm_mm': abs(plane[:3] @ work + plane[3]) * 1e3,
            'fit_rms_um': res.residuals['plane_rms_m'] * 1e6}
    return apply_result(cal, res), figs


def axis_stage(rig, cal, seed):
    """The axis by the paper's method and by the general (cone + offset) one."""
    sim = Simulator(rig, load_scene('checkerboard'), seed=seed)
    views, _ = board_poses_on_laser(sim, cal.model, AXIS_CENTRES, AXIS_DEPTHS, BOARD,
                                    offsets=(-0.05, 0.05), seed=seed)
    out = []
    for opts in ({}, {'method': 'cone', 'fit_offset': True}):
        res = run_laser_axis(views, cal, board=BOARD, **opts)
        new = apply_result(cal, res)
        figs = _axis_figures(rig, res)
        figs['plane_prediction_error_mm_max'] = plane_prediction_error(rig, new.model) * 1e3
        out.append((new, figs))
    return out


PREDICTION_VOLTS = tuple(np.linspace(-4.0, 4.0, 17))


def plane_prediction_error(rig, model, volts=PREDICTION_VOLTS):
    """Largest distance (m) between the model's laser plane and the simulator's actual one
    at U2 in +-4 V, over points of the actual plane at x in +-100 mm and 600..700 mm depth."""
    from reconstructor.model import laser_plane_v0

    sim = Simulator(rig, load_scene('sphere'), seed=0)
    worst = 0.0
    for u in volts:
        u = float(rig.dac.quantize(u))
        true = sim.render([0.0, 0.0, 0.0, u]).truth.laser_plane_V0
        pred = laser_plane_v0(model, u)
        for x in (-0.1, 0.0, 0.1):
            for z in (0.6, 0.65, 0.7):
                p = np.array([x, -(true[0] * x + true[2] * z + true[3]) / true[1], z])
                worst = max(worst, abs(pred[:3] @ p + pred[3]) / np.linalg.norm(pred[:3]))
    return worst


def _axis_figures(rig, res):
    truth = rig.true_model_parameters()
    n = np.array(res.updates['laser_axis_dir'])
    P = np.array(res.updates['laser_axis_point'])
    figs = {'direction_error_deg': angle_deg(n, truth.n),
            'distance_mm': dist_to_line(truth.P, P, n) * 1e3,
            'distance_max_550mm_mm': max(dist_to_line(truth.P + s * truth.n, P, n)
                                         for s in np.linspace(-0.55, 0.55, 23)) * 1e3,
            'k_rel_error': res.updates['g2_tilt']['k'] / truth.k2 - 1,
            'planes': res.residuals['planes_used'],
            'axis_distance_rms_um': res.residuals['axis_distance_rms_m'] * 1e6,
            'cone_angle_deg': math.degrees(res.residuals['axis_cone_angle_rad'])}
    return figs


def rms_mm(x):
    return float(np.sqrt(np.mean(np.square(x)))) * 1e3 if len(x) else float('nan')


def joint_figures(cal, res, views, truths, held, held_truths):
    table = CorrectionTable.from_dict(res.extra['joint_correction'])
    corrected = dataclasses.replace(cal.model, correction=table)
    r = res.residuals
    return {
        'error1_mm': r['error1_rms_m'] * 1e3, 'error3_mm': r['error3_rms_m'] * 1e3,
        'error2_mm': r['error2_rms_m'] * 1e3,
        'error1_dense_mm': r['error1_dense_rms_m'] * 1e3,
        'error3_dense_mm': r['error3_dense_rms_m'] * 1e3,
        'error2_dense_mm': r['error2_dense_rms_m'] * 1e3,
        'nodes_registered': int(r['nodes_registered']), 'nodes_skipped': int(r['nodes_skipped']),
        'nodes_not_converged': int(r['nodes_not_converged']),
        'true_rms_nodes_before_mm': rms_mm(stripe_point_errors(cal.model, views, truths)),
        'true_rms_nodes_after_mm': rms_mm(stripe_point_errors(corrected, views, truths)),
        'true_rms_between_before_mm': rms_mm(stripe_point_errors(cal.model, held, held_truths)),
        'true_rms_between_after_mm': rms_mm(stripe_point_errors(corrected, held, held_truths)),
    }


def joint_local(rig, cal, seed):
    sim = Simulator(rig, load_scene('sphere'), seed=seed)
    pans, tilts = np.linspace(-0.3, 0.3, 5), np.linspace(-0.2, 0.2, 5)
    views, truths, _, _ = sphere_g1_grid(sim, cal.model, 0.0, RADIUS, pans, tilts,
                                         absolute=True)
    held, held_truths, _, _ = sphere_g1_grid(sim, cal.model, 0.0, RADIUS,
                                             (pans[1:] + pans[:-1]) / 2,
                                             (tilts[1:] + tilts[:-1]) / 2, absolute=True)
    t0 = time.perf_counter()
    res = run_joint_correction(views, cal, sphere_radius=RADIUS)
    figs = joint_figures(cal, res, views, truths, held, held_truths)
    figs['compute_s'] = time.perf_counter() - t0
    return figs


def joint_wide(rig, cal, seed, laterals, u2s, step=0.1, reach=(0.3, 0.3), held_per_position=3):
    """Sphere at several positions, chained. G1 nodes on one global grid of ``step`` V."""
    from reconstructor.model import laser_plane_v0
    from reconstructor.planning import aim_g1

    sim = Simulator(rig, load_scene('sphere'), seed=seed)
    views, truths, held, held_truths = [], [], [], []
    rng = np.random.default_rng(seed)
    pose = 0
    for u2 in u2s:
        for x in laterals:
            pi = laser_plane_v0(cal.model, u2)
            centre = np.array([x, -(pi[0] * x + pi[2] * 0.65 + pi[3]) / pi[1], 0.65 + RADIUS])
            aim = aim_g1(cal.model, centre)
            pans, tilts = (np.round(np.arange(np.ceil((a - r) / step - 1e-9),
                                              np.floor((a + r) / step + 1e-9) + 1)) * step
                           for a, r in zip(aim, reach, strict=True))
            v, t, _, _ = sphere_g1_grid(sim, cal.model, u2, RADIUS, pans, tilts, lateral=x,
                                        absolute=True, pose_index=pose)
            views += v
            truths += t
            hp = rng.uniform(pans[0], pans[-1], held_per_position)
            ht = rng.uniform(tilts[0], tilts[-1], 1)
            v, t, _, _ = sphere_g1_grid(sim, cal.model, u2, RADIUS, hp, ht, lateral=x,
                                        absolute=True, pose_index=pose)
            held += v
            held_truths += t
            pose += 1
    t0 = time.perf_counter()
    res = run_joint_correction(views, cal, sphere_radius=RADIUS)
    figs = joint_figures(cal, res, views, truths, held, held_truths)
    figs['compute_s'] = time.perf_counter() - t0
    figs['positions'] = pose
    table = CorrectionTable.from_dict(res.extra['joint_correction'])
    figs['g1_range_v'] = [float(table.u1_pan[0]), float(table.u1_pan[-1]),
                          float(table.u1_tilt[0]), float(table.u1_tilt[-1])]
    return figs


def fmt(d):
    return ', '.join(f'{k} {v:.4g}' if isinstance(v, float) else f'{k} {v}'
                     for k, v in d.items())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=3, help='seeds of the ideal-rig stages')
    parser.add_argument('--quick', action='store_true', help='skip the wide joint protocol')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    out = {'paper': PAPER}
    t_start = time.perf_counter()
    for rig_name in ('ideal', 'reference'):
        rig = load_rig(rig_name)
        truth = rig.true_model_parameters()
        seeds = range(args.seeds) if rig_name == 'ideal' else range(1)
        planes, axes, cones = [], [], []
        cal = None
        for seed in seeds:
            model = operator_model(truth, np.random.default_rng(100 + seed))
            cal_p, fp = plane_stage(rig, model, seed)
            (cal_a, fa), (cal_c, fc) = axis_stage(rig, cal_p, seed)
            planes.append(fp)
            axes.append(fa)
            cones.append(fc)
            print(f'{rig_name} seed {seed}: laser plane: {fmt(fp)}')
            print(f'{rig_name} seed {seed}: laser axis (paper): {fmt(fa)}')
            print(f'{rig_name} seed {seed}: laser axis (cone + offset): {fmt(fc)}')
            if cal is None:  # the joint correction uses the paper's axis fit
                cal = cal_a
        entry = {
            'plane_normal_error_deg_max': max(p['normal_error_deg'] for p in planes),
            'plane_offset_error_mm_max': max(p['offset_error_mm'] for p in planes),
            'plane_error_at_650mm_mm_max': max(p['error_at_650mm_mm'] for p in planes),
            'axis_direction_error_deg_max': max(a['direction_error_deg'] for a in axes),
            'axis_distance_mm_max': max(a['distance_mm'] for a in axes),
            'axis_k_rel_error_max': max(abs(a['k_rel_error']) for a in axes),
            'axis_cone_direction_error_deg_max': max(a['direction_error_deg'] for a in cones),
            'axis_cone_distance_mm_max': max(a['distance_mm'] for a in cones),
            'axis_cone_k_rel_error_max': max(abs(a['k_rel_error']) for a in cones),
            'plane_prediction_error_mm_max': max(a['plane_prediction_error_mm_max']
                                                 for a in axes),
            'plane_prediction_error_cone_mm_max': max(a['plane_prediction_error_mm_max']
                                                      for a in cones),
            'seeds': len(planes),
        }
        local = joint_local(rig, cal, 0)
        print(f'{rig_name}: joint correction (local 5 x 5): {fmt(local)}')
        entry['joint_local'] = local
        if not args.quick:
            wide = joint_wide(rig, cal, 0, laterals=np.arange(-0.02, 0.2201, 0.02), u2s=(0.0,),
                              reach=(0.3, 0.1))
            print(f'{rig_name}: joint correction (wide, chained): {fmt(wide)}')
            entry['joint_wide'] = wide
        out[rig_name] = entry
    ref = out['reference'].get('joint_wide', out['reference']['joint_local'])
    print(f'reference rig joint correction: Error1 {ref["error1_mm"]:.3f} mm, Error3 '
          f'{ref["error3_mm"]:.3f} mm before, Error2 {ref["error2_mm"]:.3f} mm after '
          f'(paper: {PAPER["error1_mm"]} / {PAPER["error3_mm"]} before, {PAPER["error2_mm"]} '
          f'after)')
    out['elapsed_s'] = time.perf_counter() - t_start
    print(json.dumps(out, default=float))


if __name__ == '__main__':
    main()
