"""``galvoscan evaluate``: the main job on the simulated rig, through the real ROS graph.

1. Starts the graph (driver with the sim backend, stripe_extractor, reconstructor,
   calibration node), one process per node, under the supervisor.
2. Runs every calibration stage through the calibration node's services (capture, then
   compute) with the simulated operator (:mod:`galvoscan.operator`): it reads the node's
   instructions and places the boards and the sphere through the sim scene service with a
   person's imprecision and mistakes (seeded by ``--seed``); the scanner finds them.
3. Scans the paper's test objects through the same graph and scores the clouds against the
   scene's ground truth, every object placed around the rig's working point (where its
   laser sheet crosses its optical axis; :class:`galvoscan.eval_scenes.Site`): the stair
   block at 30 positions, the flat plate in 3 poses (each scanned edge to edge by a
   raster of G1 views), the calibration sphere, the range covered at that depth; and the
   off-nominal table: the stair block moved to each of the paper's distances in front of
   this rig, calibrated for its own distance.
4. By distance, as the paper's Fig. 13: for each of 100, 200, 350, 400, 650 and 1000 mm,
   the same rig re-set for that working distance
   (:func:`galvoscan_sim.rig_family.reset_for_distance`: sheet re-aimed, focus and exposure
   adjusted, imperfections kept) under the running graph (the driver cleaned up and
   configured on it, the calibration node restarted from its design values), calibrated
   there (quick plans, every stage) and the stair block scanned at its working point. A distance is
   the working distance as ``galvoscan_sim.rig_family.working_distance`` defines it: the
   stand-off of the crossing from the G1 exit mirror (the reference rig is set up for
   544 mm, its crossing 650 mm deep along V0). A distance that cannot be measured is
   ``null`` with its reason; every other figure is still computed.
5. Writes ``metrics.json``, ``details.json``, ``report.md`` with plots, the clouds as PLY
   and the calibration files into ``--out`` (``failure.json`` when the evaluated rig's own
   calibration fails: the stage and the message).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from galvoscan import eval_scenes, metrics
from galvoscan.progress import Progress
from galvoscan_common.executor import ServiceClients
from galvoscan_common.runtime import private_domain
from reconstructor.cloud import CLOUD_DTYPE, save_cloud, xyz
from reconstructor.model import v0_T_v
from reconstructor.planning import (
    aim_camera,
    laser_through,
    stripe_layout,
    view_edge_rays,
    view_sweep,
)

#: The paper's working distances (Fig. 13): stand-off from the G1 exit mirror [mm].
DISTANCES_MM = (100, 200, 350, 400, 650, 1000)
#: A distance this close to the rig's own working distance [mm] is the rig as given.
NOMINAL_TOLERANCE_MM = 0.5
#: Stair positions at each distance: the working point, then left, right, up and down
#: halfway out to the edge of the stair grid (indices into a 3 x 3 grid of half spread).
BY_DISTANCE_CROSS = (4, 3, 5, 1, 7)
#: The flat plate's raster (``eval_scenes.plate_raster``): stripe lines at most this far
#: apart on the plate [m] (under the 20 mm coverage cells).
PLATE_LINE_SPACING = 0.018
#: RANSAC inlier distance of the plate's plane [m], and the subsample the RANSAC
#: hypotheses are scored on (the plane is then refitted to every inlier of the whole cloud).
PLATE_RANSAC_THRESHOLD = 2e-3
PLATE_RANSAC_SAMPLE = 60000
#: Range views: the sweep covers this fraction of the view's height (the view's full
#: height less a margin for the stripe's width at the image edge).
RANGE_SWEEP_FRACTION = 0.95
#: Range views, as directions in G1 voltage: the four ends of the two axes (the range
#: covered) and the four corners (the extent of the region covered).
RANGE_VIEWS = {'x-': (-1, 0), 'x+': (1, 0), 'y-': (0, -1), 'y+': (0, 1),
               'x-y-': (-1, -1), 'x+y-': (1, -1), 'x-y+': (-1, 1), 'x+y+': (1, 1)}
PAPER = {  # the paper's figures, for comparison in the report only
    'stair_step_error_rmse_mm': 0.165, 'plate_flatness_rmse_mm': 0.281,
    'transfer_matrix_error_rmse_mm': 1.231, 'joint_error_before_mm': 4.928,
    'joint_error_after_mm': 0.197, 'range_x_mm': 1100.0, 'range_y_mm': 1300.0,
    'range_extent_x_mm': 1100.0, 'range_extent_y_mm': 1300.0,
}


class GraphClient:
    """The evaluation's own node: service calls and cloud collection."""

    def __init__(self, domain_id):
        import rclpy
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = Node('galvoscan_evaluate', context=self.ctx)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.clouds = []
        self.node.create_subscription(
            PointCloud2, 'points', self.clouds.append,
            QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE))
        self._services = ServiceClients(self.node, self.ex)

    def call(self, srv_type, name, request, timeout=60.0, resend=False):
        """One service call; resent while unanswered only with ``resend``, for requests
        safe to repeat (never a capture, a compute or a lifecycle transition: a resend
        would run it again)."""
        return self._services.call(srv_type, name, request, timeout, resend)

    def spin(self, seconds):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=min(0.05, max(t_end - time.monotonic(), 0.0)))

    def wait_ready(self, timeout=120.0):
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.node.count_subscribers('camera/image_raw') and \
                    self.node.count_publishers('points'):
                return
            self.spin(0.2)
        raise RuntimeError('the graph did not come up (no extractor or reconstructor)')

    def set_scene(self, text):
        from galvoscan_msgs.srv import SetScene

        resp = self.call(SetScene, 'sim/set_scene', SetScene.Request(scene_yaml=text),
                         resend=True)
        if not resp.success:
            raise RuntimeError(f'set_scene: {resp.message}')

    def _progress(self):
        from galvoscan_msgs.srv import GetScanProgress

        return self.call(GetScanProgress, 'scan/progress', GetScanProgress.Request(),
                         resend=True)

    def scan(self, voltages, frame_rate=500.0, laser_on=True, timeout=120.0):
        """Run a custom scan; return its per-frame clouds (structured arrays) in stamp order.

        Waits until the driver reports the scan done and every frame's cloud has arrived,
        or until clouds stop coming for 3 s after that (frames lost in the graph).
        """
        from galvoscan_msgs.srv import StartScan

        t_request = time.time() - 1e-3
        resp = self.call(StartScan, 'scan/start', StartScan.Request(
            pattern='custom', voltages=np.asarray(voltages).ravel().tolist(),
            frame_rate=frame_rate, laser_on=laser_on), resend=True)  # by its request_id
        if not resp.success:
            raise RuntimeError(f'scan/start: {resp.message}')
        n = resp.frames_total
        mine = []
        t_end = time.monotonic() + timeout
        last, done = time.monotonic(), False
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=0.02)
            if self.clouds:
                fresh = [m for m in self.clouds
                         if m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 >= t_request]
                self.clouds.clear()
                if fresh:
                    mine += fresh
                    last = time.monotonic()
            if len(mine) >= n:
                break
            if time.monotonic() - last > 0.5 and not done:
                done = self._progress().state != 'running'
                last = time.monotonic() if not done else last
            if done and time.monotonic() - last > 1.5:
                break
        while self._progress().state == 'running' and time.monotonic() < t_end:
            self.spin(0.1)
        mine.sort(key=lambda m: (m.header.stamp.sec, m.header.stamp.nanosec))
        return [np.frombuffer(bytes(m.data), CLOUD_DTYPE).copy() for m in mine], n

    def warm_up(self, voltages, timeout=60.0):
        """One-frame scans until a cloud comes back: every link of the graph is matched."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            clouds, _ = self.scan(np.asarray(voltages)[:1], frame_rate=50.0, timeout=5.0)
            if clouds:
                return
        raise RuntimeError('no cloud came back through the graph')

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)


class Evaluation:
    """Scans of the evaluation scenes through the graph, scored against the scene truth.

    Objects are placed around ``site`` (the evaluated rig's working point, see
    :class:`galvoscan.eval_scenes.Site`).
    """

    def __init__(self, args, client, progress, model, W_T_V0, site):
        self.args, self.client, self.progress = args, client, progress
        self.model = model            # the calibrated model (aiming is done with it)
        self.W_T_V0 = W_T_V0          # truth: only to express clouds in object frames
        self.V0_T_W = np.linalg.inv(W_T_V0)
        self.site = site
        self.lost_frames = 0

    def _scan(self, voltages):
        clouds, n = self.client.scan(voltages, frame_rate=self.args.frame_rate)
        self.lost_frames += n - len(clouds)
        return np.concatenate(clouds) if clouds else np.zeros(0, CLOUD_DTYPE), clouds

    def _aimed_sweep(self, aim_W, frames, fraction=0.8):
        aim_V0 = (self.V0_T_W @ np.append(aim_W, 1.0))[:3]  # where the experimenter put it
        u1 = aim_camera(self.model, aim_V0)
        return view_sweep(self.model, *u1, distance=float(np.linalg.norm(aim_V0)),
                          frames=frames, fraction=fraction)

    def _plane_sweep(self, u1, plane_V0, frames, fraction):
        """Voltages (frames, 4) sweeping the stripe over the central ``fraction`` of G1 view
        ``u1`` across the stripe (its height for a stripe along the rows) on a surface in
        the plane ``plane_V0`` (4,) (where the experimenter put it), with the calibrated
        model.

        Unlike :func:`reconstructor.planning.view_sweep`, which assumes a surface facing
        the view at one distance, the rays through the top and bottom of the swept part of
        the image are met with the plane itself: on a wall seen 40 deg off its normal, at
        the ends of G1's reach, the stripe would otherwise miss most of the view.

        Raises
        ------
        ValueError
            The plane is behind or edge-on to the view, or the laser cannot reach an end
            within the G2 range.
        """
        T = v0_T_v(self.model, *u1)
        pi = np.asarray(plane_V0, dtype=np.float64)
        ends = []
        for ray_v in view_edge_rays(self.model, fraction):   # across the stripe
            ray = T[:3, :3] @ ray_v
            denom = float(pi[:3] @ ray)
            s = -float(pi[:3] @ T[:3, 3] + pi[3]) / denom if abs(denom) > 1e-9 else -1.0
            if s <= 0:
                raise ValueError(f'the plane is not in front of the view at U1 = {u1} V')
            ends.append(T[:3, 3] + s * ray)
        u2 = self._sweep_through(u1, ends)[:, 3]
        out = np.zeros((frames, 4))
        out[:, 0], out[:, 1] = u1
        out[:, 3] = np.linspace(u2[0], u2[1], frames) if frames > 1 else u2.mean()
        return out

    def _sweep_through(self, u1, points_V0):
        """Voltages (n, 4): G1 held at ``u1``, and for each of ``points_V0`` (n, 3) the G2
        tilt voltage whose laser plane (calibrated model) passes through it.

        Raises
        ------
        ValueError
            A point the laser cannot reach within the G2 range.
        """
        out = np.zeros((len(points_V0), 4))
        out[:, 0], out[:, 1] = u1
        for i, point in enumerate(np.asarray(points_V0, dtype=np.float64)):
            out[i, 3] = laser_through(self.model, point)
        return out

    def stair_at(self, position, frames):
        """Three views (Plane-1, the riser, Plane-2), each swept by the stripe."""
        text, info = eval_scenes.stair(position, layout=stripe_layout(self.model))
        self.client.set_scene(text)
        W_T_O, sz, step = info['W_T_O'], info['size'][2], info['step_height']
        # on Plane-1, the riser and Plane-2, at their depths (the stripe's place in a view
        # depends on depth, steeply so at short range)
        aims = ((-0.03, -sz), (0.0, -sz - step / 2), (0.03, -sz - step))
        sweeps = [self._aimed_sweep((W_T_O @ np.array([x, 0.0, z, 1.0]))[:3], frames)
                  for x, z in aims]
        cloud, _ = self._scan(np.vstack(sweeps))
        O_T_V0 = np.linalg.inv(info['W_T_O']) @ self.W_T_V0
        res = metrics.stair_step(metrics.to_frame(O_T_V0, xyz(cloud)), info['size'],
                                 info['step_height'])
        return res, cloud

    def stair_series(self, title, positions, frames):
        """The stair block at each of ``positions`` (n, 3) [m] in W.

        Returns one row per position (``error_mm``, or ``None`` and the ``reason``) and the
        clouds of the positions measured.
        """
        self.progress.stage(title, len(positions), 'positions')
        rows, clouds = [], []
        for p in positions:
            try:
                res, cloud = self.stair_at(p, frames)
                rows.append({'position_m': [float(v) for v in p], 'error_mm': res.error * 1e3,
                             'thickness_mm': res.thickness * 1e3, 'n_plane1': res.n_plane1,
                             'n_plane2': res.n_plane2})
                clouds.append(cloud)
                note = f'error {res.error * 1e3:+.3f} mm'
            except (ValueError, RuntimeError) as exc:
                rows.append({'position_m': [float(v) for v in p], 'error_mm': None,
                             'reason': str(exc)})
                note = f'skipped: {exc}'
            self.progress.advance(note=note)
        return rows, clouds

    def off_nominal(self, frames):
        """The stair block moved to each paper distance (stand-off from the G1 exit mirror)
        in front of this rig, which stays calibrated and set up for its own distance."""
        self.progress.stage('stair block moved off the working distance', len(DISTANCES_MM),
                            'distances')
        out = {}
        for mm in DISTANCES_MM:
            try:
                res, _ = self.stair_at(self.site.at_standoff(mm / 1e3), frames)
                out[str(mm)] = {'error_mm': res.error * 1e3, 'n_plane1': res.n_plane1}
                note = f'{mm} mm: error {res.error * 1e3:+.3f} mm'
            except (ValueError, RuntimeError) as exc:
                out[str(mm)] = {'error_mm': None, 'reason': str(exc)}
                note = f'{mm} mm: {exc}'
            self.progress.advance(note=note)
        return out

    def plate(self, frames, skip=1, grow=False):
        """The flat plate in each pose (``eval_scenes.plate``; ``grow``: scaled with the
        working depth), scanned edge to edge by a raster of G1 views
        (:func:`galvoscan.eval_scenes.plate_raster`: ``frames`` stripe lines per view,
        every ``skip``-th row and column), one scan per pose.

        The plane is the paper's RANSAC plane (inliers within PLATE_RANSAC_THRESHOLD); the
        figure is the RMS distance of the inliers from it.

        Returns
        -------
        rows : list of dict
            Per pose: views (planned, unreachable), frames, points, inliers, coverage
            (the fraction of the plate's 20 mm cells holding an inlier), mean, RMS and
            largest distance [mm].
        rmse : float
            Over every pose's inliers [mm].
        clouds : list of structured arrays
        maps : list of dict
            Per pose, for the report's deviation map: ``xy_mm`` (n, 2) inliers in the
            plate's frame and ``d_um`` (n,) their signed distance from the fitted plane
            (positive towards the scanner), at most 50,000 of them.
        """
        poses = range(len(eval_scenes.PLATE_POSES))
        self.progress.stage('flat plate, scanned edge to edge'
                            + (', scaled with the working depth' if grow else ''),
                            len(poses), 'poses')
        intr = self.model.intrinsics
        rows, all_d, clouds, maps = [], [], [], []
        for k in poses:
            text, info = eval_scenes.plate(k, self.site, grow=grow)
            self.client.set_scene(text)
            W_T_O, size = info['W_T_O'], info['size'][0]
            depth = float(np.linalg.norm((self.V0_T_W @ W_T_O)[:3, 3]))
            view = (intr.width / intr.fx * depth, intr.height / intr.fy * depth)
            # lines at most 18 mm apart, and closer on a smaller plate (short range) so that
            # every one of its cells is still crossed
            layout = stripe_layout(self.model)
            centres, lines, spacing = eval_scenes.plate_raster(
                size, view, frames,
                min(PLATE_LINE_SPACING, 0.9 * size / eval_scenes.PLATE_CELLS), skip,
                across=layout.across)
            V0_T_O = self.V0_T_W @ W_T_O
            O_T_V0 = np.linalg.inv(V0_T_O)
            sweeps = []
            for (gx, gy), ys in zip(centres, lines, strict=True):
                # the lines run along the stripe, spaced across it (plate y for a stripe
                # along the image rows, x along the columns)
                on_plate = np.zeros((len(ys), 4))
                on_plate[:, layout.along] = (gx, gy)[layout.along]
                on_plate[:, layout.across] = ys
                on_plate[:, 3] = 1.0
                on_plate = on_plate @ V0_T_O.T
                try:
                    u1 = aim_camera(self.model, (V0_T_O @ np.array([gx, gy, 0.0, 1.0]))[:3])
                    sweeps.append(self._sweep_through(u1, on_plate[:, :3]))
                except ValueError:
                    continue      # beyond G1's or the laser's reach: counted below
            cloud = self._scan(np.vstack(sweeps))[0] if sweeps else np.zeros(0, CLOUD_DTYPE)
            p = xyz(cloud)
            row = {'pose': k, 'size_mm': size * 1e3, 'views': len(centres),
                   'views_unreachable': len(centres) - len(sweeps),
                   'frames': len(sweeps) * lines.shape[1], 'line_spacing_mm': spacing * 1e3,
                   'points': int(p.shape[0])}
            if p.shape[0] < 3:
                raise RuntimeError(f'flat plate, pose {k}: {p.shape[0]} points')
            plane, inliers = _plate_plane(p)
            # signed: positive towards the scanner (the plate's -z faces it)
            toward = -float(np.sign(plane[:3] @ O_T_V0[2, :3])) or 1.0
            s = toward * (p[inliers] @ plane[:3] + plane[3])
            d = np.abs(s)
            xy = metrics.to_frame(O_T_V0, p[inliers])[:, :2]
            all_d.append(d)
            row.update({'inliers': int(inliers.sum()),
                        'coverage_fraction': eval_scenes.plate_coverage(xy, size),
                        'mean_distance_mm': float(d.mean() * 1e3),
                        'rms_mm': metrics.rmse(d) * 1e3,
                        'max_distance_mm': float(d.max() * 1e3)})
            rows.append(row)
            clouds.append(cloud)
            keep = np.random.default_rng(k).permutation(xy.shape[0])[:50000]
            maps.append({'pose': k, 'size_mm': size * 1e3, 'xy_mm': xy[keep] * 1e3,
                         'd_um': s[keep] * 1e6, 'rms_um': row['rms_mm'] * 1e3,
                         'coverage_fraction': row['coverage_fraction']})
            self.progress.advance(note=f"{row['points']} points, coverage "
                                       f"{row['coverage_fraction']:.1%}, RMS "
                                       f"{row['rms_mm']:.3f} mm")
        return rows, metrics.rmse(np.concatenate(all_d)) * 1e3, clouds, maps

    def sphere(self, frames):
        self.progress.stage('calibration sphere', 1, 'scans')
        text, info = eval_scenes.sphere(self.site.offset((0.05, -0.04, 0.0)),
                                        eval_scenes.sphere_radius(self.site))
        self.client.set_scene(text)
        cloud, _ = self._scan(self._aimed_sweep(info['aim_W'], frames))
        centre, radius, rms = metrics.fit_sphere(xyz(cloud))
        self.progress.advance(note=f'radius error {(radius - info["radius"]) * 1e3:+.3f} mm')
        return {'radius_error_mm': (radius - info['radius']) * 1e3, 'fit_rms_mm': rms * 1e3,
                'radius_mm': info['radius'] * 1e3,
                'points': int(cloud.shape[0]), 'centre_v0_m': np.asarray(centre).tolist(),
                'centre_true_w_m': np.asarray(info['centre_W']).tolist()}, cloud

    def _extreme_view(self, direction, frames, wall_V0):
        """The G1 view furthest out along ``direction`` (G1 voltage, components -1, 0 or 1)
        that the laser can reach on the wall ``wall_V0`` (plane, 4): from 10 V inwards in
        0.5 V steps. Returns its points (n, 3) in V0 and its voltages (None when none is
        reachable)."""
        for volts in np.arange(10.0, 0.0, -0.5):
            u1 = (float(direction[0] * volts), float(direction[1] * volts))
            try:
                sweep = self._plane_sweep(u1, wall_V0, frames, RANGE_SWEEP_FRACTION)
            except ValueError:
                continue
            cloud, _ = self._scan(sweep)
            if cloud.shape[0]:
                return xyz(cloud), u1
        return np.zeros((0, 3)), None

    def coverage(self, frames):
        """Range at the working point's depth: a wall scanned in G1's outermost views.

        G1 steers the view over a pincushion: the pan reach is smallest at tilt 0 and the
        tilt reach smallest at pan 0. The range covered (x, y) is therefore measured in the
        views at the ends of the two axes: every point of the centred rectangle it spans
        can be measured. The extent (``extent_x``, ``extent_y``) is that of the whole
        region the views reach, corners included. Each view is the outermost one the
        laser reaches (10 V when G1, not the laser, ends the range).

        Returns
        -------
        rng : dict
            ``x``, ``y``, ``extent_x``, ``extent_y`` [mm] (NaN when a view is missing).
        views : dict
            Per view: the G1 voltages used (None: not reachable) and ``limit``: 'G1' when
            the view is at 10 V, else 'laser'.
        """
        distance = self.site.depth
        self.progress.stage(f'range at {distance * 1e3:.0f} mm', len(RANGE_VIEWS), 'views')
        text, _ = eval_scenes.wall(distance)
        self.client.set_scene(text)
        wall_V0 = self.W_T_V0.T @ np.array([0.0, 0.0, 1.0, -distance])
        pts, views = {}, {}
        for name, direction in RANGE_VIEWS.items():
            pts[name], u1 = self._extreme_view(direction, frames, wall_V0)
            limit = None if u1 is None else (
                'G1' if max(abs(v) for v in u1) >= 10.0 else 'laser')
            views[name] = {'u1_V': u1, 'limit': limit}
            self.progress.advance(note=f'{name}: {u1} V, limited by {limit}')

        def span(names, col):
            if any(pts[n].shape[0] == 0 for n in names):
                return float('nan')
            v = np.concatenate([pts[n][:, col] for n in names])
            return float((v.max() - v.min()) * 1e3)

        rng = {'x': span(('x-', 'x+'), 0), 'y': span(('y-', 'y+'), 1),
               'extent_x': span(tuple(RANGE_VIEWS), 0),
               'extent_y': span(tuple(RANGE_VIEWS), 1)}
        return rng, views


def _plate_plane(p):
    """The RANSAC plane of plate points ``p`` (n, 3) [m] and its inliers (n,) bool:
    hypotheses scored on a subsample, then refitted to every inlier of the whole cloud."""
    sub = p
    if p.shape[0] > PLATE_RANSAC_SAMPLE:
        sub = p[np.random.default_rng(0).choice(p.shape[0], PLATE_RANSAC_SAMPLE,
                                                replace=False)]
    plane, _ = metrics.ransac_plane(sub, threshold=PLATE_RANSAC_THRESHOLD)
    inliers = np.abs(p @ plane[:3] + plane[3]) < PLATE_RANSAC_THRESHOLD
    plane, _ = metrics.fit_plane(p[inliers])
    return plane, np.abs(p @ plane[:3] + plane[3]) < PLATE_RANSAC_THRESHOLD


def _cell_point_error_mm(cal, sphere_res):
    """How far the evaluation sphere's measured centre, taken into the cell by the file's
    ``cell_T_v0``, lies from where it truly is [mm] (None without a cell extrinsic): the
    measurement a robot uses, independent of the calibration's own choice of V0."""
    if cal.cell_T_v0 is None:
        return None
    T = np.asarray(cal.cell_T_v0)
    p = T[:3, :3] @ np.asarray(sphere_res['centre_v0_m']) + T[:3, 3]
    return float(np.linalg.norm(p - np.asarray(sphere_res['centre_true_w_m'])) * 1e3)


def _write_params(path, args, rig, cal_path, data_dir, cell_reference='', quick=False):
    params = {
        'calibration': {'ros__parameters': {
            'calibration_file': str(cal_path), 'quick': bool(quick),
            'data_dir': str(data_dir), 'cell_reference': str(cell_reference),
            'model': getattr(args, 'model', 'physical')}},
        'galvo_driver': {'ros__parameters': {
            'backend': 'sim', 'rig': str(rig), 'scene': 'stair_block', 'seed': args.seed}},
        'stripe_extractor': {'ros__parameters': {'line_width_px': 4.0}},
        'reconstructor': {'ros__parameters': {'calibration_file': str(cal_path),
                                              'marker_period': 0.0}},
    }
    path.write_text(yaml.safe_dump(params, sort_keys=False))


class Graph:
    """The graph on a simulated rig, one process per node, and the evaluation's client.

    A context manager: entering starts the nodes (the calibration node unless the
    simulator truth is used) and waits until they are up; leaving stops them.
    :meth:`switch_rig` re-sets the rig under the running graph.

    Parameters
    ----------
    args : argparse.Namespace
        ``seed`` and ``truth_calibration`` are used.
    rig : str
        The rig's name or YAML path (the driver's ``rig`` parameter).
    out : Path
        This graph's folder: parameters, logs, captured bags, ``calibration.yaml``.
    env : dict
        The nodes' environment (its ``ROS_DOMAIN_ID`` is the client's domain).
    quick : bool
        Reduced capture plans.
    cell_reference : str or Path
        The cell stage's reference file ('' when the cell stage is not run).
    """

    def __init__(self, args, rig, out, env, progress, quick=False, cell_reference=''):
        from galvoscan import bringup

        self.out, self.env, self.progress = Path(out), env, progress
        self.model = getattr(args, 'model', 'physical')  # the model form the calibrations fit
        self.cal_path = self.out / 'calibration.yaml'
        if self.cal_path.exists():
            self.cal_path.unlink()
        params = self.out / 'params.yaml'
        _write_params(params, args, rig, self.cal_path, self.out / 'calibration_data',
                      cell_reference, quick)
        self.nodes = list(bringup.DEFAULT_NODES) + (
            [] if args.truth_calibration else ['calibration'])
        params = bringup.with_sim_starting_calibration(params, self.nodes, self.out / 'start')
        params = bringup.with_stripe_orientation(params, self.nodes, self.out / 'start')
        self.sup = bringup.Supervisor(self.nodes, params, env=env, log_dir=self.out / 'logs')
        self.client = None
        self.operator = None
        self.operator_seed = int(getattr(args, 'seed', 0))
        self.exact_operator = bool(getattr(args, 'exact_operator', False))

    def __enter__(self):
        self.progress.log(f'starting the graph ({", ".join(self.nodes)}), logs in '
                          f'{self.out / "logs"}')
        self.sup.start()
        try:
            self.client = GraphClient(int(self.env['ROS_DOMAIN_ID']))
            self.client.wait_ready()
            from galvoscan.operator import EXACT, PERSON, SimulatedOperator

            self.operator = SimulatedOperator(
                int(self.env['ROS_DOMAIN_ID']), self.operator_seed,
                EXACT if self.exact_operator else PERSON, log_fn=self.progress.log).start()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc):
        if self.operator is not None:
            self.operator.stop()
        if self.client is not None:
            self.client.close()
        self.sup.stop()
        return False

    def _lifecycle(self, *transitions):
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        for label in transitions:
            tid = getattr(Transition, f'TRANSITION_{label.upper()}')
            resp = self.client.call(ChangeState, 'galvo_driver/change_state',
                                    ChangeState.Request(transition=Transition(id=tid)))
            if not resp.success:
                raise RuntimeError(f'galvo_driver: lifecycle transition {label} failed')

    def _set_parameters(self, node, **values):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        resp = self.client.call(SetParameters, f'{node}/set_parameters', SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]),
            resend=True)
        bad = [f'{k}: {r.reason}' for k, r in zip(values, resp.results, strict=True)
               if not r.successful]
        if bad:
            raise RuntimeError(f'{node}: parameters refused: {"; ".join(bad)}')

    def switch_rig(self, rig_path, folder, quick=True):
        """Re-set the simulated rig under the running graph, as a technician re-sets the
        bench while the software keeps running: the driver is cleaned up and configured on
        ``rig_path``; the calibration node starts again from that rig's design values and
        writes ``folder/calibration.yaml`` (bags under ``folder``).

        Raises
        ------
        RuntimeError
            A transition, a parameter or the starting calibration was refused.
        """
        from lifecycle_msgs.srv import GetState

        folder = Path(folder)
        state = self.client.call(GetState, 'galvo_driver/get_state', GetState.Request(),
                                 resend=True).current_state.label
        # from wherever an earlier switch left it (a refused rig leaves it unconfigured)
        self._lifecycle(*{'active': ('deactivate', 'cleanup'), 'inactive': ('cleanup',)}.get(
            state, ()))
        self._set_parameters('galvo_driver', rig=str(rig_path))
        self._lifecycle('configure', 'activate')
        self.restart_calibration(rig_path, folder, quick, self.model)

    def restart_calibration(self, rig_path, folder, quick, model):
        """Start the calibration node again from the design values of ``rig_path``, fitting
        ``model`` (``paper`` or ``physical``), writing ``folder/calibration.yaml``."""
        from galvoscan_msgs.srv import LoadCalibration

        from galvoscan.simulated_rig import nominal_calibration
        from reconstructor import calibration_file

        folder = Path(folder)
        self.cal_path = folder / 'calibration.yaml'
        self.cal_path.unlink(missing_ok=True)
        if 'calibration' not in self.nodes:
            return
        start = folder / 'start' / 'nominal_calibration.yaml'
        start.parent.mkdir(parents=True, exist_ok=True)
        calibration_file.save(nominal_calibration(str(rig_path)), start)
        self._set_parameters('calibration', calibration_file=str(self.cal_path),
                             quick=bool(quick), data_dir=str(folder / 'calibration_data'),
                             model=str(model))
        resp = self.client.call(LoadCalibration, 'calibration/load',
                                LoadCalibration.Request(path=str(start)), resend=True)
        if not resp.success:
            raise RuntimeError(f'calibration/load {start}: {resp.message}')

    def calibrate(self, args, rig, quick, cell=False):
        """Calibrate the chain through the calibration node (and the cell stage), or use the
        simulator truth with ``--truth-calibration``; load the result in the reconstructor.

        Returns
        -------
        cal : reconstructor.calibration_file.Calibration
        stage_info : dict
            The stages' figures (``cell_extrinsic`` holds ``failed`` when it failed).

        Raises
        ------
        galvoscan.calibrate_client.StageError
            A stage of the chain failed (names the stage).
        """
        from galvoscan_msgs.srv import LoadCalibration

        from galvoscan.calibrate_client import calibrate_all, calibrate_cell
        from galvoscan.simulated_rig import truth_calibration
        from reconstructor import calibration_file

        stage_info = {}
        if args.truth_calibration:
            calibration_file.save(truth_calibration(rig, kind=self.model), self.cal_path)
            self.progress.log('USING THE SIMULATOR TRUTH AS CALIBRATION (upper bound, not a '
                              'result)')
        else:
            stage_info = calibrate_all(self.client, self.cal_path, self.progress, quick=quick,
                                       operator=self.operator)
            if cell:
                try:  # a rig the cell positions do not suit still gets every other figure
                    stage_info['cell_extrinsic'] = calibrate_cell(
                        self.client, self.cal_path, rig, self.progress)
                except RuntimeError as exc:
                    stage_info['cell_extrinsic'] = {'failed': str(exc)}
                    self.progress.log(f'cell extrinsic not measured: {exc}')
        cal = calibration_file.load(self.cal_path)
        resp = self.client.call(LoadCalibration, 'reconstructor/reload_calibration',
                                LoadCalibration.Request(path=str(self.cal_path)), resend=True)
        if not resp.success:
            raise RuntimeError(resp.message)
        self.client.warm_up(np.zeros((1, 4)))
        return cal, stage_info


