"""Surface materials: a diffuse part, a glossy microfacet lobe and subsurface scattering.

A scene object without a ``material`` is Lambertian with its ``albedo`` (the model every
scene had before materials existed; its images are unchanged). A named material adds to
the diffuse reflectance ``albedo`` (which the object's ``albedo`` key still overrides):

- a specular microfacet lobe (Cook-Torrance with the GGX distribution and Smith's
  shadowing, Walter et al., "Microfacet Models for Refraction through Rough Surfaces",
  EGSR 2007, eqs. 33-34) with the full Fresnel reflectance of a conductor (complex index
  ``n + ik``) or of a dielectric (real index ``n``);
- the laser light the lobe sends on: the stripe mirrored by each planar face of the
  object onto the rest of the scene, blurred by the lobe (one bounce, see
  :mod:`galvoscan_sim.simulator`);
- subsurface scattering: a share ``sss_fraction`` of the diffuse light leaves the surface
  spread over the transport mean free path ``scattering_length`` and shifted by the
  refracted beam's travel under the surface (see :func:`subsurface_shift`).

Values are for the red laser line (the rigs' 650 nm class diode); each carries its
source. Roughness ``alpha`` is GGX's width parameter (about the RMS facet slope).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Packed material kinds (column 0 of :func:`pack`).
KIND_LAMBERT, KIND_DIELECTRIC, KIND_METAL = 0, 1, 2
KINDS = {'lambert': KIND_LAMBERT, 'dielectric': KIND_DIELECTRIC, 'metal': KIND_METAL}
#: Columns of a packed material row: kind, alpha, n, k, scattering length [m],
#: subsurface share, specular weight, spare.
PACK_WIDTH = 8


@dataclass(frozen=True)
class Material:
    """One surface material (SI units).

    Attributes
    ----------
    name : str
    kind : str
        ``'lambert'`` (diffuse only), ``'dielectric'`` or ``'metal'``.
    albedo : float
        Diffuse reflectance [1].
    alpha : float
        GGX roughness [1] (0 < alpha <= 1), ignored for ``'lambert'``.
    n, k : float
        Refractive index (real and imaginary part; k = 0 for a dielectric) at 650 nm.
    scattering_length : float
        Transport mean free path under the surface [m]; 0: opaque.
    sss_fraction : float
        Share of the diffuse light that scatters under the surface [1].
    source : str
        Where the numbers come from.
    """

    name: str
    kind: str
    albedo: float
    alpha: float = 1.0
    n: float = 1.5
    k: float = 0.0
    scattering_length: float = 0.0
    sss_fraction: float = 0.0
    source: str = ''

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f'material {self.name}: kind must be one of {tuple(KINDS)}, '
                             f'got {self.kind!r}')
        if not 0.0 <= self.albedo <= 1.0:
            raise ValueError(f'material {self.name}: albedo must be in [0, 1]')
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f'material {self.name}: alpha must be in (0, 1]')
        if not (self.n >= 1.0 and self.k >= 0.0):
            raise ValueError(f'material {self.name}: n must be >= 1 and k >= 0')
        if not (0.0 <= self.scattering_length <= 0.01 and 0.0 <= self.sss_fraction <= 1.0):
            raise ValueError(f'material {self.name}: scattering_length in [0, 0.01] m and '
                             'sss_fraction in [0, 1]')

    @property
    def specular(self) -> bool:
        """Whether the material has a specular lobe (and throws reflections)."""
        return self.kind != 'lambert'

    @property
    def normal_reflectance(self) -> float:
        """Fresnel reflectance at normal incidence [1]."""
        return fresnel(1.0, self.n, self.k)

    def packed(self) -> np.ndarray:
        """Row (PACK_WIDTH,) for the compiled tracer."""
        row = np.zeros(PACK_WIDTH)
        row[:7] = (KINDS[self.kind], self.alpha, self.n, self.k, self.scattering_length,
                   self.sss_fraction, 1.0 if self.specular else 0.0)
        return row


# --------------------------------------------------------------------------- the table
# Red line, ~650 nm, throughout.
MATERIALS = {m.name: m for m in (
    Material(
        'matte_paint', 'lambert', albedo=0.5,
        source='flat (matte) white-grey paint as a Lambertian reflector of 0.5; the '
               'Lambertian model of a matte paint: Oren & Nayar, "Generalization of the '
               'Lambertian model", IJCV 14 (1995), for rough matte surfaces'),
    Material(
        # Al at 650 nm: n = 1.47, k = 7.79 (Rakic, Appl. Opt. 34, 4755 (1995), as tabulated
        # by refractiveindex.info), R(0) = 0.91. Milled/turned Ra ~ 0.4-1.6 um is optically
        # rough at 650 nm (total integrated scatter (4 pi Ra / lambda)^2 > 1: Bennett &
        # Mattsson, Introduction to Surface Roughness and Scattering, OSA 1999), so there is
        # no mirror spike, only a lobe; alpha = 0.05 (lobe ~3 deg) is an assumed facet
        # slope of a fine machined finish, and 0.08 of diffuse from tool-mark scattering is
        # an assumed value (the lobe carries the rest).
        'machined_aluminium', 'metal', albedo=0.08, alpha=0.05, n=1.47, k=7.79,
        source='Rakic 1995 (n, k at 650 nm, R0 = 0.91); roughness assumed for a machined '
               'finish (Bennett & Mattsson 1999: Ra ~ 1 um is optically rough)'),
    Material(
        # polished aluminium: same optical constants, a near-mirror finish (alpha 0.02,
        # assumed: a lobe of ~1 deg, a lapped/polished surface)
        'polished_aluminium', 'metal', albedo=0.02, alpha=0.02, n=1.47, k=7.79,
        source='Rakic 1995 (n, k at 650 nm); near-mirror roughness assumed'),
    Material(
        # Fe at 650 nm: n ~ 2.92, k ~ 3.10 (Johnson & Christy, Phys. Rev. B 9, 5056 (1974)),
        # R(0) = 0.53. Ground finish (Ra ~ 0.2-0.8 um) again optically rough: alpha 0.25
        # assumed, grinding marks give 0.1 diffuse (assumed).
        'ground_steel', 'metal', albedo=0.10, alpha=0.25, n=2.92, k=3.10,
        source='Johnson & Christy 1974 (iron, n, k at 650 nm, R0 = 0.53); roughness '
               'assumed for a ground finish'),
    Material(
        # Black anodised aluminium: solar absorptance 0.86-0.95 (Gilmore, Spacecraft
        # Thermal Control Handbook vol. 1, 2nd ed. 2002, appendix A, "black anodize"), so a
        # diffuse reflectance of a few percent: 0.04. The sealed oxide is a dielectric
        # (Al2O3, n = 1.65 at 650 nm: Malitson, JOSA 52, 1377 (1962), sapphire, ordinary
        # ray) with a glossy top: alpha 0.3 assumed.
        'black_anodised', 'dielectric', albedo=0.04, alpha=0.3, n=1.65,
        source='Gilmore 2002 (black anodize, absorptance ~0.9); Malitson 1962 (Al2O3 '
               'n = 1.65); roughness assumed'),
    Material(
        # White ABS: n = 1.54 (ABS, e.g. Polymer Handbook, 4th ed., Brandrup et al. 1999:
        # 1.53-1.54); a white-pigmented plastic reflects ~0.8 diffusely (assumed); the
        # pigment keeps the scattering length short: 0.1 mm (assumed), 0.5 of the diffuse
        # light from under the surface (assumed).
        'white_abs', 'dielectric', albedo=0.8, alpha=0.2, n=1.54,
        scattering_length=0.1e-3, sss_fraction=0.5,
        source='Polymer Handbook 1999 (ABS n = 1.54); reflectance, gloss and scattering '
               'length assumed for a white-pigmented part'),
    Material(
        # Marble (Jensen, Marschner, Levoy, Hanrahan, "A Practical Model for Subsurface
        # Light Transport", SIGGRAPH 2001, table 2, red): sigma_s' = 2.19 /mm, sigma_a =
        # 0.0021 /mm -> transport mean free path 1/(sigma_s' + sigma_a) = 0.456 mm;
        # diffuse reflectance Rd = 0.83; eta = 1.5. Nearly all the diffuse light comes
        # from under the surface (albedo' = 0.999): sss_fraction 0.95 (assumed). Polished
        # marble: alpha 0.1 assumed.
        'marble', 'dielectric', albedo=0.83, alpha=0.1, n=1.5,
        scattering_length=0.456e-3, sss_fraction=0.95,
        source='Jensen et al. 2001, table 2 (marble, red: sigma_s\' 2.19/mm, sigma_a '
               '0.0021/mm, Rd 0.83, eta 1.5)'),
)}
#: Named materials a scene may use; ``matte_paint`` stands for the Lambertian default.
MATERIAL_NAMES = tuple(MATERIALS)


def material(name: str) -> Material:
    """The named material (KeyError listing the names otherwise)."""
    try:
        return MATERIALS[name]
    except KeyError:
        raise KeyError(f'unknown material {name!r}; known: {", ".join(MATERIAL_NAMES)}') \
            from None


# ------------------------------------------------------------------- reference maths
# The compiled tracer (raykernels) has its own copies of these; tests compare them.

def fresnel(cos_i: float, n: float, k: float = 0.0) -> float:
    """Unpolarised Fresnel reflectance from air onto a medium of index ``n + ik``.

    Exact for conductors and dielectrics (Born & Wolf, Principles of Optics, 7th ed.,
    sec. 14.2, with the complex index).
    """
    c = min(max(float(cos_i), 0.0), 1.0)
    eta = complex(n, k)
    s2 = 1.0 - c * c
    ct = np.sqrt(eta * eta - s2) / eta  # cos of the (complex) refraction angle
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return float(0.5 * (abs(rs) ** 2 + abs(rp) ** 2))


def ggx_d(cos_h: float, alpha: float) -> float:
    """GGX normal distribution D(h) [1/sr] (Walter et al. 2007, eq. 33)."""
    c2 = cos_h * cos_h
    a2 = alpha * alpha
    den = c2 * (a2 - 1.0) + 1.0
    return a2 / (math.pi * den * den) if cos_h > 0 else 0.0


def smith_g1(cos_v: float, alpha: float) -> float:
    """Smith's shadowing of one direction for GGX (Walter et al. 2007, eq. 34)."""
    if cos_v <= 0:
        return 0.0
    t2 = (1.0 - cos_v * cos_v) / (cos_v * cos_v)
    return 2.0 / (1.0 + math.sqrt(1.0 + alpha * alpha * t2))


