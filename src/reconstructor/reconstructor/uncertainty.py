"""How well a calibration knows where a point is: its parameters' covariance carried to
reconstructed points over the scanner's range (no rclpy).

- :func:`parameter_covariance`: the joint covariance of every calibrated parameter, put
  together from the covariances the calibration stages stored (``stages.<stage>.covariance``)
  in the order they ran. Each stage stores the covariance its own data give (``matrix``,
  over ``names``) and, where it held parameters of earlier stages fixed, the sensitivity of
  its estimates to them (``inputs``, ``sensitivity`` = d estimate / d input). A stage's
  estimate ``p = p0 + S (q - q0) + e`` then has ``Cov(p) = C + S Cov(q) S.T`` and
  ``Cov(p, x) = S Cov(q, x)`` for every earlier parameter x: the linearised joint covariance
  of the whole chain, correlations across stages included (e.g. the principal point and
  G1's θ0, which stand for each other in a narrow field). A parameter a later stage
  estimates again replaces the earlier estimate.
- :func:`point_uncertainty_map`: the 1-sigma error of reconstructed points that this
  covariance predicts, per G1 view over the range (pan x tilt), with each stage's share.

Parameters are named by their dotted key in ``RigModel.to_dict()``, with ``[j]`` for an
element of a list: ``intrinsics.cx``, ``intrinsics.dist[1]``, ``g1_pan.poly[0]``,
``laser_plane_v0[3]``, ``physical.camera_rotation[2]``. SI units throughout.

- :func:`frame_noise`: the galvos' per-frame noise (their repeatability) that the stages
  measured; the map carries it to the points beside the calibration's share, and the two
  together are a point's uncertainty.

What the prediction leaves out, by construction: the stripe extractor's noise on the
points themselves, a joint-correction table's own uncertainty, and any error the model
cannot represent (a model error is no random variable). Comparing the prediction with the
error measured against the simulator's truth is how the last one shows (``galvoscan
evaluate``'s ``uncertainty_ratio`` and ``uncertainty_ratio_calibration``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from reconstructor.model import RigModel, laser_plane_v0, predict_pixels, triangulate_batch, v0_T_v

_NAME = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*)(?:\[(\d+)\])?$')


# ----------------------------------------------------------------------------- names
def _split(name: str) -> tuple[list[str], int | None]:
    m = _NAME.match(name) if isinstance(name, str) else None
    if m is None:
        raise ValueError(f'parameter name {name!r}: expected a dotted model key with an '
                         f'optional [index], e.g. intrinsics.dist[1]')
    return m.group(1).split('.'), (None if m.group(2) is None else int(m.group(2)))


def _slot(data: dict, name: str):
    """(container, key) of a parameter in a model dict; lists grow with zeros (poly)."""
    keys, index = _split(name)
    node = data
    for k in keys[:-1]:
        if not isinstance(node, dict) or k not in node:
            raise ValueError(f'parameter {name}: the model has no {k!r}')
        node = node[k]
    last = keys[-1]
    if not isinstance(node, dict) or last not in node:
        raise ValueError(f'parameter {name}: the model has no {last!r}')
    if index is None:
        if isinstance(node[last], (list, tuple, dict)):
            raise ValueError(f'parameter {name}: a list or section, give an element [j]')
        return node, last
    value = node[last]
    if not isinstance(value, list):
        raise ValueError(f'parameter {name}: {last!r} is not a list')
    if index >= len(value):
        if last != 'poly' or index > 8:
            raise ValueError(f'parameter {name}: {last!r} has {len(value)} elements')
        value.extend([0.0] * (index + 1 - len(value)))
    return value, index


def parameter_value(model: RigModel, name: str) -> float:
    """The value of one named parameter of ``model`` (module docstring: names)."""
    container, key = _slot(model.to_dict(), name)
    return float(container[key])


def with_parameters(model: RigModel, changes: dict) -> RigModel:
    """``model`` with named parameters moved by the given amounts (``{name: delta}``); the
    joint correction, if any, stays. Raises ValueError naming a parameter the model lacks or
    a change it refuses (e.g. beyond a physical deviation's plausible size)."""
    data = model.to_dict()
    for name, delta in changes.items():
        container, key = _slot(data, name)
        container[key] = float(container[key]) + float(delta)
    return RigModel.from_dict(data, correction=model.correction)


def intrinsics_warp(before, after) -> np.ndarray:
    """How points that a camera measures (a target's pose by PnP, then rays onto it) move in
    its frame when its pinhole intrinsics change from ``before`` to ``after``: a 4 x 4 affine
    map, to first order and for a narrow field.

    A principal point shift turns the measured scene about the camera's centre (a shift of
    cx by du: about y by -du/fx); a longer focal length puts a target of known size further
    away (depth scaled by the mean relative change of fx and fy) with its pixels unchanged
    (lateral positions scaled by depth / focal length). Distortion is left out (its effect on
    a stripe near the image centre is second order).
    """
    ex = after.fx / before.fx - 1.0
    ey = after.fy / before.fy - 1.0
    s = 0.5 * (ex + ey)
    ay = -(after.cx - before.cx) / before.fx
    ax = (after.cy - before.cy) / before.fy
    R = np.array([[1.0, 0.0, ay], [0.0, 1.0, -ax], [-ay, ax, 1.0]])
    W = np.eye(4)
    W[:3, :3] = R @ np.diag([1.0 + s - ex, 1.0 + s - ey, 1.0 + s])
    return W


#: The stages whose parameters make up the camera (intrinsics and G1): what measures the
#: points of the laser stages.
CAMERA_STAGES = ('intrinsics', 'dynamic_camera')


def camera_inputs(calibration) -> dict:
    """``{name: 1-sigma}`` of the camera's parameters (:data:`CAMERA_STAGES`, held ones
    included) in the calibration's covariance so far: the inputs whose effect a laser stage
    measures (:func:`remeasured_sensitivity`)."""
    pc = parameter_covariance(calibration)
    return {n: s for n, s in pc.std().items()
            if s > 0 and pc.stage_of[n].split(' ')[0] in CAMERA_STAGES}


def remeasured_sensitivity(model: RigModel, groups, inputs: dict, estimate) -> np.ndarray:
    """d estimate / d input of a stage whose data are points the camera model measured.

    Parameters
    ----------
    model : RigModel
        The model the points were measured with.
    groups : sequence of (points_v0 (n, 3), u1_pan, u1_tilt)
        The measured points, with the G1 voltages they were seen at.
    inputs : dict of str to float
        Parameters (names as this module's) and the step of each (1 sigma).
    estimate : callable
        ``estimate(list of points_v0 arrays, same order) -> 1-D array``: the stage's estimate
        from the points.

    Returns
    -------
    ndarray, shape (p, len(inputs))
        Central differences: each input moved by +-step, every group's points moved as the
        moved camera would have measured them (the same pixels: the moved ``V0_T_V`` at
        their voltages and :func:`intrinsics_warp`), the estimate repeated.
    """
    base = [np.linalg.inv(v0_T_v(model, float(a), float(b))) for _, a, b in groups]
    cols = []
    for name, h in inputs.items():
        out = []
        for sign in (1.0, -1.0):
            moved = with_parameters(model, {name: sign * h})
            W = intrinsics_warp(model.intrinsics, moved.intrinsics)
            pts = []
            for (p, a, b), inv in zip(groups, base, strict=True):
                M = v0_T_v(moved, float(a), float(b)) @ W @ inv
                pts.append(p @ M[:3, :3].T + M[:3, 3])
            out.append(np.asarray(estimate(pts), dtype=np.float64))
        cols.append((out[0] - out[1]) / (2.0 * h))
    return np.array(cols).T if cols else np.zeros((0, 0))


# ----------------------------------------------------------------------------- covariance
@dataclass
class ParameterCovariance:
    """The joint covariance of a calibration's parameters.

    Attributes
    ----------
    names : list of str
    matrix : ndarray, shape (p, p), SI units
    stage_of : dict of str to str
        Which stage estimated each parameter.
    notes : list of str
        What was left out and why (stages without a covariance, unknown inputs).
    """

    names: list
    matrix: np.ndarray
    stage_of: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def std(self) -> dict:
        return {n: float(math.sqrt(max(v, 0.0)))
                for n, v in zip(self.names, np.diag(self.matrix), strict=True)}


def covariance_record(names, matrix, inputs=(), sensitivity=None, priors=None) -> dict:
    """A stage's covariance as stored in ``stages.<stage>.covariance``, checked.

    Parameters
    ----------
    names : sequence of str
        The parameters, p of them.
    matrix : array_like, shape (p, p)
        Their covariance from the stage's own data, SI units; symmetric, finite, diagonal
        >= 0.
    inputs : sequence of str
        Parameters of earlier stages the stage held fixed, q of them.
    sensitivity : array_like, shape (p, q), optional
        d estimate / d input at the solution.
    priors : dict of str to float, optional
        Inputs no stage estimates, which the stage held at their value with this 1-sigma
        tolerance (e.g. a mirror deviation the views could not determine).

    Raises
    ------
    ValueError
        A malformed record, naming what is wrong.
    """
    names = [str(n) for n in names]
    for n in names + list(inputs):
        _split(n)
    if len(set(names)) != len(names):
        raise ValueError(f'covariance: parameter names repeat: {names}')
    M = np.asarray(matrix, dtype=np.float64)
    p = len(names)
    if M.shape != (p, p):
        raise ValueError(f'covariance: matrix must be {p} x {p} for {p} names, got {M.shape}')
    if not np.isfinite(M).all():
        raise ValueError('covariance: matrix must be finite (hold an undetermined parameter '
                         'instead of giving it an infinite variance)')
    scale = np.sqrt(np.abs(np.outer(np.diag(M), np.diag(M)))) + 1e-300
    if np.any(np.diag(M) < 0) or np.max(np.abs(M - M.T) / scale) > 1e-6:
        raise ValueError('covariance: matrix must be symmetric with a diagonal >= 0')
    inputs = [str(n) for n in inputs]
    S = np.zeros((p, 0)) if sensitivity is None else np.asarray(sensitivity, dtype=np.float64)
    if S.shape != (p, len(inputs)) or not np.isfinite(S).all():
        raise ValueError(f'covariance: sensitivity must be finite, {p} x {len(inputs)}, '
                         f'got {S.shape}')
    if set(inputs) & set(names):
        raise ValueError('covariance: a parameter cannot be its own input')
    priors = {str(k): float(v) for k, v in (priors or {}).items()}
    bad = [k for k, v in priors.items() if k not in inputs or not (math.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(f'covariance: priors must be inputs with a finite tolerance > 0: {bad}')
    out = {'names': names, 'matrix': (0.5 * (M + M.T)).tolist()}
    if inputs:
        out['inputs'] = inputs
        out['sensitivity'] = S.tolist()
    if priors:
        out['priors'] = priors
    return out


def parameter_covariance(calibration) -> ParameterCovariance:
    """The joint covariance of a calibration (module docstring), stage by stage.

    Stages are taken in the order they were computed (their ``created`` stamps, file order
    among equal stamps). A stage without a stored covariance contributes nothing and is
    named in ``notes``; so is an input no earlier stage estimated (taken as exact).

    Raises
    ------
    ValueError
        A stored covariance that is malformed (the stage named).
    """
    order = sorted(enumerate((calibration.stages or {}).items()),
                   key=lambda t: (str((t[1][1] or {}).get('created', '')), t[0]))
    names: list[str] = []
    stage_of: dict[str, str] = {}
    notes: list[str] = []
    C = np.zeros((0, 0))
    for _, (stage, record) in order:
        rec = (record or {}).get('covariance') if isinstance(record, dict) else None
        if not rec:
            if isinstance(record, dict) and record.get('updated'):
                notes.append(f'{stage}: no covariance stored; its parameters count as exact')
            continue
        try:
            checked = covariance_record(rec.get('names', []), rec.get('matrix', []),
                                        rec.get('inputs', ()), rec.get('sensitivity'),
                                        rec.get('priors'))
        except (ValueError, TypeError, AttributeError) as exc:
            raise ValueError(f'stages.{stage}.covariance: {exc}') from exc
        for n, tol in checked.get('priors', {}).items():  # held: the tolerance is the prior
            if n not in names:
                C = np.block([[C, np.zeros((len(names), 1))],
                              [np.zeros((1, len(names))), np.array([[tol ** 2]])]])
                names.append(n)
                stage_of[n] = f'{stage} (held)'
        own = checked['names']
        M = np.array(checked['matrix'], dtype=np.float64).reshape(len(own), len(own))
        inputs = checked.get('inputs', [])
        S = np.array(checked.get('sensitivity', np.zeros((len(own), 0))),
                     dtype=np.float64).reshape(len(own), len(inputs))
        # drop earlier estimates this stage replaces
        keep = [i for i, n in enumerate(names) if n not in own]
        names = [names[i] for i in keep]
        C = C[np.ix_(keep, keep)]
        cols = []
        for j, n in enumerate(inputs):
            if n in names:
                cols.append((j, names.index(n)))
            else:
                notes.append(f'{stage}: input {n} has no covariance; taken as exact')
        # B maps the existing parameters to this stage's estimates
        B = np.zeros((len(own), len(names)))
        for j, i in cols:
            B[:, i] += S[:, j]
        cross = B @ C                      # Cov(new, old)
        new_block = M + B @ C @ B.T
        C = np.block([[C, cross.T], [cross, new_block]])
        names += own
        stage_of.update({n: stage for n in own})
    C = 0.5 * (C + C.T)
    return ParameterCovariance(names, C, stage_of, notes)


# ----------------------------------------------------------------------------- frame noise
#: The galvo channels whose per-frame noise the stages measure: channel -> (stage, residual
#: key, index in the (U1 pan, U1 tilt, U2 pan, U2 tilt) voltages).
FRAME_NOISE_KEYS = {'u1_pan': ('dynamic_camera', 'frame_noise_u1_pan_V', 0),
                    'u1_tilt': ('dynamic_camera', 'frame_noise_u1_tilt_V', 1),
                    'u2_tilt': ('laser_axis', 'frame_noise_u2_tilt_V', 3)}


def frame_noise(calibration) -> dict:
    """``{channel: 1 sigma [V]}`` of the galvos' per-frame noise, as the calibration's stages
    measured it (:data:`FRAME_NOISE_KEYS`; the dynamic camera's views for G1, the laser
    bundle's for G2). A channel no stage measured is absent."""
    out = {}
    for channel, (stage, key, _) in FRAME_NOISE_KEYS.items():
        rec = calibration.stages.get(stage)
        value = (rec.get('residuals') or {}).get(key) if isinstance(rec, dict) else None
        if isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value < 0.1:
            out[channel] = float(value)
    return out


# ----------------------------------------------------------------------------- map
@dataclass
class UncertaintyMap:
    """Predicted 1-sigma error of reconstructed points over G1's range.

    Attributes
    ----------
    u_pan, u_tilt : ndarray, shape (n,), volts
        The grid's axes (``sigma_m[i, j]`` is at tilt ``u_tilt[i]``, pan ``u_pan[j]``).
    sigma_m : ndarray, shape (n, n)
        RMS over the view's stripe points of the 3-D 1-sigma error (sqrt of the trace of
        the point's covariance) [m]; NaN where no stripe point could be formed.
    sigma_depth_m : ndarray, shape (n, n)
        The same along each point's viewing ray [m].
    by_stage : dict of str to ndarray, shape (n, n)
        Each stage's parameters' share of the variance (``J_k (C J.T)_k`` summed over its
        parameters; the shares add up to 1 and one may be negative where stages
        compensate each other).
    rms_m : float
        RMS of ``sigma_m`` over the views that have points.
    depth_m : float
        Depth (V0 z) of the wall the stripes lie on.
    parameters : list of str
        The parameters that entered.
    points : int
    absolute_rms_m : float
        RMS 3-D 1-sigma over all points without removing the rigid motion: how well V0
        itself is placed (a frame convention that no measurement of shape sees and that a
        cell calibration absorbs). ``sigma_m`` and ``rms_m`` are the shape's share: per
        parameter the best rigid motion of all the map's points together is removed first.
    modes_effective : float
        How many independent parameter combinations the map's mean square shape error is
        spread over, ``(sum l)**2 / sum l**2`` of its variance per mode ``l``. One
        calibration's error is one draw: with one dominant mode its RMS over the map is
        ``|z| rms_m`` (z normal), below half the prediction 38 % of the time.
    within_2x_probability : float
        The probability that one calibration drawn from this covariance measures an RMS
        shape error within a factor of 2 of ``rms_m`` (from ``modes_effective``'s
        variances, by 20,000 seeded draws).
    frame_sigma_m : ndarray, shape (n, n)
        RMS over the view's points of the 3-D 1-sigma error that the galvos' per-frame noise
        adds (``frame_noise``; independent from frame to frame) [m]; zero without it.
    frame_rms_m : float
        RMS of ``frame_sigma_m`` over the views that have points.
    frame_noise_V : dict
        The per-frame noise that entered, ``{channel: 1 sigma [V]}``.
    total_within_2x_probability : float
        As ``within_2x_probability``, for :attr:`total_rms_m` (the frame noise, spread
        over every view independently, taken as its mean).
    """

    u_pan: np.ndarray
    u_tilt: np.ndarray
    sigma_m: np.ndarray
    sigma_depth_m: np.ndarray
    by_stage: dict
    rms_m: float
    depth_m: float
    parameters: list
    points: int
    absolute_rms_m: float = math.nan
    modes_effective: float = math.nan
    within_2x_probability: float = math.nan
    frame_sigma_m: np.ndarray | None = None
    frame_rms_m: float = 0.0
    frame_noise_V: dict = field(default_factory=dict)
    total_within_2x_probability: float = math.nan

    @property
    def total_sigma_m(self) -> np.ndarray:
        """A point's 1-sigma error per view: the calibration's share and the frame noise's."""
        frame = self.frame_sigma_m if self.frame_sigma_m is not None else 0.0
        return np.sqrt(self.sigma_m ** 2 + np.square(frame))

    @property
    def total_rms_m(self) -> float:
        """RMS over the map of :attr:`total_sigma_m`: what a point measured anywhere in the
        range is uncertain by."""
        return math.sqrt(self.rms_m ** 2 + self.frame_rms_m ** 2)

    def worst(self) -> tuple[float, float, float]:
        """(sigma [m], pan [V], tilt [V]) of the view with the largest predicted error."""
        s = np.where(np.isfinite(self.sigma_m), self.sigma_m, -1.0)
        i, j = np.unravel_index(int(np.argmax(s)), s.shape)
        return float(self.sigma_m[i, j]), float(self.u_pan[j]), float(self.u_tilt[i])

    def to_dict(self) -> dict:
        def arr(a):
            return [[None if not math.isfinite(v) else float(v) for v in row] for row in a]

        return {'u_pan_V': self.u_pan.tolist(), 'u_tilt_V': self.u_tilt.tolist(),
                'sigma_m': arr(self.sigma_m), 'sigma_depth_m': arr(self.sigma_depth_m),
                'by_stage': {k: arr(v) for k, v in self.by_stage.items()},
                'rms_m': self.rms_m, 'depth_m': self.depth_m,
                'parameters': list(self.parameters), 'points': self.points,
                'absolute_rms_m': self.absolute_rms_m,
                'modes_effective': self.modes_effective,
                'within_2x_probability': self.within_2x_probability,
                'frame_sigma_m': arr(self.frame_sigma_m if self.frame_sigma_m is not None
                                     else np.zeros_like(self.sigma_m)),
                'frame_rms_m': self.frame_rms_m, 'frame_noise_V': dict(self.frame_noise_V),
                'total_rms_m': self.total_rms_m,
                'total_within_2x_probability': self.total_within_2x_probability}


def stripe_samples(model: RigModel, u_pan, u_tilt, depth: float, *, samples: int = 15,
                   margin_px: float = 10.0):
    """Pixels of a stripe on a wall at V0 depth ``depth`` in one G1 view, as ``model`` sees it.

    The laser is set (with the model) to cross the view's centre on the wall; points along
    the stripe are projected into the image and those inside it (``margin_px`` in) kept.

    Returns
    -------
    (uv (k, 2), points (k, 3) in V0, u2_tilt) or None where the wall or the laser is out of
    reach.
    """
    from reconstructor.planning import aim_laser

    T = v0_T_v(model, u_pan, u_tilt)
    ray, o = T[:3, 2], T[:3, 3]
    if not abs(ray[2]) > 1e-9 or not (depth - o[2]) / ray[2] > 0:
        return None
    distance = (depth - o[2]) / ray[2]
    centre = o + distance * ray
    try:
        u2 = aim_laser(model, u_pan, u_tilt, distance)
    except ValueError:  # beyond G2's reach
        return None
    plane = np.asarray(laser_plane_v0(model, u2))
    direction = np.cross(plane[:3], [0.0, 0.0, 1.0])
    if not np.linalg.norm(direction) > 1e-9:
        return None
    direction /= np.linalg.norm(direction)
    intr = model.intrinsics
    half = 0.6 * depth * intr.width / intr.fx
    pts = centre + np.linspace(-half, half, samples)[:, None] * direction
    uv, ok = predict_pixels(model, pts, u_pan, u_tilt)
    ok &= ((uv[:, 0] > margin_px) & (uv[:, 0] < intr.width - margin_px)
           & (uv[:, 1] > margin_px) & (uv[:, 1] < intr.height - margin_px))
    if ok.sum() < 2:
        return None
    return uv[ok], pts[ok], u2


def _checked_frame_noise(frame_noise_v) -> dict:
    """``{channel: 1 sigma [V]}`` with the zero ones left out; ValueError on an unknown
    channel or a value that is not a finite number >= 0."""
    out = {}
    for channel, sd_v in (frame_noise_v or {}).items():
        ok = isinstance(sd_v, (int, float)) and math.isfinite(sd_v) and sd_v >= 0
        if channel not in FRAME_NOISE_KEYS or not ok:
            raise ValueError(f'frame_noise_v: unknown channel or bad value {channel}={sd_v}')
        if sd_v > 0:
            out[channel] = float(sd_v)
    return out


def point_uncertainty_map(model: RigModel, covariance: ParameterCovariance, *,
                          depth: float = 0.65, span: float = 8.0, n: int = 9,
                          samples: int = 15, frame_noise_v: dict | None = None
                          ) -> UncertaintyMap:
    """The 1-sigma error of reconstructed points that ``covariance`` predicts, over an n x n
    grid of G1 voltages within +-``span`` V, for stripes on a wall at V0 depth ``depth``.

    Each point's derivatives with respect to every parameter are central differences of its
    triangulation (the same pixel and voltages, the parameter moved by +-1 sigma); the
    point's covariance is ``J C J.T``. ``frame_noise_v`` (:func:`frame_noise`) adds, per
    view, what the galvos' per-frame noise does: the same pixels triangulated at voltages
    moved by +-1 sigma per channel, the channels independent.

    Raises
    ------
    ValueError
        Bad grid arguments, or a covariance naming a parameter the model lacks.
    """
    if not (math.isfinite(depth) and depth > 0):
        raise ValueError(f'depth: expected > 0 m, got {depth}')
    if not (math.isfinite(span) and 0 <= span <= 10.0):
        raise ValueError(f'span: expected 0..10 V, got {span}')
    if not (isinstance(n, int) and 1 <= n <= 41):
        raise ValueError(f'n: expected an integer 1..41, got {n}')
    frame_noise_v = _checked_frame_noise(frame_noise_v)
    grid = np.linspace(-span, span, n) if n > 1 else np.zeros(1)
    uv_all, fi, volts, rays, cell = [], [], [], [], []
    for i, ut in enumerate(grid):
        for j, up in enumerate(grid):
            s = stripe_samples(model, float(up), float(ut), depth, samples=samples)
            if s is None:
                continue
            uv, pts, u2 = s
            k = len(volts)
            volts.append([up, ut, 0.0, u2])
            uv_all.append(uv)
            fi.append(np.full(len(uv), k))
            T = v0_T_v(model, float(up), float(ut))
            d = pts - T[:3, 3]
            rays.append(d / np.linalg.norm(d, axis=1, keepdims=True))
            cell.append(np.full(len(uv), i * n + j))
    sigma = np.full((n, n), np.nan)
    sigma_d = np.full((n, n), np.nan)
    stages = sorted(set(covariance.stage_of.values()))
    by_stage = {s: np.full((n, n), np.nan) for s in stages}
    if not volts:
        return UncertaintyMap(grid, grid, sigma, sigma_d, by_stage, math.nan, depth,
                              list(covariance.names), 0)
    uv = np.concatenate(uv_all)
    fi = np.concatenate(fi)
    volts = np.array(volts)
    rays = np.concatenate(rays)
    cell = np.concatenate(cell)
    sd = np.sqrt(np.clip(np.diag(covariance.matrix), 0.0, None))
    J = np.zeros((len(uv), 3, len(covariance.names)))
    for k, (name, h) in enumerate(zip(covariance.names, sd, strict=True)):
        if not h > 0:
            continue
        plus = triangulate_batch(with_parameters(model, {name: h}), uv, fi, volts).p_v0
        minus = triangulate_batch(with_parameters(model, {name: -h}), uv, fi, volts).p_v0
        J[:, :, k] = (plus - minus) / (2.0 * h)
    C = covariance.matrix
    P0 = triangulate_batch(model, uv, fi, volts).p_v0
    var_frame = np.zeros(len(uv))
    for channel, sd_v in frame_noise_v.items():
        step = np.zeros(4)
        step[FRAME_NOISE_KEYS[channel][2]] = sd_v
        plus = triangulate_batch(model, uv, fi, volts + step).p_v0
        minus = triangulate_batch(model, uv, fi, volts - step).p_v0
        var_frame += np.sum(((plus - minus) / 2.0) ** 2, axis=1)
    frame_sigma = np.full((n, n), np.nan)
    J_shape = _without_rigid_motion(J, P0)
    var_abs = np.einsum('nik,kl,nil->n', J, C, J)
    cov_p = np.einsum('nik,kl,njl->nij', J_shape, C, J_shape)
    var3 = np.trace(cov_p, axis1=1, axis2=2)
    var_d = np.einsum('ni,nij,nj->n', rays, cov_p, rays)
    # each parameter's share of a point's variance: J_k . (C J.T)_k, summing to the total
    share = np.einsum('nik,kl,nil->nk', J_shape, C, J_shape)
    part = {}
    for s in stages:
        idx = [k for k, nm in enumerate(covariance.names) if covariance.stage_of.get(nm) == s]
        part[s] = share[:, idx].sum(axis=1)
    for c in np.unique(cell):
        sel = cell == c
        i, j = divmod(int(c), n)
        sigma[i, j] = math.sqrt(max(float(np.mean(var3[sel])), 0.0))
        sigma_d[i, j] = math.sqrt(max(float(np.mean(var_d[sel])), 0.0))
        frame_sigma[i, j] = math.sqrt(float(np.mean(var_frame[sel])))
        for s in stages:
            by_stage[s][i, j] = float(np.mean(part[s][sel]) / max(np.mean(var3[sel]), 1e-300))
    ok = np.isfinite(sigma)
    rms = float(np.sqrt(np.mean(sigma[ok] ** 2)))
    # every view weighs the same, as in rms: weight 1 / (views * its points) per point
    counts = np.bincount(cell, minlength=n * n)
    w = 1.0 / (int(ok.sum()) * counts[cell])
    A = np.einsum('n,nik,nil->kl', w, J_shape, J_shape)
    modes, p2 = error_modes(A, C)
    frame_rms = float(np.sqrt(np.mean(frame_sigma[ok] ** 2)))
    p2_total = error_modes(A, C, floor=frame_rms ** 2)[1] if frame_rms > 0 else p2
    return UncertaintyMap(grid, grid, sigma, sigma_d, by_stage, rms, depth,
                          list(covariance.names), int(len(uv)),
                          float(np.sqrt(np.mean(var_abs))), modes, p2, frame_sigma, frame_rms,
                          frame_noise_v, p2_total)


def prediction_check(predicted, measured, probabilities, factor: float = 2.0) -> dict:
    """How a set of predictions (one per calibration) compares with the errors measured.

    Parameters
    ----------
    predicted, measured : sequence of float
        Predicted RMS uncertainty and measured RMS error per calibration (same units).
    probabilities : sequence of float
        Each prediction's own probability of falling within ``factor``
        (:attr:`UncertaintyMap.within_2x_probability`).

    Returns
    -------
    dict
        ``within`` (count within ``factor``), ``within_expected`` and ``within_expected_sd``
        (what predictions with the right covariance would give: the sum of the
        probabilities, and its binomial spread) and ``pooled_ratio``
        (``sqrt(mean predicted**2 / mean measured**2)``: 1 when the covariance is right on
        average, whatever each rig's scatter).
    """
    rows = [(float(p), float(m), float(q)) for p, m, q in
            zip(predicted, measured, probabilities, strict=True)
            if math.isfinite(p) and math.isfinite(m) and m > 0]
    if not rows:
        return {'within': 0, 'within_expected': None, 'within_expected_sd': None,
                'pooled_ratio': None}
    p, m, q = (np.array(c) for c in zip(*rows, strict=True))
    ok = np.isfinite(q)
    return {'within': int(np.sum((p / m >= 1.0 / factor) & (p / m <= factor))),
            'within_expected': float(q[ok].sum()) if ok.all() else None,
            'within_expected_sd': float(np.sqrt(np.sum(q * (1 - q)))) if ok.all() else None,
            'pooled_ratio': float(np.sqrt(np.mean(p ** 2) / np.mean(m ** 2)))}


#: The predictions ``galvoscan evaluate`` checks against the simulator's truth: (prefix of
#: the summary's keys, what, predicted key, measured key, probability key) of its metrics.
PREDICTION_PAIRS = (
    ('', 'point error', 'predicted_uncertainty_mm', 'measured_shape_error_mm',
     'uncertainty_within_2x_probability'),
    ('calibration_', "calibration's part", 'predicted_calibration_uncertainty_mm',
     'measured_systematic_error_mm', 'uncertainty_calibration_within_2x_probability'),
)


def prediction_summary(rows, factor: float = 2.0) -> tuple[dict, list]:
    """:func:`prediction_check` of both :data:`PREDICTION_PAIRS` over calibrations' metrics.

    Parameters
    ----------
    rows : sequence of dict
        One per calibration, with ``galvoscan evaluate``'s uncertainty metrics (missing or
        NaN entries are left out).

    Returns
    -------
    (dict, list of str)
        Per pair, keys ``<prefix>measured``, ``within_2x``, ``within_2x_expected``,
        ``within_2x_expected_sd``, ``pooled_ratio``, ``within_2x_fraction`` and
        ``ratio_median`` / ``ratio_min`` / ``ratio_max``; and one line of text per pair.
    """
    out, lines = {}, []
    for prefix, what, pred, meas, prob in PREDICTION_PAIRS:
        both = [r for r in rows
                if all(isinstance(r.get(k), (int, float)) and math.isfinite(r[k])
                       for k in (pred, meas)) and r[meas] > 0]
        ratios = [r[pred] / r[meas] for r in both]
        check = prediction_check([r[pred] for r in both], [r[meas] for r in both],
                                 [r.get(prob, math.nan) for r in both], factor)
        nan = math.nan
        out.update({
            f'{prefix}measured': len(ratios), f'{prefix}within_2x': check['within'],
            f'{prefix}within_2x_expected': check['within_expected'],
            f'{prefix}within_2x_expected_sd': check['within_expected_sd'],
            f'{prefix}pooled_ratio': check['pooled_ratio'],
            f'{prefix}within_2x_fraction': check['within'] / len(ratios) if ratios else None,
            f'{prefix}ratio_median': float(np.median(ratios)) if ratios else None,
            f'{prefix}ratio_min': min(ratios, default=None),
            f'{prefix}ratio_max': max(ratios, default=None)})
        lines.append(
            f"{what}: predicted within {factor:g}x of measured on {check['within']} of "
            f"{len(ratios)} calibrations; a right prediction would give "
            f"{check['within_expected'] or nan:.1f} +- {check['within_expected_sd'] or nan:.1f}"
            f" (each one's error is one draw over few modes); pooled predicted / measured "
            f"{check['pooled_ratio'] or nan:.2f}")
    return out, lines


def error_modes(A: np.ndarray, C: np.ndarray, *, factor: float = 2.0,
                draws: int = 20000, floor: float = 0.0) -> tuple[float, float]:
    """How a mean square error ``e = d.T A d`` with parameter errors ``d ~ N(0, C)`` spreads.

    ``e`` is a sum of independent ``l_k z_k**2`` (``l`` the eigenvalues of ``L.T A L``,
    ``C = L L.T``), of mean ``sum l`` (the predicted mean square). ``floor`` is a mean
    square added to every draw (noise spread over so many independent terms that it hardly
    scatters: the frame noise over the map's views); the probability is then that of
    ``sqrt(e + floor)`` about ``sqrt(sum l + floor)``.

    Returns
    -------
    (float, float)
        The effective number of modes ``(sum l)**2 / sum l**2``, and the probability that
        ``sqrt(e)`` lies within ``factor`` of ``sqrt(sum l)`` (seeded draws: repeatable).
    """
    c, V = np.linalg.eigh(0.5 * (C + C.T))
    L = V * np.sqrt(np.clip(c, 0.0, None))
    lam = np.clip(np.linalg.eigvalsh(L.T @ A @ L), 0.0, None)
    total = float(lam.sum())
    if not total > 0.0:
        return math.nan, math.nan
    lam = lam[lam > 1e-9 * lam.max()]
    rng = np.random.default_rng(0)
    r = np.sqrt(((rng.standard_normal((draws, lam.size)) ** 2) @ lam + floor)
                / (total + floor))
    inside = (r >= 1.0 / factor) & (r <= factor)
    return float(total ** 2 / float(lam @ lam)), float(np.mean(inside))


def _without_rigid_motion(J: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Point derivatives (n, 3, p) with, per parameter, the best rigid motion of all the
    points together removed (to first order: ``w x p + t`` by least squares): what changes
    the shape of what is measured, not where V0 sits."""
    n = len(points)
    B = np.zeros((n, 3, 6))
    B[:, :, :3] = np.eye(3)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    # w x p = [[0, z, -y], [-z, 0, x], [y, -x, 0]] @ w
    B[:, 0, 4], B[:, 0, 5] = z, -y
    B[:, 1, 3], B[:, 1, 5] = -z, x
    B[:, 2, 3], B[:, 2, 4] = y, -x
    Bf = B.reshape(3 * n, 6)
    Jf = J.reshape(3 * n, -1)
    coef = np.linalg.lstsq(Bf, Jf, rcond=None)[0]
    return (Jf - Bf @ coef).reshape(J.shape)
