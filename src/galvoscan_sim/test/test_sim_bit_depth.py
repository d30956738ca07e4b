"""The simulated camera at 8, 10, 12 and 16 bits: the same electrons quantised to the
chosen format's codes (uint8 at 8 bits, uint16 above), bad formats refused."""

import copy

import numpy as np
import pytest
import yaml

from galvoscan_sim import ConfigError, Simulator, load_rig_text, load_scene_text
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig import BIT_DEPTHS, RIG_DIR

WALL = """
format_version: 1
name: wall_test
objects:
  - type: plane
    name: wall
    pose: {translation: [0.0, 0.0, 0.65]}
    albedo: 0.6
"""


def _rig(bit_depth, black_level=None, **image):
    data = copy.deepcopy(read_yaml_file(RIG_DIR / 'reference.yaml'))
    data['camera']['bit_depth'] = bit_depth
    data['camera']['black_level'] = (2.0 * 2 ** (bit_depth - 8) if black_level is None
                                     else black_level)
    data['imperfections']['image'].update(image)
    return load_rig_text(yaml.safe_dump(data), f'<{bit_depth} bit>')


@pytest.fixture(scope='module')
def frames():
    scene = load_scene_text(WALL)
    out = {}
    for depth in BIT_DEPTHS:
        rig = _rig(depth)
        sim = Simulator(rig, scene, seed=4)
        out[depth] = (rig, sim.render(np.zeros(4), frame_index=0),
                      sim.calibration_frame(np.zeros(4)))
    return out


def test_every_depth_has_its_dtype_and_code_range(frames):
    for depth, (rig, laser, board) in frames.items():
        assert rig.image.white_level == 2 ** depth - 1
        for frame in (laser, board):
            assert frame.image.dtype == (np.uint8 if depth == 8 else np.uint16), depth
            assert frame.image.max() <= 2 ** depth - 1
        # the dark background sits near the black level, not clipped at 0
        assert np.median(laser.image) >= rig.image.black_level - 1


def test_the_same_electrons_at_every_depth(frames):
    """Stripe peak and board brightness in electrons agree across formats (same seed,
    same scene): only the quantisation step differs."""
    def electrons(rig, img):
        return (img.astype(np.float64) - rig.image.black_level) * rig.image.electrons_per_dn

    peaks, boards = {}, {}
    for depth, (rig, laser, board) in frames.items():
        e = electrons(rig, laser.image)
        c = int(round(rig.camera.cx))
        peaks[depth] = float(np.median(e[:, c - 40:c + 41].max(axis=0)))
        boards[depth] = float(np.median(electrons(rig, board.image)))
        # the stripe rows agree
        assert laser.truth.stripe.v.size > 600
    ref_peak, ref_board = peaks[16], boards[16]
    for depth in BIT_DEPTHS:
        step = frames[depth][0].image.electrons_per_dn
        assert abs(peaks[depth] - ref_peak) < 0.03 * ref_peak + step, (depth, peaks)
        assert abs(boards[depth] - ref_board) < 0.03 * ref_board + step, (depth, boards)
    # finer formats resolve the read noise: 16 bits has ~1/256 of the 8-bit step
    assert frames[8][0].image.electrons_per_dn > 250 * frames[16][0].image.electrons_per_dn


def test_deeper_formats_quantise_finer_without_noise():
    """Noise off: the 12-bit image scaled to 8 bits is the 8-bit one to within the two
    roundings (half a code of each)."""
    scene = load_scene_text(WALL)
    imgs = {}
    for depth in (8, 12):
        rig = _rig(depth, black_level=0.0, shot_noise=False, read_noise=0.0,
                   speckle_contrast=0.0)
        imgs[depth] = Simulator(rig, scene, seed=0).render(np.zeros(4), frame_index=0).image
    wide = imgs[12].astype(np.float64) * (255.0 / 4095.0)
    assert np.max(np.abs(wide - imgs[8])) <= 0.5 + 0.5 * 255.0 / 4095.0 + 1e-6
    assert len(np.unique(imgs[12])) > 4 * len(np.unique(imgs[8]))


@pytest.mark.parametrize('depth,black,words', [
    (9, 2.0, 'one of 8, 10, 12, 16'), (14, 2.0, 'one of 8, 10, 12, 16'),
    (24, 2.0, 'an integer in [8, 16]'), (12.0, 2.0, 'an integer'),
    (8, 65.0, 'a number in [0, 64] DN'), (12, 1025.0, 'a number in [0, 1024] DN')])
def test_bad_formats_are_refused_with_the_key_named(depth, black, words):
    with pytest.raises(ConfigError) as err:
        _rig(depth, black_level=black)
    key = 'camera.bit_depth' if black in (2.0,) else 'camera.black_level'
    assert f"key '{key}'" in str(err.value) and words in str(err.value), str(err.value)
