"""The evaluation report: a comparison table with the paper, plots and rendered clouds.

No rclpy. Plots are written with matplotlib's Agg backend as PNG beside ``report.md``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from reconstructor.cloud import xyz

_ROWS = [  # (metrics key, label, paper key)
    ('stair_step_error_rmse_mm', 'stair block, 30 mm step, RMSE over positions at the '
     'working point [mm]', 'stair_step_error_rmse_mm'),
    ('stair_step_error_max_mm', 'stair block, worst position at the working point [mm]',
     None),
    ('plate_flatness_rmse_mm', "flat plate (the paper's 740 x 740 mm; smaller only at "
     'short range, by the scene scale), RANSAC plane, RMSE [mm]',
     'plate_flatness_rmse_mm'),
    ('plate_flatness_rmse_mm_range_scaled', 'flat plate scaled with the working depth (the '
     "paper's plate's viewing angles; the same plate at scale <= 1), RMSE [mm]",
     'plate_flatness_rmse_mm'),
    ('sphere_radius_error_mm', 'calibration sphere, radius error [mm]', None),
    ('predicted_uncertainty_mm', "predicted 1-sigma point error over G1's range (the "
     "calibration's covariance and the galvos' measured frame noise; shape, RMS over the "
     'map) [mm]', None),
    ('predicted_calibration_uncertainty_mm', "its calibration's part (the same in every scan) "
     '[mm]', None),
    ('predicted_frame_noise_mm', "its frame-noise part (the galvos' repeatability, new in "
     'every frame) [mm]', None),
    ('measured_shape_error_mm', 'measured point error there against the truth (true stripe '
     'pixels, after the best rigid motion), RMS [mm]', None),
    ('measured_systematic_error_mm', "the same without the simulated galvos' frame noise: "
     "the calibration's error [mm]", None),
    ('uncertainty_ratio', 'predicted / measured point error (1 = an honest prediction)', None),
    ('uncertainty_ratio_calibration', "the calibration's part / the calibration's error (1 = "
     'an honest covariance)', None),
    ('transfer_matrix_error_rmse_mm', 'dynamic camera transfer-matrix error, RMSE [mm]',
     'transfer_matrix_error_rmse_mm'),
    ('joint_error_before_mm', 'joint correction: error before [mm]', 'joint_error_before_mm'),
    ('joint_error_after_mm', 'joint correction: error after (physical model: the table is '
     'measured, not installed) [mm]', 'joint_error_after_mm'),
    ('range_x_mm', "range covered at the working point's depth, x (every point of the "
     'centred rectangle measurable) [mm]', 'range_x_mm'),
    ('range_y_mm', "range covered at the working point's depth, y [mm]", 'range_y_mm'),
    ('range_extent_x_mm', 'extent of the region covered there (G1 corners included), x '
     '[mm]', 'range_extent_x_mm'),
    ('range_extent_y_mm', 'extent of the region covered there, y [mm]', 'range_extent_y_mm'),
]


def calibrated_vs_true(model, rig) -> dict:
    """Each calibrated parameter next to the simulator's value (SI units)."""
    p = rig.true_model_parameters()
    i = model.intrinsics
    pairs = {
        'fx_px': (i.fx, p.fx), 'fy_px': (i.fy, p.fy), 'cx_px': (i.cx, p.cx),
        'cy_px': (i.cy, p.cy), 'l_m': (model.l, p.l), 'd_m': (model.d, p.d),
        'g1_pan_theta0_rad': (model.g1_pan.theta0, p.theta0_pan),
        'g1_pan_k_rad_per_V': (model.g1_pan.k, p.k_pan),
        'g1_tilt_theta0_rad': (model.g1_tilt.theta0, p.theta0_tilt),
        'g1_tilt_k_rad_per_V': (model.g1_tilt.k, p.k_tilt),
        'g2_tilt_k_rad_per_V': (model.g2_tilt.k, p.k2),
    }
    out = {k: {'calibrated': float(a), 'true': float(b)} for k, (a, b) in pairs.items()}
    for j, name in enumerate(('k1', 'k2', 'p1', 'p2', 'k3')):
        out[f'dist_{name}'] = {'calibrated': float(i.dist[j]), 'true': float(p.distortion[j])}
    n_cal, n_true = np.asarray(model.laser_plane_v0[:3]), np.asarray(p.pi0[:3])
    # directions: the angle of the calibrated one from the true one (0 for the truth)
    out['laser_plane_normal_error_deg'] = {
        'calibrated': math.degrees(math.acos(min(1.0, abs(float(n_cal @ n_true))))),
        'true': 0.0}
    out['laser_plane_offset_m'] = {'calibrated': float(model.laser_plane_v0[3]),
                                   'true': float(p.pi0[3] * np.sign(n_cal @ n_true))}
    a_cal, a_true = np.asarray(model.laser_axis_dir), np.asarray(p.n)
    out['laser_axis_direction_error_deg'] = {
        'calibrated': math.degrees(math.acos(min(1.0, abs(float(a_cal @ a_true))))),
        'true': 0.0}
    P = np.asarray(model.laser_axis_point)
    # distance of the calibrated axis point from the true axis line
    d = (P - p.P) - ((P - p.P) @ a_true) * a_true
    out['laser_axis_point_offset_m'] = {'calibrated': float(np.linalg.norm(d)), 'true': 0.0}
    return out