def specular_reflectance(mat: Material, normal, to_light, to_view) -> float:
    """``pi`` times the Cook-Torrance BRDF, the specular addition to the diffuse albedo
    (a Lambertian surface's BRDF is albedo / pi) for unit vectors (3,)."""
    if not mat.specular:
        return 0.0
    n, l, v = (np.asarray(x, dtype=np.float64) for x in (normal, to_light, to_view))
    ci, co = float(n @ l), float(n @ v)
    if ci <= 0 or co <= 0:
        return 0.0
    h = l + v
    h /= np.linalg.norm(h)
    f = fresnel(float(l @ h), mat.n, mat.k)
    g = smith_g1(ci, mat.alpha) * smith_g1(co, mat.alpha)
    return math.pi * ggx_d(float(n @ h), mat.alpha) * f * g / (4.0 * ci * co)


def subsurface_shift(mat: Material, normal, incident, sheet_normal) -> float:
    """Where the subsurface glow of a stripe is centred, as a signed distance from the
    sheet's centre plane along its normal [m].

    The refracted beam travels one transport mean free path ``l`` before its light is
    diffuse (Jensen et al. 2001: the dipole's real source sits one mean free path deep);
    the glow is centred above that point: the beam's tangential travel ``l sin(theta_t)``
    along the surface, whose component along the sheet normal is returned.

    Parameters
    ----------
    normal : (3,) unit surface normal (outward); incident : (3,) unit beam direction
    (towards the surface); sheet_normal : (3,) unit normal of the laser sheet.
    """
    n, d, s = (np.asarray(x, dtype=np.float64) for x in (normal, incident, sheet_normal))
    tangential = d - (d @ n) * n  # |.| = sin(theta_i); refracted: sin(theta_t) = / n
    return float(mat.scattering_length / mat.n * (tangential @ s))


def pack(materials) -> np.ndarray:
    """Rows (K, PACK_WIDTH) for a list of materials (None: Lambertian, all zeros)."""
    out = np.zeros((len(materials), PACK_WIDTH))
    for i, m in enumerate(materials):
        if m is not None:
            out[i] = m.packed()
    return out