def _output_folder(out: Path) -> Path:
    """Create ``out`` (and parents) and check that files can be written in it.

    Raises
    ------
    OSError
        Naming the folder; a folder created here is removed again.
    """
    created = [p for p in [out, *out.parents] if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / '.galvoscan_write_test'
        probe.write_bytes(b'')
        probe.unlink()
    except OSError as exc:
        for p in created:  # innermost first
            try:
                p.rmdir()
            except OSError:
                break
        raise OSError(f'--out {out}: cannot write there ({exc.strerror or exc})') from None
    return out


def _nominal(args, graph, rig, site, progress):
    """The evaluated rig as given: calibrate (full plans unless ``--quick``, cell stage
    included), then every scene around its working point and the off-nominal table.

    Returns ``(result, details, clouds)``: metrics, details and the clouds for the report.
    """
    from galvoscan import report
    from galvoscan.calibrate_client import true_transfer_error_mm

    q = args.quick
    cal, stage_info = graph.calibrate(args, rig, quick=q, cell=True)
    ev = Evaluation(args, graph.client, progress, cal.model, rig.W_T_V0, site)
    stair_rows, stair_clouds = ev.stair_series(
        f'stair block at the working point ({site.depth * 1e3:.0f} mm deep)',
        site.stair_grid(2 if q else 6, 1 if q else 5), 4 if q else 8)
    off_nominal = ev.off_nominal(4 if q else 8)
    # the plate edge to edge: 3 stripe lines a view (every third row and column of views
    # and 2 lines with --quick)
    plate_rows, plate_rmse, plate_clouds, plate_maps = ev.plate(2 if q else 3, 3 if q else 1)
    scaled_rows, scaled_rmse = plate_rows, plate_rmse  # the same plate where scale <= 1
    if site.scale > 1.0:
        scaled_rows, scaled_rmse, _, _ = ev.plate(2 if q else 3, 3 if q else 1, grow=True)
    sphere_res, sphere_cloud = ev.sphere(10 if q else 40)
    rng, range_views = ev.coverage(3)
    errors = [r['error_mm'] for r in stair_rows if r['error_mm'] is not None]
    cell = stage_info.get('cell_extrinsic', {})
    uncertainty = predicted_uncertainty(cal, rig, site.depth)
    result = {
        'stair_step_error_rmse_mm': metrics.rmse(errors),
        'stair_step_error_max_mm': max((abs(e) for e in errors), default=None),
        'stair_step_error_rmse_mm_off_nominal': {
            k: (abs(v['error_mm']) if v.get('error_mm') is not None else None)
            for k, v in off_nominal.items()},
        'plate_flatness_rmse_mm': plate_rmse,
        'plate_flatness_rmse_mm_range_scaled': scaled_rmse,
        'sphere_radius_error_mm': sphere_res['radius_error_mm'],
        'sphere_fit_rms_mm': sphere_res['fit_rms_mm'],
        'transfer_matrix_error_rmse_mm': true_transfer_error_mm(cal.model, rig),
        'joint_error_before_mm': stage_info.get('joint_error_before_mm'),
        'joint_error_after_mm': stage_info.get('joint_error_after_mm'),
        'cell_extrinsic_error_mm': cell.get('error_mm'),
        'cell_extrinsic_error_deg': cell.get('error_deg'),
        'cell_sphere_centre_error_mm': _cell_point_error_mm(cal, sphere_res),
        'plate_coverage_fraction': min(r['coverage_fraction'] for r in plate_rows),
        'plate_points': sum(r['points'] for r in plate_rows),
        'range_x_mm': rng['x'], 'range_y_mm': rng['y'],
        'range_extent_x_mm': rng['extent_x'], 'range_extent_y_mm': rng['extent_y'],
        'stair_positions_used': len(errors), 'stair_positions_total': len(stair_rows),
        'frames_lost': ev.lost_frames,
        'calibration_source': cal.source,
        'calibrated_vs_true': report.calibrated_vs_true(cal.model, rig),
        **{k: v for k, v in uncertainty.items() if not isinstance(v, dict)},
    }
    details = {'uncertainty': uncertainty.get('map'),
               'stair': stair_rows, 'stair_off_nominal': off_nominal, 'plate': plate_rows,
               'plate_range_scaled': scaled_rows,
               'sphere': sphere_res, 'range_views': range_views, 'stages': stage_info}
    return result, details, {'stair': stair_clouds, 'plate': plate_clouds,
                             'plate_maps': plate_maps, 'sphere': sphere_cloud}


#: The uncertainty map's grid: n x n G1 views within +-span V.
UNCERTAINTY_SPAN_V = 8.0
UNCERTAINTY_GRID = 9


def predicted_uncertainty(cal, rig, depth: float) -> dict:
    """The calibration's predicted 1-sigma point error over the range
    (:func:`reconstructor.uncertainty.point_uncertainty_map`) against the error measured on
    the simulator with its true stripe pixels, on the same grid of views and wall
    (:func:`galvoscan.sim_scores.reconstruction_errors`, after the best rigid motion: the
    shape, as the prediction).

    A point's error has two parts: the calibration's (the same in every scan: what its
    parameters' covariance predicts) and the galvos' per-frame noise (new in every frame:
    what the stages measured as :func:`reconstructor.uncertainty.frame_noise`). The
    simulator's galvos scatter too, so the total is measured on the rig as it is and the
    calibration's part on the same rig without that scatter (``Rig.without_jitter``).

    Returns
    -------
    dict
        ``predicted_uncertainty_mm`` (RMS over the map of both parts together),
        ``predicted_calibration_uncertainty_mm`` and ``predicted_frame_noise_mm`` (the
        parts), ``predicted_uncertainty_max_mm`` (the calibration's worst view),
        ``predicted_v0_placement_mm`` (the rigid part, not in the map),
        ``measured_shape_error_mm`` (the rig as it is) and
        ``measured_systematic_error_mm`` (without the galvos' scatter),
        ``uncertainty_ratio`` (predicted / measured, both parts) and
        ``uncertainty_ratio_calibration`` (the calibration's part / the systematic error),
        ``uncertainty_modes_effective``, ``uncertainty_within_2x_probability`` (of the
        total) and ``uncertainty_calibration_within_2x_probability`` (how widely one
        calibration's error scatters about the prediction: see
        :class:`reconstructor.uncertainty.UncertaintyMap`), ``frame_noise_V`` and ``map``
        (the map, and per stage the G1 voltages its views used); NaN figures and
        ``uncertainty_failed`` when it cannot be formed.
    """
    from galvoscan import sim_scores
    from reconstructor.uncertainty import frame_noise, parameter_covariance, point_uncertainty_map

    try:
        pc = parameter_covariance(cal)
        if not pc.names:
            raise ValueError('the calibration holds no covariance')
        noise = frame_noise(cal)
        umap = point_uncertainty_map(cal.model, pc, depth=depth, span=UNCERTAINTY_SPAN_V,
                                     n=UNCERTAINTY_GRID, frame_noise_v=noise)
        measured = sim_scores.reconstruction_errors(
            cal.model, rig, span=UNCERTAINTY_SPAN_V, n=UNCERTAINTY_GRID, depth=depth)
        systematic = sim_scores.reconstruction_errors(
            cal.model, rig.without_jitter(), span=UNCERTAINTY_SPAN_V, n=UNCERTAINTY_GRID,
            depth=depth)
    except (ValueError, RuntimeError) as exc:
        nan = float('nan')
        return {'predicted_uncertainty_mm': nan, 'measured_shape_error_mm': nan,
                'uncertainty_ratio': nan, 'uncertainty_failed': str(exc)}
    predicted = umap.total_rms_m * 1e3
    calib = umap.rms_m * 1e3
    shape = measured['aligned_rms_m'] * 1e3
    steady = systematic['aligned_rms_m'] * 1e3
    views = {stage: rec.get('views_u1_V') for stage, rec in cal.stages.items()
             if isinstance(rec, dict) and rec.get('views_u1_V')}
    return {'predicted_uncertainty_mm': predicted,
            'predicted_calibration_uncertainty_mm': calib,
            'predicted_frame_noise_mm': umap.frame_rms_m * 1e3,
            'predicted_uncertainty_max_mm': umap.worst()[0] * 1e3,
            'predicted_v0_placement_mm': umap.absolute_rms_m * 1e3,
            'measured_shape_error_mm': shape,
            'measured_systematic_error_mm': steady,
            'uncertainty_ratio': predicted / shape if shape > 0 else float('nan'),
            'uncertainty_ratio_calibration': calib / steady if steady > 0 else float('nan'),
            'uncertainty_modes_effective': umap.modes_effective,
            'uncertainty_within_2x_probability': umap.total_within_2x_probability,
            'uncertainty_calibration_within_2x_probability': umap.within_2x_probability,
            'frame_noise_V': noise,
            'map': {**umap.to_dict(), 'views_u1_V': views, 'notes': pc.notes,
                    'measured_shape_error_mm': shape,
                    'measured_systematic_error_mm': steady}}


def _paper_method(args, graph, rig, site, out, progress) -> dict:
    """The paper's own model and calibration on the same rig, graph and scenes (the
    reproduction of the paper): the chain calibrated again from the design values with
    ``model: paper``, then the stair block at the working point and the flat plate. Written
    beside the main figures as ``paper_method``; its calibration is
    ``paper_method/calibration.yaml``."""
    from galvoscan.calibrate_client import true_transfer_error_mm

    q = args.quick
    progress.log("paper's method: the chain calibrated again with the paper's model")
    graph.restart_calibration(args.rig, out / 'paper_method', q, 'paper')
    cal, info = graph.calibrate(args, rig, quick=q)  # the next switch_rig fits graph.model
    ev = Evaluation(args, graph.client, progress, cal.model, rig.W_T_V0, site)
    rows, _ = ev.stair_series("paper's method: stair block at the working point",
                              site.stair_grid(2 if q else 6, 1 if q else 5), 4 if q else 8)
    _, plate_rmse, _, _ = ev.plate(2 if q else 3, 3 if q else 1)
    errors = [r['error_mm'] for r in rows if r['error_mm'] is not None]
    return {'stair_step_error_rmse_mm': metrics.rmse(errors),
            'stair_step_error_max_mm': max((abs(e) for e in errors), default=None),
            'plate_flatness_rmse_mm': plate_rmse,
            'transfer_matrix_error_rmse_mm': true_transfer_error_mm(cal.model, rig),
            'joint_error_before_mm': info.get('joint_error_before_mm'),
            'joint_error_after_mm': info.get('joint_error_after_mm'),
            'stair_positions_used': len(errors)}


def _not_measured(exc, **extra) -> dict:
    row = {'error_mm': None, 'reason': f'not measured: {exc}', **extra}
    stage = getattr(exc, 'stage', None)
    if stage:
        row['failed_stage'] = stage
    return row


def _at_distance(args, graph, description, mm, out, progress) -> dict:
    """The evaluated rig re-set for stand-off ``mm`` under the running ``graph``, calibrated
    there (quick plans, every stage) and the stair block scanned at its working point.

    Returns the distance's row: ``error_mm`` (RMSE over the positions) or ``None`` with the
    ``reason`` (and ``failed_stage`` when a calibration stage failed).
    """
    from galvoscan.calibrate_client import true_transfer_error_mm
    from galvoscan_sim import load_rig
    from galvoscan_sim.rig_family import reset_for_distance

    t0 = time.monotonic()
    try:
        folder = out / 'by_distance' / f'{mm}mm'
        folder.mkdir(parents=True, exist_ok=True)
        rig_path = folder / 'rig.yaml'
        rig_path.write_text(yaml.safe_dump(reset_for_distance(description, mm / 1e3),
                                           sort_keys=False))
        rig = load_rig(str(rig_path))
        site = eval_scenes.site_of(rig)
    except (ValueError, RuntimeError, OSError) as exc:
        return _not_measured(f're-set for {mm} mm: {exc}')
    row = {'rig': str(rig_path), 'working_point_w_m': site.centre_W.tolist(),
           'scene_scale': site.scale, 'calibration_plans': 'quick'}
    grid = site.stair_grid(3, 3, spread=0.5)
    positions = [grid[k] for k in BY_DISTANCE_CROSS[:1 if args.quick else None]]
    try:
        graph.switch_rig(rig_path, folder, quick=True)
        cal, _ = graph.calibrate(args, rig, quick=True)
        t_cal = time.monotonic()
        row['transfer_matrix_error_rmse_mm'] = true_transfer_error_mm(cal.model, rig)
        ev = Evaluation(args, graph.client, progress, cal.model, rig.W_T_V0, site)
        rows, _ = ev.stair_series(f'{mm} mm: stair block at the working point',
                                  positions, 4 if args.quick else 8)
    except (ValueError, RuntimeError, OSError) as exc:
        return {**row, **_not_measured(exc), 'wall_s': time.monotonic() - t0}
    except Exception as exc:  # noqa: BLE001 - one distance never stops the others
        return {**row, **_not_measured(f'{type(exc).__name__}: {exc}'),
                'wall_s': time.monotonic() - t0}
    errors = [r['error_mm'] for r in rows if r['error_mm'] is not None]
    row.update({'positions': rows, 'positions_used': len(errors),
                'calibration_s': t_cal - t0, 'scan_s': time.monotonic() - t_cal,
                'wall_s': time.monotonic() - t0})
    if not errors:
        return {**row, **_not_measured('no stair position measured: ' + '; '.join(
            r['reason'] for r in rows))}
    return {**row, 'error_mm': metrics.rmse(errors)}


def _by_distance(args, graph, description, nominal_mm, nominal_rmse, out, progress) -> dict:
    """:func:`_at_distance` at each of ``args.distances``; a distance within
    NOMINAL_TOLERANCE_MM of the rig's own working distance takes the nominal evaluation."""
    rows = {}
    for mm in args.distances:
        if abs(mm - nominal_mm) <= NOMINAL_TOLERANCE_MM:
            rows[str(mm)] = {'error_mm': nominal_rmse, 'calibration_plans': 'as evaluated',
                             'note': 'the evaluated rig as given (its own working distance)'}
        else:
            progress.log(f'by distance: the rig re-set for {mm} mm')
            rows[str(mm)] = _at_distance(args, graph, description, mm, out, progress)
        r = rows[str(mm)]
        progress.log(f'by distance, {mm} mm: ' + (
            f"stair RMSE {r['error_mm']:.3f} mm" if r['error_mm'] is not None
            else r['reason']))
    return rows


#: Frame rate of scans through the twin when ``--frame-rate`` is left at its default [Hz]:
#: the simulator renders a 720 x 540 exposure in tens of ms on a shared 2-core machine.
TWIN_FRAME_RATE = 10.0
#: The twin board's simulated seconds per wall-clock second: at a quarter speed a node that
#: the shared machine stalls has 600 ms, not 150, before the board's watchdog trips.
TWIN_BOARD_RATE = 0.25
#: Frames of the twin's first scan, which starts the driver's camera-to-board clock fit.
TWIN_FIT_FRAMES = 8
#: How long the twin may take to come up [s] (the renderer compiles on its first run).
TWIN_START_TIMEOUT_S = 300.0


class TwinGraph(Graph):
    """The graph on the rig's hardware-in-the-loop twin (:mod:`galvo_driver.twin`).

    The driver runs the ``rig`` backend against the twin's board (the firmware in simavr,
    behind a pty) and camera (Aravis' GigE Vision fake camera, rendering each triggered
    exposure with the simulator at the DAC outputs of its trigger edge). The twin runs as
    its own process (``python -m galvo_driver.twin_node``), which serves ``sim/set_scene``
    for the simulated operator; the board and render logs go to ``out/twin``. The
    calibration node starts from the rig's design values, as a real rig's would.
    """

    def __init__(self, args, rig, out, env, progress, quick=False,
                 board_rate=TWIN_BOARD_RATE):
        super().__init__(args, rig, out, env, progress, quick=quick)
        self.rig_name = str(rig)
        self.board_rate = float(board_rate)
        self.twin_dir = self.out / 'twin'
        self.twin_proc = None
        #: The driver parameters the twin printed (backend rig, serial port, camera...).
        self.driver_params = {}

    def _start_twin(self):
        import subprocess

        from galvoscan_common.runtime import child_env, die_with_parent

        self.twin_dir.mkdir(parents=True, exist_ok=True)
        self.progress.log(f'starting the twin of rig {self.rig_name} (firmware in simavr, '
                          f'GigE Vision camera rendering the simulator), logs in '
                          f'{self.twin_dir}')
        err = open(self.twin_dir / 'twin_node.log', 'ab')  # noqa: SIM115
        self.twin_proc = subprocess.Popen(
            [sys.executable, '-m', 'galvo_driver.twin_node', '--rig', self.rig_name,
             '--seed', str(self.operator_seed), '--workdir', str(self.twin_dir),
             '--rate', repr(self.board_rate)],
            env=child_env(self.env), stdout=subprocess.PIPE, stderr=err, text=True,
            preexec_fn=die_with_parent())
        err.close()
        import select

        deadline = time.monotonic() + TWIN_START_TIMEOUT_S
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.twin_proc.stdout], [], [], 0.5)
            if ready:
                line = self.twin_proc.stdout.readline()
                if line.startswith('TWIN_READY '):
                    self.driver_params = json.loads(line.split(' ', 1)[1])
                    return
                if not line:
                    break
            if self.twin_proc.poll() is not None:
                break
        self._stop_twin()
        raise RuntimeError(f'the twin did not start (see {self.twin_dir / "twin_node.log"})')

    def _stop_twin(self):
        import signal
        import subprocess

        proc, self.twin_proc = self.twin_proc, None
        if proc is None:
            return
        for sig in (signal.SIGINT, signal.SIGKILL):
            if proc.poll() is None:
                proc.send_signal(sig)
            try:
                proc.wait(timeout=15.0)
                break
            except subprocess.TimeoutExpired:
                continue
        if proc.stdout is not None:
            proc.stdout.close()

    def __enter__(self):
        from galvoscan import bringup

        self._start_twin()
        try:
            params_path = Path(self.sup.params_file)
            params = bringup.load_params(params_path)
            driver = dict(self.driver_params)
            params['galvo_driver'] = {'ros__parameters': driver}
            twin_params = self.out / 'twin_params.yaml'
            twin_params.write_text(yaml.safe_dump(params, sort_keys=False))
            self.sup = bringup.Supervisor(self.nodes, twin_params, env=self.env,
                                          log_dir=self.out / 'logs')
        except BaseException:
            self._stop_twin()
            raise
        try:
            super().__enter__()
        except BaseException:
            self._stop_twin()
            raise
        # The twin's camera stamps frames on its own clock (camera_clock: camera), and the
        # driver pairs a lone frame only once its clock fit exists: a first scan of a few
        # frames makes it (the calibration's first view is a single frame).
        try:
            self.client.scan(np.zeros((TWIN_FIT_FRAMES, 4)), frame_rate=TWIN_FRAME_RATE,
                             laser_on=False, timeout=30.0)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc):
        try:
            super().__exit__(*exc)
        finally:
            self._stop_twin()
        return False

    def twin_counts(self) -> dict:
        """Trigger edges the board fired and frames the camera rendered so far."""
        from galvo_driver.serial_link.simavr_board import parse_log
        from galvo_driver.twin import read_render_log

        board = self.twin_dir / 'board.log'
        edges = len(parse_log(board).rising_edges()) if board.exists() else 0
        return {'frames_triggered': edges,
                'frames_rendered': len(read_render_log(self.twin_dir / 'render.log'))}


