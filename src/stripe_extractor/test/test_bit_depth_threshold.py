"""min_strength follows the image's bit depth: stated at 8 bits, the same share of full scale
on a 12-bit image; the white level read from the image or stated; saturation at 12 bits."""

import numpy as np
import pytest

from stripe_extractor.config import ExtractorConfig, white_level
from stripe_extractor.exposure import frame_levels
from stripe_extractor.extractor import METHODS, extract, warm_up
from stripe_extractor.synthetic import StripeSpec, render

SHAPE = (200, 240)
#: 12-bit codes per 8-bit code: the same light on a Mono12 camera
K12 = 4095 / 255


@pytest.fixture(scope='module', autouse=True)
def _compiled():
    warm_up()


def _image(amplitude_8bit: float, depth: int, seed: int) -> np.ndarray:
    """A stripe of ``amplitude_8bit`` (in 8-bit DN) at ``depth`` bits, noise scaled alike."""
    k = (2 ** depth - 1) / 255
    spec = StripeSpec(v0=100.3, slope=0.05, curvature=0.0, sigma_px=2.0,
                      amplitude=amplitude_8bit * k)
    return render(SHAPE, spec, background=12.0 * k, noise_dn=1.0 * k,
                  rng=np.random.default_rng(seed), dtype=np.uint8 if depth == 8 else np.uint16)


@pytest.mark.parametrize('method', METHODS)
def test_a_12_bit_image_is_held_to_the_8_bit_threshold(method):
    """A stripe 14 DN high at 8 bits is below min_strength 20 and gives no centre; the same
    light on a Mono12 camera (225 DN of 4095) gives none either (an absolute 20 DN would
    have accepted it), and a stripe 60 DN high is found at both depths, at the same rows.
    The dim 12-bit frame needs its depth stated (its brightest pixel, 463, would read as a
    10-bit camera's); the bright one's is read from it."""
    cfg = ExtractorConfig(method=method, min_strength=20.0)
    cfg12 = ExtractorConfig(method=method, min_strength=20.0, bit_depth=12)
    weak8, weak12 = _image(14.0, 8, 1), _image(14.0, 12, 1)
    assert len(extract(weak8, cfg)) == 0
    weak = extract(weak12, cfg12)
    assert weak.white_level == 4095 and len(weak) == 0
    assert len(extract(weak12, ExtractorConfig(method=method, min_strength=20.0 * 255 / 4095,
                                               bit_depth=12))) >= 0.99 * SHAPE[1]
    strong8, strong12 = extract(_image(60.0, 8, 2), cfg), extract(_image(60.0, 12, 2), cfg)
    assert strong12.white_level == 4095
    assert len(strong8) >= 0.99 * SHAPE[1] and len(strong12) >= 0.99 * SHAPE[1]
    np.testing.assert_allclose(np.median(strong12.v), np.median(strong8.v), atol=0.05)
    np.testing.assert_allclose(np.median(strong12.strength),
                               K12 * np.median(strong8.strength), rtol=0.1)
    # the threshold applied, in the image's DN
    assert cfg.threshold_dn(strong12.white_level) == pytest.approx(20.0 * K12)
    assert cfg.threshold_dn(strong8.white_level) == 20.0


def test_the_white_level_is_read_from_the_image_or_stated():
    assert white_level(np.zeros((4, 4), np.uint8)) == 255
    assert white_level(np.full((4, 4), 700, np.uint16)) == 1023
    assert white_level(np.full((4, 4), 4000, np.uint16)) == 4095
    assert white_level(np.full((4, 4), 4096, np.uint16)) == 65535
    dark12 = np.full((4, 4), 300, np.uint16)
    assert white_level(dark12, 12) == 4095
    # stated: a dark 12-bit frame keeps the 12-bit threshold
    img = _image(14.0, 12, 3)
    assert len(extract(img // 8, ExtractorConfig(min_strength=2.0, bit_depth=12))) == 0
    with pytest.raises(ValueError, match='bit_depth'):
        ExtractorConfig(bit_depth=11)
    with pytest.raises(ValueError, match='min_strength'):
        ExtractorConfig(min_strength=20.0 * 256)


def test_a_clipped_12_bit_frame_is_saturated():
    img = _image(40.0, 12, 4)
    img[100:103, :] = 4095
    sat, peak = frame_levels(img)
    assert sat == 1.0 and peak == 1.0
    sat, _ = frame_levels(_image(40.0, 12, 4))
    assert sat == 0.0
    # 8-bit behaviour unchanged
    img8 = _image(40.0, 8, 4)
    img8[100, :120] = 255
    assert frame_levels(img8) == (0.5, pytest.approx(float(np.percentile(img8.max(0), 50)) / 255))