def reproduces(ours, paper, key='') -> str:
    """'yes' when ours is within a factor 1.5 of the paper's figure either way; otherwise
    'no', saying whether ours is better or worse than the paper's."""
    if ours is None or paper is None or not math.isfinite(ours) or paper == 0:
        return ''
    ratio = abs(ours) / abs(paper)
    if 1 / 1.5 <= ratio <= 1.5:
        return 'yes'
    larger_is_better = key.startswith('range')
    better = ratio > 1.5 if larger_is_better else ratio < 1 / 1.5
    return f"no ({'better' if better else 'worse'}, x{ratio:.2g})"


def _fmt0(v):
    return 'n/a' if v is None or not math.isfinite(v) else f'{v:.0f}'


def _fmt(v):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return 'n/a'
    return f'{v:.3f}'


def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend (imported when a report is drawn)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path) -> bool:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _plot_stair_errors(details, path):
    plt = _pyplot()
    rows = [r for r in details['stair'] if r.get('error_mm') is not None]
    if not rows:
        return False
    p = np.array([r['position_m'] for r in rows])
    e = np.array([r['error_mm'] for r in rows])
    ang_x = np.degrees(np.arctan2(p[:, 0], p[:, 2]))
    ang_y = np.degrees(np.arctan2(p[:, 1], p[:, 2]))
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].scatter(ang_x, e)
    ax[0].set_xlabel('viewing angle, pan direction [deg]')
    ax[1].scatter(ang_y, e)
    ax[1].set_xlabel('viewing angle, tilt direction [deg]')
    for a in ax:
        a.axhline(0, color='k', lw=0.5)
        a.set_ylabel('stair step error [mm]')
        a.grid(alpha=0.3)
    fig.suptitle('Stair-block step error against viewing direction (cf. paper Fig. 12b)')
    return _save(plt, fig, path)


def _distance_tables(result, details) -> list:
    """The report's by-distance (rig re-set there) and off-nominal (object moved) tables."""
    wd = result.get('working_distance_mm')
    lines = ['', '## Stair block by working distance (cf. paper Fig. 13)', '',
             'A distance is the working distance: the stand-off from the G1 exit mirror of '
             'the point where the laser sheet crosses the optical axis. At each, this rig is '
             're-set for the distance as a technician would (sheet re-aimed, lens and laser '
             'refocused, exposure adjusted; its imperfections stay), calibrated there '
             'through the graph (quick plans, every stage) and the stair block scanned at '
             'its working point.', '',
             '| distance [mm] | step error RMSE [mm] | positions | transfer-matrix error '
             '[mm] | note |', '|---|---|---|---|---|']
    rows = details.get('stair_by_distance') or {}
    for k, v in result.get('stair_step_error_rmse_mm_by_distance', {}).items():
        row = rows.get(k, {})
        note = row.get('reason') or row.get('note') or ''
        used = row.get('positions_used')
        total = len(row.get('positions', []))
        lines.append(f"| {k} | {_fmt(v)} | {f'{used}/{total}' if total else ''} | "
                     f"{_fmt(row.get('transfer_matrix_error_rmse_mm'))} | {note} |")
    lines += ['', '## Off-nominal: calibrated at the rig\'s own distance, object moved', '',
              f"The rig as evaluated above (set up and calibrated for {_fmt0(wd)} mm), with "
              'the stair block moved along its axis to each distance: NOT the paper\'s '
              'comparison (the scanner is not set up for these distances).', '',
              '| distance [mm] | step error [mm] |', '|---|---|']
    off = details.get('stair_off_nominal') or {}
    for k, v in result.get('stair_step_error_rmse_mm_off_nominal', {}).items():
        lines.append(f"| {k} | {_fmt(v)} {off.get(k, {}).get('reason', '')} |")
    return lines


