"""Parameters of the stripe-centre extractors and the Gaussian kernels they imply.

No rclpy, no numba here. :class:`ExtractorConfig` is validated on construction (its ranges
are also the node's parameter ranges); :func:`gaussian_kernels` samples the Gaussian and its
first two derivatives at the scale ``config.sigma`` that both extractors
(:mod:`.steger`, :mod:`.cog`) smooth the column profiles with.

- ``line_width_px`` is the expected stripe FWHM [px]; it sets the Gaussian derivative scale
  ``sigma = max(line_width_px / 2.3548, 1.0)`` (the matched filter for a Gaussian profile,
  floored at 1 px so that the sampled derivative kernels stay accurate).
- ``adapt_line_width``: the stripe's width is a property of the build (the laser's sheet
  thickness, the distance, the lens), not a constant: a matched filter four times too narrow
  leaves the speckle of a wide stripe in its centres (the flat plate's RMS triples, see
  ``benchmarks/extractor_width.py``). When the width measured in an image lies outside
  ``line_width_px`` times [1/:data:`WIDTH_ADAPT_NARROWER`, :data:`WIDTH_ADAPT_WIDER`], the
  image is extracted again at that width. The filter's own width reading decides
  whether to measure (it costs nothing); the width is then measured at half maximum around
  the centres found (:mod:`.width`), not through the filter, so one more pass is enough at
  any width.
- ``min_strength`` is stated in 8-bit DN (full scale 255) and scaled by the image's white
  level (:func:`white_level`): the same share of full scale at every bit depth, so a
  threshold chosen on an 8-bit camera keeps its meaning on a 10, 12 or 16-bit one.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

#: FWHM of a Gaussian in units of its standard deviation, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))

METHODS = ('steger', 'center_of_gravity')
#: Peak selection modes (see :mod:`.selection`).
PEAK_MODES = ('strongest', 'nearest', 'widest', 'unambiguous')
#: Range of ``ambiguity_ratio`` [1].
AMBIGUITY_RATIO_RANGE = (0.05, 1.0)
#: Range of ``max_offset_px`` [px] (0: no limit).
MAX_OFFSET_RANGE_PX = (0.0, 1000.0)
ORIENTATIONS = ('horizontal', 'vertical')
SUPPORTED_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))

#: Ranges accepted by :class:`ExtractorConfig` (the node's parameter descriptors reuse them).
LINE_WIDTH_RANGE_PX = (0.5, 30.0)
#: ``min_strength`` [DN at 8 bits: a share of full scale times 255].
MIN_STRENGTH_RANGE_DN = (0.0, 255.0)
#: Bit depths an image's codes may have (``bit_depth``; 0: read from the image).
BIT_DEPTHS = (0, 8, 10, 12, 14, 16)
#: The white level ``min_strength`` is stated against [DN].
WHITE_LEVEL_8BIT = 255
ROI_HALF_HEIGHT_RANGE_PX = (3, 200)
#: ``adapt_line_width``: an image whose stripe is wider than ``line_width_px`` by more than
#: this factor is extracted again at its own width [1]. A filter narrower than the stripe
#: leaves its speckle in the centres, fast: on the family rig of seed 6
#: (``benchmarks/extractor_width.py --seed 6``, an 11.8 px stripe) 10 px stated costs the
#: flat plate's RMS about 10 %, 4.7 px nearly three times.
WIDTH_ADAPT_WIDER = 1.25
#: ``adapt_line_width``: an image whose stripe is narrower than ``line_width_px`` by more than
#: this factor is extracted again at its own width [1]. A filter wider than the stripe
#: averages more speckle (on the reference rig 10 px stated for a 4.4 px stripe gives the flat
#: plate a lower RMS than 4.7 px, ``benchmarks/extractor_width.py``); it costs at edges and
#: steps, which it blurs, and in a weak stripe's strength, so only a large excess is undone.
WIDTH_ADAPT_NARROWER = 1.6
#: ``adapt_line_width``: fewest columns whose median width is trusted [1] (a few specks or a
#: stripe's end say little about its width).
WIDTH_ADAPT_MIN_CENTRES = 20


@dataclass(frozen=True)
class ExtractorConfig:
    """Parameters of one extraction; validated on construction (``ValueError`` naming the field).

    Attributes
    ----------
    method : str
        ``'steger'`` (Hessian, sub-pixel along the stripe normal) or ``'center_of_gravity'``.
    line_width_px : float
        Expected stripe FWHM [px], 0.5..30; sets :attr:`sigma`.
    min_strength : float
        Weakest accepted peak of the smoothed profile above background [DN at 8 bits],
        0..255: scaled by the image's white level over 255 (:func:`white_level`), so 20
        means 20 DN on a Mono8 image and 321 DN on a Mono12 one.
    roi_half_height : int
        Half height of the window searched around each column's candidate peak [px]; also the
        half size of the zone around the chosen peak in which no secondary peak is counted.
        Must be at least ``ceil(line_width_px)`` so the window ends see background.
    orientation : str
        ``'horizontal'`` (one centre per column) or ``'vertical'`` (one centre per row).
    peak_mode : str
        Which of two peaks in a column is the stripe (:mod:`.selection`): ``'strongest'``
        (default), ``'nearest'`` (the expected row), ``'widest'`` or ``'unambiguous'``.
    ambiguity_ratio : float
        ``'unambiguous'``: a column whose second peak reaches this share of the first's
        strength gives no centre [1], 0.05..1.
    max_offset_px : float
        ``'nearest'``: a centre farther than this from its column's expected row is dropped
        [px] (a reflection merged into the stripe); 0: no limit.
    bit_depth : int
        Bit depth of the image's codes [bit] (:data:`BIT_DEPTHS`), which sets its white
        level ``2**bit_depth - 1``; 0: read from the image (:func:`white_level`).
    adapt_line_width : bool
        Extract an image again at its stripe's measured width when that differs from
        ``line_width_px`` by more than :data:`WIDTH_ADAPT_WIDER` (wider) or
        :data:`WIDTH_ADAPT_NARROWER` (narrower); see the module.
    """

    method: str = 'steger'
    line_width_px: float = 4.7
    min_strength: float = 20.0
    roi_half_height: int = 12
    orientation: str = 'horizontal'
    peak_mode: str = 'strongest'
    ambiguity_ratio: float = 0.3
    max_offset_px: float = 0.0
    bit_depth: int = 0
    adapt_line_width: bool = True

    def __post_init__(self):
        if not isinstance(self.adapt_line_width, (bool, np.bool_)):
            raise ValueError(f'adapt_line_width must be a bool, got {self.adapt_line_width!r}')
        object.__setattr__(self, 'adapt_line_width', bool(self.adapt_line_width))
        if isinstance(self.bit_depth, bool) or self.bit_depth not in BIT_DEPTHS:
            raise ValueError(f'bit_depth must be one of {BIT_DEPTHS} bit, got {self.bit_depth!r}')
        object.__setattr__(self, 'bit_depth', int(self.bit_depth))
        if self.method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {self.method!r}')
        if self.peak_mode not in PEAK_MODES:
            raise ValueError(f'peak_mode must be one of {PEAK_MODES}, got {self.peak_mode!r}')
        ar = float(self.ambiguity_ratio)
        if not (AMBIGUITY_RATIO_RANGE[0] <= ar <= AMBIGUITY_RATIO_RANGE[1]):
            raise ValueError(f'ambiguity_ratio must be in {AMBIGUITY_RATIO_RANGE}, '
                             f'got {self.ambiguity_ratio}')
        object.__setattr__(self, 'ambiguity_ratio', ar)
        mo = float(self.max_offset_px)
        if not (MAX_OFFSET_RANGE_PX[0] <= mo <= MAX_OFFSET_RANGE_PX[1]):
            raise ValueError(f'max_offset_px must be in {MAX_OFFSET_RANGE_PX} px, '
                             f'got {self.max_offset_px}')
        object.__setattr__(self, 'max_offset_px', mo)
        if self.orientation not in ORIENTATIONS:
            raise ValueError(
                f'orientation must be one of {ORIENTATIONS}, got {self.orientation!r}')
        lw = float(self.line_width_px)
        if not (LINE_WIDTH_RANGE_PX[0] <= lw <= LINE_WIDTH_RANGE_PX[1]):
            raise ValueError(
                f'line_width_px must be in {LINE_WIDTH_RANGE_PX} px, got {self.line_width_px}')
        ms = float(self.min_strength)
        if not (MIN_STRENGTH_RANGE_DN[0] <= ms <= MIN_STRENGTH_RANGE_DN[1]):
            raise ValueError(f'min_strength must be in {MIN_STRENGTH_RANGE_DN} DN at 8 bits, '
                             f'got {self.min_strength}')
        if isinstance(self.roi_half_height, bool) or int(self.roi_half_height) != \
                self.roi_half_height:
            raise ValueError(f'roi_half_height must be an integer, got {self.roi_half_height!r}')
        rh = int(self.roi_half_height)
        if not (ROI_HALF_HEIGHT_RANGE_PX[0] <= rh <= ROI_HALF_HEIGHT_RANGE_PX[1]):
            raise ValueError(f'roi_half_height must be in {ROI_HALF_HEIGHT_RANGE_PX} px, '
                             f'got {self.roi_half_height}')
        if rh < math.ceil(lw):
            raise ValueError(f'roi_half_height ({rh} px) must be >= ceil(line_width_px) '
                             f'({math.ceil(lw)} px)')
        object.__setattr__(self, 'line_width_px', lw)
        object.__setattr__(self, 'min_strength', ms)
        object.__setattr__(self, 'roi_half_height', rh)

    @property
    def sigma(self) -> float:
        """Gaussian derivative scale [px]: the stripe's expected standard deviation, >= 1."""
        return max(self.line_width_px / FWHM_PER_SIGMA, 1.0)

    @property
    def kernel_radius(self) -> int:
        """Half length of the sampled Gaussian kernels [px]: ceil(3 sigma)."""
        return int(math.ceil(3.0 * self.sigma))

    def at_width(self, width_px: float) -> ExtractorConfig:
        """This configuration matched to a stripe ``width_px`` wide [px] (clipped to
        :data:`LINE_WIDTH_RANGE_PX`), its window widened to hold it."""
        lw = float(np.clip(width_px, *LINE_WIDTH_RANGE_PX))
        # +-1.5 FWHM (+-3.5 sigma): the window's ends see background, so the width measured
        # in it is not cut short
        rh = min(max(self.roi_half_height, math.ceil(1.5 * lw)), ROI_HALF_HEIGHT_RANGE_PX[1])
        return dataclasses.replace(self, line_width_px=lw, roi_half_height=rh)

    def width_to_adapt(self, measured_px: float, columns: int) -> float | None:
        """The width [px] to extract an image again at, given its stripe's width measured
        over ``columns`` columns (:func:`.width.measure_fwhm`), or None: not adapting, too
        few columns, or near enough to ``line_width_px``."""
        if not self.adapt_line_width or columns < WIDTH_ADAPT_MIN_CENTRES:
            return None
        if not math.isfinite(measured_px) or measured_px <= 0:
            return None
        ratio = measured_px / self.line_width_px
        if 1.0 / WIDTH_ADAPT_NARROWER <= ratio <= WIDTH_ADAPT_WIDER:
            return None
        return float(measured_px)

    def threshold_dn(self, white: int) -> float:
        """``min_strength`` in the DN of an image whose white level is ``white`` [DN]."""
        return self.min_strength * float(white) / WHITE_LEVEL_8BIT


