"""Robustness of the stripe extractor: empty frames, clipping, speckle, secondary reflections,
occlusion, widths 1..6 px, 8/16-bit, orientation and input validation."""

import numpy as np
import pytest

from stripe_extractor.extractor import (
    FWHM_PER_SIGMA,
    METHODS,
    ExtractorConfig,
    StripeResult,
    extract,
    warm_up,
)
from stripe_extractor.synthetic import StripeSpec, render, score, stripe_profile

SHAPE = (400, 480)


@pytest.fixture(scope='module', autouse=True)
def _compiled():
    warm_up()


def _spec(**kw):
    base = dict(v0=200.3, slope=0.07, curvature=2e-4, sigma_px=2.0, amplitude=180.0)
    base.update(kw)
    return StripeSpec(**base)


@pytest.mark.parametrize('method', METHODS)
def test_no_stripe_gives_empty_result(method):
    rng = np.random.default_rng(0)
    cfg = ExtractorConfig(method=method)
    for img in (np.full(SHAPE, 40, np.uint8), render(SHAPE, _spec(amplitude=0.0),
                                                     noise_dn=4.0, rng=rng),
                np.zeros(SHAPE, np.uint16)):
        res = extract(img, cfg)
        assert isinstance(res, StripeResult)
        assert len(res) == 0 and res.rejected_secondary == 0
        for arr in (res.u, res.v, res.width, res.strength):
            assert arr.shape == (0,) and arr.dtype == np.float32


def test_result_carries_parameters():
    cfg = ExtractorConfig(line_width_px=3.0, min_strength=15.0, roi_half_height=9,
                          adapt_line_width=False)
    res = extract(render(SHAPE, _spec(), rng=np.random.default_rng(1)), cfg)
    assert res.config is cfg
    assert res.sigma == pytest.approx(3.0 / FWHM_PER_SIGMA if 3.0 / FWHM_PER_SIGMA > 1 else 1)
    assert res.image_shape == SHAPE


@pytest.mark.parametrize(('amplitude', 'sigma_px', 'width_px'),
                         [(700.0, 2.0, 4.7), (1500.0, 2.5, 6.0)])
def test_saturated_stripe(amplitude, sigma_px, width_px):
    """Clipped at 255 over several rows: still centred, strength near the clip level."""
    spec = _spec(amplitude=amplitude, sigma_px=sigma_px)
    img = render(SHAPE, spec, noise_dn=4.0, rng=np.random.default_rng(2))
    assert np.count_nonzero(img == 255) > 3 * SHAPE[1]
    # the clipped stripe is wider than its Gaussian: centred at the stated width and at
    # the width it is measured at
    for adapt in (False, True):
        res = extract(img, ExtractorConfig(line_width_px=width_px, adapt_line_width=adapt))
        rms, cov, err = score(res.u, res.v, spec, SHAPE[1])
        assert cov >= 0.995
        assert rms <= 0.04 and np.abs(err).max() <= 0.15
        if not adapt:  # the filter as narrow as the top: its peak is the clip level
            assert np.median(res.strength) > 0.8 * (255 - 12)


def test_laser_speckle_on_the_stripe():
    """Multiplicative speckle (contrast 0.3, 1 px grain) distorts each column's profile: the
    centres stay on the stripe, within the speckle-limited error, and no false secondaries."""
    spec = _spec()
    img = render(SHAPE, spec, noise_dn=4.0, rng=np.random.default_rng(3),
                 speckle_contrast=0.3, speckle_grain_px=1.0)
    res = extract(img, ExtractorConfig())
    rms, cov, err = score(res.u, res.v, spec, SHAPE[1])
    assert cov >= 0.99
    assert rms <= 0.3 and np.abs(err).max() <= 1.5
    assert res.rejected_secondary == 0


