"""The rig family: random rigs drawn inside documented ranges, set up for a distance, checked
with the simulator; re-set for another distance; bad rig descriptions refused; the CLI."""

import copy
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from galvoscan_sim import ConfigError, Simulator, load_rig, load_rig_text, load_scene_text
from galvoscan_sim import rig_family as rf
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig import RIG_DIR

SEEDS = range(50)


@pytest.fixture(scope='module')
def drawn():
    return {seed: rf.draw_rig(seed) for seed in SEEDS}


def _within(value, key, slack=1e-12, r=None):
    r = r or rf.RANGES[key]
    values = np.abs(np.atleast_1d(value)) if r.signed else np.atleast_1d(value)
    return bool(np.all(values >= r.lo - slack) and np.all(values <= r.hi + slack))


def _focal_length(data, distance):
    """The thin lens focused at the object distance s whose image distance is fx * pixel."""
    s = data['g1']['l'] + data['g1']['d'] + distance
    s_img = data['camera']['fx'] * data['camera']['pixel_size']
    return s * s_img / (s + s_img), s


def _triangulation_angle(data):
    """Angle between the optical axis and the G2 tilt axis point to the crossing, in the
    plane of V0's z and the laser's side (y below or above, x beside), from the loaded rig."""
    rig = load_rig_text(yaml.safe_dump(data))
    p_W = (rig.W_T_G @ rig.G_T_G2 @ np.array([0.0, data['g2']['d'], 0.0, 1.0]))[:3]
    cross = rf.working_point(rig)
    side = rf.LASER_SIDES[rf.build_of(data)['laser']]
    off = p_W[:2] - cross[:2]
    across = math.sin(side) * -off[0] + math.cos(side) * off[1]   # towards the laser's side
    return math.atan2(across, cross[2] - p_W[2])


def test_draws_are_deterministic_per_seed(drawn):
    assert rf.draw_rig(7) == drawn[7]
    assert rf.draw_rig(7, 0.4) == rf.draw_rig(7, 0.4)
    assert drawn[7] != drawn[8]
    assert rf.draw_rig(7, 0.4) != rf.draw_rig(7, 0.5)


def test_ranges_are_respected_and_used(drawn):
    mirrors = ('g1_pan', 'g1_tilt', 'g2_pan', 'g2_tilt')
    distances, lenses = [], []
    for seed, data in drawn.items():
        imp = data['imperfections']
        build = rf.build_of(data)
        head, sensor = rf.HEADS[build['head']], rf.SENSORS[build['sensor']]
        for m in mirrors:
            for key in ('zero_offset', 'surface_offset', 'axis_tilt'):
                assert _within(imp[m][key], key), (seed, m, key, imp[m][key])
            for key in ('gain_error', 'nonlinearity', 'jitter'):
                assert _within(imp[m][key], key, r=getattr(head, key)), (seed, m, key)
        k1, k2, p1, p2, k3 = imp['lens_distortion']
        assert _within(k1, 'k1') and _within(k2, 'k2') and _within([p1, p2], 'p1p2')
        assert k3 == 0.0
        for key in ('camera_mount_rotation', 'laser_fan_roll', 'laser_fan_offset'):
            assert _within(imp[key], key), (seed, key)
        assert _within(imp['image']['read_noise'], 'read_noise', r=sensor.read_noise)
        assert _within(data['g1']['l'], 'l') and _within(data['g1']['d'], 'd')
        assert _within(data['g2']['d'], 'd')
        cam = data['camera']
        assert abs(cam['cx'] - (cam['width'] - 1) / 2) <= 10.0
        assert abs(cam['cy'] - (cam['height'] - 1) / 2) <= 10.0
        assert _within(cam['fy'] / cam['fx'], 'fy_over_fx', 1e-9)
        z = rf.working_distance(data)
        assert _within(z, 'distance', 1e-6), (seed, z)
        f, s = _focal_length(data, z)
        assert 0.035 - 1e-9 <= f <= 0.075 + 1e-9, (seed, f)
        # the lens focuses there on its own helicoid (a 54 mm lens does not at s = 0.2 m)
        assert f / (s - f) <= rf.MAX_MAGNIFICATION_HELICOID + 1e-9, (seed, f, s)
        angle = _triangulation_angle(data)
        assert math.radians(15.0) - 1e-3 <= angle <= math.radians(35.0) + 1e-3, (seed, angle)
        assert rf.EXPOSURE_RANGE[0] <= cam['exposure'] <= rf.EXPOSURE_RANGE[1]
        distances.append(z)
        lenses.append(f)
    # the family spreads over its ranges (not one rig with noise)
    assert min(distances) < 0.25 and max(distances) > 0.85
    assert min(lenses) < 0.045 and max(lenses) > 0.065
    assert len({d['g1']['l'] for d in drawn.values()}) == len(drawn)


