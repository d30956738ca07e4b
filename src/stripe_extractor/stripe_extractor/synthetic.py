"""Synthetic laser-stripe images with known sub-pixel centres, for tests and benchmarks.

No rclpy here. The stripe is a Gaussian ridge of standard deviation ``sigma_px`` measured
along its normal, centred on the curve ``v = v_c(u)``:

    v_c(u) = v0 + slope * (u - u_mid) + curvature * (u - u_mid)^2 / 2,  u_mid = (W - 1) / 2

Each pixel is integrated exactly over its height (erf), point-sampled across its width. A
column's profile is then symmetric about ``v_c(u)`` (to O(curvature^2)), so ``v_c`` is the
ground truth. Noise, laser speckle, isolated bright specks, secondary reflections, occlusions
and clipping at the dtype's maximum can be added.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf


@dataclass(frozen=True)
class StripeSpec:
    """Geometry and radiometry of a synthetic stripe.

    Attributes
    ----------
    v0 : float
        Row of the centre line at the middle column [px].
    slope : float
        dv/du at the middle column [px/px].
    curvature : float
        d2v/du2 [1/px].
    sigma_px : float
        Standard deviation of the profile along the stripe normal [px].
    amplitude : float
        Peak intensity above background [DN] (before clipping).
    """

    v0: float = 270.3
    slope: float = 0.08
    curvature: float = 2.0e-4
    sigma_px: float = 2.0
    amplitude: float = 180.0

    def centre(self, u, width: int) -> np.ndarray:
        """Row of the centre line at columns ``u`` (float array) of an image ``width`` wide."""
        x = np.asarray(u, dtype=np.float64) - 0.5 * (width - 1)
        return self.v0 + self.slope * x + 0.5 * self.curvature * x * x

    def centre_slope(self, u, width: int) -> np.ndarray:
        x = np.asarray(u, dtype=np.float64) - 0.5 * (width - 1)
        return self.slope + self.curvature * x


def stripe_profile(shape: tuple[int, int], spec: StripeSpec,
                   columns: np.ndarray | None = None) -> np.ndarray:
    """Noise-free stripe intensity above background [DN], float64, shape ``shape``.

    ``columns`` (bool, shape (W,)) selects the columns where the stripe is visible.
    """
    H, W = int(shape[0]), int(shape[1])
    u = np.arange(W, dtype=np.float64)
    vc = spec.centre(u, W)
    sv = spec.sigma_px * np.sqrt(1.0 + spec.centre_slope(u, W) ** 2)   # s / cos(theta)
    r = np.arange(H, dtype=np.float64)[:, None]
    z1 = (r + 0.5 - vc[None, :]) / (math.sqrt(2.0) * sv[None, :])
    z0 = (r - 0.5 - vc[None, :]) / (math.sqrt(2.0) * sv[None, :])
    out = spec.amplitude * sv[None, :] * math.sqrt(math.pi / 2.0) * (erf(z1) - erf(z0))
    if columns is not None:
        out[:, ~np.asarray(columns, dtype=bool)] = 0.0
    return out


def speckle_field(shape: tuple[int, int], grain_px: float, contrast: float,
                  rng: np.random.Generator) -> np.ndarray:
    """Multiplicative laser-speckle pattern of mean 1 and standard deviation ``contrast``.

    Fully developed speckle (|complex Gaussian field|^2, exponential intensity statistics)
    with correlation length ``grain_px``, blended with 1 to the requested contrast (pixel
    integration and a partly coherent source lower the contrast below 1).
    """
    from scipy.ndimage import gaussian_filter
    field = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    field = gaussian_filter(field.real, grain_px) + 1j * gaussian_filter(field.imag, grain_px)
    inten = np.abs(field) ** 2
    inten /= inten.mean()
    return 1.0 + contrast * (inten - 1.0) / inten.std()


def render(shape: tuple[int, int], spec: StripeSpec, *, background: float = 12.0,
           noise_dn: float = 0.0, dtype=np.uint8, rng: np.random.Generator | None = None,
           speckle_contrast: float = 0.0, speckle_grain_px: float = 1.0,
           columns: np.ndarray | None = None, extra: np.ndarray | None = None) -> np.ndarray:
    """Render one stripe image (clipped to the dtype's range, rounded).

    Parameters
    ----------
    shape : (H, W)
    spec : StripeSpec
    background : float
        Constant background [DN].
    noise_dn : float
        Standard deviation of additive Gaussian read noise [DN].
    dtype : numpy integer dtype
        uint8 or uint16.
    speckle_contrast, speckle_grain_px : float
        Multiplicative speckle on the stripe (0 = none).
    columns : ndarray, shape (W,), bool, optional
        Columns where the stripe is visible (occlusion elsewhere).
    extra : ndarray, shape (H, W), float, optional
        Additional intensity [DN] added before noise (e.g. a secondary reflection).

    Returns
    -------
    ndarray, shape (H, W), dtype
    """
    rng = np.random.default_rng(0) if rng is None else rng  # repeatable by default
    img = stripe_profile(shape, spec, columns)
    if speckle_contrast > 0.0:
        img *= speckle_field(shape, speckle_grain_px, speckle_contrast, rng)
    img += background
    if extra is not None:
        img += extra
    if noise_dn > 0.0:
        img += rng.normal(0.0, noise_dn, size=img.shape)
    top = np.iinfo(dtype).max
    return np.clip(np.rint(img), 0, top).astype(dtype)


def score(u: np.ndarray, v: np.ndarray, spec: StripeSpec, width: int,
          visible_columns: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
    """RMS error [px] and coverage of centres (u, v) against ``spec``.

    The error of a centre is ``v - v_c(u)`` (vertical distance to the true centre line at
    the reported column). Coverage is the fraction of visible columns with a centre whose
    rounded ``u`` is that column.

    Returns
    -------
    rms_px : float
    coverage : float
    err : ndarray, shape (n,), px
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.shape != v.shape or u.ndim != 1:
        raise ValueError(f'u and v must be 1-D of equal shape, got {u.shape}, {v.shape}')
    vis = np.ones(width, bool) if visible_columns is None else np.asarray(visible_columns,
                                                                         bool)
    err = v - spec.centre(u, width)
    rms = float(np.sqrt(np.mean(err**2))) if err.size else float('nan')
    cols = np.clip(np.rint(u).astype(np.int64), 0, width - 1)
    found = np.zeros(width, bool)
    found[cols] = True
    coverage = float(np.count_nonzero(found & vis) / max(np.count_nonzero(vis), 1))
    return rms, coverage, err
