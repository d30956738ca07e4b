"""``galvoscan calibrate STAGE --bags ...`` on real rosbag2 directories written as the
calibration node writes them, and the bag helpers of stage_runner."""

import hashlib
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration_tools import stage_runner
from calibration_tools.registry import plan
from calibration_tools.stages import apply_result
from galvoscan import offline, sim_scores, simulated_rig
from galvoscan.simulated_rig import execute_in_process
from galvoscan_bag.typestore import default_typestore
from galvoscan_bag.writer import BagWriter
from galvoscan_sim import Simulator, load_rig, load_scene
from reconstructor import calibration_file

STORE = default_typestore()


def _stamp(t):
    Time = STORE.types['builtin_interfaces/msg/Time']
    Header = STORE.types['std_msgs/msg/Header']
    ns = int(round(t * 1e9))
    return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id='camera_optical')


def write_node_bags(root, steps, views, t0=1_700_000_000.0):
    """One rosbag2 directory per step, ``poseNNN_stepMMM``, as calibration_node records:
    camera/image_raw and galvo/state with the same header stamp per frame."""
    Image = STORE.types['sensor_msgs/msg/Image']
    State = STORE.types['galvoscan_msgs/msg/GalvoState']
    dirs, k = [], 0
    for i, step in enumerate(steps):
        bag = root / f'pose{step.pose_index:03d}_step{i:03d}'
        with BagWriter(bag) as w:
            w.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
            w.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
            for _ in range(step.frames):
                v = views[k]
                h, wd = v.image.shape
                header = _stamp(t0 + v.stamp)
                img = Image(header=header, height=h, width=wd, encoding='mono8',
                            is_bigendian=0, step=wd, data=np.ascontiguousarray(v.image).ravel())
                state = State(header=header, seq=k, g1_pan_voltage=v.voltages[0],
                              g1_tilt_voltage=v.voltages[1], g2_pan_voltage=v.voltages[2],
                              g2_tilt_voltage=v.voltages[3], laser_on=v.laser_on, status=0)
                log = int((t0 + v.stamp) * 1e9) + 1000
                # States may arrive before or after their images.
                order = [('/galvo/state', state), ('/camera/image_raw', img)]
                for topic, msg in (order if k % 2 else order[::-1]):
                    w.write(topic, bytes(STORE.serialize_cdr(msg, msg.__msgtype__)), log)
                k += 1
        dirs.append(bag)
    return dirs


@pytest.fixture(scope='module')
def captured(tmp_path_factory):
    rig = load_rig('reference')
    cal = simulated_rig.nominal_calibration('reference')
    steps = plan('laser_plane', cal, quick=True)
    views, _ = execute_in_process(Simulator(rig, load_scene('plane'), seed=5), steps)
    run = tmp_path_factory.mktemp('capture') / 'laser_plane_20261121-100000'
    bags = write_node_bags(run, steps, views)
    return rig, cal, steps, views, run, bags


def test_views_come_back_from_the_bags_unchanged(captured):
    _, _, steps, views, run, bags = captured
    back = stage_runner.views_from_bags([run])  # the run folder stands for its bags
    assert len(back) == len(views)
    for a, b in zip(views, back, strict=True):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.voltages, b.voltages)
        assert a.laser_on == b.laser_on and a.pose_index == b.pose_index
    assert stage_runner.expand_bag_dirs([run]) == bags
    # Without the node's names, a bag's pose is its place in the list.
    assert {v.pose_index for v in stage_runner.views_from_bags(bags[::-1])} == {0}
    for bag in bags:
        mcap = next(bag.glob('*.mcap'))
        assert stage_runner.bag_digest(bag) == hashlib.sha256(mcap.read_bytes()).hexdigest()


def test_a_bag_without_frames_is_skipped_but_not_all(captured, tmp_path):
    _, _, _, views, _, bags = captured
    empty = tmp_path / 'pose007_step009'
    with BagWriter(empty) as w:
        w.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        w.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
    assert len(stage_runner.views_from_bags([*bags, empty])) == len(views)
    with pytest.raises(ValueError, match='no camera frames'):
        stage_runner.views_from_bags([empty])