def test_drawn_rigs_load_and_pass_the_simulator_check(drawn):
    for seed, data in drawn.items():
        rig = load_rig_text(yaml.safe_dump(data), f'<seed {seed}>')
        assert rig.name == f'random-{seed}'
        assert rig.geometric_imperfection
    for seed in list(SEEDS)[:3]:
        assert rf.check_rig(drawn[seed]) == [], seed
        assert rf.check_rig(drawn[seed], rf.working_distance(drawn[seed])) == []
    # and the check can fail: the same rig asked for another distance
    z = rf.working_distance(drawn[0])
    assert any('working distance' in p for p in rf.check_rig(drawn[0], z + 0.01))


def _plane(z_W, albedo=0.5):
    return load_scene_text(
        'format_version: 1\nname: p\nobjects:\n  - type: plane\n    name: p\n'
        f'    pose: {{translation: [0.0, 0.0, {z_W!r}], rotation_vector: [0.0, 0.0, 0.0]}}\n'
        f'    albedo: {albedo}\n')


def _stripe_row(rig, z_W, seed=3):
    """Median brightest row of the 61 central columns (column of the 61 central rows for a
    stripe along the columns), the peak over the background (in 8-bit DN) and the frame's
    true laser plane in W, on a grey plane at W z = z_W, all voltages 0."""
    frame = Simulator(rig, _plane(z_W), seed=seed).render(np.zeros(4), frame_index=0)
    vertical = rig.stripe_layout().orientation == 'vertical'
    image = frame.image.T if vertical else frame.image
    c = int(round(rig.camera.cy if vertical else rig.camera.cx))
    block = image[:, c - 30:c + 31].astype(float)
    return (float(np.median(np.argmax(block, axis=0))),
            float(np.median(block.max(axis=0)) - np.median(block)) * 255.0
            / rig.image.white_level, frame.truth.laser_plane_W)


@pytest.mark.parametrize('seed,distance', [(11, 0.1), (12, 0.35), (13, 1.0)])
def test_stripe_crosses_the_image_centre_at_the_working_distance(seed, distance):
    data = rf.draw_rig(seed, distance)
    rig = load_rig_text(yaml.safe_dump(data))
    # the camera's central ray traced off the actual G1 mirrors meets the simulated sheet
    # at the working distance from the exit mirror
    _, _, plane = _stripe_row(rig, rig.l + rig.d + distance)
    o, d = rig.trace_camera_rays(np.zeros((1, 2)), *rig.mirror_angles(np.zeros(4))[:2])
    o_W, d_W = rig.W_T_G[:3, :3] @ o[0] + rig.W_T_G[:3, 3], rig.W_T_G[:3, :3] @ d[0]
    t = -(plane[:3] @ o_W + plane[3]) / (plane[:3] @ d_W)
    assert abs(t - distance) < 1e-3, (t, distance)
    z_W = float((o_W + t * d_W)[2])
    row, peak, _ = _stripe_row(rig, z_W)
    # across the stripe: the rows for a laser below or above, the columns beside
    centre = rig.camera.cx if rig.stripe_layout().orientation == 'vertical' else rig.camera.cy
    assert abs(row - centre) <= 3.0, (row, centre)
    assert 40.0 <= peak < 250.0
    # nearer and farther planes put the stripe on either side of the centre
    near, _, _ = _stripe_row(rig, z_W - 0.05 * distance)
    far, _, _ = _stripe_row(rig, z_W + 0.05 * distance)
    assert (near - centre) * (far - centre) < 0
    assert min(abs(near - rig.camera.cy), abs(far - rig.camera.cy)) > 5.0


