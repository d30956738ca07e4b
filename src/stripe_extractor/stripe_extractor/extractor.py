"""Common configuration, result type and entry point of the stripe-centre extractors.

No rclpy here. ``extract(image, config)`` dispatches to the Steger (:mod:`.steger`) or the
centre-of-gravity (:mod:`.cog`) method. Both share the per-column candidate search of
:mod:`.candidates` and return one :class:`StripeResult`.

Conventions
-----------
- Pixel centres are at integer coordinates; ``u`` is the column, ``v`` the row [px].
- ``orientation='horizontal'``: the stripe runs along the image rows, so there is at most one
  centre per column. ``'vertical'``: the stripe runs along the columns, at most one centre per
  row (the image is transposed internally; ``u``/``v`` are always image column/row).
- ``line_width_px`` is the expected stripe FWHM [px]; it sets the Gaussian derivative scale
  ``sigma = max(line_width_px / 2.3548, 1.0)`` (the matched filter for a Gaussian profile,
  floored at 1 px so that the sampled derivative kernels stay accurate).
- ``strength`` is the peak of the Gaussian-smoothed profile above the local background [DN];
  ``width`` is the FWHM-equivalent ``2.3548 * s`` of the stripe profile [px], ``s`` being its
  standard deviation as sampled by the pixels.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

#: FWHM of a Gaussian in units of its standard deviation, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))

METHODS = ('steger', 'center_of_gravity')
ORIENTATIONS = ('horizontal', 'vertical')
SUPPORTED_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))

#: Ranges accepted by :class:`ExtractorConfig` (the node's parameter descriptors reuse them).
LINE_WIDTH_RANGE_PX = (0.5, 30.0)
MIN_STRENGTH_RANGE_DN = (0.0, 65535.0)
ROI_HALF_HEIGHT_RANGE_PX = (3, 200)


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
        Weakest accepted peak of the smoothed profile above background [DN].
    roi_half_height : int
        Half height of the window searched around each column's candidate peak [px]; also the
        half size of the zone around the chosen peak in which no secondary peak is counted.
        Must be at least ``ceil(line_width_px)`` so the window ends see background.
    orientation : str
        ``'horizontal'`` (one centre per column) or ``'vertical'`` (one centre per row).
    """

    method: str = 'steger'
    line_width_px: float = 4.7
    min_strength: float = 20.0
    roi_half_height: int = 12
    orientation: str = 'horizontal'

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {self.method!r}')
        if self.orientation not in ORIENTATIONS:
            raise ValueError(
                f'orientation must be one of {ORIENTATIONS}, got {self.orientation!r}')
        lw = float(self.line_width_px)
        if not (LINE_WIDTH_RANGE_PX[0] <= lw <= LINE_WIDTH_RANGE_PX[1]):
            raise ValueError(
                f'line_width_px must be in {LINE_WIDTH_RANGE_PX} px, got {self.line_width_px}')
        ms = float(self.min_strength)
        if not (MIN_STRENGTH_RANGE_DN[0] <= ms <= MIN_STRENGTH_RANGE_DN[1]):
            raise ValueError(
                f'min_strength must be in {MIN_STRENGTH_RANGE_DN} DN, got {self.min_strength}')
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


@dataclass(frozen=True)
class StripeResult:
    """Stripe centres of one image; all arrays have shape (n,) and dtype float32.

    Attributes
    ----------
    u : ndarray, shape (n,), px
        Image column of each centre (sub-pixel; pixel centres at integers).
    v : ndarray, shape (n,), px
        Image row of each centre.
    width : ndarray, shape (n,), px
        FWHM-equivalent stripe width (2.3548 sigma of the profile).
    strength : ndarray, shape (n,), DN
        Peak of the smoothed profile above background.
    rejected_secondary : int
        Columns (rows, if vertical) where a weaker secondary peak was found and rejected.
    config : ExtractorConfig
        Parameters used; ``config.sigma`` is the derivative scale used [px].
    image_shape : tuple of int
        (height, width) of the source image [px].
    """

    u: np.ndarray
    v: np.ndarray
    width: np.ndarray
    strength: np.ndarray
    rejected_secondary: int
    config: ExtractorConfig
    image_shape: tuple = field(default=(0, 0))

    def __len__(self) -> int:
        return int(self.u.shape[0])

    @property
    def sigma(self) -> float:
        """Gaussian derivative scale used [px]."""
        return self.config.sigma


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


def check_image(image) -> np.ndarray:
    """Return ``image`` as a C-contiguous 2-D uint8/uint16 array or raise ``ValueError``."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f'image must be a numpy array, got {type(image).__name__}')
    if image.ndim != 2:
        raise ValueError(f'image must be 2-D (height, width), got shape {image.shape}')
    if image.dtype.kind != 'u' or image.dtype.itemsize not in (1, 2):
        raise ValueError(f'image dtype must be uint8 or uint16, got {image.dtype}')
    if image.shape[0] < 3 or image.shape[1] < 3:
        raise ValueError(f'image must be at least 3x3 px, got shape {image.shape}')
    if not image.dtype.isnative:
        image = image.astype(image.dtype.newbyteorder('='))
    return np.ascontiguousarray(image)


def extract(image: np.ndarray, config: ExtractorConfig | None = None) -> StripeResult:
    """Extract at most one sub-pixel stripe centre per column (per row if vertical).

    Parameters
    ----------
    image : ndarray, shape (height, width), uint8 or uint16, DN
        Monochrome camera image.
    config : ExtractorConfig, optional
        Method and parameters; defaults to ``ExtractorConfig()``.

    Returns
    -------
    StripeResult
        Centres sorted by column (by row if vertical).
    """
    config = ExtractorConfig() if config is None else config
    if not isinstance(config, ExtractorConfig):
        raise ValueError(f'config must be an ExtractorConfig, got {type(config).__name__}')
    img = check_image(image)
    shape = (int(img.shape[0]), int(img.shape[1]))
    vertical = config.orientation == 'vertical'
    if vertical:
        img = np.ascontiguousarray(img.T)
    if config.method == 'steger':
        from .steger import extract_columns
    else:
        from .cog import extract_columns
    a, b, w, s, nsec = extract_columns(img, config)
    u, v = (b, a) if vertical else (a, b)
    return StripeResult(u=u, v=v, width=w, strength=s, rejected_secondary=int(nsec),
                        config=config, image_shape=shape)


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) every kernel for uint8 and uint16 images.

    Call once per process before timing or before the first real frame.
    """
    rng = np.random.default_rng(0)
    rows = np.arange(40, dtype=np.float64)[:, None]
    img = 10.0 + 150.0 * np.exp(-0.5 * ((rows - 20.3) / 2.0) ** 2) + rng.normal(0, 1, (40, 48))
    for dtype, scale in ((np.uint8, 1), (np.uint16, 200)):
        frame = np.clip(img * scale, 0, np.iinfo(dtype).max).astype(dtype)
        for method in METHODS:
            extract(frame, ExtractorConfig(method=method, min_strength=5.0 * scale))