def _plot_by_distance(result, path):
    plt = _pyplot()
    curves = []
    for key, label, marker in (
            ('stair_step_error_rmse_mm_by_distance', 'rig re-set and calibrated there', 'o'),
            ('stair_step_error_rmse_mm_off_nominal',
             'off-nominal: calibrated at its own distance, object moved', 'x')):
        pts = [(float(k), v) for k, v in (result.get(key) or {}).items()
               if v is not None and math.isfinite(v)]
        if pts:
            curves.append((np.array(pts), label, marker))
    if not curves:
        return False
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for pts, label, marker in curves:
        ax.plot(pts[:, 0], pts[:, 1], marker=marker, label=label)
    wd = result.get('working_distance_mm')
    if wd is not None:
        ax.axvline(wd, color='k', lw=0.5, ls='--', label=f'own working distance {wd:.0f} mm')
    ax.set_xlabel('working distance (stand-off from the G1 exit mirror) [mm]')
    ax.set_ylabel('stair step error [mm]')
    ax.set_yscale('log')
    missing = [k for k, v in (result.get('stair_step_error_rmse_mm_by_distance') or {}).items()
               if v is None or not math.isfinite(v)]
    if missing:
        ax.text(0.02, 0.02, f"re-set rig not measured at {', '.join(missing)} mm (see table)",
                transform=ax.transAxes, fontsize=8, color='C0')
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=8)
    ax.set_title('Stair-block error by working distance (cf. paper Fig. 13)')
    return _save(plt, fig, path)


def _plot_joint(details, path):
    plt = _pyplot()
    jc = (details.get('stages') or {}).get('joint_correction_curves')
    if not jc:
        return False
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, values in jc.items():
        ax.plot(np.asarray(values, float), marker='o', label=name)
    ax.set_xlabel('view')
    ax.set_ylabel('registration error [mm]')
    ax.legend()
    ax.grid(alpha=0.3)
    ax.set_title('Joint correction: error per view before and after (cf. paper Fig. 6c)')
    return _save(plt, fig, path)


def _plate_table(details) -> list:
    """The report's per-pose rows of the flat plate scan."""
    rows = details.get('plate') or []
    if not rows:
        return []
    lines = ['', '## Flat plate, per pose', '',
             'Each pose scanned edge to edge by a raster of G1 views, one scan through the '
             'graph; coverage is the fraction of the plate\'s 20 mm cells (37 x 37) holding '
             'an inlier of the RANSAC plane.', '',
             '| pose | plate [mm] | views (unreachable) | frames | line spacing [mm] | '
             'points | inliers | coverage | RMS [mm] | largest distance [mm] |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(
            f"| {r['pose']} | {r.get('size_mm', float('nan')):.0f} | {r.get('views', '')} "
            f"({r.get('views_unreachable', '')}) | {r.get('frames', '')} | "
            f"{r.get('line_spacing_mm', float('nan')):.1f} | {r['points']} | "
            f"{r.get('inliers', '')} | {r.get('coverage_fraction', float('nan')):.1%} | "
            f"{_fmt(r.get('rms_mm'))} | {_fmt(r.get('max_distance_mm'))} |")
    return lines


def _plot_plate_map(maps, path):
    """Deviation map of the flat plate: each pose's inliers in the plate's frame, coloured
    by their signed distance from the fitted plane [um], one colour scale for all poses."""
    maps = [m for m in maps or [] if len(m['d_um'])]
    if not maps:
        return False
    plt = _pyplot()
    lim = float(np.percentile(np.abs(np.concatenate([m['d_um'] for m in maps])), 99.5))
    lim = max(lim, 1.0)
    fig, axes = plt.subplots(1, len(maps), figsize=(4.0 * len(maps) + 1.2, 4.6),
                             squeeze=False, layout='constrained')
    for ax, m in zip(axes[0], maps, strict=True):
        xy, half = np.asarray(m['xy_mm']), m['size_mm'] / 2.0
        sc = ax.scatter(xy[:, 0], xy[:, 1], c=m['d_um'], s=1.5, cmap='RdBu_r', vmin=-lim,
                        vmax=lim, rasterized=True, linewidths=0)
        ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, fill=False, lw=0.6,
                                   ec='k'))
        ax.set_xlim(-half * 1.04, half * 1.04)
        ax.set_ylim(half * 1.04, -half * 1.04)      # y down, as the scanner sees it
        ax.set_aspect('equal')
        ax.set_xlabel('plate x [mm]')
        ax.set_title(f"pose {m['pose']}: RMS {m['rms_um']:.0f} um, "
                     f"coverage {m['coverage_fraction']:.0%}", fontsize=9)
    axes[0][0].set_ylabel('plate y [mm]')
    cb = fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.9)
    cb.set_label('signed distance from the fitted plane [um]')
    fig.suptitle('Flat plate deviation map: each pose\'s RANSAC plane, + towards the scanner')
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