def test_isolated_bright_specks():
    """0.3 % of pixels set to 255 (hot pixels, glints) do not pull the centres away."""
    rng = np.random.default_rng(4)
    spec = _spec()
    img = render(SHAPE, spec, noise_dn=4.0, rng=rng)
    img.flat[rng.choice(img.size, img.size * 3 // 1000, replace=False)] = 255
    res = extract(img, ExtractorConfig())
    rms, cov, err = score(res.u, res.v, spec, SHAPE[1])
    assert cov >= 0.995
    assert rms <= 0.05 and np.abs(err).max() <= 0.8


@pytest.mark.parametrize('method', METHODS)
@pytest.mark.parametrize('distance', [25.0, 120.0])
def test_weaker_secondary_reflection_is_rejected_and_counted(method, distance):
    """A second, weaker stripe over the middle half of the columns: the strong one is kept,
    and each column with the secondary is counted once."""
    spec = _spec()
    cols = np.zeros(SHAPE[1], bool)
    cols[120:360] = True
    ghost = StripeSpec(v0=spec.v0 + distance, slope=spec.slope, curvature=spec.curvature,
                       sigma_px=2.5, amplitude=90.0)
    img = render(SHAPE, spec, noise_dn=4.0, rng=np.random.default_rng(5),
                 extra=stripe_profile(SHAPE, ghost, cols))
    res = extract(img, ExtractorConfig(method=method))
    rms, cov, err = score(res.u, res.v, spec, SHAPE[1])
    assert cov >= 0.995
    assert np.abs(err).max() <= (0.2 if method == 'steger' else 0.5)
    assert abs(res.rejected_secondary - 240) <= 4


def test_secondary_below_min_strength_is_not_counted():
    spec = _spec()
    ghost = StripeSpec(v0=spec.v0 + 100, slope=0.0, curvature=0.0, sigma_px=2.0,
                       amplitude=15.0)
    img = render(SHAPE, spec, noise_dn=2.0, rng=np.random.default_rng(6),
                 extra=stripe_profile(SHAPE, ghost))
    res = extract(img, ExtractorConfig(min_strength=20.0))
    assert len(res) == SHAPE[1]
    assert res.rejected_secondary == 0


def test_stripe_broken_by_occlusion_with_a_depth_step():
    """A gap of 80 columns, after which the stripe continues 15 rows lower (a step in depth):
    nothing inside the gap, every reported centre on its own stripe part."""
    left = _spec(v0=200.3, slope=0.07, curvature=0.0)
    right = _spec(v0=215.8, slope=0.07, curvature=0.0)
    W = SHAPE[1]
    u = np.arange(W)
    vis_l = u < 200
    vis_r = u >= 280
    img = render(SHAPE, left, noise_dn=4.0, rng=np.random.default_rng(7), columns=vis_l,
                 extra=stripe_profile(SHAPE, right, vis_r))
    res = extract(img, ExtractorConfig())
    col = np.rint(res.u).astype(int)
    assert not np.any((col >= 200) & (col < 280))
    on_l = col < 200
    _, cov_l, err_l = score(res.u[on_l], res.v[on_l], left, W, vis_l)
    _, cov_r, err_r = score(res.u[~on_l], res.v[~on_l], right, W, vis_r)
    assert cov_l >= 0.99 and cov_r >= 0.99
    err = np.r_[err_l, err_r]
    assert np.sqrt(np.mean(err**2)) <= 0.025
    assert np.abs(err).max() <= 0.15


@pytest.mark.parametrize('width', [1, 2, 3, 4, 5, 6])
def test_stripe_widths_1_to_6_px(width):
    """FWHM 1..6 px with the matching line_width_px: centres and widths right."""
    s = width / FWHM_PER_SIGMA
    spec = _spec(sigma_px=s)
    img = render(SHAPE, spec, noise_dn=2.0, rng=np.random.default_rng(10 + width))
    res = extract(img, ExtractorConfig(line_width_px=float(width)))
    rms, cov, _ = score(res.u, res.v, spec, SHAPE[1])
    assert cov >= 0.995
    assert rms <= {1: 0.06, 2: 0.04}.get(width, 0.025)
    # Width of the profile as sampled by the pixels (Gaussian plus the 1 px box).
    expect = FWHM_PER_SIGMA * np.sqrt(s * s * (1 + 0.07**2) + 1.0 / 12.0)
    assert np.median(res.width) == pytest.approx(expect, rel=0.2)


@pytest.mark.parametrize('method', METHODS)
def test_8_and_16_bit_images_agree(method):
    """The same scene at 8 and 16 bit (x256, noise scaled too): same centres and truth."""
    spec = _spec(amplitude=150.0)
    rng = np.random.default_rng(20)
    img = render(SHAPE, spec, background=12.0, rng=rng)
    noise = rng.normal(0.0, 3.0, SHAPE)
    img8 = np.clip(np.rint(img + noise), 0, 255).astype(np.uint8)
    img16 = np.clip(np.rint((img + noise) * 256.0), 0, 65535).astype(np.uint16)
    r8 = extract(img8, ExtractorConfig(method=method, min_strength=20.0))
    r16 = extract(img16, ExtractorConfig(method=method, min_strength=20.0))
    assert len(r8) == len(r16) >= 0.995 * SHAPE[1]
    np.testing.assert_allclose(r16.v, r8.v, atol=0.03 if method == 'steger' else 0.1)
    np.testing.assert_allclose(r16.strength, 256.0 * r8.strength, rtol=0.02)
    rms16, _, _ = score(r16.u, r16.v, spec, SHAPE[1])
    assert rms16 <= (0.02 if method == 'steger' else 0.07)


@pytest.mark.parametrize('method', METHODS)
def test_vertical_orientation_is_the_transpose(method):
    spec = _spec(v0=240.2)
    img = render((480, 400), spec, noise_dn=4.0, rng=np.random.default_rng(30))
    h = extract(img, ExtractorConfig(method=method))
    v = extract(np.ascontiguousarray(img.T), ExtractorConfig(method=method,
                                                             orientation='vertical'))
    np.testing.assert_array_equal(v.u, h.v)
    np.testing.assert_array_equal(v.v, h.u)
    assert v.image_shape == (400, 480)
    rms, cov, _ = score(v.v, v.u, spec, 400)
    assert cov >= 0.995 and rms <= (0.025 if method == 'steger' else 0.08)


def test_non_contiguous_and_big_endian_inputs():
    spec = _spec()
    img = render(SHAPE, spec, noise_dn=2.0, rng=np.random.default_rng(40), dtype=np.uint16)
    ref = extract(img, ExtractorConfig(min_strength=10.0))
    padded = np.zeros((SHAPE[0], SHAPE[1] + 16), np.uint16)
    padded[:, :SHAPE[1]] = img
    a = extract(padded[:, :SHAPE[1]], ExtractorConfig(min_strength=10.0))
    b = extract(img.astype('>u2'), ExtractorConfig(min_strength=10.0))
    for r in (a, b):
        np.testing.assert_array_equal(r.v, ref.v)


@pytest.mark.parametrize(('kwargs', 'field'), [
    ({'method': 'sobel'}, 'method'),
    ({'orientation': 'diagonal'}, 'orientation'),
    ({'line_width_px': 0.1}, 'line_width_px'),
    ({'line_width_px': float('nan')}, 'line_width_px'),
    ({'min_strength': -1.0}, 'min_strength'),
    ({'roi_half_height': 2}, 'roi_half_height'),
    ({'roi_half_height': 5.5}, 'roi_half_height'),
    ({'roi_half_height': 4, 'line_width_px': 6.0}, 'roi_half_height'),
])
def test_config_validation_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ExtractorConfig(**kwargs)


@pytest.mark.parametrize('bad', [
    np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10), np.float32),
    np.zeros((2, 10), np.uint8), np.zeros((0, 0), np.uint8), [[1, 2, 3]]])
