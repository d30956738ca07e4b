"""Result type and entry point of the stripe-centre extractors.

No rclpy here. ``extract(image, config)`` runs the numba kernel of the Steger
(:mod:`.steger`) or the centre-of-gravity (:mod:`.cog`) method. Both share the per-column
candidate search of :mod:`.candidates` and the smoothed column profile of :mod:`.profile`,
and return one :class:`StripeResult`. The parameters (:class:`~.config.ExtractorConfig`) and
kernels live in :mod:`.config` and are re-exported here.

Conventions
-----------
- Pixel centres are at integer coordinates; ``u`` is the column, ``v`` the row [px].
- ``orientation='horizontal'``: the stripe runs along the image rows, so there is at most one
  centre per column. ``'vertical'``: the stripe runs along the columns, at most one centre per
  row (the image is transposed internally; ``u``/``v`` are always image column/row).
- ``line_width_px`` is the expected stripe FWHM [px]; it sets the Gaussian derivative scale
  ``sigma`` (:attr:`.config.ExtractorConfig.sigma`). With ``adapt_line_width`` an image whose
  stripe is measured much wider or narrower is extracted again at its own width.
- ``strength`` is the peak of the Gaussian-smoothed profile above the local background [DN];
  ``width`` is the FWHM-equivalent ``2.3548 * s`` of the stripe profile [px], ``s`` being its
  standard deviation as sampled by the pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cog import cog_columns, cog_half_window
from .config import (
    FWHM_PER_SIGMA,
    LINE_WIDTH_RANGE_PX,
    METHODS,
    MIN_STRENGTH_RANGE_DN,
    ORIENTATIONS,
    ROI_HALF_HEIGHT_RANGE_PX,
    SUPPORTED_DTYPES,
    WIDTH_ADAPT_MIN_CENTRES,
    ExtractorConfig,
    gaussian_kernels,
    stacked_kernels,
    white_level,
)
from .selection import COUNT_NAMES, MODE_CODES, kernel_expected, no_expectation
from .steger import steger_columns
from .width import measure_fwhm

__all__ = ['FWHM_PER_SIGMA', 'LINE_WIDTH_RANGE_PX', 'METHODS', 'MIN_STRENGTH_RANGE_DN',
           'ORIENTATIONS', 'ROI_HALF_HEIGHT_RANGE_PX', 'SUPPORTED_DTYPES', 'ExtractorConfig',
           'StripeResult', 'check_image', 'extract', 'extract_columns', 'gaussian_kernels',
           'stacked_kernels', 'warm_up']


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
    selection : dict
        Peak selection counts (``config.peak_mode``; :data:`.selection.COUNT_NAMES`):
        columns with two peaks, the strongest kept, the other taken, the column dropped.
    config : ExtractorConfig
        Parameters used; ``config.sigma`` is the derivative scale used [px]
        (``line_width_px`` is the stripe's measured width where it was adapted).
    image_shape : tuple of int
        (height, width) of the source image [px].
    white_level : int
        The image's top code the threshold was scaled by [DN] (:func:`.config.white_level`);
        the threshold applied is ``config.threshold_dn(white_level)``.
    """

    u: np.ndarray
    v: np.ndarray
    width: np.ndarray
    strength: np.ndarray
    rejected_secondary: int
    config: ExtractorConfig
    image_shape: tuple = field(default=(0, 0))
    selection: dict = field(default_factory=dict)
    white_level: int = 255

    def __len__(self) -> int:
        return int(self.u.shape[0])

    @property
    def sigma(self) -> float:
        """Gaussian derivative scale used [px]."""
        return self.config.sigma


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


def _expected_across(expected, n: int) -> np.ndarray:
    """``expected`` as float32 (n,), one per position along the stripe (the columns of the
    image :func:`extract_columns` works on: the image's rows for a vertical stripe): None ->
    NaN, a scalar broadcast, an array checked."""
    if expected is None:
        return no_expectation(n)
    e = np.asarray(expected, dtype=np.float32)
    if e.ndim == 0:
        return np.full(n, float(e), np.float32)
    if e.shape != (n,):
        raise ValueError(f'expected_v: expected a scalar or shape ({n},) (one per image '
                         f'column, per row for a vertical stripe), got {e.shape}')
    return np.ascontiguousarray(e)


def _prior_offset(img, config, columns, method_arg, rows, threshold) -> np.float32:
    """The prior's own error (calibration, the part's placement): the median offset from the
    expected rows of the peaks nearest them, over the columns that have both (0 if none).
    The prior need only be nearer the stripe than the reflections are."""
    out = np.empty((4, img.shape[1]), np.float32)
    counts = np.zeros(len(COUNT_NAMES), np.int64)
    n, _ = columns(img, config.roi_half_height, stacked_kernels(config.sigma), method_arg,
                   threshold, out, MODE_CODES['nearest'], kernel_expected(rows),
                   config.ambiguity_ratio, counts)
    d = out[1, :n] - rows[np.clip(np.rint(out[0, :n]).astype(np.int64), 0, len(rows) - 1)]
    d = d[np.isfinite(d)]
    return np.float32(np.median(d)) if d.size else np.float32(0.0)