def _twin_evaluate(args) -> int:
    """``galvoscan evaluate --twin``: the rig's twin as the graph's backend; calibrate it
    through the calibration node and the simulated operator (or use the simulator truth with
    ``--truth-calibration``), then scan the stair block at the working point. Writes
    ``metrics.json`` (and ``failure.json`` when it stops) into ``--out``."""
    t0 = time.monotonic()
    loaded = _load_fresh(args)
    if loaded is None:
        return 2
    rig, _, site, wd, out = loaded
    if args.frame_rate == build_parser().get_default('frame_rate'):
        args.frame_rate = TWIN_FRAME_RATE
    q = args.quick
    progress = Progress()
    progress.log(f'twin of rig {rig.name}: scans at {args.frame_rate:g} Hz of board time, '
                 f'the board at {TWIN_BOARD_RATE:g} x real time' + (', quick plans' if q else ''))
    domain = os.environ.get('ROS_DOMAIN_ID') or str(private_domain())
    env = {**os.environ, 'ROS_DOMAIN_ID': domain, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    result = {'backend': 'rig (twin)', 'frame_rate_hz': args.frame_rate,
              'board_rate': TWIN_BOARD_RATE, 'quick': bool(q)}
    reached = 'start'
    try:
        with TwinGraph(args, args.rig, out, env, progress, quick=q) as graph:
            reached = 'calibration'
            t_cal = time.monotonic()
            cal, stage_info = graph.calibrate(args, rig, quick=q)
            from galvoscan.calibrate_client import true_transfer_error_mm

            result.update({'calibration_source': cal.source,
                           'calibration_s': time.monotonic() - t_cal,
                           'transfer_matrix_error_rmse_mm': true_transfer_error_mm(cal.model,
                                                                                   rig),
                           'joint_error_after_mm': stage_info.get('joint_error_after_mm')})
            reached = 'stair'
            ev = Evaluation(args, graph.client, progress, cal.model, rig.W_T_V0, site)
            rows, clouds = ev.stair_series(
                f'twin: stair block at the working point ({site.depth * 1e3:.0f} mm deep)',
                site.stair_grid(2 if q else 6, 1 if q else 5), 4 if q else 8)
            errors = [r['error_mm'] for r in rows if r['error_mm'] is not None]
            result.update({'stair_step_error_rmse_mm': metrics.rmse(errors),
                           'stair_positions_used': len(errors),
                           'stair_positions_total': len(rows), 'frames_lost': ev.lost_frames,
                           **graph.twin_counts()})
            reached = 'done'
    except (RuntimeError, ValueError) as exc:
        progress.log(f'twin evaluation stopped at {reached}: {exc}')
        (out / 'failure.json').write_text(json.dumps(
            {'stage': getattr(exc, 'stage', None) or reached, 'message': str(exc)}, indent=1))
        return 1
    result.update({'working_distance_mm': wd * 1e3, 'runtime_s': time.monotonic() - t0})
    if clouds:
        save_cloud(np.concatenate(clouds), out / 'stair_working_point.ply')
    (out / 'metrics.json').write_text(json.dumps(result, indent=1, default=float))
    progress.log(f'wrote {out}/metrics.json in {time.monotonic() - t0:.0f} s')
    print(json.dumps(result, default=float))
    return 0


def build_parser():
    p = argparse.ArgumentParser(prog='galvoscan evaluate', description=__doc__.split('\n')[0])
    p.add_argument('--rig', default='reference', help='rig name or YAML (default: reference)')
    p.add_argument('--seed', type=int, default=0, help='simulator seed')
    p.add_argument('--quick', action='store_true', help='reduced run (for tests)')
    p.add_argument('--model', choices=('paper', 'physical'), default='physical',
                   help="model form the calibration fits: physical (each mirror a plane on its "
                        "own axis, default) or paper (the paper's model as published)")
    p.add_argument('--no-paper-method', dest='paper_method', action='store_false',
                   help="with --model physical: skip calibrating and scanning again with the "
                        "paper's model (the paper_method figures)")
    p.add_argument('--out', default='out', help='output folder (default: out)')
    p.add_argument('--frame-rate', type=float, default=500.0, help='scan frame rate [Hz]')
    p.add_argument('--truth-calibration', action='store_true',
                   help="skip calibration and use the simulator's true parameters "
                        '(labelled as such: an upper bound, not a result)')
    p.add_argument('--distances', type=_distances, default=DISTANCES_MM, metavar='MM[,MM..]',
                   help='working distances [mm] of the by-distance evaluation (the rig '
                        're-set, calibrated and scanned at each), 100 to 1000; "none" skips '
                        'it (default: the paper\'s ' + ','.join(map(str, DISTANCES_MM)) + ')')
    p.add_argument('--exact-operator', action='store_true',
                   help='the zero-error simulated operator: every target exactly where the '
                        'instruction asks (the reference for the operator\'s imprecision)')
    p.add_argument('--twin', action='store_true',
                   help="run on the rig's hardware-in-the-loop twin (backend rig: the board "
                        'firmware in simavr, a GigE Vision camera rendering the simulator): '
                        'calibrate and scan the stair block through it, at '
                        f'{TWIN_FRAME_RATE:g} Hz unless --frame-rate is given')
    p.add_argument('--demo', action='store_true',
                   help="what `galvoscan demo` runs: the rig's own calibration through the "
                        "simulated operator and every scene, without the paper's-method "
                        'recalibration and the re-set distances (each calibrates the chain '
                        'again; the full evaluation runs them)')
    p.add_argument('--materials', action='store_true',
                   help='instead: accuracy per surface material with and without each '
                        'countermeasure (galvoscan.materials_eval; materials.json, .md)')
    return p


def _distances(text: str) -> tuple:
    """``--distances``: comma-separated working distances [mm] in 100..1000, or 'none'."""
    if text.strip().lower() == 'none':
        return ()
    out = []
    for part in text.split(','):
        try:
            mm = int(part)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"'{part}' is not a whole number of millimetres") from None
        if not 100 <= mm <= 1000:
            raise argparse.ArgumentTypeError(f'{mm} mm is outside 100..1000 mm')
        out.append(mm)
    return tuple(dict.fromkeys(out))


