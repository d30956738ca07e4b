"""cell_T_v0 from a sphere at robot-reported positions: the solver, its refusals, the file,
and the whole measurement on the simulated (ideal-image) rig."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration_tools.cell_extrinsic import (
    capture_steps,
    read_reference,
    rotation_angle,
    solve_cell_T_v0,
    sphere_centres,
)

#: Sphere positions over the range [m] in V0, not on one line or plane.
POSITIONS = np.array([[0.0, 0.0, 0.65], [0.35, 0.2, 0.6], [-0.35, 0.2, 0.7],
                      [0.3, -0.2, 0.72], [-0.3, -0.22, 0.58], [0.05, 0.25, 0.66]])


def cell_pose(seed=0):
    """A scanner mounted somewhere in a cell: 4x4 cell_T_v0."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.6, 3)).as_matrix()
    T[:3, 3] = rng.uniform(-1.5, 1.5, 3)
    return T


def to_cell(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def test_exact_points_give_the_pose_exactly():
    T = cell_pose(1)
    sol = solve_cell_T_v0(POSITIONS, to_cell(T, POSITIONS))
    np.testing.assert_allclose(sol.cell_T_v0, T, atol=1e-12)
    assert sol.rms < 1e-12 and np.all(sol.translation_std < 1e-12)


def test_noise_gives_errors_within_the_stated_uncertainty():
    """Over 200 noisy draws, the stated standard errors match the scatter of the solutions."""
    T = cell_pose(2)
    rng = np.random.default_rng(3)
    errs, stds = [], []
    for _ in range(200):
        p_cell = to_cell(T, POSITIONS) + rng.normal(0, 20e-6, POSITIONS.shape)
        sol = solve_cell_T_v0(POSITIONS, p_cell)
        errs.append(sol.cell_T_v0[:3, 3] - T[:3, 3])
        stds.append(sol.translation_std)
    ratio = np.std(errs, axis=0) / np.sqrt(np.mean(np.square(stds), axis=0))
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


@pytest.mark.parametrize('p_v0, match', [
    (POSITIONS[:2], 'at least 3'),
    (np.column_stack([np.linspace(-0.3, 0.3, 5), np.zeros(5), np.full(5, 0.65)]), 'one line'),
    (POSITIONS * 0.01 + [0, 0, 0.65], 'spread'),
    (POSITIONS * 1000.0, 'millimetres'),
    (np.vstack([POSITIONS[:-1], [np.nan, 0, 0.6]]), 'not finite'),
])
def test_positions_that_cannot_fix_the_pose_are_refused(p_v0, match):
    T = cell_pose(0)
    with pytest.raises(ValueError, match=match):
        solve_cell_T_v0(p_v0, to_cell(T, np.nan_to_num(p_v0)))


def test_reference_file(tmp_path):
    good = tmp_path / 'ref.yaml'
    good.write_text('cell_frame: world\nunit: m\npositions:\n  0: [1.0, 0.5, 0.2]\n'
                    '  1: [1.1, 0.5, 0.2]\n  2: [1.0, 0.6, 0.25]\n')
    ref = read_reference(good)
    assert ref.cell_frame == 'world' and sorted(ref.positions) == [0, 1, 2]
    np.testing.assert_array_equal(ref.positions[2], [1.0, 0.6, 0.25])
    assert ref.nominal_cell_T_v0 is None
    nominal = cell_pose(3)
    with_nominal = tmp_path / 'ref2.yaml'
    with_nominal.write_text(good.read_text() + f'nominal_cell_T_v0: {nominal.tolist()}\n')
    np.testing.assert_allclose(read_reference(with_nominal).nominal_cell_T_v0, nominal)
    positions = ('positions: {0: [1, 2, 3], 1: [0, 0, 0], 2: [1, 1, 1]}\n'
                 'unit: m\ncell_frame: world\n')
    for text, key in (('unit: mm', 'unit'), ('unit: m\ncolour: red', 'colour'),
                      (positions + 'nominal_cell_T_v0: [[1, 0, 0, 0], [0, 1, 0, 0]]',
                       'nominal_cell_T_v0'),
                      (positions + 'nominal_cell_T_v0: [[1, 0, 0, 650.0], [0, 1, 0, 0], '
                                   '[0, 0, 1, 0], [0, 0, 0, 1]]', 'millimetres'),
                      ('unit: m\ncell_frame: ""', 'cell_frame'),
                      ('unit: m\ncell_frame: world\npositions: {0: [1, 2, .nan], 1: [0, 0, 0],'
                       ' 2: [1, 1, 1]}', 'positions.0'),
                      ('unit: m\ncell_frame: world\npositions: {0: [1, 2, 3]}', 'positions')):
        bad = tmp_path / 'bad.yaml'
        bad.write_text(text + '\n')
        with pytest.raises(ValueError, match=key):
            read_reference(bad)


def test_the_simulated_cell_pose_is_recovered():
    """The ideal-image rig with its true model: the sphere swept at 6 positions, the robot
    reporting them with 10 um noise. Within 0.1 mm and 0.01 deg."""
    from galvoscan.simulated_rig import execute_in_process, truth_calibration
    from galvoscan_sim.rig import load_rig
    from galvoscan_sim.scene import load_scene
    from galvoscan_sim.simulator import Simulator

    rig = load_rig('ideal')
    model = truth_calibration(rig).model
    sim = Simulator(rig, load_scene('sphere'), seed=0)
    views, _ = execute_in_process(sim, capture_steps(model, POSITIONS, sphere_radius=0.01))
    centres, rejected = sphere_centres(views, model, sphere_radius=0.01)
    assert not rejected and sorted(centres) == list(range(len(POSITIONS)))
    T = cell_pose(4)
    p_cell = to_cell(T, POSITIONS) + np.random.default_rng(5).normal(0, 10e-6, POSITIONS.shape)
    sol = solve_cell_T_v0(np.array([centres[k][0] for k in range(len(POSITIONS))]), p_cell)
    dt = np.linalg.norm(sol.cell_T_v0[:3, 3] - T[:3, 3])
    angle = np.degrees(rotation_angle(sol.cell_T_v0[:3, :3] @ T[:3, :3].T))
    print(f'\ncell_T_v0 on the simulator: {dt * 1e3:.4f} mm, {angle:.5f} deg off; fit RMS '
          f'{sol.rms * 1e3:.4f} mm; stated 1-sigma {np.round(sol.translation_std * 1e3, 4)} mm,'
          f' {np.round(np.degrees(sol.rotation_std), 5)} deg')
    assert dt < 0.1e-3 and angle < 0.01


# ----------------------------------------------------------------------------- the stage
def mounted_rig(tmp_path):
    """The ideal-image rig mounted somewhere in a cell: its world frame W is the cell."""
    import yaml

    from galvoscan_sim.rig import RIG_DIR, load_rig

    data = yaml.safe_load((RIG_DIR / 'ideal.yaml').read_text())
    data['world']['pose_g1'] = {'translation': [0.8, -0.4, 1.1],
                                'rotation_vector': [0.3, -0.5, 0.2]}
    path = tmp_path / 'mounted.yaml'
    path.write_text(yaml.safe_dump(data))
    return path, load_rig(path)


def perturbed(T, mm=3.0, deg=0.5, seed=0):
    """``T`` moved by ``mm`` and turned by ``deg``: a mounting as designed, not as built."""
    rng = np.random.default_rng(seed)
    D = np.eye(4)
    axis = rng.normal(size=3)
    D[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    D[:3, 3] = rng.normal(size=3) * mm * 1e-3 / np.sqrt(3)
    return T @ D


def test_the_stage_recovers_the_mounting_through_the_offline_command(tmp_path, capsys):
    """``galvoscan calibrate cell_extrinsic --sim``: G1 aimed with a nominal mounting 3 mm and
    0.5 deg off, the robot's positions in the cell frame; the file's cell_T_v0 is the
    simulator's true W_T_V0 within 0.1 mm and 0.01 deg, and survives a later rig stage."""
    import dataclasses

    from calibration_tools.stages import StageResult, apply_result
    from galvoscan.offline import main
    from galvoscan.simulated_rig import truth_calibration
    from reconstructor import calibration_file

    rig_path, rig = mounted_rig(tmp_path)
    truth = rig.W_T_V0
    start = dataclasses.replace(truth_calibration(rig), source='calibrated')
    cal_path = tmp_path / 'cal.yaml'
    calibration_file.save(start, cal_path)
    p_cell = to_cell(truth, POSITIONS)
    ref = tmp_path / 'ref.yaml'
    ref.write_text('cell_frame: robot_base\nunit: m\npositions:\n' + ''.join(
        f'  {k + 10}: {p.tolist()}\n' for k, p in enumerate(p_cell))
        + f'nominal_cell_T_v0: {perturbed(truth).tolist()}\n')
    assert main(['cell_extrinsic', '--sim', '--quick', '--rig', str(rig_path),
                 '--calibration', str(cal_path), '--reference', str(ref)]) == 0
    out = capsys.readouterr().out
    assert 'cell_extrinsic: 6 samples used, 0 rejected' in out, out
    cal = calibration_file.load(cal_path)
    dt = np.linalg.norm(cal.cell_T_v0[:3, 3] - truth[:3, 3])
    angle = np.degrees(rotation_angle(cal.cell_T_v0[:3, :3] @ truth[:3, :3].T))
    entry = cal.stages['cell_extrinsic']
    print(f'\nstage on the mounted rig: {dt * 1e3:.4f} mm, {angle:.5f} deg off; stated '
          f"1-sigma {np.round(np.array(entry['translation_std_m']) * 1e3, 4)} mm")
    assert dt < 0.1e-3 and angle < 0.01
    assert entry['cell_frame'] == 'robot_base' and entry['positions'] == list(range(10, 16))
    assert entry['residuals']['sphere_centre_rms_m'] < 0.1e-3
    # a later rig stage keeps the mounting but says the model moved under it
    later = apply_result(cal, StageResult('laser_plane', updates={'l': cal.model.l + 1e-5}))
    np.testing.assert_array_equal(later.cell_T_v0, cal.cell_T_v0)
    assert later.stages['cell_extrinsic']['model_changed_by'] == 'laser_plane'
    assert apply_result(cal, StageResult('laser_plane')).cell_T_v0 is not None


def test_the_stage_needs_its_reference(tmp_path):
    from calibration_tools.registry import plan, stage_inputs
    from galvoscan.offline import main
    from galvoscan.simulated_rig import truth_calibration
    from galvoscan_sim.rig import load_rig

    cal = truth_calibration(load_rig('ideal'))
    with pytest.raises(ValueError, match='cell_extrinsic needs cell_reference'):
        plan('cell_extrinsic', cal)
    with pytest.raises(ValueError, match='intrinsics takes no input cell_reference'):
        stage_inputs('intrinsics', {'cell_reference': 'ref.yaml'})
    ref = tmp_path / 'ref.yaml'
    ref.write_text('cell_frame: world\nunit: m\npositions:\n' + ''.join(
        f'  {k}: {p.tolist()}\n' for k, p in enumerate(POSITIONS)))
    with pytest.raises(ValueError, match='nominal_cell_T_v0 is needed'):
        plan('cell_extrinsic', cal, inputs={'cell_reference': str(ref)})
    assert main(['all', '--sim', '--calibration', str(tmp_path / 'c.yaml'),
                 '--reference', str(ref)]) == 1
