"""A family of plausible rigs: random builds of the paper's scanner, set up for a distance.

:func:`draw_rig` returns a rig description (a dict in the format of ``rigs/reference.yaml``,
read unchanged by :func:`galvoscan_sim.rig_from_dict`) of a scanner as another workshop
might have built it: every imperfection of docs/design.md §5 drawn inside the range of
:data:`RANGES` (the one place where the ranges and their reasons are written), the geometry
(l, d, lens, principal point, G2 head placement, triangulation angle) varied as real builds
vary, and the whole set up for a working distance: the laser sheet at U2 = 0 crosses the
camera's optical axis at U1 = 0 there, and the lens focus, the laser line's focus, the
exposure and the laser power suit that distance.

Builds
    Each draw also picks a build: a camera sensor class (:data:`SENSORS`: size, pitch,
    full well, read noise, output formats, each from its data sheet), one of its bit
    depths, and a galvo head class (:data:`HEADS`: scan angle at the DAC's full scale,
    linearity, repeatability) for both heads. ``draw_rig(seed, build=...)`` fixes any of
    them; :func:`build_of` names a description's build. The range follows the head: G1's
    reach is its scan angle's.

Working distance
    The stand-off of the crossing from the scanner's front, the G1 exit (tilt) mirror:
    measured along the optical axis at U1 = 0 from the tilt mirror's axis, which sits at
    z = l + d in V0. In the world frame W (the nominal V0) the crossing is near
    ``(0, 0, l + d + distance)``; :func:`working_point` gives it exactly. (A distance
    from V0's origin, the virtual camera centre, cannot go down to 100 mm: the exit mirror
    alone is l + d = 79..132 mm in front of it.)

:func:`reset_for_distance` sets an existing rig up for another distance as a technician
would: the G2 head is slid along its rail to keep the rig's triangulation angle and the
sheet is re-aimed (by the stripe seen through the actual mirrors) to cross the axis there;
the lens is refocused (extension rings where needed), the laser line refocused, the laser
power and exposure adjusted. Its imperfections, lens, principal point and sensor stay.

:func:`check_rig` checks a description with the simulator (mirrors ray-traced as planes,
never the reconstruction model).

Optics assumed (thin lens, f-number fixed at f/8 as the reference's)
    A lens of focal length f focused at object distance s (along the folded optical path,
    i.e. V0's z) has image distance s' = f s / (s - f) and magnification m = f / (s - f);
    the pinhole focal length is fx = s' / pixel size. A build picks a lens that focuses at
    its distance on its own helicoid, m <= :data:`MAX_MAGNIFICATION_HELICOID` (1:4, a
    machine-vision C-mount lens' close-focus limit): a 54 mm lens does not focus at
    s = 200 mm. A re-set keeps the lens and adds extension rings, up to
    m <= :data:`MAX_MAGNIFICATION_RINGS`. The blur is diffraction (Gaussian sigma
    0.42 lambda N (1 + m)) combined with the residual defocus of focusing by eye, a
    per-rig number of pixels that a re-set keeps. Image signals scale as
    1 / (N (1 + m))^2 (image-side irradiance), the laser's irradiance as
    power / (distance x line thickness).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from galvoscan_common.stripe_layout import MAX_STRIPE_TILT as _STRIPE_MAX_TILT
from galvoscan_common.stripe_layout import StripeLayout

from .config import ConfigError, read_yaml_file
from .rig import RIG_DIR, Rig, load_rig_text, rig_from_dict
from .scene import load_scene_text
from .simulator import Simulator
from .spatial import invert_transform, transform_plane


@dataclass(frozen=True)
class Range:
    """A drawn quantity's range.

    Attributes
    ----------
    lo, hi : float
        Bounds in ``unit``. Symmetric imperfections are drawn in [lo, hi]; a magnitude
        range (``signed``) is drawn in [lo, hi] and given a random sign.
    unit : str
    reason : str
        Where the range comes from.
    signed : bool
    """

    lo: float
    hi: float
    unit: str
    reason: str
    signed: bool = False


_MIRROR = 'each of the four galvo mirrors (G1 pan, G1 tilt, G2 pan, G2 tilt)'

#: Every drawn quantity, its range and why: the one table of the family (see README).
RANGES: dict[str, Range] = {
    # ---------------------------------------------------------- Table 3 imperfections
    'zero_offset': Range(-3e-4, 3e-4, 'rad', f'{_MIRROR}: angle at 0 V minus nominal; '
                         'mirror clamped on the shaft to ~0.01-0.02 deg (sources 1, 5)'),
    'surface_offset': Range(1e-4, 2e-4, 'm', f'{_MIRROR}: coating in front of (or behind) '
                            'the shaft axis; mirrors glued near, not on, the axis '
                            '(source 2)', signed=True),
    'axis_tilt': Range(-5e-4, 5e-4, 'rad', f'{_MIRROR}: two angles of the shaft not square '
                       'to the head, ~0.02-0.03 deg machining tolerance (source 2)'),
    'camera_mount_rotation': Range(-1e-3, 1e-3, 'rad', 'each of three angles: camera not '
                                   'square to the pan axis, ~0.05 deg (source 2)'),
    'laser_fan_roll': Range(-4e-3, 4e-3, 'rad', 'hand-aligned line laser rolled about its '
                            'beam, up to ~0.23 deg (source 6)'),
    'laser_fan_offset': Range(-5e-4, 5e-4, 'm', 'fan plane off the G2 tilt axis by a '
                              'hand-aligned mount (source 6)'),
    'k1': Range(-1.2, 0.6, '1', 'radial distortion of the reference order (k1 -0.6): a '
                'C-mount telephoto distorts well under 0.1 % (source 4)'),
    'k2': Range(-8.0, 8.0, '1', 'radial distortion of the reference order (k2 4.0)'),
    'p1p2': Range(-5e-4, 5e-4, '1', 'decentring of the reference order (3e-4, -2e-4)'),
    'speckle_contrast': Range(0.3, 0.6, '1', '650 nm laser speckle on machined or painted '
                              'surfaces before blur (source 8)'),
    # ---------------------------------------------------------------- geometry
    'l': Range(0.75 * 0.08345, 1.25 * 0.08345, 'm', 'camera to G1 pan axis: the paper\'s '
               '83.45 mm within +-25 % (other heads, other brackets)'),
    'd': Range(0.75 * 0.02214, 1.25 * 0.02214, 'm', 'pan to tilt axis of a head: the '
               'paper\'s 22.14 mm within +-25 % (other galvo models); G1 and G2 drawn apart'),
    'focal_length': Range(0.035, 0.075, 'm', 'C-mount lenses from 35 to 75 mm, at most '
                          'the helicoid close-focus limit at the working distance'),
    'fy_over_fx': Range(1.0 - 5e-4, 1.0 + 5e-4, '1', 'square pixels; the paper\'s '
                        'calibration gave fy/fx = 0.9996'),
    'principal_point': Range(-10.0, 10.0, 'px', 'each of cx, cy from the sensor centre: '
                             'lens centring tolerance'),
    'distance': Range(0.1, 1.0, 'm', 'working distance (stand-off from the G1 exit '
                      'mirror): the paper\'s Fig. 13 spans 100 to 1000 mm'),
    'triangulation_angle': Range(math.radians(15.0), math.radians(35.0), 'rad',
                                 'camera axis to laser ray at the crossing: below 15 deg '
                                 'depth resolution suffers, above 35 deg shadows grow'),
    'g2_lateral': Range(-0.03, 0.03, 'm', 'G2 tilt mirror off the camera\'s vertical plane '
                        '(x in V0): bracket placement'),
    'g2_depth': Range(-0.03, 0.03, 'm', 'G2 tilt mirror in front of / behind V0\'s origin '
                      '(z in V0): bracket placement'),
    'g2_roll': Range(-0.02, 0.02, 'rad', 'G2 head turned about the optical axis; the '
                     'paper\'s n = (0.99, 0.02, -0.0004) is ~1.2 deg off x'),
    # --------------------------------------------------- set-up for the distance
    'focus_blur': Range(0.3, 0.7, 'px', 'residual defocus (Gaussian sigma) of focusing by '
                        'eye on the live image; the reference has ~0.6 px'),
    'line_divergence': Range(6e-4, 1.2e-3, 'm/m', 'laser line thickness (1/e^2) per metre '
                             'of throw when focused there; the reference is 0.6 mm at 0.72 m'),
    'peak_fraction': Range(0.8, 1.1, '1', 'stripe peak on a white target at the working '
                           'distance over full well, as set with power and exposure; the '
                           'reference is 1.0 (white surfaces saturate slightly)'),
    'room_light': Range(0.5, 2.0, '1', 'room light relative to the reference lab'),
}


@dataclass(frozen=True)
class SensorClass:
    """A camera sensor a build may choose, as its data sheet gives it.

    Attributes
    ----------
    width, height : int
        Pixels read [px].
    pixel_size : float
        Pixel pitch [m].
    full_well : float
        Saturation capacity [e-].
    read_noise : Range
        Temporal dark noise [e-] over units and camera electronics.
    bit_depths : tuple of int
        Output formats the camera offers (Mono8/10/12/16) [bit].
    black_level_8bit : float
        Dark offset at 8 bits [DN]; scaled with the bit depth (the same electrons).
    reason : str
        Data-sheet source.
    """

    width: int
    height: int
    pixel_size: float
    full_well: float
    read_noise: Range
    bit_depths: tuple
    black_level_8bit: float
    reason: str


#: Sensor classes of fast (about 300 to 800 fps) machine-vision cameras. Mono16 of a
#: 12-bit ADC carries 12-bit codes MSB-aligned; the simulator quantises to 16 bits
#: instead, which differs by the 12-bit step's 0.29 DN12 rms (~1.5 e- on IMX287), below
#: every class' read noise.
SENSORS: dict[str, SensorClass] = {
    # Sony IMX287LLR (1/2.9", 0.4 MP, Pregius global shutter, 12-bit ADC, 522 fps full
    # frame): the reference rig's sensor. EMVA 1288 data sheets of IMX287 cameras (Basler
    # acA720-520um, FLIR BFS-U3-04S2M): saturation capacity ~22-23 ke-, temporal dark
    # noise ~8-14 e- depending on the camera (source 8).
    'IMX287': SensorClass(720, 540, 6.9e-6, 22000.0,
                          Range(8.0, 14.0, 'e-', 'IMX287 cameras\' EMVA 1288 sheets'),
                          (8, 10, 12, 16), 2.0, 'Sony IMX287LLR data sheet; EMVA 1288 '
                          'sheets of acA720-520um / BFS-U3-04S2M'),
    # Sony IMX273LLR (1/2.9", 1.6 MP 1440 x 1080, 3.45 um Pregius, 12-bit ADC, ~276 fps
    # full frame at 8/10 bit): the same sensor area as the IMX287 at a quarter of the
    # pixel area; read at full frame (a region of interest for 500 fps would halve the
    # field's height, too short for the calibration sphere's views), so its scans run at
    # up to ~276 fps. EMVA 1288 sheets of IMX273 cameras (Basler acA1440-220um, FLIR
    # BFS-U3-16S2M): saturation capacity ~10.5 ke-, temporal dark noise ~2-3 e-.
    'IMX273': SensorClass(1440, 1080, 3.45e-6, 10500.0,
                          Range(2.0, 3.0, 'e-', 'IMX273 cameras\' EMVA 1288 sheets'),
                          (8, 10, 12, 16), 2.0, 'Sony IMX273LLR data sheet; EMVA 1288 '
                          'sheets of acA1440-220um / BFS-U3-16S2M'),
    # onsemi PYTHON 300 (NOIP1SN0300A: 640 x 480 VGA, 4.8 um global shutter pixel, 10-bit
    # ADC, 815 fps): full well ~10 ke-, temporal noise < 9 e- in global shutter mode by the
    # data sheet; camera units measure ~9-16 e-.
    'PYTHON300': SensorClass(640, 480, 4.8e-6, 10000.0,
                             Range(9.0, 16.0, 'e-', 'PYTHON 300/500 data sheet and cameras'),
                             (8, 10), 2.0, 'onsemi PYTHON 300 data sheet (NOIP1SN0300A)'),
    # onsemi PYTHON 500 (NOIP1SN0500A: 800 x 600 SVGA, the same 4.8 um pixel, 10-bit ADC,
    # 545 fps, e.g. Basler acA800-510um).
    'PYTHON500': SensorClass(800, 600, 4.8e-6, 10000.0,
                             Range(9.0, 16.0, 'e-', 'PYTHON 300/500 data sheet and cameras'),
                             (8, 10), 2.0, 'onsemi PYTHON 500 data sheet (NOIP1SN0500A)'),
}


@dataclass(frozen=True)
class HeadClass:
    """A galvo head a build may choose (both heads of a rig are the same model).

    Attributes
    ----------
    max_angle : float
        Mechanical angle at the DAC's full scale (+-10 V) [rad]: the gain times 10 V.
    gain_error, nonlinearity, jitter : Range
        Per mirror: servo scale error [1]; c2 and c3 on U/10 V each [rad] from the
        linearity spec over the full span; per-frame angle noise [rad] up to the
        repeatability spec.
    reason : str
        Data-sheet source.
    """

    max_angle: float
    gain_error: Range
    nonlinearity: Range
    jitter: Range
    reason: str


def _head(max_deg: float, linearity: float, repeatability: float, scale_error: float,
          reason: str) -> HeadClass:
    """A head class from its data sheet: +-max_deg mechanical at +-10 V, linearity (e.g.
    0.999) over the whole span, repeatability [rad], scale (gain) error [1]. The drawn
    nonlinearity coefficients are a third of the linearity spec's angle each (the TSH8310's
    99.9 % over 40 deg gives +-0.25 mrad), the jitter half to all of the repeatability."""
    span = math.radians(2.0 * max_deg)
    nl = (1.0 - linearity) * span / 2.8
    return HeadClass(math.radians(max_deg),
                     Range(-scale_error, scale_error, '1', f'{_MIRROR}: servo scale error'),
                     Range(-nl, nl, 'rad', f'{_MIRROR}: c2 and c3 on U/10 V each; linearity '
                           f'{linearity:.1%} over {2 * max_deg:g} deg'),
                     Range(0.5 * repeatability, repeatability, 'rad',
                           f'{_MIRROR}: per-frame angle noise up to the repeatability'),
                     reason)


#: Galvo head classes: scan angle (the DAC's +-10 V full scale), linearity, repeatability.
HEADS: dict[str, HeadClass] = {
    # Thorlabs GVS011/GVS012-class small-beam head: +-12.5 deg mechanical (input scaled
    # 0.8 V/deg: +-10 V full range), linearity 99.9 %, repeatability 15 urad (GVS series
    # specifications).
    'GVS011': _head(12.5, 0.999, 15e-6, 5e-3, 'Thorlabs GVS011/012 specifications'),
    # Sunny Technology TSH8310-class head (the reference rig's head, docs/design.md §5):
    # +-20 deg mechanical at +-10 V, linearity 99.9 % over 40 deg, repeatability 8 urad,
    # scale error < 0.5 %.
    'TSH8310': _head(20.0, 0.999, 8e-6, 5e-3, 'TSH8310 data sheet (sources 1, 5)'),
    # Wide-angle moving-magnet head class: +-25 deg mechanical, the top of the rated
    # excursion of wide-angle heads (e.g. the ScannerMAX Saturn series), linearity 99.9 %,
    # repeatability 8 urad (makers' specifications).
    'WIDE25': _head(25.0, 0.999, 8e-6, 5e-3, 'wide-angle head class specifications '
                    '(e.g. ScannerMAX Saturn series)'),
}
#: Where the laser (the G2 head) sits, seen from the camera, as the turn of the whole G2
#: placement about the optical axis [rad] from the paper's layout (below). Light-section
#: heads are built all four ways: below (the paper's), above (a head hung from a gantry, the
#: same triangulation mirrored: the stripe still along the rows, moving the other way) and
#: beside, left or right (a layout common in line-scan and robot-mounted sensors: the sheet
#: vertical, the stripe along the image columns, G2 sweeping it sideways and G1's pan
#: moving the view across it). The triangulation angle, baseline and bracket offsets of
#: :data:`RANGES` are drawn the same way for every side, in the turned frame.
LASER_SIDES: dict[str, float] = {'below': 0.0, 'left': math.pi / 2, 'above': math.pi,
                                 'right': -math.pi / 2}
#: The reference rig's build: what :func:`build_of` calls it.
REFERENCE_BUILD = {'sensor': 'IMX287', 'bit_depth': 8, 'head': 'TSH8310', 'laser': 'below'}

#: Close-focus limit of a lens on its own helicoid (1:4): what a build may choose.
MAX_MAGNIFICATION_HELICOID = 0.25
#: Close-focus limit with extension rings: what a re-set may use.
MAX_MAGNIFICATION_RINGS = 1.0
F_NUMBER = 8.0               # [1] every rig's aperture, as the reference's "f/8"
WAVELENGTH = 650e-9          # [m]
MIN_BASELINE = 0.05          # [m] G2 tilt mirror at least this far below the camera axis
EXPOSURE_RANGE = (5e-5, 2e-3)   # [s] laser frames: at most one 500 fps frame
POWER_RANGE = (0.05, 2.0)    # [1] laser power relative to the reference laser's
NOMINAL_EXPOSURE = 5e-4      # [s] the exposure a technician starts from
#: The reference rig's design point the radiometry is scaled from.
_REF = {'peak_rate': 4.84e7, 'reference_distance': 0.65, 'line_width': 6e-4,
        'magnification': 0.0827, 'ambient_rate': 1.8e6, 'calibration_exposure': 0.01,
        'pixel_size': 6.9e-6, 'full_well': 22000.0}
#: Usable stripe widths (Gaussian sigma in the image) [px]: at least the PSF's order; at
#: most 10 px, a FWHM of 23.5 px inside the stripe extractor's 30 px limit.
STRIPE_SIGMA_PX = (0.5, 10.0)
#: Largest angle of the stripe to the nearer of the image rows and columns at the working
#: point [rad]: the chain's (``galvoscan_common.stripe_layout``, where the reason is
#: written). The family's head roll and fan roll keep its stripes within ~1.4 deg.
MAX_STRIPE_TILT = _STRIPE_MAX_TILT
#: Tolerance of the sheet/axis crossing against the asked distance [m].
CROSSING_TOLERANCE = 1e-3
_MAX_ATTEMPTS = 25


@dataclass(frozen=True)
class Setup:
    """What stays of a rig's build when it is re-set for a distance.

    Attributes
    ----------
    focal_length : float
        Lens focal length [m].
    triangulation_angle : float
        [rad], in V0's y-z plane.
    g2_lateral, g2_depth, g2_roll : float
        G2 tilt mirror x, z in V0 [m] and head roll about V0's z [rad].
    focus_blur : float
        Residual defocus sigma [px].
    line_divergence : float
        Laser line thickness per metre of throw [1].
    peak_fraction : float
        Stripe peak on a white target at the working distance over full well [1].
    laser_side : float
        Turn of the G2 placement about the optical axis (:data:`LASER_SIDES`) [rad];
        ``triangulation_angle``, ``g2_lateral`` and ``g2_roll`` are taken in the turned frame.
    """

    focal_length: float
    triangulation_angle: float
    g2_lateral: float
    g2_depth: float
    g2_roll: float
    focus_blur: float
    line_divergence: float
    peak_fraction: float
    laser_side: float = 0.0


@lru_cache(maxsize=1)
def _reference() -> dict:
    return read_yaml_file(RIG_DIR / 'reference.yaml')


def _template() -> dict:
    """A fresh copy of the reference description, the layout every drawn rig shares."""
    return copy.deepcopy(_reference())


def check_distance(distance) -> float:
    """A working distance [m] in the family's range, as float.

    Raises
    ------
    ValueError
        Not a finite number, a value that looks like millimetres, or out of range.
    """
    try:
        z = float(distance)
    except (TypeError, ValueError):
        raise ValueError(f'distance: expected a number of metres, got {distance!r}') \
            from None
    r = RANGES['distance']
    if not math.isfinite(z) or z <= 0.0:
        raise ValueError(f'distance: expected a positive number of metres, got {distance!r}')
    if z >= 10.0 * r.hi:
        raise ValueError(f'distance: {z:g} looks like millimetres; give metres '
                         f'(e.g. {z / 1000:g})')
    if not r.lo - 1e-12 <= z <= r.hi + 1e-12:
        raise ValueError(f'distance: expected {r.lo:g} to {r.hi:g} m, got {z:g}')
    return z


# ------------------------------------------------------------------ optics
def _magnification(f: float, s: float) -> float:
    return f / (s - f)


def _diffraction_px(m: float, pixel: float) -> float:
    """Gaussian sigma of the diffraction blur at f/8, working f-number N (1 + m) [px]."""
    return 0.42 * WAVELENGTH * F_NUMBER * (1.0 + m) / pixel


def _aperture_gain(m: float) -> float:
    """Image-side irradiance relative to the reference design, 1 / (N (1 + m))^2."""
    return ((1.0 + _REF['magnification']) / (1.0 + m)) ** 2


def _pixel_gain(pixel: float) -> float:
    """A pixel's signal at a given image irradiance relative to the reference's: its area
    (the fill factor and quantum efficiency of the classes taken as the reference's)."""
    return (pixel / _REF['pixel_size']) ** 2


# ---------------------------------------------------------------- geometry
def _g1_offset(data: dict) -> np.ndarray:
    """V0's nominal origin in G, (0, d, -(l + d)) [m]: W (nominal V0) = G minus this."""
    l, d = data['g1']['l'], data['g1']['d']
    return np.array([0.0, d, -(l + d)])


def _place_g2(data: dict, setup: Setup, z_cross: float, aim: float) -> None:
    """Write the G2 pose: tilt mirror point on its rail, head turned by ``aim`` about x."""
    d2 = data['g2']['d']
    y_b = (z_cross - setup.g2_depth) * math.tan(setup.triangulation_angle)
    side = Rotation.from_rotvec([0.0, 0.0, setup.laser_side])
    p_W = side.apply([setup.g2_lateral, y_b, setup.g2_depth])
    R = (side * Rotation.from_rotvec([0.0, 0.0, setup.g2_roll])
         * Rotation.from_rotvec([aim, 0.0, 0.0]))
    t = p_W + _g1_offset(data) - R.apply([0.0, d2, 0.0])
    data['g2']['pose_in_g1'] = {'translation': [float(v) for v in t],
                                'rotation_vector': [float(v) for v in R.as_rotvec()]}


def _crossing_V0(rig: Rig) -> float:
    """z in the actual V0 where the actual sheet at U2 = 0 crosses V0's optical axis [m]."""
    th = rig.mirror_angles(rig.applied_voltages(np.zeros(4)))
    sheet = rig.laser_sheet_G(th[2], th[3])
    pi = transform_plane(invert_transform(rig.G_T_V0), sheet.plane)
    if abs(pi[2]) < 1e-9:
        return math.inf
    return float(-pi[3] / pi[2])


def _aim_sheet(data: dict, setup: Setup, z_cross: float) -> None:
    """Re-aim the G2 head (about its tilt axis) until the actual sheet crosses the actual
    optical axis at ``z_cross`` in V0: what a technician does by the stripe in the image."""
    _place_g2(data, setup, z_cross, 0.0)
    base = rig_from_dict(data, '<rig family>')
    pivot = base.G_T_G2 @ np.array([0.0, data['g2']['d'], 0.0, 1.0])

    def miss(aim):
        R = (Rotation.from_rotvec([0.0, 0.0, setup.laser_side + setup.g2_roll])
             * Rotation.from_rotvec([aim, 0.0, 0.0])).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = pivot[:3] - R @ np.array([0.0, data['g2']['d'], 0.0])
        return _crossing_V0(replace(base, G_T_G2=T)) - z_cross

    y_b = (z_cross - setup.g2_depth) * math.tan(setup.triangulation_angle)
    a0 = math.atan2(y_b, z_cross - setup.g2_depth)
    a1 = a0 + 1e-3
    f0, f1 = miss(a0), miss(a1)
    for _ in range(30):
        if abs(f1) < 1e-8 or f1 == f0:
            break
        a0, a1, f0 = a1, a1 - f1 * (a1 - a0) / (f1 - f0), f1
        f1 = miss(a1)
    _place_g2(data, setup, z_cross, a1)


# ---------------------------------------------------------------- set-up
def _apply_setup(data: dict, distance: float, setup: Setup, max_magnification: float,
                 room_light: float) -> dict:
    """Set a rig description up for ``distance`` [m] (stand-off) with a build's ``setup``.

    Writes the intrinsics (focus), the G2 placement and aim, the laser's line width, the
    radiometry (peak rate, exposure), the blur and the room light's signal.
    """
    cam, g1, las = data['camera'], data['g1'], data['laser']
    s = g1['l'] + g1['d'] + distance
    f = setup.focal_length
    if not f < s:
        raise ValueError(f'distance: the {f * 1e3:.0f} mm lens cannot focus at {s:.3f} m')
    m = _magnification(f, s)
    if m > max_magnification + 1e-12:
        raise ValueError(f'distance: the {f * 1e3:.0f} mm lens cannot focus at {s:.3f} m '
                         f'(magnification {m:.2f} > {max_magnification:g})')
    ratio = cam['fy'] / cam['fx']
    cam['fx'] = f * (1.0 + m) / cam['pixel_size']          # image distance s' / pixel
    cam['fy'] = cam['fx'] * ratio
    img = data['imperfections']['image']
    if float(img['psf_sigma']) > 0.0:          # 0: a rig without blur (ideal) keeps none
        img['psf_sigma'] = float(math.hypot(_diffraction_px(m, cam['pixel_size']),
                                            setup.focus_blur))
    _aim_sheet(data, setup, s)
    # laser: focused at the crossing, power and exposure for the wanted peak
    rig = rig_from_dict(data, '<rig family>')
    th = rig.mirror_angles(rig.applied_voltages(np.zeros(4)))
    src = rig.laser_sheet_G(th[2], th[3]).source
    cross_G = rig.G_T_V0 @ np.array([0.0, 0.0, s, 1.0])
    throw = float(np.linalg.norm(cross_G[:3] - src))
    width = setup.line_divergence * throw
    rate = (_REF['peak_rate'] * (_REF['reference_distance'] / throw)
            * (_REF['line_width'] / width) * _aperture_gain(m)
            * _pixel_gain(cam['pixel_size']))                         # at power 1
    wanted = setup.peak_fraction * cam['full_well']
    exposure = NOMINAL_EXPOSURE
    power = min(max(wanted / (rate * exposure), POWER_RANGE[0]), POWER_RANGE[1])
    exposure = min(max(wanted / (rate * power), EXPOSURE_RANGE[0]), EXPOSURE_RANGE[1])
    las['line_width'] = float(width)
    las['reference_distance'] = float(throw)
    las['peak_rate'] = float(rate * power)
    cam['exposure'] = float(exposure)
    # room light: its signal scales with the aperture and the pixel area; board frames
    # keep the reference's ~80 % of full well on white (~200 DN at 8 bits)
    ambient = _REF['ambient_rate'] * room_light * _aperture_gain(m) * _pixel_gain(
        cam['pixel_size'])
    data['illumination']['ambient_rate'] = float(ambient)
    cam['calibration_exposure'] = float(min(max(
        _REF['calibration_exposure'] * _REF['ambient_rate'] / ambient
        * cam['full_well'] / _REF['full_well'], 1e-3), 0.05))
    return data


def _draw_setup(rng: np.random.Generator, s: float) -> Setup:
    """A build's lens, G2 placement and set-up habits for object distance ``s`` [m]."""
    def u(key):
        r = RANGES[key]
        return float(rng.uniform(r.lo, r.hi))

    fr = RANGES['focal_length']
    f_max = min(fr.hi, s * MAX_MAGNIFICATION_HELICOID / (1.0 + MAX_MAGNIFICATION_HELICOID))
    if f_max < fr.lo:
        raise ValueError(f'no lens of {fr.lo * 1e3:.0f} mm or more focuses at {s:.3f} m')
    focal = float(rng.uniform(fr.lo, f_max))
    depth = u('g2_depth')
    ar = RANGES['triangulation_angle']
    a_lo = max(ar.lo, math.atan(MIN_BASELINE / (s - depth)))
    angle = float(rng.uniform(a_lo, ar.hi))
    return Setup(focal, angle, u('g2_lateral'), depth, u('g2_roll'), u('focus_blur'),
                 u('line_divergence'), u('peak_fraction'))


def _draw_imperfections(rng: np.random.Generator, imp: dict, sensor: SensorClass,
                        head: HeadClass) -> None:
    """Every Table 3 source drawn from :data:`RANGES` and the build's sensor and head
    classes into an ``imperfections`` section."""
    ranges = {**RANGES, 'gain_error': head.gain_error, 'nonlinearity': head.nonlinearity,
              'jitter': head.jitter, 'read_noise': sensor.read_noise}

    def u(key, n=None):
        r = ranges[key]
        x = rng.uniform(r.lo, r.hi, n)
        if r.signed:
            x = x * rng.choice([-1.0, 1.0], n)
        return [float(v) for v in x] if n else float(x)

    k1, k2 = u('k1'), u('k2')
    p1, p2 = u('p1p2', 2)
    imp['lens_distortion'] = [k1, k2, p1, p2, 0.0]
    imp['camera_mount_rotation'] = u('camera_mount_rotation', 3)
    imp['laser_fan_roll'] = u('laser_fan_roll')
    imp['laser_fan_offset'] = u('laser_fan_offset')
    for key in ('g1_pan', 'g1_tilt', 'g2_pan', 'g2_tilt'):
        imp[key] = {'zero_offset': u('zero_offset'), 'gain_error': u('gain_error'),
                    'nonlinearity': u('nonlinearity', 2), 'jitter': u('jitter'),
                    'surface_offset': u('surface_offset'), 'axis_tilt': u('axis_tilt', 2)}
    img = imp['image']
    img['read_noise'] = u('read_noise')
    img['speckle_contrast'] = u('speckle_contrast')


def _draw_build(rng: np.random.Generator, build: dict) -> dict:
    """The build's kind: sensor class, bit depth, head class, laser side; ``build``'s given
    ones kept."""
    depth = build.get('bit_depth')
    sensor = build.get('sensor') or str(rng.choice(
        [n for n in sorted(SENSORS) if depth is None or depth in SENSORS[n].bit_depths]))
    depth = build.get('bit_depth') or int(rng.choice(SENSORS[sensor].bit_depths))
    head = build.get('head') or str(rng.choice(sorted(HEADS)))
    laser = build.get('laser') or str(rng.choice(list(LASER_SIDES)))
    return {'sensor': sensor, 'bit_depth': int(depth), 'head': head, 'laser': laser}


def side_words(side: str) -> str:
    """Where a :data:`LASER_SIDES` side puts the laser, in words."""
    return {'below': 'below the camera', 'above': 'above the camera',
            'left': 'left of the camera (beside it)',
            'right': 'right of the camera (beside it)'}[side]


def _nearest_side(turn: float) -> str:
    """The :data:`LASER_SIDES` name nearest to a G2 placement's turn about the optical axis."""
    return min(LASER_SIDES, key=lambda k: abs(math.remainder(turn - LASER_SIDES[k],
                                                             2.0 * math.pi)))


def _apply_build(data: dict, kind: dict) -> None:
    """Write the sensor (size, pitch, full well, format, black level) and the heads' gains."""
    sensor, head = SENSORS[kind['sensor']], HEADS[kind['head']]
    cam = data['camera']
    cam.update(width=sensor.width, height=sensor.height, pixel_size=sensor.pixel_size,
               full_well=sensor.full_well, bit_depth=kind['bit_depth'],
               black_level=sensor.black_level_8bit * 2.0 ** (kind['bit_depth'] - 8))
    gain = head.max_angle / float(data['dac']['full_scale'])
    for sec in ('g1', 'g2'):
        for axis in ('pan', 'tilt'):
            data[sec][axis]['gain'] = float(gain)


def check_build(build) -> dict:
    """A build request (``sensor``, ``bit_depth``, ``head``, ``laser``, each optional) checked.

    Raises
    ------
    ValueError
        Not a dict, an unknown key or class, or a bit depth the sensor does not offer.
    """
    if build is None:
        return {}
    if not isinstance(build, dict):
        raise ValueError(f'build: expected a dict of sensor, bit_depth, head, laser, got '
                         f'{build!r}')
    unknown = set(build) - {'sensor', 'bit_depth', 'head', 'laser'}
    if unknown:
        raise ValueError(f'build: unknown key(s) {sorted(unknown)}; known: sensor, '
                         'bit_depth, head, laser')
    if build.get('laser') is not None and build['laser'] not in LASER_SIDES:
        raise ValueError(f"build: laser {build['laser']!r} is not one of "
                         f"{', '.join(LASER_SIDES)}")
    if build.get('sensor') is not None and build['sensor'] not in SENSORS:
        raise ValueError(f"build: sensor {build['sensor']!r} is not one of "
                         f"{', '.join(sorted(SENSORS))}")
    if build.get('head') is not None and build['head'] not in HEADS:
        raise ValueError(f"build: head {build['head']!r} is not one of "
                         f"{', '.join(sorted(HEADS))}")
    depth = build.get('bit_depth')
    if depth is not None:
        offered = (SENSORS[build['sensor']].bit_depths if build.get('sensor')
                   else sorted({d for c in SENSORS.values() for d in c.bit_depths}))
        if isinstance(depth, bool) or depth not in offered:
            raise ValueError(f'build: bit_depth {depth!r} is not one of '
                             f'{", ".join(map(str, offered))}')
    return {k: v for k, v in build.items() if v is not None}


def build_of(rig: dict) -> dict:
    """The kind of a rig description's build: ``sensor`` and ``head`` class names (or
    ``'other'`` for a camera or head outside the classes), ``bit_depth``, ``laser`` (the
    :data:`LASER_SIDES` name nearest to the G2 placement's turn about the optical axis)."""
    cam = rig['camera']
    sensor = next((name for name, c in SENSORS.items()
                   if (c.width, c.height) == (cam['width'], cam['height'])
                   and math.isclose(c.pixel_size, float(cam['pixel_size']), rel_tol=1e-6)),
                  'other')
    gain = float(rig['g1']['pan']['gain']) * float(rig['dac']['full_scale'])
    head = next((name for name, h in HEADS.items()
                 if math.isclose(h.max_angle, gain, rel_tol=1e-6)), 'other')
    r = rig_from_dict(copy.deepcopy(rig), '<rig>')
    laser = _nearest_side(math.atan2(r.G_T_G2[1, 0], r.G_T_G2[0, 0]))
    return {'sensor': sensor, 'bit_depth': int(cam['bit_depth']), 'head': head,
            'laser': laser}


def _draw_once(rng: np.random.Generator, distance: float | None,
               kind: dict) -> tuple[dict, float]:
    """One draw: (rig description of build ``kind`` set up for its distance, the distance
    [m]); unchecked."""
    data = _template()
    _apply_build(data, kind)
    z = check_distance(distance) if distance is not None else float(
        rng.uniform(RANGES['distance'].lo, RANGES['distance'].hi))
    _draw_imperfections(rng, data['imperfections'], SENSORS[kind['sensor']],
                        HEADS[kind['head']])
    g1, g2, cam = data['g1'], data['g2'], data['camera']
    g1['l'] = float(rng.uniform(RANGES['l'].lo, RANGES['l'].hi))
    g1['d'] = float(rng.uniform(RANGES['d'].lo, RANGES['d'].hi))
    g2['d'] = float(rng.uniform(RANGES['d'].lo, RANGES['d'].hi))
    data['world']['pose_g1'] = {'translation': [0.0, -g1['d'], g1['l'] + g1['d']],
                                'rotation_vector': [0.0, 0.0, 0.0]}
    pp = RANGES['principal_point']
    cam['cx'] = float((cam['width'] - 1) / 2.0 + rng.uniform(pp.lo, pp.hi))
    cam['cy'] = float((cam['height'] - 1) / 2.0 + rng.uniform(pp.lo, pp.hi))
    cam['fx'] = 1.0                     # fy / fx drawn here; _apply_setup sets fx by focus
    cam['fy'] = float(rng.uniform(RANGES['fy_over_fx'].lo, RANGES['fy_over_fx'].hi))
    for key in ('peak_rate', 'reference_distance', 'line_width'):   # YAML 1.1 '4.84e7'
        data['laser'][key] = float(data['laser'][key])
    setup = replace(_draw_setup(rng, g1['l'] + g1['d'] + z),
                    laser_side=LASER_SIDES[kind['laser']])
    room = float(rng.uniform(RANGES['room_light'].lo, RANGES['room_light'].hi))
    return _apply_setup(data, z, setup, MAX_MAGNIFICATION_HELICOID, room), z


def draw_rig(seed: int, distance: float | None = None, build: dict | None = None) -> dict:
    """A random, physically valid rig description of the family.

    Parameters
    ----------
    seed : int
        Same seed (and distance, build), same rig.
    distance : float, optional
        Working distance [m], stand-off from the G1 exit mirror, in [0.1, 1.0]; drawn
        from that range when not given.
    build : dict, optional
        Any of ``sensor`` (a :data:`SENSORS` name), ``bit_depth`` (one the sensor offers)
        and ``head`` (a :data:`HEADS` name) to fix; the others are drawn (uniformly over
        the classes and the sensor's formats).

    Returns
    -------
    dict
        A rig description in the format of ``rigs/reference.yaml`` that passes
        :func:`check_rig` (a draw that does not is redrawn from a derived seed).

    Raises
    ------
    ValueError
        A bad seed or distance.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f'seed: expected a non-negative integer, got {seed!r}')
    if distance is not None:
        distance = check_distance(distance)
    build = check_build(build)
    # the build's kind from a stream of its own: a seed's geometry and imperfections do not
    # depend on which classes are drawn
    kind = _draw_build(np.random.default_rng([int(seed), 0xB1D]), build)
    problems = []
    for attempt in range(_MAX_ATTEMPTS):
        rng = np.random.default_rng([int(seed), attempt, 0x51A6])
        data, z = _draw_once(rng, distance, kind)
        data['name'] = f'random-{int(seed)}'
        data['description'] = (
            f'Drawn by galvoscan_sim.rig_family.draw_rig(seed={int(seed)}'
            + (f', distance={distance!r}' if distance is not None else '')
            + (f', build={build!r}' if build else '')
            + f') (attempt {attempt}): working distance {z:.4f} m from the G1 exit mirror; '
            f"{kind['sensor']} sensor at {kind['bit_depth']} bits, {kind['head']}-class galvo "
            f"heads, the laser {side_words(kind['laser'])}; every imperfection inside "
            'galvoscan_sim.rig_family.RANGES and the classes\' ranges.')
        problems = check_rig(data, z)
        if not problems:
            return data
    raise RuntimeError(f'seed {seed}: no valid rig in {_MAX_ATTEMPTS} draws; last problems: '
                       + '; '.join(problems))


def _infer_setup(data: dict) -> tuple[Setup, float]:
    """The build (:class:`Setup`) and room light of a description, from its values."""
    rig = rig_from_dict(data, '<rig family>')
    cam, g1 = data['camera'], data['g1']
    s = _crossing_V0(rig)
    if not math.isfinite(s) or s <= g1['l'] + g1['d']:
        raise ValueError('rig: its laser sheet does not cross the optical axis in front of '
                         'the scanner, so the distance it is set up for is unknown')
    s_img = float(cam['fx']) * float(cam['pixel_size'])
    f = s * s_img / (s + s_img)
    m = _magnification(f, s)
    diff = _diffraction_px(m, float(cam['pixel_size']))
    psf = float(data['imperfections']['image']['psf_sigma'])
    blur = math.sqrt(max(psf * psf - diff * diff, 0.0))
    G_T_G2 = rig.G_T_G2
    p_W = (G_T_G2 @ np.array([0.0, float(data['g2']['d']), 0.0, 1.0]))[:3] - _g1_offset(data)
    turn = math.atan2(G_T_G2[1, 0], G_T_G2[0, 0])
    side = LASER_SIDES[_nearest_side(turn)]
    roll = math.remainder(turn - side, 2.0 * math.pi)
    p_W = Rotation.from_rotvec([0.0, 0.0, -side]).apply(p_W)
    angle = math.atan2(p_W[1], s - p_W[2])
    th = rig.mirror_angles(rig.applied_voltages(np.zeros(4)))
    src = rig.laser_sheet_G(th[2], th[3]).source
    throw = float(np.linalg.norm((rig.G_T_V0 @ np.array([0.0, 0.0, s, 1.0]))[:3] - src))
    las = data['laser']
    peak = (float(las['peak_rate']) * float(las['reference_distance']) / throw
            * float(cam['exposure']) / float(cam['full_well']))
    room = float(data['illumination']['ambient_rate']) / (
        _REF['ambient_rate'] * _aperture_gain(m) * _pixel_gain(float(cam['pixel_size'])))
    setup = Setup(f, angle, float(p_W[0]), float(p_W[2]), roll, blur,
                  float(las['line_width']) / throw, peak, side)
    return setup, room


def reset_for_distance(rig: dict, distance: float) -> dict:
    """The same rig re-set for another working distance, as a technician would.

    The G2 head slides along its rail so that the triangulation angle stays, the sheet is
    re-aimed to cross the optical axis at ``distance``, the lens is refocused (extension
    rings up to magnification :data:`MAX_MAGNIFICATION_RINGS`), the laser line refocused,
    laser power and exposure set for the same stripe peak. Imperfections, lens, sensor,
    principal point and distortion stay as they are.

    Parameters
    ----------
    rig : dict
        A rig description (e.g. from :func:`draw_rig` or ``rigs/reference.yaml``); it is
        not modified.
    distance : float
        New working distance [m], stand-off from the G1 exit mirror, in [0.1, 1.0].

    Returns
    -------
    dict
        The re-set description.

    Raises
    ------
    ValueError
        A bad distance, or a rig whose set-up cannot be read from it.
    ConfigError
        ``rig`` is not a valid rig description.
    """
    z = check_distance(distance)
    data = copy.deepcopy(rig)
    rig_from_dict(data, '<rig>')                       # refuse a bad description first
    for sec, key in (('laser', 'peak_rate'), ('laser', 'reference_distance'),
                     ('laser', 'line_width'), ('camera', 'fx'), ('camera', 'fy'),
                     ('illumination', 'ambient_rate')):
        data[sec][key] = float(data[sec][key])
    setup, room = _infer_setup(data)
    out = _apply_setup(data, z, setup, MAX_MAGNIFICATION_RINGS, room)
    out['description'] = (f'{rig.get("description", "")} Re-set by '
                          f'galvoscan_sim.rig_family.reset_for_distance for a working '
                          f'distance of {z:.4f} m.').strip()
    return out


# ------------------------------------------------------------------ checks
def working_point(rig: dict | Rig) -> np.ndarray:
    """Where the actual sheet at U2 = 0 crosses the actual optical axis at U1 = 0.

    Returns
    -------
    ndarray, shape (3,), metres
        The point in the world frame W.
    """
    r = rig if isinstance(rig, Rig) else rig_from_dict(rig, '<rig>')
    s = _crossing_V0(r)
    return (r.W_T_V0 @ np.array([0.0, 0.0, s, 1.0]))[:3]


def g2_turned(data: dict, degrees: float) -> dict:
    """A rig description (``rigs/*.yaml`` as a dict) with its G2 head turned about the
    camera's optical axis (the actual V0's z) by ``degrees``: the laser moved round the
    camera, the sheet still crossing the axis where it did. ``data`` is left unchanged."""
    rig = load_rig_text(yaml.safe_dump(data))
    R = np.eye(4)
    R[:3, :3] = Rotation.from_rotvec([0.0, 0.0, math.radians(degrees)]).as_matrix()
    T = rig.G_T_V0 @ R @ invert_transform(rig.G_T_V0) @ rig.G_T_G2
    out = copy.deepcopy(data)
    out['g2']['pose_in_g1'] = {
        'translation': [float(v) for v in T[:3, 3]],
        'rotation_vector': [float(v) for v in Rotation.from_matrix(T[:3, :3]).as_rotvec()]}
    return out


def working_distance(rig: dict | Rig) -> float:
    """The working distance a rig is set up for: its crossing's stand-off [m]."""
    r = rig if isinstance(rig, Rig) else rig_from_dict(rig, '<rig>')
    return _crossing_V0(r) - (r.l + r.d)


def _central_ray(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """The camera's central ray at U1 = 0 traced off the actual G1 mirrors, in G: (origin
    on the exit mirror, unit direction)."""
    th = rig.mirror_angles(rig.applied_voltages(np.zeros(4)))
    o, d = rig.trace_camera_rays(np.zeros((1, 2)), th[0], th[1])
    return o[0], d[0]


def _check_crossing(rig: Rig, distance: float | None) -> list[str]:
    """The central ray meets the sheet (inside its fan) at the working distance."""
    o, d = _central_ray(rig)
    th = rig.mirror_angles(rig.applied_voltages(np.zeros(4)))
    sheet = rig.laser_sheet_G(th[2], th[3])
    denom = float(sheet.plane[:3] @ d)
    if abs(denom) < 1e-9:
        return ['the camera\'s central ray is parallel to the laser sheet']
    t = -float(sheet.plane[:3] @ o + sheet.plane[3]) / denom
    p = o + t * d
    out = []
    if distance is not None and abs(t - distance) > CROSSING_TOLERANCE:
        out.append(f'the central ray meets the sheet {t * 1e3:.2f} mm from the exit mirror, '
                   f'not at the working distance {distance * 1e3:.2f} mm')
    r = RANGES['distance']
    if distance is None and not r.lo - CROSSING_TOLERANCE <= t <= r.hi + CROSSING_TOLERANCE:
        out.append(f'the central ray meets the sheet {t * 1e3:.2f} mm from the exit mirror, '
                   f'outside {r.lo * 1e3:g}..{r.hi * 1e3:g} mm')
    if np.any(sheet.edge_normals @ (p - sheet.source) < 0.0):
        out.append('the crossing lies outside the laser fan')
    return out


def _front_faces(origins, directions, planes, points: int) -> bool:
    """Whether rays meet each mirror plane on its reflective side (the normals point away
    from the light), the first ``points`` of them also in front of the ray (t > 0)."""
    o, d = np.array(origins, dtype=np.float64), np.array(directions, dtype=np.float64)
    for n, c in planes:
        dn = d @ n
        if np.any(dn <= 0.0):
            return False
        t = (c - o @ n) / dn
        if np.any(t[:points] <= 0.0):
            return False
        o = o + t[:, None] * d
        d = d - 2.0 * dn[:, None] * n
    return True


def _check_mirrors(rig: Rig, steps: int = 5) -> list[str]:
    """Over the voltage range used (G1 pan and tilt and G2 tilt over the DAC's full scale,
    G2 pan at 0 V as every scan and the model use it): the laser's central beam meets both
    G2 mirror faces and the whole fan arrives on their reflective sides (the mirrors are
    planes: their extent is not modelled), and the camera's central and corner rays meet
    both G1 mirror faces."""
    fs = rig.dac.full_scale
    volts = np.linspace(-fs, fs, steps)
    L = rig.laser
    half, e = 0.5 * L.fan_angle, L.spread_direction
    fan = np.array([L.direction, math.cos(half) * L.direction + math.sin(half) * e,
                    math.cos(half) * L.direction - math.sin(half) * e])
    cam = rig.camera
    corners = cam.pixel_to_normalized(np.array(
        [[cam.cx, cam.cy], [0, 0], [cam.width - 1, 0], [0, cam.height - 1],
         [cam.width - 1, cam.height - 1]], dtype=np.float64))
    R, c = rig.G_T_C[:3, :3], rig.G_T_C[:3, 3]
    rays = np.column_stack([corners, np.ones(len(corners))]) @ R.T
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    out = []
    for u in volts:
        th = rig.mirror_angles(rig.applied_voltages([0.0, 0.0, 0.0, u]))
        if not _front_faces(np.tile(L.position, (3, 1)), fan,
                            [rig.g2.pan.plane(th[2]), rig.g2.tilt.plane(th[3])], 1):
            out.append(f'the laser fan misses a G2 mirror face at U2_tilt = {u:g} V')
        for u_tilt in volts:
            th = rig.mirror_angles(rig.applied_voltages([u, u_tilt, 0.0, 0.0]))
            if not _front_faces(np.tile(c, (len(rays), 1)), rays,
                                rig.g1_planes(th[0], th[1]), len(rays)):
                out.append(f'the camera\'s rays miss a G1 mirror face at U1 = ({u:g}, '
                           f'{u_tilt:g}) V')
    return out[:4]


def _plane_scene(point_W: np.ndarray, albedo: float = 0.5):
    return load_scene_text(
        'format_version: 1\nname: check_plane\nobjects:\n  - type: plane\n    name: plane\n'
        f'    pose: {{translation: [0.0, 0.0, {float(point_W[2])!r}], '
        'rotation_vector: [0.0, 0.0, 0.0]}\n'
        f'    albedo: {albedo}\n', '<check plane>')


def stripe_profile(image: np.ndarray, column: int, half_columns: int = 60,
                   white_level: int = 255):
    """Peak, background, noise and width of the stripe in the columns around ``column``.

    Parameters
    ----------
    image : ndarray, shape (height, width), uint8 or uint16 [DN]
    column : int
    half_columns : int
    white_level : int
        The camera's top code [DN] (2**bit_depth - 1).

    Returns
    -------
    dict
        ``peak_dn`` (median over the columns of the brightest pixel), ``row`` (median row
        of it) [px], ``background_dn``, ``noise_dn`` (robust std away from the stripe),
        ``width_px`` (median Gaussian sigma of the background-subtracted profile),
        ``saturated`` (fraction of columns whose peak is at the top code).
    """
    h, w = image.shape
    cols = np.arange(max(column - half_columns, 0), min(column + half_columns + 1, w))
    block = image[:, cols].astype(np.float64)
    rows = np.argmax(block, axis=0)
    peaks = block[rows, np.arange(len(cols))]
    far = np.abs(np.arange(h)[:, None] - rows[None, :]) > 30
    bg = float(np.median(block[far]))
    noise = float(1.4826 * np.median(np.abs(block[far] - bg)))
    widths = []
    for j, r in enumerate(rows):
        lo, hi = max(r - 15, 0), min(r + 16, h)
        prof = np.clip(block[lo:hi, j] - bg, 0.0, None)
        if prof.sum() > 0:
            y = np.arange(lo, hi)
            mu = float(prof @ y / prof.sum())
            widths.append(math.sqrt(float(prof @ (y - mu) ** 2 / prof.sum())))
    return {'peak_dn': float(np.median(peaks)), 'row': float(np.median(rows)),
            'background_dn': bg, 'noise_dn': max(noise, 0.5),
            'width_px': float(np.median(widths)) if widths else math.nan,
            'saturated': float(np.mean(peaks >= white_level))}


def stripe_layout(rig: Rig) -> StripeLayout:
    """The stripe's layout at the working point (:meth:`Rig.stripe_layout`)."""
    return rig.stripe_layout()


def stripe_tilt(rig: Rig) -> float:
    """Angle of the stripe to the nearer of the image rows and columns at the working point,
    in [0, pi/4] [rad]."""
    return stripe_layout(rig).tilt


def _check_stripe_direction(rig: Rig) -> list[str]:
    """The stripe runs along the image rows or columns, as the chain takes it
    (:data:`MAX_STRIPE_TILT`)."""
    why = stripe_layout(rig).refusal()
    return [why] if why else []


def _check_stripe(rig: Rig) -> list[str]:
    """The stripe on a grey plane at the working point: in the image, through the centre,
    in focus, with a usable peak."""
    point = working_point(rig)
    sim = Simulator(rig, _plane_scene(point), seed=0)
    frame = sim.render(np.zeros(4), frame_index=0)
    cam = rig.camera
    truth = frame.truth.stripe
    out = []
    vertical = stripe_layout(rig).orientation == 'vertical'
    # along the stripe: columns (u) for a stripe along the rows, rows (v) along the columns
    along, across = (truth.v, truth.u) if vertical else (truth.u, truth.v)
    n_along, c_along, c_across = ((cam.height, cam.cy, cam.cx) if vertical
                                  else (cam.width, cam.cx, cam.cy))
    lines = 'rows' if vertical else 'columns'
    covered = len(np.unique(np.round(along)))
    if covered < 0.9 * n_along:
        return [f'the stripe covers {covered} of {n_along} {lines}']
    near = np.abs(along - c_along) <= 1.0
    if not np.any(near) or np.min(np.abs(across[near] - c_across)) > 3.0:
        out.append('the stripe does not cross the image centre')
    white = rig.image.white_level
    image = frame.image.T if vertical else frame.image
    prof = stripe_profile(image, int(round(c_along)), white_level=white)
    signal = prof['peak_dn'] - prof['background_dn']
    if signal < max(10.0 * prof['noise_dn'], 20.0 * white / 255.0):   # 20 DN at 8 bits
        out.append(f'stripe peak {signal:.0f} DN over background is not well above the '
                   f'noise ({prof["noise_dn"]:.1f} DN)')
    if prof['saturated'] > 0.5:
        out.append(f'the stripe saturates in {prof["saturated"]:.0%} of the columns on a '
                   'grey target')
    if rig.image.psf_sigma > 1.5:
        out.append(f'out of focus: blur sigma {rig.image.psf_sigma:.2f} px > 1.5 px')
    lo, hi = STRIPE_SIGMA_PX
    if not lo <= prof['width_px'] <= hi:
        out.append(f'stripe width sigma {prof["width_px"]:.2f} px outside {lo:g}..{hi:g} px')
    return out


def check_rig(rig: dict, distance: float | None = None) -> list[str]:
    """Physical validity of a rig description, checked with the simulator.

    Parameters
    ----------
    rig : dict
        A rig description (not modified).
    distance : float, optional
        The working distance [m] it should be set up for; without it the crossing must
        lie in the family's distance range.

    Returns
    -------
    list of str
        The problems found; empty for a valid rig.
    """
    try:
        r = rig_from_dict(copy.deepcopy(rig), '<rig>')
    except ConfigError as exc:
        return [str(exc)]
    direction = _check_stripe_direction(r)
    out = direction + _check_crossing(r, distance) + _check_mirrors(r)
    if not out:
        out += _check_stripe(r)
    return out
