"""Robot flange poses for hand-eye calibration: the YAML and CSV files, their refusals, the
written file read back, and the watch over a pose stream (fresh, still)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration_tools.robot_poses import (
    PoseWatch,
    RobotPoses,
    pose_fields,
    pose_matrix,
    read_robot_poses,
    write_robot_poses,
)

#: Six flange poses [m] and quaternions (x, y, z, w), written out by hand.
POSITIONS = [[0.512, -0.103, 0.634], [0.48, -0.05, 0.61], [0.55, -0.12, 0.66],
             [0.5, -0.08, 0.7], [0.47, -0.15, 0.62], [0.53, -0.1, 0.58]]
QUATS = [[0.0, 0.7071068, 0.0, 0.7071068], [0.1, 0.7, 0.0, 0.7071068],
         [0.0, 0.7, 0.1, 0.7071068], [-0.1, 0.7, 0.0, 0.7071068],
         [0.0, 0.7, -0.1, 0.7071068], [0.0499, 0.7063, 0.0499, 0.7044]]


def yaml_text(positions=POSITIONS, quats=QUATS, head='base_frame: base_link\n'
              'flange_frame: tool0\nunit: m\n'):
    return head + 'poses:\n' + ''.join(
        f'  - position: {p}\n    orientation: {q}\n' for p, q in zip(positions, quats,
                                                                   strict=True))


def csv_text(positions=POSITIONS, quats=QUATS):
    return ('# exported from the robot controller\nbase_frame,flange_frame,x,y,z,qx,qy,qz,qw\n'
            + ''.join(f"base_link,tool0,{','.join(map(str, p + q))}\n"
                      for p, q in zip(positions, quats, strict=True)))


def expected(i):
    """Pose i computed independently of the module (scipy's quaternion, normalised)."""
    q = np.array(QUATS[i]) / np.linalg.norm(QUATS[i])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = POSITIONS[i]
    return T


@pytest.mark.parametrize('name, text', [('poses.yaml', yaml_text()), ('poses.csv', csv_text())])
def test_yaml_and_csv_give_the_same_poses(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    poses = read_robot_poses(path)
    assert (poses.base_frame, poses.flange_frame) == ('base_link', 'tool0')
    assert poses.keys == tuple(range(6))
    for i in range(6):
        np.testing.assert_allclose(poses.base_T_flange[i], expected(i), atol=1e-12)


def test_a_written_file_reads_back(tmp_path):
    poses = RobotPoses('world', 'flange', np.stack([expected(i) for i in range(6)]),
                       tuple(range(6)), 'robot/flange_pose')
    write_robot_poses(poses, tmp_path / 'out.yaml')
    back = read_robot_poses(tmp_path / 'out.yaml')
    assert (back.base_frame, back.flange_frame) == ('world', 'flange')
    np.testing.assert_allclose(back.base_T_flange, poses.base_T_flange, atol=1e-9)


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1), st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_pose_fields_and_pose_matrix_round_trip(q, p):
    q = np.array(q) / np.linalg.norm(q)
    T = pose_matrix(p, q)
    position, quat = pose_fields(T)
    np.testing.assert_allclose(pose_matrix(position, quat), T, atol=1e-12)
    assert quat[3] >= 0


def _bad_yaml(i, key, value):
    entries = [{'position': p, 'orientation': q} for p, q in zip(POSITIONS, QUATS, strict=True)]
    entries[i] = {**entries[i], key: value}
    return ('base_frame: base_link\nflange_frame: tool0\nunit: m\nposes:\n'
            + ''.join(f'  - {e}\n' for e in entries).replace("'", ''))


@pytest.mark.parametrize('text, match', [
    (_bad_yaml(2, 'position', [0.5, float('nan'), 0.6]).replace('nan', '.nan'),
     r'poses\[2\]: position: not finite'),
    (_bad_yaml(3, 'position', [512.0, -103.0, 634.0]), r'poses\[3\]: position .*millimetres'),
    (_bad_yaml(1, 'orientation', [0.0, 0.5, 0.0, 0.5]), r'poses\[1\]: orientation is not a unit'),
    (_bad_yaml(0, 'orientation', [0.0, 0.0, 1.0]), r'poses\[0\]: orientation: expected 4'),
    (_bad_yaml(4, 'speed', 0.1), r"poses\[4\]: unknown keys \['speed'\]"),
    (yaml_text(POSITIONS[:4], QUATS[:4]), '4 poses: .* at least 5'),
    (yaml_text() + 'colour: red\n', r"unknown keys \['colour'\]"),
    (yaml_text(head='base_frame: base_link\nflange_frame: tool0\nunit: mm\n'), 'unit'),
    (yaml_text(head='base_frame: base_link\nflange_frame: ""\nunit: m\n'), 'flange_frame'),
    ('base_frame: b\nflange_frame: f\nunit: m\nposes: {0: [1, 2, 3]}\n', 'poses: expected a list'),
])
def test_bad_yaml_files_are_refused_naming_the_key(tmp_path, text, match):
    path = tmp_path / 'poses.yaml'
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_robot_poses(path)


def _bad_csv(line, column, value):
    rows = csv_text().splitlines()
    cells = rows[line - 1].split(',')
    cells[column] = value
    rows[line - 1] = ','.join(cells)
    return '\n'.join(rows) + '\n'


@pytest.mark.parametrize('text, match', [
    (_bad_csv(4, 3, 'nan'), 'line 4: position: not finite'),
    (_bad_csv(5, 2, '512.0'), 'line 5: position .*millimetres'),
    (_bad_csv(6, 8, '0.2'), 'line 6: orientation is not a unit'),
    (_bad_csv(3, 5, 'abc'), "line 3: qx: not a number: 'abc'"),
    (_bad_csv(7, 1, 'tool1'), 'line 7: frames base_link -> tool1 differ'),
    (_bad_csv(2, 8, 'qw,speed'), r"line 2: columns .*unknown \['speed'\]"),
    (csv_text() + 'base_link,tool0,0.5,0.1\n', 'line 9: 4 fields, expected 9'),
    (csv_text(POSITIONS[:3], QUATS[:3]), '3 poses: .* at least 5'),
])
def test_bad_csv_files_are_refused_naming_the_line(tmp_path, text, match):
    path = tmp_path / 'poses.csv'
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_robot_poses(path)


# ----------------------------------------------------------------------------- the stream
def test_the_watch_refuses_stale_moving_and_unreadable_poses():
    T = expected(0)
    watch = PoseWatch(max_age=0.5, still_m=1e-4, still_rad=2e-4)
    with pytest.raises(ValueError, match='no robot pose received on robot/flange_pose'):
        watch.fresh(100.0, 'robot/flange_pose')
    watch.add(T, 98.0, 'base_link')
    with pytest.raises(ValueError, match='stamped 2.00 s ago, older than robot_pose_max_age'):
        watch.hold(100.0)
    watch.add(T, 101.0, 'base_link')
    with pytest.raises(ValueError, match='in the future'):
        watch.hold(100.0)
    # still: micrometre jitter passes
    watch.add(T, 99.9, 'base_link')
    held, _, frame = watch.hold(100.0)
    np.testing.assert_array_equal(held, T)
    assert frame == 'base_link'
    jitter = T.copy()
    jitter[:3, 3] += 5e-6
    watch.add(jitter, 100.1, 'base_link')
    watch.check_still(100.2, 'step 0')
    # moved by 1 mm during the step
    moved = T.copy()
    moved[0, 3] += 1e-3
    watch.add(moved, 100.3, 'base_link')
    watch.add(T, 100.4, 'base_link')  # and back: the excursion still counts
    with pytest.raises(ValueError, match=r'step 1: the robot moved by 1\.000 mm'):
        watch.check_still(100.5, 'step 1')
    # turned by 0.05 deg
    watch.hold(100.5)
    turned = T.copy()
    turned[:3, :3] = Rotation.from_rotvec([0, 0, math.radians(0.05)]).as_matrix() @ T[:3, :3]
    watch.add(turned, 100.6, 'base_link')
    with pytest.raises(ValueError, match=r'0\.0500 deg'):
        watch.check_still(100.6, 'step 2')
    # the stream stopped during the step
    watch.hold(100.6)
    with pytest.raises(ValueError, match='step 3: the latest robot pose .* stamped 1.40 s ago'):
        watch.check_still(102.0, 'step 3')
    # an unreadable pose during the step, and a frame that changed
    watch.add(T, 102.0, 'base_link')
    watch.hold(102.0)
    watch.reject('orientation is not a unit quaternion')
    with pytest.raises(ValueError, match='step 4: an unreadable pose arrived'):
        watch.check_still(102.1, 'step 4')
    watch.reject('orientation is not a unit quaternion')
    with pytest.raises(ValueError, match=r'stamped 1\.00 s ago.*; 2 later message\(s\) could '
                                         'not be read'):
        watch.hold(103.0)
    watch.add(T, 102.1, 'base_link')
    watch.hold(102.1)
    watch.add(T, 102.2, 'world')
    with pytest.raises(ValueError, match='frame changed from base_link to world'):
        watch.check_still(102.2, 'step 5')
    assert watch.received == 10 and watch.rejected == 2
    with pytest.raises(ValueError, match='max_age'):
        PoseWatch(0.0, 1e-4, 1e-4)