_MARKERS = {'intrinsics': ('s', 'k'), 'dynamic_camera': ('o', 'w'),
            'laser_plane': ('^', 'm'), 'laser_axis': ('v', 'c'),
            'joint_correction': ('x', 'r')}


def _plot_uncertainty(umap, path):
    """The predicted 1-sigma point error over G1's range (pan x tilt) with the G1 voltages of
    every calibration stage's views on it (the coverage map)."""
    if not umap or not umap.get('sigma_m'):
        return False
    sigma = np.array([[np.nan if v is None else v for v in row] for row in umap['sigma_m']],
                     dtype=float) * 1e6
    if not np.isfinite(sigma).any():
        return False
    plt = _pyplot()
    up, ut = np.array(umap['u_pan_V']), np.array(umap['u_tilt_V'])
    step = (up[1] - up[0]) / 2 if len(up) > 1 else 1.0
    fig, ax = plt.subplots(figsize=(7.4, 5.6), layout='constrained')
    im = ax.imshow(sigma, origin='lower', cmap='viridis', interpolation='nearest',
                   extent=(up[0] - step, up[-1] + step, ut[0] - step, ut[-1] + step))
    for i, tv in enumerate(ut):
        for j, pv in enumerate(up):
            if np.isfinite(sigma[i, j]):
                ax.text(pv, tv, f'{sigma[i, j]:.0f}', ha='center', va='center', fontsize=7,
                        color='w' if sigma[i, j] < np.nanmax(sigma) * 0.6 else 'k')
    for stage, pts in (umap.get('views_u1_V') or {}).items():
        p = np.asarray(pts, dtype=float).reshape(-1, 2)
        marker, colour = _MARKERS.get(stage, ('+', 'y'))
        # a filled marker gets a black outline; a line marker ('x', '+') is its colour alone
        outline = {} if marker in ('x', '+', '1', '2', '3', '4', '|', '_') else \
            {'edgecolors': 'k'}
        ax.scatter(p[:, 0], p[:, 1], s=14, marker=marker, c=colour, linewidths=0.5,
                   label=f'{stage} views ({len(p)})', **outline)
    ax.set_xlim(-10.5, 10.5)
    ax.set_ylim(-10.5, 10.5)
    ax.set_xlabel('G1 pan voltage [V]')
    ax.set_ylabel('G1 tilt voltage [V]')
    if umap.get('views_u1_V'):
        ax.legend(loc='upper center', bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=7)
    cb = fig.colorbar(im, ax=ax, shrink=0.9)
    cb.set_label("calibration's predicted 1-sigma point error (shape) [um]")
    nan = float('nan')
    ax.set_title(f"Predicted uncertainty at {umap['depth_m'] * 1e3:.0f} mm, calibration's "
                 f"part: RMS {umap['rms_m'] * 1e6:.0f} um (measured without frame noise: "
                 f"{umap.get('measured_systematic_error_mm', nan) * 1e3:.0f} um)\n"
                 f"with the galvos' frame noise ({umap.get('frame_rms_m', 0.0) * 1e6:.0f} um): "
                 f"{umap.get('total_rms_m', umap['rms_m']) * 1e6:.0f} um (measured: "
                 f"{umap.get('measured_shape_error_mm', nan) * 1e3:.0f} um)", fontsize=9)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _render_cloud(cloud, path, title):
    plt = _pyplot()
    p = xyz(cloud) * 1e3
    if p.shape[0] == 0:
        return False
    if p.shape[0] > 60000:
        p = p[np.random.default_rng(0).choice(p.shape[0], 60000, replace=False)]
    fig = plt.figure(figsize=(5, 4))
    ax = fig.add_subplot(projection='3d')
    ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=p[:, 2], s=0.2, cmap='viridis')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('y [mm]')
    ax.set_zlabel('z [mm]')
    ax.invert_yaxis()
    ax.view_init(elev=-60, azim=-90)
    ax.set_title(title)
    return _save(plt, fig, path)