def test_offline_stage_on_bags_writes_a_valid_calibration(captured, tmp_path, capsys):
    rig, cal, steps, views, run, bags = captured
    out = tmp_path / 'cal' / 'calibration.yaml'
    rc = offline.main(['laser_plane', '--bags', str(run), '--calibration', str(out),
                       '--rig', 'reference'])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert 'plane_rms_m' in text and 'laser_plane_v0[0]' in text
    new = calibration_file.load(out)
    meta = new.stages['laser_plane']
    assert [b['path'] for b in meta['bags']] == [str(b.resolve()) for b in bags]
    assert [b['sha256'] for b in meta['bags']] == [
        hashlib.sha256(next(b.glob('*.mcap')).read_bytes()).hexdigest() for b in bags]
    assert meta['samples_used'] == 4 and meta['updated'] == ['laser_plane_v0']
    # The same numbers as computing on the frames in memory: the bags lose nothing.
    direct = apply_result(cal, stage_runner.compute('laser_plane', views, cal))
    np.testing.assert_allclose(new.model.laser_plane_v0, direct.model.laser_plane_v0,
                               atol=1e-12)
    # ... and a plane near the true one (design intrinsics: no distortion yet).
    err = sim_scores.laser_plane_errors(new.model, rig)
    assert err['normal_deg'] < 0.3 and err['at_work_m'] < 1e-3
    # A second stage on top of the file merges into it.
    rc = offline.main(['laser_plane', '--bags', *map(str, bags), '--calibration', str(out)])
    assert rc == 0 and 'laser_plane' in calibration_file.load(out).stages


def test_bad_input_is_refused_and_changes_nothing(captured, tmp_path, capsys):
    _, _, _, _, run, _ = captured
    out = tmp_path / 'calibration.yaml'
    calibration_file.save(simulated_rig.nominal_calibration('reference'), out)
    before = out.read_bytes()

    def fails(argv, match):
        rc = offline.main(argv)
        err = capsys.readouterr().err
        assert rc == 1 and match in err, err
        assert out.read_bytes() == before

    fails(['focus', '--bags', str(run), '--calibration', str(out)], "unknown stage 'focus'")
    fails(['laser_plane', '--bags', str(tmp_path / 'nope'), '--calibration', str(out)],
          'does not exist')
    fails(['laser_plane', '--calibration', str(out)], 'needs --bags')
    fails(['laser_plane', '--bags', str(tmp_path), '--calibration', str(out)],
          'holds no rosbag2')
    fails(['all', '--calibration', str(out)], 'needs --sim')
    fails(['intrinsics', '--bags', str(run), '--calibration', str(out)], 'intrinsics')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('format_version: 1\nmodel: {l: 83.45}\n')
    fails(['laser_plane', '--bags', str(run), '--calibration', str(tmp_path / 'new.yaml'),
           '--initial', str(bad)], 'bad.yaml')
    fails(['laser_plane', '--bags', str(run), '--calibration', str(tmp_path / 'new.yaml')],
          '--initial FILE or --rig NAME')
    from galvoscan.simulated_rig import truth_calibration

    truth = tmp_path / 'truth.yaml'
    calibration_file.save(truth_calibration(load_rig('reference')), truth)
    fails(['laser_plane', '--bags', str(run), '--calibration', str(tmp_path / 'new.yaml'),
           '--initial', str(truth)], 'simulator_truth')
    fails(['laser_plane', '--bags', str(run), '--calibration', str(tmp_path / 'new.yaml'),
           '--initial', str(out), '--rig', 'reference'], '--initial and --rig both')
    assert not (tmp_path / 'new.yaml').exists()
    assert offline.main(['--help']) == 0


@settings(max_examples=30, deadline=None)
@given(st.dictionaries(st.sampled_from(['l', 'd', 'k', 'theta0']),
                       st.floats(-1e3, 1e3, allow_nan=False), min_size=1),
       st.lists(st.floats(-1.0, 1.0, allow_nan=False), max_size=5))
def test_flatten_names_every_value_once(scalars, vector):
    updates = {'g1_pan': dict(scalars), 'laser_plane_v0': list(vector), 'l': 0.08}
    flat = stage_runner.flatten(updates)
    assert len(flat) == len(scalars) + len(vector) + 1
    for k, v in scalars.items():
        assert flat[f'g1_pan.{k}'] == v
    for j, v in enumerate(vector):
        assert flat[f'laser_plane_v0[{j}]'] == v
    assert flat['l'] == 0.08 and all(isinstance(v, float) for v in flat.values())
    assert math.isfinite(sum(flat.values()))


def test_compute_refuses_what_it_cannot_use(captured):
    _, cal, _, views, _, _ = captured
    with pytest.raises(ValueError, match='stage'):
        stage_runner.compute('focus', views, cal)
    with pytest.raises(ValueError, match='no views'):
        stage_runner.compute('laser_plane', [], cal)
    with pytest.raises(ValueError, match='pose_index'):
        stage_runner.compute('dynamic_camera', [views[0].__class__(views[0].image,
                                                                    views[0].voltages,
                                                                    False, 9)], cal)
    with pytest.raises(ValueError, match='bag'):
        stage_runner.bag_digest('/nonexistent')