def white_level(image: np.ndarray, bit_depth: int = 0) -> int:
    """The top code of ``image`` [DN]: ``2**bit_depth - 1``.

    With ``bit_depth`` 0 it is read from the image: 255 for uint8; for uint16 (the mono16
    of a Mono10, Mono12 or Mono16 camera, which sensor_msgs/Image does not tell apart) the
    top code of the shallowest of 10, 12 and 16 bits that holds the image's brightest
    pixel. A camera's exposed frame reaches beyond a quarter of its full scale, so this is
    its depth; a frame darker than that is read as a shallower camera's (a laxer
    threshold, never a stricter one). State the depth (``bit_depth``) to take the guess out.
    """
    if bit_depth:
        return (1 << int(bit_depth)) - 1
    if image.dtype.itemsize == 1:
        return 255
    top = int(image.max()) if image.size else 0
    for depth in (10, 12):
        if top < (1 << depth):
            return (1 << depth) - 1
    return 65535


def gaussian_kernels(sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half kernels (index k = 0..K) of the sampled Gaussian and its first two derivatives.

    Used as correlations: ``f'(x) ~ sum_k d1[|k|] sign(k) f(x + k)`` over k = -K..K, likewise
    ``f ~ sum g0[|k|] f(x + k)`` and ``f'' ~ sum d2[|k|] f(x + k)``. The kernels are normalised
    so they are exact on constants (g0), linear ramps (d1) and parabolas (d2).

    Parameters
    ----------
    sigma : float
        Gaussian standard deviation [px], > 0.

    Returns
    -------
    g0, d1, d2 : ndarray, shape (K + 1,), float64
        K = ceil(3 sigma).
    """
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f'sigma must be a positive finite number, got {sigma}')
    K = int(math.ceil(3.0 * sigma))
    k = np.arange(-K, K + 1, dtype=np.float64)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    g0 = g / g.sum()
    d1 = k * g
    d1 /= np.sum(k * d1)                      # sum k d1 = 1: exact on f = x
    d2 = (k * k / sigma**2 - 1.0) * g
    d2 -= g0 * d2.sum()                       # sum d2 = 0: blind to constants
    d2 /= 0.5 * np.sum(k * k * d2)            # sum k^2 d2 / 2 = 1: exact on f = x^2
    return (np.ascontiguousarray(g0[K:]), np.ascontiguousarray(d1[K:]),
            np.ascontiguousarray(d2[K:]))


@functools.lru_cache(maxsize=32)
def stacked_kernels(sigma: float) -> np.ndarray:
    """``gaussian_kernels(sigma)`` stacked to shape (3, K + 1), float32, read-only (cached)."""
    kern = np.ascontiguousarray(np.stack(gaussian_kernels(sigma)), dtype=np.float32)
    kern.setflags(write=False)
    return kern