def _load(args):
    """The evaluated rig, its description, its site and the output folder.

    Raises
    ------
    ValueError, OSError
        A rig that cannot be read, has no working point, or an unwritable ``--out``.
    """
    from galvoscan_sim import load_rig
    from galvoscan_sim.config import read_yaml_file
    from galvoscan_sim.rig_family import working_distance

    rig = load_rig(args.rig)
    description = read_yaml_file(Path(rig.source))
    site = eval_scenes.site_of(rig)
    return rig, description, site, working_distance(rig), _output_folder(Path(args.out))


def _load_fresh(args):
    """:func:`_load`, saying on stderr why it failed (then None), with the last run's
    ``failure.json`` and ``metrics.json`` removed from the output folder."""
    try:
        loaded = _load(args)
    except (ValueError, OSError) as exc:
        print(f'galvoscan evaluate: {exc}', file=sys.stderr)
        return None
    for stale in ('failure.json', 'metrics.json'):
        (loaded[-1] / stale).unlink(missing_ok=True)
    return loaded


def _operator_metrics(operator, details) -> dict:
    """``metrics.json``'s ``operator``: the simulated operator's figures of the evaluated
    rig's own calibration (per stage: placements made and kept, instructions given, views
    rejected by reason, search views, wall time) and its mistakes over the whole run."""
    stages = details.get('stages', {}).get('operator', {})
    return {'seed': operator.seed if operator is not None else None,
            'exact': operator is not None and operator.person.position_m == 0.0,
            'placements': {k: v['placements'] for k, v in stages.items()},
            'placements_kept': {k: v['placements_kept'] for k, v in stages.items()},
            'instructions': {k: v['instructions'] for k, v in stages.items()},
            'views_rejected': {k: v['views_rejected'] for k, v in stages.items()},
            'search_views': {k: v['search_views'] for k, v in stages.items()},
            'wall_s': {k: v['wall_s'] for k, v in stages.items()},
            'mistakes_whole_run': dict(operator.stats['mistakes']) if operator else {},
            'placements_whole_run': sum(operator.stats['placements'].values())
            if operator else 0}


