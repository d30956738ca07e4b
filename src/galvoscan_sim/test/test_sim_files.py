"""Rig and scene files: the shipped ones load, bad ones fail with file, key and expectation."""

import math
import re

import numpy as np
import pytest
import yaml

from galvoscan_sim import (
    ConfigError,
    load_rig,
    load_rig_text,
    load_scene,
    load_scene_text,
    shipped_rigs,
    shipped_scenes,
)
from galvoscan_sim.rig import RIG_DIR
from galvoscan_sim.scene import OBJECT_TYPES


def _reference_rig_dict():
    return yaml.safe_load((RIG_DIR / 'reference.yaml').read_text())


def _write(tmp_path, name, data):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_shipped_rigs_and_scenes_load():
    assert {'ideal', 'reference'} <= set(shipped_rigs())
    expected = {'plane', 'box', 'stair_block', 'sphere', 'flat_plate', 'checkerboard',
                'circle_board'}
    assert expected <= set(shipped_scenes())
    for name in shipped_rigs():
        rig = load_rig(name)
        assert rig.camera.width == 720 and rig.camera.height == 540
    types = set()
    for name in shipped_scenes():
        types |= {o.type for o in load_scene(name).objects}
    assert types == set(OBJECT_TYPES)


def test_reference_rig_values_are_the_papers_in_si():
    rig = load_rig('reference')
    assert rig.l == pytest.approx(0.08345)
    assert rig.d == pytest.approx(0.02214)
    assert rig.camera.fx == pytest.approx(7801.38)
    assert rig.camera.pixel_size == pytest.approx(6.9e-6)
    assert rig.dac.bits == 16
    # +-10 V -> +-20 deg mechanical
    assert rig.g1.pan_drive.gain * 10.0 == pytest.approx(math.radians(20.0))
    assert rig.g1.pan_drive.theta0 == pytest.approx(math.radians(45.0))
    assert rig.geometric_imperfection
    assert not load_rig('ideal').geometric_imperfection


def test_ideal_rig_has_every_imperfection_zero():
    rig = load_rig('ideal')
    imp = rig.imperfections
    for mirror in ('g1_pan', 'g1_tilt', 'g2_pan', 'g2_tilt'):
        assert all(np.all(np.asarray(v) == 0.0) for v in imp[mirror].values()), mirror
    assert np.all(rig.camera.distortion == 0.0)
    assert imp['laser_fan_roll'] == 0.0 and imp['laser_fan_offset'] == 0.0
    assert not rig.image.noisy and rig.image.speckle_contrast == 0.0
    assert rig.image.psf_sigma == 0.0


def test_missing_key_names_file_and_key(tmp_path):
    data = _reference_rig_dict()
    del data['g1']['d']
    path = _write(tmp_path, 'no_d.yaml', data)
    with pytest.raises(ConfigError) as err:
        load_rig(path)
    msg = str(err.value)
    assert str(path) in msg and "'g1.d'" in msg and 'missing' in msg and 'm' in msg


def test_millimetres_instead_of_metres_is_caught(tmp_path):
    data = _reference_rig_dict()
    data['g1']['l'] = 83.45
    path = _write(tmp_path, 'mm.yaml', data)
    with pytest.raises(ConfigError) as err:
        load_rig(path)
    msg = str(err.value)
    assert str(path) in msg and "'g1.l'" in msg and '83.45' in msg
    assert 'metres' in msg and 'implausible' in msg


@pytest.mark.parametrize('section,key,value', [
    ('laser', 'line_width', 0.6),             # mm given
    ('camera', 'exposure', 500.0),            # us given
    ('g1', 'pan', {'theta0': 45.0, 'gain': 0.0349}),   # degrees given
])
def test_other_unit_mistakes_are_caught(tmp_path, section, key, value):
    data = _reference_rig_dict()
    data[section][key] = value
    with pytest.raises(ConfigError, match=re.escape(section + '.' + key)):
        load_rig_text(yaml.safe_dump(data), 'inline.yaml')


def test_unknown_key_is_rejected():
    data = _reference_rig_dict()
    data['g1']['lenght'] = 0.08
    with pytest.raises(ConfigError, match=r"'g1\.lenght'.*no such key"):
        load_rig_text(yaml.safe_dump(data), 'typo.yaml')


def test_wrong_format_version():
    data = _reference_rig_dict()
    data['format_version'] = 2
    with pytest.raises(ConfigError, match='format_version'):
        load_rig_text(yaml.safe_dump(data), 'v2.yaml')


def test_missing_file_names_the_file(tmp_path):
    with pytest.raises(ConfigError, match='nope.yaml'):
        load_rig(tmp_path / 'nope.yaml')


SCENE = """
format_version: 1
name: t
objects:
  - type: {typ}
    pose: {{translation: [0, 0, 0.65]}}
    albedo: 0.5
    {extra}
"""


def test_unknown_object_type_names_file_key_and_choices(tmp_path):
    path = tmp_path / 'cube.yaml'
    path.write_text(SCENE.format(typ='cube', extra='size: [0.1, 0.1, 0.1]'))
    with pytest.raises(ConfigError) as err:
        load_scene(path)
    msg = str(err.value)
    assert str(path) in msg and "'objects[0].type'" in msg and "'cube'" in msg
    for t in OBJECT_TYPES:
        assert t in msg


def test_scene_missing_and_implausible_keys():
    with pytest.raises(ConfigError, match=r"'objects\[0\]\.radius'.*missing"):
        load_scene_text(SCENE.format(typ='sphere', extra=''), 's.yaml')
    with pytest.raises(ConfigError, match=r"'objects\[0\]\.radius'.*metres"):
        load_scene_text(SCENE.format(typ='sphere', extra='radius: 25.4'), 's.yaml')
    with pytest.raises(ConfigError, match=r"'objects\[0\]\.pose\.translation'"):
        load_scene_text(SCENE.format(typ='sphere', extra='radius: 0.02').replace(
            '0.65', '650'), 's.yaml')
    with pytest.raises(ConfigError, match=r"'objects\[0\]\.albedo'"):
        load_scene_text(SCENE.format(typ='sphere', extra='radius: 0.02').replace(
            'albedo: 0.5', 'albedo: 50'), 's.yaml')


def test_scene_yaml_text_loads():
    scene = load_scene_text(SCENE.format(typ='sphere', extra='radius: 0.02'))
    assert len(scene) == 1 and scene.objects[0].params['radius'] == 0.02


def test_circle_board_is_the_papers():
    board = load_scene('circle_board').objects[0]
    fp = board.feature_points()
    assert fp['object_points'].shape == (35 * 35, 3)
    assert int(fp['big'].sum()) == 25
    # 25 sub-patterns of 7 x 7, the big circle in the middle of each
    big_ids = fp['ids'][fp['big']]
    assert set(big_ids[:, 0] % 7) == {3} and set(big_ids[:, 1] % 7) == {3}
    assert np.allclose(np.diff(np.unique(fp['object_points'][:, 0])), 0.02)
    assert set(np.round(fp['diameters'], 6)) == {0.010, 0.015}
    assert board.params['size'].tolist() == [0.74, 0.74]