def test_reset_for_distance_keeps_imperfections_and_moves_the_crossing():
    data = rf.draw_rig(21, 0.8)
    before = copy.deepcopy(data)
    near = rf.reset_for_distance(data, 0.2)
    assert data == before                                       # input untouched
    assert abs(rf.working_distance(near) - 0.2) < 1e-6
    assert abs(rf.working_distance(data) - 0.8) < 1e-6
    assert rf.check_rig(near, 0.2) == []
    imp0, imp1 = copy.deepcopy(data['imperfections']), copy.deepcopy(near['imperfections'])
    psf0, psf1 = imp0['image'].pop('psf_sigma'), imp1['image'].pop('psf_sigma')
    assert imp0 == imp1
    assert psf0 != psf1                                          # refocused: m changed
    for key in ('cx', 'cy', 'pixel_size', 'full_well'):
        assert near['camera'][key] == data['camera'][key]
    assert near['camera']['fx'] > data['camera']['fx']           # closer focus, longer s'
    assert near['g1'] == data['g1'] and near['world'] == data['world']
    assert math.isclose(_triangulation_angle(near), _triangulation_angle(data),
                        abs_tol=1e-3)
    # re-set for its own distance, a drawn rig comes back as it was drawn
    same = rf.reset_for_distance(data, 0.8)
    assert math.isclose(same['camera']['fx'], data['camera']['fx'], rel_tol=1e-9)
    assert np.allclose(same['g2']['pose_in_g1']['translation'],
                       data['g2']['pose_in_g1']['translation'], atol=1e-9)
    assert math.isclose(same['laser']['peak_rate'] * same['camera']['exposure'],
                        data['laser']['peak_rate'] * data['camera']['exposure'], rel_tol=1e-6)


@pytest.mark.parametrize('distance', [0.1, 0.65, 1.0])
def test_reference_rig_can_be_reset_for_the_papers_distances(distance):
    ref = read_yaml_file(RIG_DIR / 'reference.yaml')
    out = rf.reset_for_distance(ref, distance)
    assert rf.check_rig(out, distance) == []
    assert out['imperfections'] | {'image': None} == ref['imperfections'] | {'image': None}


@pytest.mark.parametrize('bad,words', [
    (650, 'millimetres'), (float('nan'), 'positive'), (-0.3, 'positive'),
    (0.05, '0.1 to 1'), ('far', 'number of metres')])
def test_bad_distances_are_refused(bad, words):
    with pytest.raises(ValueError, match=words):
        rf.reset_for_distance(read_yaml_file(RIG_DIR / 'reference.yaml'), bad)
    with pytest.raises(ValueError, match=words):
        rf.draw_rig(1, bad)


def _set(data, dotted, value):
    keys = dotted.split('.')
    node = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value


@pytest.mark.parametrize('key,value,words', [
    ('camera.fx', -7801.38, 'implausible'),             # a negative focal length
    ('camera.fy', -5000.0, 'implausible'),
    ('g1.l', float('nan'), 'a number'),                  # a NaN
    ('laser.peak_rate', float('nan'), 'a number'),
    ('camera.focal_length', 0.054, 'no such key'),       # an unknown key
    ('imperfections.g1_pan.offset', 0.0001, 'no such key'),
    ('g1.l', 83.45, 'metres expected'),                  # mm where m belong
    ('g2.d', 22.14, 'metres'),
    ('laser.reference_distance', 650.0, 'implausible'),
    ('imperfections.g2_tilt.surface_offset', 0.15, 'metres expected'),
])
def test_bad_rig_descriptions_are_refused_with_the_key_named(key, value, words, tmp_path,
                                                           drawn):
    data = copy.deepcopy(drawn[2])
    _set(data, key, value)
    with pytest.raises(ConfigError) as err:
        load_rig_text(yaml.safe_dump(data), 'bad.yaml')
    assert f"key '{key}'" in str(err.value) and words in str(err.value)
    problems = rf.check_rig(data)
    assert len(problems) == 1 and f"key '{key}'" in problems[0]
    with pytest.raises(ConfigError, match=key.replace('.', r'\.')):
        rf.reset_for_distance(data, 0.5)
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=key.replace('.', r'\.')):
        load_rig(path)


