"""``galvoscan evaluate``: the main job on the simulated rig, through the real ROS graph.

1. Starts the graph (driver with the sim backend, stripe_extractor, reconstructor,
   calibration node), one process per node, under the supervisor.
2. Runs every calibration stage through the calibration node's services (capture, then
   compute); the sim scene service places the boards and the sphere.
3. Scans the paper's test objects through the same graph and scores the clouds against the
   scene's ground truth: the stair block at 30 positions at 650 mm and at the paper's
   other working distances, the flat plate in 3 poses, the calibration sphere, the range
   covered at 650 mm.
4. Writes ``metrics.json``, ``report.md`` with plots, the clouds as PLY and the
   calibration file into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from galvoscan import eval_scenes, metrics
from galvoscan.progress import Progress
from galvoscan_common.executor import call_service
from reconstructor.cloud import CLOUD_DTYPE, save_cloud, xyz
from reconstructor.model import v0_T_v
from reconstructor.planning import aim_camera, view_sweep

DISTANCES_MM = (100, 200, 350, 400, 650, 1000)
PAPER = {  # the paper's figures, for comparison in the report only
    'stair_step_error_rmse_mm': 0.165, 'plate_flatness_rmse_mm': 0.281,
    'transfer_matrix_error_rmse_mm': 1.231, 'joint_error_before_mm': 4.928,
    'joint_error_after_mm': 0.197, 'range_x_mm': 1100.0, 'range_y_mm': 1300.0,
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
        self._clients = {}

    def call(self, srv_type, name, request, timeout=60.0):
        client = self._clients.get(name)
        if client is None:
            client = self._clients[name] = self.node.create_client(srv_type, name)
        return call_service(self.ex, client, request, timeout)

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

        resp = self.call(SetScene, 'sim/set_scene', SetScene.Request(scene_yaml=text))
        if not resp.success:
            raise RuntimeError(f'set_scene: {resp.message}')

    def _progress(self):
        from galvoscan_msgs.srv import GetScanProgress

        return self.call(GetScanProgress, 'scan/progress', GetScanProgress.Request())

    def scan(self, voltages, frame_rate=500.0, laser_on=True, timeout=120.0):
        """Run a custom scan; return its per-frame clouds (structured arrays) in stamp order.

        Waits until the driver reports the scan done and every frame's cloud has arrived,
        or until clouds stop coming for 3 s after that (frames lost in the graph).
        """
        from galvoscan_msgs.srv import StartScan

        t_request = time.time() - 1e-3
        resp = self.call(StartScan, 'scan/start', StartScan.Request(
            pattern='custom', voltages=np.asarray(voltages).ravel().tolist(),
            frame_rate=frame_rate, laser_on=laser_on))
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
    def __init__(self, args, client, progress, model, W_T_V0):
        self.args, self.client, self.progress = args, client, progress
        self.model = model            # the calibrated model (aiming is done with it)
        self.W_T_V0 = W_T_V0          # truth: only to express clouds in object frames
        self.V0_T_W = np.linalg.inv(W_T_V0)
        self.out = Path(args.out)
        self.lost_frames = 0

    def _scan(self, voltages):
        clouds, n = self.client.scan(voltages, frame_rate=self.args.frame_rate)
        self.lost_frames += n - len(clouds)
        return np.concatenate(clouds) if clouds else np.zeros(0, CLOUD_DTYPE), clouds

    def _aimed_sweep(self, aim_W, frames):
        aim_V0 = (self.V0_T_W @ np.append(aim_W, 1.0))[:3]  # where the experimenter put it
        u1 = aim_camera(self.model, aim_V0)
        return view_sweep(self.model, *u1, distance=float(np.linalg.norm(aim_V0)),
                          frames=frames)

    def stair_at(self, position, frames):
        """Three views (Plane-1, the riser, Plane-2), each swept by the stripe."""
        text, info = eval_scenes.stair(position)
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

    def stair_grid(self, n_x, n_y, frames):
        xs = np.linspace(-0.38, 0.38, n_x) if n_x > 1 else [0.0]
        ys = np.linspace(-0.33, 0.33, n_y) if n_y > 1 else [0.0]
        positions = [(x, y, 0.65) for y in ys for x in xs]
        self.progress.stage('stair block at 650 mm', len(positions), 'positions')
        rows, clouds = [], []
        for p in positions:
            try:
                res, cloud = self.stair_at(p, frames)
                rows.append({'position_m': list(p), 'error_mm': res.error * 1e3,
                             'thickness_mm': res.thickness * 1e3, 'n_plane1': res.n_plane1,
                             'n_plane2': res.n_plane2})
                clouds.append(cloud)
                note = f'error {res.error * 1e3:+.3f} mm'
            except (ValueError, RuntimeError) as exc:
                rows.append({'position_m': list(p), 'error_mm': None, 'reason': str(exc)})
                note = f'skipped: {exc}'
            self.progress.advance(note=note)
        return rows, clouds

    def stair_distances(self, frames):
        self.progress.stage('stair block at other distances', len(DISTANCES_MM), 'distances')
        out = {}
        for mm in DISTANCES_MM:
            try:
                res, _ = self.stair_at((0.0, 0.0, mm / 1e3), frames)
                out[str(mm)] = {'error_mm': res.error * 1e3, 'n_plane1': res.n_plane1}
                note = f'{mm} mm: error {res.error * 1e3:+.3f} mm'
            except (ValueError, RuntimeError) as exc:
                out[str(mm)] = {'error_mm': None, 'reason': str(exc)}
                note = f'{mm} mm: {exc}'
            self.progress.advance(note=note)
        return out

    def plate(self, views_per_axis, frames):
        poses = range(len(eval_scenes.PLATE_POSES))
        self.progress.stage('flat plate', len(poses), 'poses')
        rows, all_d, clouds = [], [], []
        for k in poses:
            text, info = eval_scenes.plate(k)
            self.client.set_scene(text)
            parts = []
            half = 0.28
            grid = np.linspace(-half, half, views_per_axis) if views_per_axis > 1 else [0.0]
            for gx in grid:
                for gy in grid:
                    aim_W = (info['W_T_O'] @ np.array([gx, gy, 0.0, 1.0]))[:3]
                    try:
                        cloud, _ = self._scan(self._aimed_sweep(aim_W, frames))
                    except (ValueError, RuntimeError):
                        continue
                    parts.append(cloud)
            cloud = np.concatenate(parts) if parts else np.zeros(0, CLOUD_DTYPE)
            plane, inliers = metrics.ransac_plane(xyz(cloud), threshold=2e-3)
            d = np.abs(xyz(cloud)[inliers] @ plane[:3] + plane[3])
            all_d.append(d)
            rows.append({'pose': k, 'points': int(cloud.shape[0]),
                         'inliers': int(inliers.sum()), 'mean_distance_mm': float(d.mean() * 1e3),
                         'rms_mm': metrics.rmse(d) * 1e3})
            clouds.append(cloud)
            self.progress.advance(note=f'mean distance {d.mean() * 1e3:.3f} mm')
        return rows, metrics.rmse(np.concatenate(all_d)) * 1e3, clouds

    def sphere(self, frames):
        self.progress.stage('calibration sphere', 1, 'scans')
        text, info = eval_scenes.sphere((0.05, -0.04, 0.65))
        self.client.set_scene(text)
        cloud, _ = self._scan(self._aimed_sweep(info['aim_W'], frames))
        centre, radius, rms = metrics.fit_sphere(xyz(cloud))
        self.progress.advance(note=f'radius error {(radius - info["radius"]) * 1e3:+.3f} mm')
        return {'radius_error_mm': (radius - info['radius']) * 1e3, 'fit_rms_mm': rms * 1e3,
                'points': int(cloud.shape[0]), 'centre_v0_m': np.asarray(centre).tolist(),
                'centre_true_w_m': np.asarray(info['centre_W']).tolist()}, cloud

    def _extreme_view(self, axis, sign, frames, distance):
        """The most extreme G1 voltage along ``axis`` whose view the laser can reach."""
        for volts in np.arange(10.0, 0.0, -0.5):
            u1 = (sign * volts, 0.0) if axis == 'x' else (0.0, sign * volts)
            T = v0_T_v(self.model, *u1)
            try:
                sweep = view_sweep(self.model, *u1, distance=distance / max(T[2, 2], 1e-3),
                                   frames=frames)
            except ValueError:
                continue
            cloud, _ = self._scan(sweep)
            if cloud.shape[0]:
                return xyz(cloud), u1
        return np.zeros((0, 3)), None

    def coverage(self, frames, distance=0.65):
        """Range covered at ``distance``: a wall scanned at the extreme reachable views."""
        self.progress.stage(f'range at {distance * 1e3:.0f} mm', 4, 'views')
        text, _ = eval_scenes.wall(distance)
        self.client.set_scene(text)
        rng, views = {}, {}
        for axis in ('x', 'y'):
            col = 0 if axis == 'x' else 1
            lo, u_lo = self._extreme_view(axis, -1, frames, distance)
            self.progress.advance()
            hi, u_hi = self._extreme_view(axis, 1, frames, distance)
            self.progress.advance()
            vals = np.concatenate([lo[:, col], hi[:, col]])
            ok = lo.shape[0] and hi.shape[0]
            rng[axis] = float((vals.max() - vals.min()) * 1e3) if ok else float('nan')
            views[axis] = [u_lo, u_hi]
        return rng, views


def _cell_point_error_mm(cal, sphere_res):
    """How far the evaluation sphere's measured centre, taken into the cell by the file's
    ``cell_T_v0``, lies from where it truly is [mm] (None without a cell extrinsic): the
    measurement a robot uses, independent of the calibration's own choice of V0."""
    if cal.cell_T_v0 is None:
        return None
    T = np.asarray(cal.cell_T_v0)
    p = T[:3, :3] @ np.asarray(sphere_res['centre_v0_m']) + T[:3, 3]
    return float(np.linalg.norm(p - np.asarray(sphere_res['centre_true_w_m'])) * 1e3)


