"""``galvoscan evaluate`` refuses a bad rig or output folder by name, before starting
anything, and leaves no folder behind."""

import pytest

from galvoscan.evaluate import main


def refused(argv, capsys, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith('galvoscan evaluate: ') and 'Traceback' not in err
    for needle in needles:
        assert needle in err
    return err


def test_unknown_rig_is_named_and_no_folder_is_made(tmp_path, capsys):
    refused(['--rig', 'nosuchrig', '--out', str(tmp_path / 'o')], capsys, 'nosuchrig.yaml',
            'readable file')
    assert not (tmp_path / 'o').exists()


@pytest.mark.parametrize('content, why', [
    (bytes(range(256)) * 4, 'binary or UTF-16'),
    ('a: 1\n'.encode('utf-16'), 'binary or UTF-16'),
    (b'name: x\x00\n', 'NUL'),
    (b'- just\n- a list\n', 'mapping'),
])
def test_a_rig_file_that_is_not_a_rig_is_named(tmp_path, capsys, content, why):
    rig = tmp_path / 'rig.yaml'
    rig.write_bytes(content)
    refused(['--rig', str(rig), '--out', str(tmp_path / 'o')], capsys, str(rig), why)
    assert not (tmp_path / 'o').exists()


def test_an_output_folder_that_cannot_be_made_is_named(tmp_path, capsys):
    (tmp_path / 'file').write_text('')
    refused(['--quick', '--out', str(tmp_path / 'file' / 'o')], capsys, '--out',
            str(tmp_path / 'file' / 'o'))
    refused(['--quick', '--out', '/proc/galvoscan/o'], capsys, '/proc/galvoscan/o')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['file']