def test_bad_images_raise_naming_image(bad):
    with pytest.raises(ValueError, match='image'):
        extract(bad)


@pytest.mark.parametrize('method', METHODS)
@pytest.mark.parametrize('sigma_px', [4.5, 8.0])
def test_a_wide_stripe_is_extracted_at_its_own_width(method, sigma_px):
    """A stripe two and four times wider than stated (FWHM 10.6 and 18.8 px against 4.7),
    under speckle of contrast 0.5: the image is extracted again at the width it measures,
    and the centres' error falls by more than half."""
    spec = _spec(sigma_px=sigma_px, amplitude=150.0)
    img = render(SHAPE, spec, noise_dn=2.0, rng=np.random.default_rng(5),
                 speckle_contrast=0.5, speckle_grain_px=1.0)
    fixed = extract(img, ExtractorConfig(method=method, adapt_line_width=False))
    adapted = extract(img, ExtractorConfig(method=method))
    assert adapted.config.line_width_px == pytest.approx(sigma_px * FWHM_PER_SIGMA, rel=0.1)
    assert adapted.config.roi_half_height >= np.ceil(adapted.config.line_width_px)
    rms_fixed, _, _ = score(fixed.u, fixed.v, spec, SHAPE[1])
    rms_adapted, coverage, _ = score(adapted.u, adapted.v, spec, SHAPE[1])
    assert coverage >= 0.85
    assert rms_adapted < 0.5 * rms_fixed, (rms_adapted, rms_fixed)


def test_a_stripe_near_the_stated_width_is_extracted_once():
    """Within the adaptation band the stated configuration is the one used (one pass)."""
    cfg = ExtractorConfig(line_width_px=4.0)  # the stripe is 4.7 px: within 1.25x
    res = extract(render(SHAPE, _spec(), noise_dn=2.0, rng=np.random.default_rng(2)), cfg)
    assert res.config is cfg


def test_a_narrow_stripe_is_extracted_at_its_own_width():
    spec = _spec(sigma_px=2.0)  # FWHM 4.7 px against the stated 10
    img = render(SHAPE, spec, noise_dn=2.0, rng=np.random.default_rng(3))
    res = extract(img, ExtractorConfig(line_width_px=10.0, roi_half_height=15))
    assert res.config.line_width_px == pytest.approx(2.0 * FWHM_PER_SIGMA, rel=0.1)
    rms, coverage, _ = score(res.u, res.v, spec, SHAPE[1])
    assert coverage > 0.95 and rms < 0.1


def test_adapt_line_width_must_be_a_bool():
    with pytest.raises(ValueError, match='adapt_line_width'):
        ExtractorConfig(adapt_line_width='yes')
