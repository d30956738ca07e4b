"""Calibration file: validation names the problem; writes are atomic even under SIGKILL."""

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from reconstructor import calibration_file as cf
from reconstructor.model import nominal_example_rig


def _doc():
    cal = cf.Calibration(model=nominal_example_rig(), source='simulator_truth',
                         stages={'intrinsics': {'residuals': {'reprojection_rms_px': 0.05}}})
    return cal.to_dict()


def _write(tmp_path, data, name='cal.yaml'):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_round_trip_keeps_every_parameter(tmp_path):
    model = nominal_example_rig(dist=(-0.1, 0.2, 1e-4, -2e-4, 0.0))
    cal = cf.Calibration(model=model, stages={'laser_axis': {'residuals': {'axis_rms_m': 1e-5}}})
    digest = cf.save(cal, tmp_path / 'c.yaml')
    loaded = cf.load(tmp_path / 'c.yaml')
    assert loaded.content_hash == digest == cf.file_sha256(tmp_path / 'c.yaml')
    assert loaded.model.to_dict() == model.to_dict()
    assert loaded.stages == cal.stages
    assert not list(tmp_path.glob('.*.tmp'))


@pytest.mark.parametrize('mutate, message', [
    (lambda d: d['model']['intrinsics'].pop('fx'), r'missing key intrinsics\.fx'),
    (lambda d: d.pop('model'), r"missing key 'model'"),
    (lambda d: d['model'].__setitem__('l', math.nan), r'\bl must be finite'),
    (lambda d: d['model']['laser_axis_dir'].__setitem__(1, float('nan')), r'laser_axis_dir\[1\]'),
    (lambda d: d.__setitem__('format_version', 99), r'format_version is 99'),
    (lambda d: d['model'].__setitem__('l', 83.45), r'model\.l = 83\.45 .* millimetres'),
    (lambda d: d['model'].__setitem__('d', 22.14), r'model\.d = 22\.14 .* millimetres'),
    (lambda d: d['model']['g1_pan'].__setitem__('theta0', 45.0), r'g1_pan\.theta0 .* degrees'),
    (lambda d: d['model'].__setitem__('laser_axis_point', [0, -195.9, 258.0]),
     r'laser_axis_point .* millimetres'),
    (lambda d: d['model']['laser_plane_v0'].__setitem__(3, -272.4),
     r'laser_plane_v0\[3\] = -272\.4 .* millimetres'),
    (lambda d: d['model']['intrinsics'].__setitem__('dist', [0, 0, 0]), r'intrinsics\.dist'),
    (lambda d: d.__setitem__('source', 'guess'), r'source must be one of'),
])
def test_bad_files_are_refused_naming_the_problem(tmp_path, mutate, message):
    data = _doc()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ValueError, match=message) as info:
        cf.load(path)
    assert str(path) in str(info.value)


def test_unreadable_and_non_yaml_files(tmp_path):
    with pytest.raises(ValueError, match='cannot read'):
        cf.load(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('model: [unclosed\n')
    with pytest.raises(ValueError, match='not valid YAML'):
        cf.load(bad)
    for name, data, message in (('bin.yaml', bytes(range(256)), 'not UTF-8'),
                                ('utf16.yaml', 'format_version: 1\n'.encode('utf-16'),
                                 'not UTF-8'),
                                ('nul.yaml', b'format_version: 1\x00\n', 'NUL bytes')):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(ValueError, match=message) as info:
            cf.load(path)
        assert str(path) in str(info.value)


def test_save_refuses_what_load_would_refuse_and_keeps_the_old_file(tmp_path):
    path = tmp_path / 'c.yaml'
    cf.save(cf.Calibration(model=nominal_example_rig()), path)
    before = path.read_bytes()
    with pytest.raises(ValueError, match='source must be one of'):
        cf.save(cf.Calibration(model=nominal_example_rig(), source='nonsense'), path)
    assert path.read_bytes() == before


WRITER = r'''
import sys
from reconstructor import calibration_file as cf
from reconstructor.model import nominal_example_rig
path = sys.argv[1]
big = {'views': [{'i': i, 'rms': 0.1 * i, 'pose': [float(i)] * 16} for i in range(20000)]}
i = 0
print('ready', flush=True)
while True:
    i += 1
    cf.save(cf.Calibration(model=nominal_example_rig(standoff=0.5 + (i % 50) * 0.01),
                           stages={'dynamic_camera': {'generation': i, 'residuals': big}}), path)
'''


def test_killing_the_writer_never_leaves_half_a_file(tmp_path):
    path = tmp_path / 'cal.yaml'
    cf.save(cf.Calibration(model=nominal_example_rig()), path)
    rng = np.random.default_rng(0)
    kills = 0
    for _ in range(6):
        proc = subprocess.Popen([sys.executable, '-c', WRITER, str(path)],
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == 'ready'
        time.sleep(float(rng.uniform(0.3, 1.2)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        kills += 1
        cal = cf.load(path)  # must parse and validate every time
        assert cal.model.l == pytest.approx(0.08345)
    assert kills == 6
