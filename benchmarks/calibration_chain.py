"""The whole calibration chain on the simulated reference rig, in-process, with the capture
plans of ``calibration_tools.capture_plans``.

Run: ``.venv/bin/python benchmarks/calibration_chain.py [--rig NAME] [--seed N] [--no-quick]``

Starting from the rig's design values (``simulated_rig.nominal_calibration``), every stage in
order: plan (with the calibration so far) -> render as the driver's sim backend would
(``simulated_rig.execute_in_process``) -> compute -> merge. Once with the quick plans (the CI
end-to-end run), once with the full plans. Per stage: capture steps, frames (board frames
at the calibration exposure / stripe frames), render and compute seconds, residuals.

The calibrated model is then scored against the simulator's physics
(``galvoscan.sim_scores``), next to the design values and the simulator's
model-equivalent "true" parameters:

- reconstruction: the true stripe pixels of a wall at 650 mm, scanned at 5 x 5 G1 positions
  over +-8 V, triangulated with the model and compared with the true points (RMS in V0, and
  after the best rigid motion: the shape error), with and without the joint correction;
- dynamic camera: the paper's transfer-matrix RMSE (Eq. 18-1) at its 36 G1 positions against
  the exact virtual-camera poses, and the RMS distance of points seen at 650 mm;
- intrinsics: RMS pixel distance over the image, fx, cx, cy errors;
- laser: U2 = 0 plane normal angle and distance at the working volume; largest plane
  distance over a +-4 V sweep;
- joint correction: the paper's Error1 / Error3 before and Error2 after.

The paper's figures (transfer matrix 1.231 mm; joint 4.928 / 5.475 -> 0.197 mm) are printed
for comparison only. Times are wall-clock on a shared machine. The last line of stdout is one
JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import time

from calibration_tools import stage_runner
from calibration_tools.capture_plans import total_frames
from calibration_tools.registry import plan
from calibration_tools.stages import STAGES, apply_result
from galvoscan import sim_scores, simulated_rig
from galvoscan.simulated_rig import execute_in_process, truth_model
from galvoscan_sim import Simulator, load_rig, load_scene
from reconstructor import calibration_file

PAPER = {'transfer_matrix_rmse_mm': 1.231, 'joint_error1_mm': 4.928, 'joint_error3_mm': 5.475,
         'joint_error2_mm': 0.197}


def run_chain(rig_name: str, quick: bool, seed: int):
    rig = load_rig(rig_name)
    sim = Simulator(rig, load_scene('plane'), seed=seed)
    cal = simulated_rig.nominal_calibration(rig_name)
    stages = {}
    for stage in STAGES:
        t0 = time.perf_counter()
        steps = plan(stage, cal, quick=quick)
        t1 = time.perf_counter()
        views, _ = execute_in_process(sim, steps)
        t2 = time.perf_counter()
        result = stage_runner.compute(stage, views, cal)
        t3 = time.perf_counter()
        cal = apply_result(cal, result, [{'path': 'in-process',
                                          'sha256': stage_runner.views_digest(views)}])
        off = sum(s.frames for s in steps if not s.laser_on)
        stages[stage] = {
            'steps': len(steps), 'frames': total_frames(steps), 'board_frames': off,
            'stripe_frames': total_frames(steps) - off, 'plan_s': t1 - t0,
            'render_s': t2 - t1, 'compute_s': t3 - t2,
            'samples_used': result.samples_used, 'samples_rejected': result.samples_rejected,
            'residuals': dict(result.residuals),
        }
        print(f"  {'quick' if quick else 'full'} {stage}: {len(steps)} steps, "
              f"{total_frames(steps)} frames ({off} board, {total_frames(steps) - off} stripe),"
              f" render {t2 - t1:.1f} s, compute {t3 - t2:.1f} s, used "
              f"{result.samples_used}, rejected {result.samples_rejected}", flush=True)
    return cal, stages


def figures(model, rig, joint_residuals=None) -> dict:
    s = sim_scores.scores(model, rig)
    cam = rig.camera
    out = {
        'reconstruction_rms_mm': 1e3 * s['reconstruction_rms_m'],
        'reconstruction_shape_rms_mm': 1e3 * s['reconstruction_shape_rms_m'],
        'reconstruction_rms_without_joint_mm': 1e3 * s['reconstruction_rms_without_joint_m'],
        'transfer_matrix_rmse_mm': s['transfer_matrix_rmse_mm'],
        'pointing_rms_mm': 1e3 * s['pointing_rms_m'],
        'intrinsics_rms_px': s['intrinsics_rms_px'],
        'fx_error_pct': 100 * s['fx_rel_error'],
        'cx_error_px': model.intrinsics.cx - cam.cx, 'cy_error_px': model.intrinsics.cy - cam.cy,
        'k1': model.intrinsics.dist[0],
        'l_mm': 1e3 * model.l, 'd_mm': 1e3 * model.d,
        'laser_plane_normal_deg': s['laser_plane_normal_deg'],
        'laser_plane_at_work_mm': 1e3 * s['laser_plane_at_work_m'],
        'laser_sweep_max_mm': 1e3 * s['laser_sweep_max_m'],
    }
    if joint_residuals:
        for k in ('error1', 'error3', 'error2'):
            out[f'joint_{k}_mm'] = 1e3 * joint_residuals[f'{k}_rms_m']
    return out


def fmt(d):
    return ', '.join(f'{k} {v:.4g}' if isinstance(v, float) else f'{k} {v}'
                     for k, v in d.items())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rig', default='reference')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--no-quick', action='store_true', help='full plans only')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rig = load_rig(args.rig)
    t_start = time.perf_counter()
    out = {'rig': args.rig, 'seed': args.seed, 'paper': PAPER}
    out['design_values'] = figures(simulated_rig.nominal_calibration(args.rig).model, rig)
    out['simulator_model_equivalent'] = figures(truth_model(rig), rig)
    print(f'design values: {fmt(out["design_values"])}')
    print(f'simulator model-equivalent parameters: {fmt(out["simulator_model_equivalent"])}')
    for quick in ((False,) if args.no_quick else (True, False)):
        label = 'quick' if quick else 'full'
        t0 = time.perf_counter()
        cal, stages = run_chain(args.rig, quick, args.seed)
        total = time.perf_counter() - t0
        # The model with its joint-correction table, as the reconstructor loads the file.
        model = calibration_file.validate(cal.to_dict()).model
        figs = figures(model, rig, stages['joint_correction']['residuals'])
        print(f'{label} plans: {sum(s["frames"] for s in stages.values())} frames, '
              f'render {sum(s["render_s"] for s in stages.values()):.1f} s, compute '
              f'{sum(s["compute_s"] for s in stages.values()):.1f} s, total {total:.1f} s')
        print(f'{label} calibrated: {fmt(figs)}')
        out[label] = {'stages': stages, 'total_s': total, 'calibrated': figs}
    full = out.get('full', {}).get('calibrated')
    if full:
        print(f"full chain vs the paper: transfer-matrix RMSE "
              f"{full['transfer_matrix_rmse_mm']:.3f} mm (paper "
              f"{PAPER['transfer_matrix_rmse_mm']} mm, measured); joint correction "
              f"Error1 {full['joint_error1_mm']:.3f} / Error3 {full['joint_error3_mm']:.3f} mm "
              f"before, Error2 {full['joint_error2_mm']:.3f} mm after (paper "
              f"{PAPER['joint_error1_mm']} / {PAPER['joint_error3_mm']} -> "
              f"{PAPER['joint_error2_mm']} mm)")
    out['elapsed_s'] = time.perf_counter() - t_start
    print(json.dumps(out, default=float))


if __name__ == '__main__':
    main()
