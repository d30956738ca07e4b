"""Hand-eye calibration (AX = XB): the solver, its refusals, and the whole measurement on
the simulated rig carried by a simulated robot."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration_tools.cell_extrinsic import capture_steps, rotation_angle, sphere_centres
from calibration_tools.hand_eye import artefact_scene_yaml, solve_hand_eye, target_pose

#: The artefact: four 10 mm spheres on a plate, centres in its frame [m].
LAYOUT = np.array([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.10, 0.0], [0.11, 0.09, 0.03]])
RADIUS = 0.01


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


#: The truth: the scanner 150 mm out on the flange, turned; the artefact on the table.
FLANGE_T_V0 = pose([0.1, -0.2, 1.4], [0.03, -0.05, 0.15])
BASE_T_TARGET = pose([0.0, 0.0, 0.3], [1.1, 0.2, 0.05])


def robot_poses(n=7, seed=0):
    """Flange poses that show the artefact at ~0.6 m from V0, turned by up to ~15 deg."""
    rng = np.random.default_rng(seed)
    out, shown = [], []
    for _ in range(n):
        v0_T_target = pose(rng.uniform(-0.25, 0.25, 3) + [np.pi, 0, 0],
                           [rng.uniform(-0.12, 0.0), rng.uniform(-0.1, 0.0),
                            rng.uniform(0.55, 0.7)])
        out.append(BASE_T_TARGET @ np.linalg.inv(v0_T_target) @ np.linalg.inv(FLANGE_T_V0))
        shown.append(v0_T_target)
    return np.array(out), np.array(shown)


def test_exact_poses_give_the_mounting():
    A, B = robot_poses()
    sol = solve_hand_eye(A, B)
    np.testing.assert_allclose(sol.flange_T_v0, FLANGE_T_V0, atol=1e-8)
    np.testing.assert_allclose(sol.base_T_target, BASE_T_TARGET, atol=1e-8)
    assert sol.translation_rms < 1e-9 and sol.rotation_rms < 1e-9
    assert sol.closed_form_step[0] < 1e-6


def test_poses_that_cannot_fix_the_mounting_are_refused():
    A, B = robot_poses()
    with pytest.raises(ValueError, match='at least 5'):
        solve_hand_eye(A[:4], B[:4])
    one_axis = np.array([BASE_T_TARGET @ np.linalg.inv(pose([np.pi + a, 0, 0], [0, 0, 0.6]))
                         @ np.linalg.inv(FLANGE_T_V0) for a in np.linspace(-0.3, 0.3, 6)])
    shown = np.array([pose([np.pi + a, 0, 0], [0, 0, 0.6]) for a in np.linspace(-0.3, 0.3, 6)])
    with pytest.raises(ValueError, match='one axis'):
        solve_hand_eye(one_axis, shown)
    in_mm = A.copy()
    in_mm[:, :3, 3] *= 1000.0
    with pytest.raises(ValueError, match='millimetres'):
        solve_hand_eye(in_mm, B)
    bad = A.copy()
    bad[2, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r'base_T_flange\[2\]'):
        solve_hand_eye(bad, B)


def test_the_simulated_mounting_is_recovered():
    """The ideal-image rig on a simulated robot: 7 flange poses, 4 spheres swept at each,
    G1 aimed with a mounting 3 mm / 1 deg off the truth. With exact robot poses,
    flange_T_v0 within 0.05 mm and 0.01 deg; a robot reporting its flange with 20 um /
    0.005 deg noise shows in the consistency residual (its effect on flange_T_v0, ~0.3-0.6
    mm with +-15 deg of tilt, is the method's, not the scanner's)."""
    from galvoscan.simulated_rig import execute_in_process, truth_calibration
    from galvoscan_sim.rig import load_rig
    from galvoscan_sim.scene import load_scene
    from galvoscan_sim.simulator import Simulator

    rig = load_rig('ideal')
    model = truth_calibration(rig).model
    W_T_V0 = rig.W_T_V0
    A, shown = robot_poses()
    nominal_X = FLANGE_T_V0 @ pose(np.radians([0.6, -0.5, 0.6]), [0.002, -0.002, 0.001])
    steps = []
    for i, (T_flange, v0_T_target) in enumerate(zip(A, shown, strict=True)):
        true_v0 = LAYOUT @ v0_T_target[:3, :3].T + v0_T_target[:3, 3]
        aim = np.linalg.inv(nominal_X) @ np.linalg.inv(T_flange) @ BASE_T_TARGET
        aim_v0 = LAYOUT @ aim[:3, :3].T + aim[:3, 3]
        scene = artefact_scene_yaml(true_v0 @ W_T_V0[:3, :3].T + W_T_V0[:3, 3], RADIUS)
        for step in capture_steps(model, aim_v0, sphere_radius=RADIUS, frames=24,
                                  pose_indices=range(10 * i, 10 * i + len(LAYOUT))):
            steps.append(dataclasses.replace(step, scene_yaml=scene))
    views, _ = execute_in_process(Simulator(rig, load_scene('sphere'), seed=0), steps)
    centres, rejected = sphere_centres(views, model, sphere_radius=RADIUS)
    assert not rejected
    measured = np.array([target_pose([centres[10 * i + k][0] for k in range(len(LAYOUT))],
                                     LAYOUT) for i in range(len(A))])
    sol = solve_hand_eye(A, measured)
    dt = np.linalg.norm(sol.flange_T_v0[:3, 3] - FLANGE_T_V0[:3, 3])
    angle = np.degrees(rotation_angle(sol.flange_T_v0[:3, :3] @ FLANGE_T_V0[:3, :3].T))
    print(f'\nhand-eye on the simulator: {dt * 1e3:.4f} mm, {angle:.5f} deg off; consistency '
          f'{sol.translation_rms * 1e3:.4f} mm, {np.degrees(sol.rotation_rms):.5f} deg; '
          f'refinement moved the closed form by {sol.closed_form_step[0] * 1e3:.4f} mm')
    assert dt < 0.05e-3 and angle < 0.01 and sol.translation_rms < 0.05e-3
    rng = np.random.default_rng(1)
    reported = np.array([T @ pose(rng.normal(0, np.radians(0.005), 3), rng.normal(0, 20e-6, 3))
                         for T in A])
    noisy = solve_hand_eye(reported, measured)
    off = np.linalg.norm(noisy.flange_T_v0[:3, 3] - FLANGE_T_V0[:3, 3])
    print(f'with robot noise: {off * 1e3:.4f} mm off, consistency '
          f'{noisy.translation_rms * 1e3:.4f} mm')
    assert noisy.translation_rms > 3 * sol.translation_rms


def test_the_stated_standard_errors_match_the_scatter():
    """Over 80 draws of scanner noise (20 um, and 0.2 mrad: the refinement's lever of 0.1 m),
    the stated standard errors of flange_T_v0 match the scatter of the solutions."""
    A, B = robot_poses(8, seed=2)
    rng = np.random.default_rng(4)
    errs, stds = [], []
    for _ in range(80):
        noisy = np.array([C @ pose(rng.normal(0, 2e-4, 3), rng.normal(0, 20e-6, 3)) for C in B])
        sol = solve_hand_eye(A, noisy)
        turn = sol.flange_T_v0[:3, :3] @ FLANGE_T_V0[:3, :3].T  # about the flange axes
        errs.append(np.concatenate([sol.flange_T_v0[:3, 3] - FLANGE_T_V0[:3, 3],
                                    Rotation.from_matrix(turn).as_rotvec()]))
        stds.append(np.concatenate([sol.translation_std, sol.rotation_std]))
    ratio = np.std(errs, axis=0) / np.sqrt(np.mean(np.square(stds), axis=0))
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


# ----------------------------------------------------------------------------- the stage
def flange_rig(tmp_path, mounting):
    """The ideal-image rig bolted to a flange: its world frame W is the flange, and
    ``W_T_V0`` (the ideal rig's W is its nominal V0) becomes ``mounting``."""
    import yaml

    from galvoscan_sim.rig import RIG_DIR, load_rig

    data = yaml.safe_load((RIG_DIR / 'ideal.yaml').read_text())
    W_T_G = pose(data['world']['pose_g1']['rotation_vector'],
                 data['world']['pose_g1']['translation'])
    T = mounting @ W_T_G
    data['world']['pose_g1'] = {
        'translation': T[:3, 3].tolist(),
        'rotation_vector': Rotation.from_matrix(T[:3, :3]).as_rotvec().tolist()}
    path = tmp_path / 'on_flange.yaml'
    path.write_text(yaml.safe_dump(data))
    return path, load_rig(path)


def write_stage_inputs(tmp_path, nominal, n=7, seed=0, layout=LAYOUT, csv=True):
    """The operator's files: the flange poses of a robot program made with the ``nominal``
    mounting (the artefact in view at ~0.6 m, tilted by up to ~15 deg), and the artefact."""
    from calibration_tools.robot_poses import pose_fields

    rng = np.random.default_rng(seed)
    lines = ['base_frame,flange_frame,x,y,z,qx,qy,qz,qw']
    for _ in range(n):
        v0_T_target = pose(rng.uniform(-0.25, 0.25, 3) + [np.pi, 0, 0],
                           [rng.uniform(-0.12, 0.0), rng.uniform(-0.1, 0.0),
                            rng.uniform(0.55, 0.7)])
        T = BASE_T_TARGET @ np.linalg.inv(v0_T_target) @ np.linalg.inv(nominal)
        p, q = pose_fields(T)
        lines.append(','.join(['base_link', 'tool0'] + [repr(v) for v in p + q]))
    poses = tmp_path / 'robot_poses.csv'
    poses.write_text('\n'.join(lines) + '\n')
    artefact = tmp_path / 'artefact.yaml'
    artefact.write_text(f'unit: m\nsphere_radius: {RADIUS}\nlayout: {layout.tolist()}\n'
                        f'base_T_target: {BASE_T_TARGET.tolist()}\n'
                        f'nominal_flange_T_v0: {nominal.tolist()}\n')
    return poses, artefact


def test_the_stage_recovers_the_mounting_through_the_offline_command(tmp_path, capsys):
    """``galvoscan calibrate hand_eye --sim``: the ideal-image rig on a simulated flange,
    carried to 7 poses (a robot program made with a mounting 3 mm and 1 deg off), the
    artefact's 4 spheres swept at each through the capture steps every stage uses; the
    file's cell_T_v0 is the rig's true mounting within 0.05 mm and 0.01 deg, its frame the
    flange, and it supersedes an earlier cell_extrinsic result."""
    import dataclasses

    from galvoscan.offline import main
    from galvoscan.simulated_rig import truth_calibration
    from reconstructor import calibration_file

    rig_path, rig = flange_rig(tmp_path, FLANGE_T_V0)
    truth = rig.W_T_V0
    nominal = truth @ pose(np.radians([0.6, -0.5, 0.6]), [0.002, -0.002, 0.001])
    poses, artefact = write_stage_inputs(tmp_path, nominal)
    start = dataclasses.replace(truth_calibration(rig), source='calibrated',
                                cell_T_v0=np.eye(4), stages={'cell_extrinsic': {}})
    cal_path = tmp_path / 'cal.yaml'
    calibration_file.save(start, cal_path)
    assert main(['hand_eye', '--sim', '--quick', '--rig', str(rig_path), '--calibration',
                 str(cal_path), '--robot-poses', str(poses), '--artefact', str(artefact)]) == 0
    out = capsys.readouterr().out
    assert 'hand_eye: 7 samples used, 0 rejected' in out, out
    assert 'hand_eye: simulator check: cell_T_v0 is' in out, out
    cal = calibration_file.load(cal_path)
    dt = np.linalg.norm(cal.cell_T_v0[:3, 3] - truth[:3, 3])
    angle = np.degrees(rotation_angle(cal.cell_T_v0[:3, :3] @ truth[:3, :3].T))
    entry = cal.stages['hand_eye']
    print(f"\nhand_eye stage on the simulated flange: {dt * 1e3:.4f} mm, {angle:.5f} deg "
          f"off; stated 1-sigma {np.round(np.array(entry['translation_std_m']) * 1e3, 4)} mm, "
          f"{np.round(np.degrees(entry['rotation_std_rad']), 5)} deg; base_T_target scatter "
          f"{entry['residuals']['base_T_target_rms_m'] * 1e3:.4f} mm")
    assert dt < 0.05e-3 and angle < 0.01
    assert entry['cell_frame'] == 'tool0' and entry['base_frame'] == 'base_link'
    assert entry['poses'] == list(range(7)) and len(entry['translation_std_m']) == 3
    assert 0 < max(entry['translation_std_m']) < 0.05e-3
    np.testing.assert_allclose(entry['base_T_target'], BASE_T_TARGET, atol=1e-4)
    assert cal.stages['cell_extrinsic']['superseded_by'] == 'hand_eye'


def test_the_stage_refuses_what_cannot_fix_the_mounting(tmp_path):
    """Too few poses, an artefact file with a bad layout or no mounting to aim with, and
    inputs given to a stage that does not take them: each refused, saying why."""
    from calibration_tools.registry import plan, stage_inputs
    from galvoscan.offline import main
    from galvoscan.simulated_rig import truth_calibration
    from galvoscan_sim.rig import load_rig

    cal = truth_calibration(load_rig('ideal'))
    poses, artefact = write_stage_inputs(tmp_path, FLANGE_T_V0, n=4)
    inputs = {'robot_poses': str(poses), 'hand_eye_artefact': str(artefact)}
    with pytest.raises(ValueError, match='4 poses: hand-eye calibration needs at least 5'):
        plan('hand_eye', cal, inputs=inputs)
    with pytest.raises(ValueError, match='hand_eye needs robot_poses'):
        plan('hand_eye', cal, inputs={'hand_eye_artefact': str(artefact)})
    with pytest.raises(ValueError, match='cell_extrinsic takes no input hand_eye_artefact, '
                                         'robot_poses'):
        stage_inputs('cell_extrinsic', {**inputs, 'cell_reference': 'ref.yaml'})
    poses, _ = write_stage_inputs(tmp_path, FLANGE_T_V0)
    inputs['robot_poses'] = str(poses)
    for text, match in (
            (artefact.read_text().replace('nominal_flange_T_v0', '# '), 'nominal_flange_T_v0 is '
                                                                       'needed'),
            (artefact.read_text().replace('0.03]]', '0.0]]').replace('[0.0, 0.1, 0.0]',
                                                                     '[0.2, 0.0, 0.0]')
             .replace('[0.11, 0.09, 0.0]', '[0.3, 0.0, 0.0]'), 'layout: .*one line'),
            (artefact.read_text() + 'colour: red\n', r"unknown keys \['colour'\]"),
            (artefact.read_text().replace('unit: m', 'unit: mm'), 'unit'),
            (artefact.read_text().replace(f'sphere_radius: {RADIUS}', 'sphere_radius: 10'),
             'sphere_radius')):
        bad = tmp_path / 'bad_artefact.yaml'
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            plan('hand_eye', cal, inputs={**inputs, 'hand_eye_artefact': str(bad)})
    assert main(['all', '--sim', '--calibration', str(tmp_path / 'c.yaml'),
                 '--robot-poses', str(poses)]) == 1
