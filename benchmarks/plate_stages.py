"""Which calibration stage carries a rig's flat-plate error: the plate's stripes triangulated by
the calibration, by its dynamic camera alone, and by the truth.

Run: ``.venv/bin/python benchmarks/plate_stages.py --rig RIG.yaml --calibration CAL.yaml
[--grid 21] [--pose 0] [--extracted]``

With a simulated rig and a calibration of it (e.g. ``galvoscan evaluate``'s
``calibration.yaml``), the evaluation's flat plate (``eval_scenes.plate``, pose ``--pose``, at
the rig's working point) is crossed by the laser at a ``--grid`` x ``--grid`` lattice of points
over 95 % of its side: G1 aimed at each point, G2 set so that the true laser sheet passes
through it. The simulator's exact stripe pixels of each frame (no extraction error; the galvos
scatter from frame to frame as on the rig), or with ``--extracted`` the stripe extractor's
centres in the rendered image (``stripe_extractor.extractor.extract``, configured for the
calibration as the laser stages configure it), are triangulated at the commanded, DAC-quantised
voltages by three models:

- ``calibrated``: the calibration;
- ``dynamic_camera_only``: the true rig (the simulator's physical model) with the
  calibration's camera and G1 (intrinsics, l, d, G1's responses, the camera's and G1's
  mounting deviations): the warp that the dynamic camera's errors alone put into the plate;
- ``truth``: the true rig: what the galvos' frame-to-frame scatter leaves, which no
  calibration removes.

Each figure is the RMS distance of the points from their least-squares plane [mm], beside the
model's transfer-matrix error (36 G1 positions, mm). ``dynamic_camera`` compares, for l and d,
the standard errors the stopping rule predicts for the stage's plan
(``calibration_tools.stopping.assess`` at the poses planned, the stage's own feature noise and
the intrinsics stage's standard errors), those the stage's solver stated, and the calibration's
error against the truth [mm]. A laser stage calibrated through this
camera compensates part of the camera's errors, so the calibrated figure can be below the
camera-alone one. The plate's views out of G1's or G2's reach are left out (``views`` says
how many were kept). The last line is one JSON object, with the ratio of the calibrated
figure to the truth's, measured in the same run. Figures against the simulator's truth:
for simulated rigs only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import yaml

from galvoscan import eval_scenes, metrics
from galvoscan.sim_scores import transfer_matrix_rmse_mm
from galvoscan.simulated_rig import truth_model
from galvoscan_sim import Simulator, load_scene_text
from galvoscan_sim.rig import rig_from_dict
from reconstructor import calibration_file
from reconstructor.model import triangulate
from reconstructor.planning import aim_g1, laser_through

#: The physical model's deviations that belong to the camera and G1 (the dynamic camera
#: stage estimates them; the G2 ones belong to the laser stages).
CAMERA_DEVIATIONS = ('camera_rotation', 'camera_offset', 'g1_axes_angle',
                     'g1_pan_surface_offset', 'g1_pan_normal_tilt', 'g1_tilt_surface_offset',
                     'g1_tilt_normal_tilt')
#: Largest |U| aimed [V] (as the plans).
MAX_ABS_U = 9.9


def with_camera_of(base, src):
    """``base`` with ``src``'s camera and G1: intrinsics, l, d, G1's responses and the
    camera's and G1's mounting deviations (both physical models)."""
    if base.physical is None or src.physical is None:
        raise ValueError('both models must be physical models')
    phys = dataclasses.replace(base.physical,
                               **{k: getattr(src.physical, k) for k in CAMERA_DEVIATIONS})
    return dataclasses.replace(base, intrinsics=src.intrinsics, g1_pan=src.g1_pan,
                               g1_tilt=src.g1_tilt, l=src.l, d=src.d, physical=phys)


def plate_frames(rig, truth, grid: int = 21, pose: int = 0, seed: int = 1):
    """The flat plate (pose ``pose``, at the rig's working point) crossed by the true laser
    sheet at a ``grid`` x ``grid`` lattice over 95 % of its side: (voltages (4,), DAC-quantised,
    simulator frame) for each lattice point within G1's and G2's reach."""
    text, info = eval_scenes.plate(pose, eval_scenes.site_of(rig))
    sim = Simulator(rig, load_scene_text(text, 'plate'), seed=seed)
    V0_T_O = np.linalg.inv(sim.W_T_V0) @ info['W_T_O']
    half = 0.5 * 0.95 * info['size'][0]
    for x in np.linspace(-half, half, grid):
        for y in np.linspace(-half, half, grid):
            p = V0_T_O @ np.array([x, y, 0.0, 1.0])
            u1 = aim_g1(truth, p[:3], max_abs_u=MAX_ABS_U)
            if not np.all(np.isfinite(u1)):
                continue
            try:
                u2 = laser_through(truth, p[:3], max_abs_u=MAX_ABS_U)
            except ValueError:
                continue
            q = rig.dac.quantize(np.array([u1[0], u1[1], 0.0, u2]))
            yield q, sim.render(q)


def plate_rms_mm(points) -> float:
    """RMS distance of points (n, 3) [m] from their least-squares plane [mm]."""
    P = np.vstack(points)
    plane, _ = metrics.fit_plane(P)
    d = P @ plane[:3] + plane[3]
    return float(np.sqrt(np.mean(d ** 2))) * 1e3


def plate_stages(rig, calibrated, grid: int = 21, pose: int = 0,
                 extracted: bool = False) -> dict:
    """The plate figures of the three models (see the module) [mm]."""
    from calibration_tools.laser_plane import stripe_extractor_config
    from stripe_extractor.extractor import extract

    config = stripe_extractor_config(calibrated)
    truth = truth_model(rig, kind='physical')
    models = {'calibrated': calibrated,
              'dynamic_camera_only': with_camera_of(truth, calibrated), 'truth': truth}
    pts = {k: [] for k in models}
    views = 0
    for q, frame in plate_frames(rig, truth, grid, pose):
        stripe = extract(frame.image, config) if extracted else frame.truth.stripe
        if len(stripe.u) == 0:
            continue
        views += 1
        uv = np.column_stack([stripe.u, stripe.v]).astype(np.float64)
        for k, m in models.items():
            res = triangulate(m, uv, q[0], q[1], q[3])
            pts[k].append(res.p_v0[res.valid])
    if views < 3:
        raise RuntimeError(f'the plate is crossed in {views} view(s) within reach')
    out = {'views': views, 'grid': grid, 'pose': pose, 'extracted': extracted}
    for k, m in models.items():
        out[k] = {'plate_rms_mm': plate_rms_mm(pts[k]),
                  'transfer_matrix_error_mm': transfer_matrix_rmse_mm(m, rig)}
    out['ratio_calibrated_to_truth'] = (out['calibrated']['plate_rms_mm']
                                        / out['truth']['plate_rms_mm'])
    return out


def dynamic_camera_sigmas(cal, truth) -> dict:
    """l and d [mm]: the stopping rule's prediction for the stage's plan, the solver's
    stated standard errors and the calibration's error against ``truth``."""
    from calibration_tools import capture_plans as cp
    from calibration_tools import operator_flow as of
    from calibration_tools import stopping
    from calibration_tools.registry import plan

    entry = cal.stages.get('dynamic_camera') or {}
    steps = plan('dynamic_camera', cal)
    places = of.placements('dynamic_camera', steps)
    model = cp.current_model(cal)
    prior = {k.split('.', 1)[1]: v for k, v in
             (cal.stages.get('intrinsics') or {}).get('standard_errors', {}).items()
             if k.startswith('intrinsics.')}
    a = stopping.assess('dynamic_camera', model, steps.targets,
                        [(p, p.V0_T_target) for p in places], [], places,
                        noise_px=(entry.get('residuals') or {}).get('reprojection_rms_px'),
                        prior_sigma=prior)
    stated = entry.get('standard_errors') or {}
    out = {}
    for j, name in enumerate(a.names):
        out[name] = {'predicted_sigma_mm': float(a.sigma[j]) * 1e3,
                     'target_mm': float(a.target[j]) * 1e3,
                     'stated_sigma_mm': (float(stated[name]) * 1e3 if name in stated
                                         else None),
                     'error_mm': (getattr(cal.model, name) - getattr(truth, name)) * 1e3}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rig', required=True, help='rig description YAML')
    p.add_argument('--calibration', required=True, help='calibration YAML of that rig')
    p.add_argument('--grid', type=int, default=21, help='points per side of the plate')
    p.add_argument('--pose', type=int, default=0, help='plate pose (eval_scenes.PLATE_POSES)')
    p.add_argument('--extracted', action='store_true',
                   help="the extractor's stripe centres in the rendered images")
    args = p.parse_args(argv)
    if args.grid < 2:
        p.error('--grid must be >= 2')
    with open(args.rig) as f:
        rig = rig_from_dict(yaml.safe_load(f), args.rig)
    cal = calibration_file.load(args.calibration)
    out = plate_stages(rig, cal.model, args.grid, args.pose, args.extracted)
    out['dynamic_camera'] = dynamic_camera_sigmas(cal, truth_model(rig, kind='physical'))
    for k in ('calibrated', 'dynamic_camera_only', 'truth'):
        print(f"{k}: plate {out[k]['plate_rms_mm']:.4f} mm, transfer-matrix error "
              f"{out[k]['transfer_matrix_error_mm']:.3f} mm")
    for name, v in out['dynamic_camera'].items():
        stated = 'none' if v['stated_sigma_mm'] is None else f"{v['stated_sigma_mm']:.3f} mm"
        print(f"dynamic camera {name}: predicted sigma {v['predicted_sigma_mm']:.3f} mm "
              f"(target {v['target_mm']:.3f} mm), stated {stated}, error "
              f"{v['error_mm']:+.3f} mm")
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
