"""The bag type store: galvoscan_msgs found on disk, hashes equal to rosidl's own."""

import json
import sys
from pathlib import Path

import pytest

from galvoscan_bag import typestore as typestore_module
from galvoscan_bag.typestore import find_msg_dir, make_typestore, msg_dir_candidates

REPO_MSG_DIR = Path(__file__).resolve().parents[3] / 'msgs' / 'msg'
INSTALLED_MSG_DIR = Path(sys.prefix) / 'share' / 'galvoscan_msgs' / 'msg'
OUR_TYPES = ['CalibrationInstruction', 'CalibrationProgress', 'CalibrationStage', 'GalvoState',
             'StripeCenters']


def test_repo_has_the_messages_this_test_expects():
    assert sorted(p.stem for p in REPO_MSG_DIR.glob('*.msg')) == OUR_TYPES


def test_installed_share_dir_is_found_first(monkeypatch):
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    if not INSTALLED_MSG_DIR.is_dir():
        pytest.skip('galvoscan_msgs is not installed into this interpreter prefix')
    assert find_msg_dir() == INSTALLED_MSG_DIR
    # The cmake install copies the repository's files unchanged.
    for name in OUR_TYPES:
        installed = (INSTALLED_MSG_DIR / f'{name}.msg').read_text()
        assert installed == (REPO_MSG_DIR / f'{name}.msg').read_text()


def test_ament_prefix_path_wins(monkeypatch, tmp_path):
    share = tmp_path / 'share' / 'galvoscan_msgs' / 'msg'
    share.mkdir(parents=True)
    (share / 'GalvoState.msg').write_text((REPO_MSG_DIR / 'GalvoState.msg').read_text())
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    assert find_msg_dir() == share
    store = make_typestore()
    assert 'galvoscan_msgs/msg/GalvoState' in store.fielddefs
    assert 'galvoscan_msgs/msg/StripeCenters' not in store.fielddefs


def test_falls_back_to_the_repository(monkeypatch, tmp_path):
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    monkeypatch.setattr(typestore_module.sys, 'prefix', str(tmp_path))
    assert find_msg_dir() == REPO_MSG_DIR


def test_nothing_found_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setattr(typestore_module, 'msg_dir_candidates', lambda: [tmp_path / 'none'])
    with pytest.raises(FileNotFoundError, match='galvoscan_msgs'):
        find_msg_dir()
    with pytest.raises(ValueError, match='msg_dir'):
        make_typestore(tmp_path)


def test_candidates_end_with_the_repository():
    assert msg_dir_candidates()[-1] == REPO_MSG_DIR


@pytest.mark.parametrize('name', OUR_TYPES)
def test_type_hash_equals_rosidl_generated_hash(name):
    # rosidl writes the RIHS01 hash it computed into <share>/msg/<Name>.json at build time.
    if not INSTALLED_MSG_DIR.is_dir():
        pytest.skip('no rosidl build output in this prefix')
    described = json.loads((INSTALLED_MSG_DIR / f'{name}.json').read_text())
    expected = {h['type_name']: h['hash_string'] for h in described['type_hashes']}
    store = make_typestore(REPO_MSG_DIR)
    msgtype = f'galvoscan_msgs/msg/{name}'
    assert store.hash_rihs01(msgtype) == expected[msgtype]


def test_string_constants_are_unquoted():
    store = make_typestore(REPO_MSG_DIR)
    stage = store.types['galvoscan_msgs/msg/CalibrationStage']
    assert stage.INTRINSICS == 'intrinsics'
    assert stage.JOINT_CORRECTION == 'joint_correction'
    state = store.types['galvoscan_msgs/msg/GalvoState']
    assert (state.STATUS_SETTLED, state.STATUS_MOVING, state.STATUS_FAULT) == (0, 1, 2)