# ------------------------------------------------------------------------------ CLI
def test_cli_writes_a_rig_the_reader_loads(tmp_path, capsys):
    from galvoscan import rig_cli

    out = tmp_path / 'rig.yaml'
    assert rig_cli.main(['random', '--seed', '4', '--distance', '0.35', '--out',
                         str(out)]) == 0
    text = out.read_text()
    assert text.startswith('# Random rig of the galvoscan family: galvoscan rig random '
                           '--seed 4')
    assert 'rig_family.RANGES' in text
    rig = load_rig(out)
    assert rig.name == 'random-4'
    assert yaml.safe_load(text) == rf.draw_rig(4, 0.35)
    assert abs(rf.working_distance(rig) - 0.35) < 1e-6
    assert '350.0 mm' in capsys.readouterr().out
    # re-set and check through the same command
    out2 = tmp_path / 'rig_100.yaml'
    assert rig_cli.main(['reset', '--rig', str(out), '--distance', '0.1', '--out',
                         str(out2)]) == 0
    assert abs(rf.working_distance(load_rig(out2)) - 0.1) < 1e-6
    assert rig_cli.main(['check', str(out2), '--distance', '0.1']) == 0
    assert rig_cli.main(['check', str(out2), '--distance', '0.2']) == 1


@pytest.mark.parametrize('args,words', [
    (['--distance', '650'], 'looks like millimetres'),
    (['--distance', 'nan'], 'positive number of metres'),
    (['--distance', '-0.4'], 'positive number of metres'),
    (['--distance', '1.5'], '0.1 to 1'),
    (['--seed', '-1'], 'non-negative'),
    (['--seed', 'x'], 'invalid int'),
    (['--out', '/nonexistent-dir/rig.yaml'], 'does not exist'),
])
def test_cli_refuses_bad_arguments(args, words, tmp_path, capsys):
    from galvoscan import rig_cli

    out = tmp_path / 'rig.yaml'
    base = {'--seed': '1', '--out': str(out)}
    for flag, value in zip(args[::2], args[1::2], strict=True):
        base[flag] = value
    argv = ['random'] + [x for kv in base.items() for x in kv]
    assert rig_cli.main(argv) == 2
    assert words in capsys.readouterr().err
    assert not out.exists()


def test_cli_refuses_a_bad_rig_file(tmp_path, capsys):
    from galvoscan import rig_cli

    bad = tmp_path / 'bad.yaml'
    data = rf.draw_rig(3)
    data['camera']['fx'] = -100.0
    bad.write_text(yaml.safe_dump(data))
    assert rig_cli.main(['check', str(bad)]) == 1
    assert "key 'camera.fx'" in capsys.readouterr().err
    assert rig_cli.main(['reset', '--rig', str(bad), '--distance', '0.3', '--out',
                         str(tmp_path / 'o.yaml')]) == 2
    assert "key 'camera.fx'" in capsys.readouterr().err
    assert not (tmp_path / 'o.yaml').exists()