def _write_params(path, args, cal_path, data_dir, cell_reference=''):
    params = {
        'calibration': {'ros__parameters': {
            'calibration_file': str(cal_path), 'quick': bool(args.quick),
            'data_dir': str(data_dir), 'cell_reference': str(cell_reference)}},
        'galvo_driver': {'ros__parameters': {
            'backend': 'sim', 'rig': args.rig, 'scene': 'stair_block', 'seed': args.seed}},
        'stripe_extractor': {'ros__parameters': {'line_width_px': 4.0}},
        'reconstructor': {'ros__parameters': {'calibration_file': str(cal_path),
                                              'marker_period': 0.0}},
    }
    path.write_text(yaml.safe_dump(params, sort_keys=False))


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


def build_parser():
    p = argparse.ArgumentParser(prog='galvoscan evaluate', description=__doc__.split('\n')[0])
    p.add_argument('--rig', default='reference', help='rig name or YAML (default: reference)')
    p.add_argument('--seed', type=int, default=0, help='simulator seed')
    p.add_argument('--quick', action='store_true', help='reduced run (for tests)')
    p.add_argument('--out', default='out', help='output folder (default: out)')
    p.add_argument('--frame-rate', type=float, default=500.0, help='scan frame rate [Hz]')
    p.add_argument('--truth-calibration', action='store_true',
                   help="skip calibration and use the simulator's true parameters "
                        '(labelled as such: an upper bound, not a result)')
    p.add_argument('--demo', action='store_true', help=argparse.SUPPRESS)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    from galvoscan import bringup, report
    from galvoscan.calibrate_client import calibrate_all, calibrate_cell, true_transfer_error_mm
    from galvoscan.simulated_rig import nominal_rig, truth_calibration
    from galvoscan_sim import load_rig
    from reconstructor import calibration_file

    t0 = time.monotonic()
    try:
        rig = load_rig(args.rig)
        out = _output_folder(Path(args.out))
    except (ValueError, OSError) as exc:
        print(f'galvoscan evaluate: {exc}', file=sys.stderr)
        return 2
    progress = Progress()
    cal_path = out / 'calibration.yaml'
    if cal_path.exists():
        cal_path.unlink()
    domain = os.environ.get('ROS_DOMAIN_ID') or str(random.randint(101, 230))
    env = {**os.environ, 'ROS_DOMAIN_ID': domain,
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    params = out / 'params.yaml'
    cell_ref = out / 'cell_reference.yaml'
    cell_ref.write_text(eval_scenes.cell_reference(nominal_rig(rig).W_T_V0)[0])
    _write_params(params, args, cal_path, out / 'calibration_data', cell_ref)
    nodes = list(bringup.DEFAULT_NODES) + ([] if args.truth_calibration else ['calibration'])
    params = bringup.with_sim_starting_calibration(params, nodes, out / 'start')
    sup = bringup.Supervisor(nodes, params, env=env, log_dir=out / 'logs')
    progress.log(f'starting the graph ({", ".join(nodes)}), logs in {out / "logs"}')
    sup.start()
    client = GraphClient(int(domain))
    result = {}
    try:
        client.wait_ready()
        if args.truth_calibration:
            cal = truth_calibration(rig)
            calibration_file.save(cal, cal_path)
            stage_info = {}
            progress.log('USING THE SIMULATOR TRUTH AS CALIBRATION (upper bound, not a result)')
        else:
            stage_info = calibrate_all(client, cal_path, progress, quick=args.quick)
            try:  # a rig the cell positions do not suit still gets every other figure
                stage_info['cell_extrinsic'] = calibrate_cell(client, cal_path, rig, progress)
            except RuntimeError as exc:
                stage_info['cell_extrinsic'] = {'failed': str(exc)}
                progress.log(f'cell extrinsic not measured: {exc}')
            cal = calibration_file.load(cal_path)
        from galvoscan_msgs.srv import LoadCalibration
        resp = client.call(LoadCalibration, 'reconstructor/reload_calibration',
                           LoadCalibration.Request(path=str(cal_path)))
        if not resp.success:
            raise RuntimeError(resp.message)
        client.warm_up(np.zeros((1, 4)))
        ev = Evaluation(args, client, progress, cal.model, rig.W_T_V0)
        q = args.quick
        stair_rows, stair_clouds = ev.stair_grid(2 if q else 6, 1 if q else 5, 4 if q else 8)
        by_distance = ev.stair_distances(4 if q else 8)
        plate_rows, plate_rmse, plate_clouds = ev.plate(2 if q else 3, 4 if q else 6)
        sphere_res, sphere_cloud = ev.sphere(10 if q else 40)
        rng, range_views = ev.coverage(3)
        errors = [r['error_mm'] for r in stair_rows if r['error_mm'] is not None]
        by_distance['650'] = {'error_mm': metrics.rmse(errors)}
        result = {
            'stair_step_error_rmse_mm': metrics.rmse(errors),
            'stair_step_error_rmse_mm_by_distance': {
                k: (abs(v['error_mm']) if v.get('error_mm') is not None else None)
                for k, v in by_distance.items()},
            'plate_flatness_rmse_mm': plate_rmse,
            'sphere_radius_error_mm': sphere_res['radius_error_mm'],
            'sphere_fit_rms_mm': sphere_res['fit_rms_mm'],
            'transfer_matrix_error_rmse_mm': true_transfer_error_mm(cal.model, rig),
            'joint_error_before_mm': stage_info.get('joint_error_before_mm'),
            'joint_error_after_mm': stage_info.get('joint_error_after_mm'),
            'cell_extrinsic_error_mm': stage_info.get('cell_extrinsic', {}).get('error_mm'),
            'cell_extrinsic_error_deg': stage_info.get('cell_extrinsic', {}).get('error_deg'),
            'cell_sphere_centre_error_mm': _cell_point_error_mm(cal, sphere_res),
            'range_x_mm': rng['x'], 'range_y_mm': rng['y'],
            'stair_positions_used': len(errors), 'stair_positions_total': len(stair_rows),
            'frames_lost': ev.lost_frames,
            'calibration_source': cal.source,
            'calibrated_vs_true': report.calibrated_vs_true(cal.model, rig),
            'runtime_s': time.monotonic() - t0,
        }
        save_cloud(np.concatenate(stair_clouds), out / 'stair_650mm.ply')
        save_cloud(np.concatenate(plate_clouds), out / 'plate.ply')
        save_cloud(sphere_cloud, out / 'sphere.ply')
        details = {'stair': stair_rows, 'stair_by_distance': by_distance, 'plate': plate_rows,
                   'sphere': sphere_res, 'range_views_V': range_views, 'stages': stage_info}
        (out / 'details.json').write_text(json.dumps(details, indent=1, default=float))
        (out / 'metrics.json').write_text(json.dumps(result, indent=1, default=float))
        report.write_report(out, result, details, PAPER,
                            {'stair': stair_clouds, 'plate': plate_clouds})
        progress.log(f'wrote {out}/metrics.json, report.md, clouds and calibration '
                     f'in {time.monotonic() - t0:.0f} s')
        print(json.dumps({k: v for k, v in result.items() if k != 'calibrated_vs_true'},
                         default=float))
        return 0
    except (RuntimeError, ValueError) as exc:
        progress.log(f'evaluation failed: {exc}')
        return 1
    finally:
        client.close()
        sup.stop()


if __name__ == '__main__':
    sys.exit(main())