def _write_failure(out, exc):
    """``failure.json``: what stopped the evaluation (the stage, when a stage failed)."""
    (out / 'failure.json').write_text(json.dumps(
        {'stage': getattr(exc, 'stage', None), 'message': str(exc)}, indent=1))


def main(argv=None):
    args = build_parser().parse_args(argv)
    if args.twin:
        return _twin_evaluate(args)
    if args.demo:  # the main job only; the paper's method and the re-set distances each
        args.paper_method, args.distances = False, ()  # calibrate the chain again
    if args.materials:
        from galvoscan import materials_eval
        return materials_eval.main(args, Graph, _load, _write_failure)
    from galvoscan import report
    from galvoscan.simulated_rig import nominal_rig

    t0 = time.monotonic()
    loaded = _load_fresh(args)
    if loaded is None:
        return 2
    rig, description, site, wd, out = loaded
    progress = Progress()
    progress.log(f'rig {rig.name}: working distance {wd * 1e3:.1f} mm (stand-off from the '
                 f'G1 exit mirror), working point {site.depth * 1e3:.1f} mm deep, scene '
                 f'scale {site.scale:g}')
    domain = os.environ.get('ROS_DOMAIN_ID') or str(private_domain())
    env = {**os.environ, 'ROS_DOMAIN_ID': domain,
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    cell_ref = out / 'cell_reference.yaml'
    cell_ref.write_text(eval_scenes.cell_reference(nominal_rig(rig).W_T_V0, site)[0])
    try:
        with Graph(args, args.rig, out, env, progress, quick=args.quick,
                   cell_reference=cell_ref) as graph:
            result, details, clouds = _nominal(args, graph, rig, site, progress)
            paper_method = None
            if args.model == 'physical' and args.paper_method:
                paper_method = _paper_method(args, graph, rig, site, out, progress)
            by_distance = _by_distance(args, graph, description, wd * 1e3,
                                       result['stair_step_error_rmse_mm'], out, progress)
            graph_operator = graph.operator
    except (RuntimeError, ValueError) as exc:
        progress.log(f'evaluation failed: {exc}')
        _write_failure(out, exc)
        return 1
    details['stair_by_distance'] = by_distance
    result = {'stair_step_error_rmse_mm': result.pop('stair_step_error_rmse_mm'),
              'stair_step_error_rmse_mm_by_distance': {
                  k: v['error_mm'] for k, v in by_distance.items()},
              **result,
              **({'paper_method': paper_method} if paper_method is not None else {}),
              'operator': _operator_metrics(graph_operator, details),
              'model': args.model, 'working_distance_mm': wd * 1e3,
              'working_point_depth_mm': site.depth * 1e3, 'scene_scale': site.scale,
              'runtime_s': time.monotonic() - t0}
    save_cloud(np.concatenate(clouds['stair']), out / 'stair_working_point.ply')
    save_cloud(np.concatenate(clouds['plate']), out / 'plate.ply')
    save_cloud(clouds['sphere'], out / 'sphere.ply')
    (out / 'details.json').write_text(json.dumps(details, indent=1, default=float))
    (out / 'metrics.json').write_text(json.dumps(result, indent=1, default=float))
    report.write_report(out, result, details, PAPER, clouds)
    progress.log(f'wrote {out}/metrics.json, report.md, clouds and calibration '
                 f'in {time.monotonic() - t0:.0f} s')
    print(json.dumps({k: v for k, v in result.items() if k != 'calibrated_vs_true'},
                     default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