def test_galvoscan_rig_random_command(tmp_path):
    exe = Path(sys.executable).parent / 'galvoscan'
    out = tmp_path / 'cmd.yaml'
    res = subprocess.run([str(exe), 'rig', 'random', '--seed', '9', '--out', str(out)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert load_rig(out).name == 'random-9'
    assert yaml.safe_load(out.read_text()) == rf.draw_rig(9)


# ------------------------------------------------------------------------------ builds
def test_the_family_spans_sensors_bit_depths_and_heads(drawn):
    builds = [rf.build_of(d) for d in drawn.values()]
    assert {b['sensor'] for b in builds} == set(rf.SENSORS)
    assert {b['head'] for b in builds} == set(rf.HEADS)
    assert {b['bit_depth'] for b in builds} >= {8, 10, 12}
    assert {b['laser'] for b in builds} == set(rf.LASER_SIDES)
    for seed, data in drawn.items():
        b = rf.build_of(data)
        sensor, head = rf.SENSORS[b['sensor']], rf.HEADS[b['head']]
        cam = data['camera']
        assert b['bit_depth'] in sensor.bit_depths
        assert cam['full_well'] == sensor.full_well
        assert cam['black_level'] == sensor.black_level_8bit * 2 ** (b['bit_depth'] - 8)
        for sec in ('g1', 'g2'):
            for axis in ('pan', 'tilt'):
                assert math.isclose(data[sec][axis]['gain'] * data['dac']['full_scale'],
                                    head.max_angle), (seed, sec, axis)
        assert f"{b['sensor']} sensor at {b['bit_depth']} bits" in data['description']
        # the laser's side is where the chain finds the stripe
        layout = load_rig_text(yaml.safe_dump(data)).stripe_layout()
        assert layout.orientation == ('horizontal' if b['laser'] in ('below', 'above')
                                      else 'vertical'), (seed, b, layout)
    assert rf.build_of(read_yaml_file(RIG_DIR / 'reference.yaml')) == rf.REFERENCE_BUILD


def test_a_build_can_be_asked_for_and_bad_builds_are_refused():
    data = rf.draw_rig(5, 0.5, build={'sensor': 'IMX273', 'bit_depth': 12, 'head': 'GVS011',
                                      'laser': 'right'})
    assert rf.build_of(data) == {'sensor': 'IMX273', 'bit_depth': 12, 'head': 'GVS011',
                                 'laser': 'right'}
    assert rf.check_rig(data, 0.5) == []
    # the build does not change the seed's geometry or its mirrors' placement errors
    other = rf.draw_rig(5, 0.5, build={'sensor': 'IMX287', 'bit_depth': 8, 'head': 'TSH8310'})
    assert data['g1'].keys() == other['g1'].keys() and data['g1']['l'] == other['g1']['l']
    assert rf.build_of(rf.draw_rig(5, 0.5, build={'bit_depth': 12}))['sensor'] in (
        'IMX287', 'IMX273')
    for bad, words in (({'sensor': 'IMX999'}, 'not one of'), ({'head': 'huge'}, 'not one of'),
                       ({'sensor': 'PYTHON300', 'bit_depth': 12}, 'bit_depth 12'),
                       ({'bit_depth': 9}, 'bit_depth 9'), ({'lens': 1}, 'unknown key'),
                       ({'laser': 'behind'}, 'laser .behind. is not one of'),
                       ('IMX287', 'expected a dict')):
        with pytest.raises(ValueError, match=words):
            rf.draw_rig(5, 0.5, build=bad)


def test_a_12_bit_rig_sees_the_stripe_as_an_8_bit_one_does():
    """Same seed and geometry at 8 and 12 bits: the stripe lands on the same row with the
    same peak (in 8-bit DN), the 12-bit image in uint16 codes below 4096."""
    rows = {}
    for depth in (8, 12):
        data = rf.draw_rig(6, 0.4, build={'sensor': 'IMX287', 'bit_depth': depth})
        rig = load_rig_text(yaml.safe_dump(data))
        z_W = float(rf.working_point(rig)[2])
        rows[depth] = _stripe_row(rig, z_W)[:2]
        img = Simulator(rig, _plane(z_W), seed=1).render(np.zeros(4), frame_index=0).image
        assert img.dtype == (np.uint8 if depth == 8 else np.uint16) and img.max() < 2 ** depth
    assert abs(rows[8][0] - rows[12][0]) <= 1.0
    assert abs(rows[8][1] - rows[12][1]) < 0.05 * rows[8][1] + 1.0


def test_a_laser_beside_the_camera_is_taken_and_an_oblique_sheet_refused_up_front():
    ref = read_yaml_file(RIG_DIR / 'reference.yaml')
    z = rf.working_distance(ref)
    assert math.degrees(rf.stripe_tilt(load_rig_text(yaml.safe_dump(ref)))) < 0.5
    # the laser moved round the camera: along the rows (a few degrees of roll, above) or
    # along the columns (beside it), each within MAX_STRIPE_TILT
    for degrees, orientation in ((3.0, 'horizontal'), (180.0, 'horizontal'),
                                 (90.0, 'vertical'), (-90.0, 'vertical'),
                                 (75.0, 'vertical')):
        turned = rf.g2_turned(ref, degrees)
        rig = load_rig_text(yaml.safe_dump(turned))
        assert rig.stripe_layout().orientation == orientation, degrees
        assert rf.check_rig(turned, z) == [], degrees
    limit = math.degrees(rf.MAX_STRIPE_TILT)
    for degrees in (30.0, -45.0, 135.0):
        turned = rf.g2_turned(ref, degrees)
        tilt = math.degrees(rf.stripe_tilt(load_rig_text(yaml.safe_dump(turned))))
        off = abs(degrees) % 90.0
        assert abs(tilt - min(off, 90.0 - off)) < 1.0, (degrees, tilt)
        assert tilt > limit
        problems = rf.check_rig(turned, z)
        assert problems[0].startswith(f'the stripe runs {tilt:.1f} deg off the nearest of '
                                      'the image rows and columns')
        assert f'within {limit:.0f} deg' in problems[0]
        # refused before the simulator renders a stripe (not "covers 0 of 720 columns")
        assert not any('covers' in p for p in problems), problems