def extract_columns(img: np.ndarray, config: ExtractorConfig, expected=None,
                    white: int | None = None):
    """Centres of a checked image, one per column at most, by the method of ``config``.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8 or uint16, DN
        Already validated and C-contiguous (see :func:`check_image`); the stripe runs along
        the rows.
    config : ExtractorConfig
    expected : array_like, shape (W,) or scalar, px, optional
        Expected row of the stripe per column (``peak_mode='nearest'``; NaN: none). It is
        first moved by the median offset of the peaks nearest it (the prior's own error,
        e.g. of the calibration or the part's placement).
    white : int, optional
        The image's white level [DN]; default :func:`.config.white_level` of ``img``.

    Returns
    -------
    u, v, width, strength : ndarray, shape (n,), float32
        Column [px], row [px], FWHM [px], strength [DN].
    rejected_secondary : int
    counts : ndarray, shape (4,), int64
        Peak selection counts (:data:`.selection.COUNT_NAMES`).
    """
    if config.method == 'steger':
        columns, method_arg = steger_columns, config.sigma
    else:
        columns, method_arg = cog_columns, cog_half_window(config.line_width_px)
    threshold = config.threshold_dn(white_level(img, config.bit_depth) if white is None
                                    else white)
    rows = _expected_across(expected, img.shape[1])
    if config.peak_mode == 'nearest' and np.any(np.isfinite(rows)):
        rows = rows + _prior_offset(img, config, columns, method_arg, rows, threshold)
    out = np.empty((4, img.shape[1]), np.float32)
    counts = np.zeros(len(COUNT_NAMES), np.int64)
    n, nsec = columns(img, config.roi_half_height, stacked_kernels(config.sigma), method_arg,
                      threshold, out, MODE_CODES[config.peak_mode], kernel_expected(rows),
                      config.ambiguity_ratio, counts)
    u, v, w, s = out[0, :n], out[1, :n], out[2, :n], out[3, :n]
    if config.peak_mode == 'nearest' and config.max_offset_px > 0 and n:
        e = rows[np.clip(np.rint(u).astype(np.int64), 0, img.shape[1] - 1)]
        far = np.abs(v - e) > config.max_offset_px  # NaN (no expectation) is not far
        counts[-1] = int(np.sum(far))
        u, v, w, s = u[~far], v[~far], w[~far], s[~far]
    return u, v, w, s, nsec, counts


def extract(image: np.ndarray, config: ExtractorConfig | None = None,
            expected_v=None) -> StripeResult:
    """Extract at most one sub-pixel stripe centre per column (per row if vertical).

    Parameters
    ----------
    image : ndarray, shape (height, width), uint8 or uint16, DN
        Monochrome camera image.
    config : ExtractorConfig, optional
        Method and parameters; defaults to ``ExtractorConfig()``.
    expected_v : array_like, shape (width,) or scalar, px, optional
        Where the stripe is expected, per column (per row if vertical: the expected
        column), for ``peak_mode='nearest'``; NaN or None: no expectation.

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
    white = white_level(img, config.bit_depth)
    a, b, w, s, nsec, counts = extract_columns(img, config, expected_v, white)
    # The filter's own width reading (free, but short for a stripe wider than its window)
    # says whether to measure; the measurement at half maximum says at what width to redo.
    if (config.adapt_line_width and len(a) >= WIDTH_ADAPT_MIN_CENTRES
            and config.width_to_adapt(float(np.median(w)), len(a)) is not None):
        width = config.width_to_adapt(*measure_fwhm(img, a, b))
        if width is not None:  # not as wide as stated: match the filter to the stripe
            config = config.at_width(width)
            a, b, w, s, nsec, counts = extract_columns(img, config, expected_v, white)
    u, v = (b, a) if vertical else (a, b)
    return StripeResult(u=u, v=v, width=w, strength=s, rejected_secondary=int(nsec),
                        config=config, image_shape=shape, white_level=white,
                        selection=dict(zip(COUNT_NAMES, (int(x) for x in counts),
                                           strict=True)))


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) every kernel for uint8 and uint16 images,
    writable and read-only (a node's images are read-only views of the messages' buffers,
    a type of their own to numba).

    Call once per process before timing or before the first real frame.
    """
    rng = np.random.default_rng(0)
    rows = np.arange(40, dtype=np.float64)[:, None]
    img = 10.0 + 150.0 * np.exp(-0.5 * ((rows - 20.3) / 2.0) ** 2) + rng.normal(0, 1, (40, 48))
    for dtype, scale in ((np.uint8, 1), (np.uint16, 200)):
        frame = np.clip(img * scale, 0, np.iinfo(dtype).max).astype(dtype)
        read_only = frame.copy()
        read_only.setflags(write=False)
        for method in METHODS:
            for f in (frame, read_only):
                extract(f, ExtractorConfig(method=method, min_strength=5.0))
