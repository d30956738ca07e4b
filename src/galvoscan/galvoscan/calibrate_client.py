"""Run every calibration stage through the calibration node's services (capture, compute).

Used by ``galvoscan evaluate``; ``client`` is its GraphClient (``call(srv, name, req)``).
The figures returned are read back from the calibration file the node wrote.
"""

from __future__ import annotations

import numpy as np

from calibration_tools.stages import STAGES
from reconstructor import calibration_file


class StageError(RuntimeError):
    """A calibration stage failed; ``stage`` names it, the message says why."""

    def __init__(self, stage: str, message: str):
        super().__init__(message)
        self.stage = stage


def capture_and_compute(client, stage: str):
    """One stage through the node's services: ``(capture response, compute response)``.

    Raises
    ------
    StageError
        Either service reports failure, or does not answer (its message).
    """
    from galvoscan_msgs.srv import CaptureCalibration, ComputeCalibration

    try:
        cap = client.call(CaptureCalibration, 'calibration/capture',
                          CaptureCalibration.Request(stage=stage), timeout=900.0)
    except RuntimeError as exc:
        raise StageError(stage, f'capture {stage}: {exc}') from None
    if not cap.success:
        raise StageError(stage, f'capture {stage}: {cap.message}')
    try:
        comp = client.call(ComputeCalibration, 'calibration/compute',
                           ComputeCalibration.Request(stage=stage), timeout=900.0)
    except RuntimeError as exc:
        raise StageError(stage, f'compute {stage}: {exc}') from None
    if not comp.success:
        raise StageError(stage, f'compute {stage}: {comp.message}')
    return cap, comp


def calibrate_all(client, cal_path, progress, quick=False, operator=None) -> dict:
    """Capture and compute each stage in order; return the stage figures for the report.

    With the simulated ``operator`` (:class:`galvoscan.operator.SimulatedOperator`) that
    placed the targets, ``info['operator']`` holds its figures per stage: placements it
    made (retakes included) and kept, instructions given, views rejected by reason, search
    views and wall time.
    """
    import time

    progress.stage('calibration (capture + compute)', len(STAGES), 'stages')
    info = {}
    ops = {}
    for stage in STAGES:
        before = dict(operator.stats['placements']) if operator is not None else {}
        asked = dict(operator.stats['instructions_by_stage']) if operator is not None else {}
        t0 = time.monotonic()
        cap, comp = capture_and_compute(client, stage)
        info[stage] = {'frames': cap.frames_recorded, 'capture_s': cap.duration,
                       'samples_used': comp.samples_used,
                       'samples_rejected': comp.samples_rejected}
        if operator is not None:
            done = operator.finished.get(stage, {})
            ops[stage] = {
                'placements': operator.stats['placements'].get(stage, 0)
                - before.get(stage, 0),
                'placements_kept': cap.poses,
                'instructions': operator.stats['instructions_by_stage'].get(stage, 0)
                - asked.get(stage, 0),
                'views_rejected': done.get('views_rejected', {}),
                'search_views': done.get('search_views', 0),
                'wall_s': time.monotonic() - t0}
        progress.advance(note=f'{stage}: {cap.frames_recorded} frames, '
                              f'{comp.samples_used} used, {comp.samples_rejected} rejected')
    if operator is not None:
        info['operator'] = ops
    cal = calibration_file.load(cal_path)
    for stage in STAGES:
        info[stage]['residuals'] = cal.stages.get(stage, {}).get('residuals', {})
    nodes = [n for n in cal.stages.get('joint_correction', {}).get('nodes', [])
             if 'error2_rms_m' in n]
    if nodes:
        info['joint_correction_curves'] = {
            label: [n[key] * 1e3 for n in nodes] for label, key in (
                ('Error1, before', 'error1_rms_m'), ('Error3, before', 'error3_rms_m'),
                ('Error2, after', 'error2_rms_m'))}
    jc = info['joint_correction']['residuals']
    for key, name in (('joint_error_before_mm', 'error1_rms_m'),
                      ('joint_error_before_error3_mm', 'error3_rms_m'),
                      ('joint_error_after_mm', 'error2_rms_m')):
        if name in jc:
            info[key] = jc[name] * 1e3
    return info


def calibrate_cell(client, cal_path, rig, progress) -> dict:
    """The cell stage through the node (its ``cell_reference`` parameter set by the caller),
    and its error against the simulator's true mounting ``rig.W_T_V0`` (W is the cell)."""
    from calibration_tools.cell_extrinsic import rotation_angle
    from calibration_tools.stages import CELL_STAGE

    progress.stage('cell extrinsic (capture + compute)', 1, 'stages')
    cap, comp = capture_and_compute(client, CELL_STAGE)
    cal = calibration_file.load(cal_path)
    T, truth = cal.cell_T_v0, rig.W_T_V0
    entry = cal.stages[CELL_STAGE]
    info = {'positions': comp.samples_used, 'frames': cap.frames_recorded,
            'error_mm': float(np.linalg.norm(T[:3, 3] - truth[:3, 3]) * 1e3),
            'error_deg': float(np.degrees(rotation_angle(T[:3, :3] @ truth[:3, :3].T))),
            'stated_translation_std_mm': [v * 1e3 for v in entry['translation_std_m']],
            'stated_rotation_std_deg': [float(np.degrees(v)) for v in
                                        entry['rotation_std_rad']],
            'sphere_centre_rms_mm': entry['residuals']['sphere_centre_rms_m'] * 1e3}
    progress.advance(note=f"{CELL_STAGE}: {comp.samples_used} positions, "
                          f"{info['error_mm']:.4f} mm / {info['error_deg']:.5f} deg from "
                          'the true mounting')
    return info


def true_transfer_error_mm(model, rig) -> float:
    """The paper's transfer-matrix error (Eq. 18-1, 36 G1 positions, -10..10 V in 4 V steps)
    of ``model`` against the simulator's exact virtual-camera poses."""
    from calibration_tools.dynamic_camera import transfer_matrix_error

    G0_inv = np.linalg.inv(rig.G_T_V0)

    def exact(up, ut):
        out = []
        for a, b in zip(up, ut, strict=True):
            th = rig.mirror_angles(rig.applied_voltages(np.array([a, b, 0.0, 0.0])))
            out.append(G0_inv @ rig.G_T_V(th[0], th[1]))
        return np.stack(out)

    return transfer_matrix_error(model, exact).rmse_mm