def write_report(out, result, details, paper, clouds):
    out = Path(out)
    lines = ['# galvoscan evaluation on the simulated rig', '',
             f"Calibration source: **{result.get('calibration_source')}**. Every figure below "
             'was computed in this run from reconstructed clouds against the simulator\'s '
             'ground truth; the paper column is the published figure, for comparison.', '',
             'The rig is set up for a working distance of '
             f"{_fmt0(result.get('working_distance_mm'))} mm (stand-off from the G1 exit "
             'mirror): its working point, where every object below is placed, lies '
             f"{_fmt0(result.get('working_point_depth_mm'))} mm deep along V0; scene scale "
             f"{result.get('scene_scale')}.", '',
             f"Model: **{result.get('model', 'paper')}**."
             + (" The paper's-method column is the same rig, graph and scenes calibrated "
                "again with the paper's own model and joint correction (`paper_method`)."
                if result.get('paper_method') else ''), '',
             "| quantity | ours | ours, paper's method | paper | reproduced (within 1.5x) "
             "| paper's method reproduced |", '|---|---|---|---|---|---|']
    pm = result.get('paper_method') or {}
    for key, label, pkey in _ROWS:
        ours = result.get(key)
        ref = paper.get(pkey) if pkey else None
        theirs = pm.get(key)
        lines.append(f'| {label} | {_fmt(ours)} | {_fmt(theirs)} | {_fmt(ref)} | '
                     f'{reproduces(ours, ref, key)} | '
                     f"{reproduces(theirs, ref, key) if theirs is not None else ''} |")
    lines += _plate_table(details)
    lines += _distance_tables(result, details)
    cell = (details.get('stages') or {}).get('cell_extrinsic')
    if cell and 'failed' in cell:
        lines += ['', '## Where the scanner sits in the cell (cell_extrinsic)', '',
                  f"Not measured: {cell['failed']}"]
    elif cell:
        lines += ['', '## Where the scanner sits in the cell (cell_extrinsic)', '',
                  f"The sphere at {cell['positions']} robot-reported positions, swept through "
                  'the calibration node; `cell_T_v0` against the simulator\'s true mounting: '
                  f"**{cell['error_mm']:.4f} mm, {cell['error_deg']:.5f} deg** (stated 1-sigma "
                  f"{', '.join(f'{v:.4f}' for v in cell['stated_translation_std_mm'])} mm; "
                  f"sphere centres fit to {cell['sphere_centre_rms_mm']:.4f} mm RMS). The pose "
                  'difference includes where this calibration puts V0 (a rigid choice that '
                  'no shape figure sees); what a robot uses is the next figure: the '
                  'evaluation sphere\'s measured centre taken into the cell lies '
                  f"**{_fmt(result.get('cell_sphere_centre_error_mm'))} mm** from its true "
                  'position.']
    lines += ['', f"Run time: {result['runtime_s']:.0f} s; frames lost in the graph: "
              f"{result['frames_lost']}.", '']
    if _plot_stair_errors(details, out / 'stair_error_vs_angle.png'):
        lines += ['![stair error](stair_error_vs_angle.png)', '']
    if _plot_by_distance(result, out / 'stair_error_by_distance.png'):
        lines += ['![stair error by distance](stair_error_by_distance.png)', '']
    if _plot_uncertainty(details.get('uncertainty'), out / 'uncertainty_map.png'):
        lines += ['![predicted uncertainty and calibration coverage](uncertainty_map.png)',
                  '']
    if _plot_joint(details, out / 'joint_correction.png'):
        lines += ['![joint correction](joint_correction.png)', '']
    if clouds.get('stair') and _render_cloud(clouds['stair'][0], out / 'stair_cloud.png',
                                             'stair block (one position)'):
        lines += ['![stair cloud](stair_cloud.png)', '']
    if _plot_plate_map(clouds.get('plate_maps'), out / 'plate_deviation_map.png'):
        lines += ['![plate deviation map](plate_deviation_map.png)', '']
    if clouds.get('plate') and _render_cloud(np.concatenate(clouds['plate'][:1]),
                                             out / 'plate_cloud.png', 'flat plate (pose 0)'):
        lines += ['![plate cloud](plate_cloud.png)', '']
    lines += ['## Calibrated against true parameters', '', '| parameter | calibrated | true |',
              '|---|---|---|']
    for k, v in result['calibrated_vs_true'].items():
        lines.append(f"| {k} | {v['calibrated']:.9g} | {v['true']:.9g} |")
    (out / 'report.md').write_text('\n'.join(lines) + '\n')
