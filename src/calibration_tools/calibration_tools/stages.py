"""Data contract shared by every calibration stage (no rclpy).

A stage is a pure function ``run(views, calibration, **options) -> StageResult``:

- ``views`` are the captured frames (from bags recorded by the calibration node, from
  ``galvoscan calibrate`` on a bag directory, or straight from the simulator in tests);
- ``calibration`` is the current :class:`reconstructor.calibration_file.Calibration`
  (approximate values that earlier stages or nominal rig data provide);
- the result names the parameters it estimated and carries the residuals and the
  standard error of every estimated parameter (:func:`covariance_from_jacobian`). The
  caller merges ``result.updates`` into the model and the stage's record (residuals,
  ``standard_errors``, ...) into ``calibration.stages[stage]`` (:func:`apply_result`), then
  saves the file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

#: The rig's calibration chain, in order: each stage refines the model of the scanner itself.
STAGES = ('intrinsics', 'dynamic_camera', 'laser_plane', 'laser_axis', 'joint_correction')
#: Where the calibrated scanner sits in the robot cell (``cell_T_v0``): done once the rig is
#: calibrated and mounted, with a robot; not part of the rig's chain.
CELL_STAGE = 'cell_extrinsic'
#: Where the scanner sits on a robot's flange (``cell_T_v0`` with the flange as the cell
#: frame), by hand-eye calibration; like the cell stage, not part of the rig's chain.
HAND_EYE_STAGE = 'hand_eye'
#: The stages that measure the file's ``cell_T_v0``: each stores it under its own name in
#: ``StageResult.extra``, with its frame and standard errors.
MOUNTING_STAGES = (CELL_STAGE, HAND_EYE_STAGE)
#: Every stage the node and the offline command run.
KNOWN_STAGES = (*STAGES, *MOUNTING_STAGES)
#: Voltages closer than this are one and the same command (one board placement, one G1
#: node of a grid, one laser plane) [V].
VOLTAGE_TOL = 1e-3


@dataclass
class CaptureView:
    """One captured camera frame.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8 or uint16
    voltages : ndarray, shape (4,), volts
        (U1_pan, U1_tilt, U2_pan, U2_tilt) of the frame.
    laser_on : bool
    pose_index : int
        Which scene/board pose the frame belongs to (one bag per pose when captured live).
    stamp : float
        Middle of the exposure [s].
    """

    image: np.ndarray
    voltages: np.ndarray
    laser_on: bool = False
    pose_index: int = 0
    stamp: float = 0.0


@dataclass
class CaptureStep:
    """One scan of a capture plan.

    Attributes
    ----------
    pose_index : int
        Scene / target placement the frames belong to (``CaptureView.pose_index``).
    scene_yaml : str or None
        Simulator scene to set before the scan (None: keep the current scene). On real
        hardware the operator places the object described by ``note`` instead.
    voltages : ndarray, shape (n, 4), volts
        (U1_pan, U1_tilt, U2_pan, U2_tilt) of the n frames.
    laser_on : bool
        Laser frames (stripe) or laser-off frames (textured board under room light).
    frame_rate : float, Hz
    note : str
        What the step captures, for logs and the operator.
    """

    pose_index: int
    scene_yaml: str | None
    voltages: np.ndarray
    laser_on: bool
    frame_rate: float = 50.0
    note: str = ''

    def __post_init__(self):
        v = np.array(self.voltages, dtype=np.float64)
        if v.ndim == 1 and v.shape == (4,):
            v = v.reshape(1, 4)
        if v.ndim != 2 or v.shape[1] != 4 or v.shape[0] < 1:
            raise ValueError(f'voltages must have shape (n >= 1, 4), got {v.shape}')
        if not np.all(np.isfinite(v)) or np.abs(v).max() > 10.0:
            raise ValueError('voltages must be finite and within +-10 V')
        try:
            ok = not isinstance(self.pose_index, bool) and int(self.pose_index) == \
                self.pose_index and self.pose_index >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f'pose_index must be an integer >= 0, got {self.pose_index!r}')
        if isinstance(self.frame_rate, bool) or not isinstance(self.frame_rate, (int, float)) \
                or not (math.isfinite(self.frame_rate) and self.frame_rate > 0):
            raise ValueError(f'frame_rate must be > 0 Hz, got {self.frame_rate!r}')
        if self.scene_yaml is not None and not isinstance(self.scene_yaml, str):
            raise ValueError('scene_yaml must be a string or None')
        v.flags.writeable = False
        self.voltages = v
        self.pose_index = int(self.pose_index)
        self.laser_on = bool(self.laser_on)
        self.frame_rate = float(self.frame_rate)

    @property
    def frames(self) -> int:
        """Number of frames of the step."""
        return int(self.voltages.shape[0])

    def truncated(self, n: int) -> CaptureStep:
        """The same step with only its first ``n`` frames (n >= 1)."""
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ValueError(f'n must be an integer >= 1, got {n!r}')
        return dataclasses.replace(self, voltages=self.voltages[: int(n)].copy())


@dataclass
class StageResult:
    """What a stage estimated, how well, and from how much data.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`.
    updates : dict
        Model parameters to replace, keyed as in ``RigModel.to_dict()`` (nested dicts merge,
        e.g. ``{'l': 0.0834, 'g1_pan': {'k': 0.0349}}``), SI units.
    residuals : dict
        Named residual figures in SI units with the unit in the name
        (``reprojection_rms_px``, ``plane_rms_m``, ...).
    samples_used, samples_rejected : int
    rejected : list of str
        One line per rejected sample with the reason.
    extra : dict
        Stage-specific results to store in the calibration file beside the model
        (e.g. ``{'joint_correction': {...}}``).
    standard_errors : dict
        1-sigma standard error of each estimated parameter, keyed as ``updates`` (nested
        dicts; list-valued parameters such as ``intrinsics.dist`` as lists of the same
        length), in the same SI units. From the Jacobian at the stage's solution
        (:func:`covariance_from_jacobian`); a parameter the stage holds fixed or pins with
        a prior says so in ``extra`` and in its module's docstring. Stored in the
        calibration file as ``stages.<stage>.standard_errors`` (flat dotted keys).
    covariance : dict
        The full covariance behind ``standard_errors``, where the stage has it, as
        :func:`reconstructor.uncertainty.covariance_record` makes it: ``names`` (dotted keys
        of updated parameters, ``[j]`` for list elements), ``matrix`` from the stage's own
        data and, for parameters of earlier stages it held fixed, ``inputs`` and
        ``sensitivity`` (d estimate / d input). Stored as ``stages.<stage>.covariance``;
        :func:`reconstructor.uncertainty.parameter_covariance` joins the stages' records.
    """

    stage: str
    updates: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    samples_used: int = 0
    samples_rejected: int = 0
    rejected: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    standard_errors: dict = field(default_factory=dict)
    covariance: dict = field(default_factory=dict)


def covariance_from_jacobian(jac, residuals, *, n_params: int | None = None,
                             prior_sigma=None) -> tuple[np.ndarray, float]:
    """Covariance of least-squares parameters from the Jacobian at the solution.

    ``cov = inv(J.T @ J / s2 + diag(1 / prior_sigma**2))`` with ``s2 = sum(r**2) / (m - p)``,
    the residual variance of the data (the classical ``s2 * inv(J.T @ J)`` without priors).
    Parameters that the fit held fixed must not be columns of ``jac``.

    Parameters
    ----------
    jac : array_like, shape (m, p)
        Derivatives of the m data residuals with respect to the p free parameters (any
        units; the covariance comes out in the units of the columns).
    residuals : array_like, shape (m,)
        Data residuals at the solution (prior terms excluded).
    n_params : int, optional
        Number of parameters the fit estimated, for the degrees of freedom (default p).
    prior_sigma : array_like, shape (p,), optional
        1-sigma width of a Gaussian prior per parameter, in column units (``inf``: none).

    Returns
    -------
    cov : ndarray, shape (p, p)
        Covariance; rows of parameters the data and priors do not fix are ``inf``.
    s : float
        Residual standard deviation, in residual units.
    """
    J = np.asarray(jac, dtype=np.float64)
    r = np.asarray(residuals, dtype=np.float64).ravel()
    if J.ndim != 2 or J.shape[0] != r.size:
        raise ValueError(f'jac must have shape ({r.size}, p), got {J.shape}')
    p = J.shape[1]
    n = p if n_params is None else int(n_params)
    if not (np.isfinite(J).all() and np.isfinite(r).all()):
        raise ValueError('jac and residuals must be finite')
    if r.size <= n:
        raise ValueError(f'{r.size} residuals cannot give the spread of {n} parameters')
    s2 = float(r @ r) / (r.size - n)
    info = J.T @ J / max(s2, 1e-300)
    if prior_sigma is not None:
        ps = np.asarray(prior_sigma, dtype=np.float64)
        if ps.shape != (p,) or np.any(~(ps > 0)):
            raise ValueError(f'prior_sigma must have shape ({p},) and be > 0')
        info = info + np.diag(1.0 / ps**2)
    # Scale the columns to unit norm before inverting (units differ by many decades).
    d = np.sqrt(np.diag(info))
    d = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(info / np.outer(d, d))
    rank_ok = w > w.max() * 1e-12
    inv_w = np.where(rank_ok, 1.0 / np.where(rank_ok, w, 1.0), 0.0)
    cov = (V * inv_w) @ V.T / np.outer(d, d)
    if not rank_ok.all():  # directions nothing determines: infinite variance there
        null = V[:, ~rank_ok]
        bad = np.abs(null).max(axis=1) > 1e-6
        cov[bad, :] = np.inf
        cov[:, bad] = np.inf
    return cov, math.sqrt(s2)


def clustered_covariance(jac, residuals, cluster) -> np.ndarray | None:
    """Cluster-robust covariance of least-squares parameters: samples are clusters.

    ``inv(J.T J) (sum_c s_c s_c.T) inv(J.T J)`` with ``s_c`` the sum of ``J.T r`` over the
    rows of cluster ``c``, scaled by ``C / (C - p)`` for C clusters and p parameters. It
    holds whatever the correlation of the residuals within a cluster (the circles of one
    view, the lit frames of one board: what one frame's galvo scatter moves together).

    Parameters
    ----------
    jac : array_like, shape (m, p)
    residuals : array_like, shape (m,)
        At the solution (rows left out of the fit: zero).
    cluster : array_like of int, shape (m,)
        Cluster index of each row, 0..C-1.

    Returns
    -------
    ndarray, shape (p, p), or None
        None with too few clusters (C <= p + 2) or a singular or non-finite result: the
        caller keeps its row-wise covariance.
    """
    J = np.asarray(jac, dtype=np.float64)
    r = np.asarray(residuals, dtype=np.float64).ravel()
    c = np.asarray(cluster, dtype=np.intp).ravel()
    n_clusters, p = (int(c.max()) + 1 if c.size else 0), J.shape[1]
    if n_clusters <= p + 2:
        return None
    try:
        B = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    scores = np.zeros((n_clusters, p))
    np.add.at(scores, c, J * r[:, None])
    out = n_clusters / (n_clusters - p) * B @ (scores.T @ scores) @ B
    return 0.5 * (out + out.T) if np.isfinite(out).all() else None


def correlation(cov) -> np.ndarray:
    """Correlation matrix of a covariance, shape (p, p) (NaN where a variance is 0 or inf)."""
    c = np.asarray(cov, dtype=np.float64)
    sd = np.sqrt(np.diag(c))
    with np.errstate(invalid='ignore', divide='ignore'):
        return c / np.outer(sd, sd)


#: Top-level model keys a stage may add to a paper model: the switch to the physical model.
_PHYSICAL_KEYS = ('model', 'physical')


def _merge(base: dict, updates: dict, prefix: str = '') -> dict:
    out = dict(base)
    for key, value in updates.items():
        if key not in base:
            if prefix or key not in _PHYSICAL_KEYS:
                raise ValueError(f'stage update names unknown model key {prefix}{key}')
            out[key] = value
            continue
        if isinstance(value, dict):
            out[key] = _merge(base[key], value, f'{prefix}{key}.')
        else:
            out[key] = value
    return out


def apply_result(calibration, result: StageResult, sources=()):
    """A new Calibration with ``result`` merged in (the input is left unchanged).

    Parameters
    ----------
    calibration : reconstructor.calibration_file.Calibration
    result : StageResult
    sources : sequence of dict
        ``{'path': ..., 'sha256': ...}`` of the data the stage used.
    """
    from reconstructor import calibration_file
    from reconstructor.model import RigModel

    if result.stage not in KNOWN_STAGES:
        raise ValueError(f"stage: unknown '{result.stage}'")
    merged = _merge(calibration.model.to_dict(), result.updates)
    if merged.get('model') == 'paper':  # back to the paper's model: no physical section
        merged.pop('physical', None)
    model = RigModel.from_dict(merged)
    errors = _flat_errors(result.standard_errors)
    _check_errors(errors, result)
    stages = dict(calibration.stages)
    cell_T_v0 = calibration.cell_T_v0
    mounting = result.extra.get(result.stage) if result.stage in MOUNTING_STAGES else None
    if mounting is not None:
        cell_T_v0 = np.asarray(mounting['cell_T_v0'], dtype=np.float64)
        for other in MOUNTING_STAGES:  # the file holds one cell_T_v0: the newest
            if other != result.stage and other in stages:
                stages[other] = {**stages[other], 'superseded_by': result.stage}
    elif cell_T_v0 is not None and result.updates:
        # V0 is the model's frame: a changed model moves it by as much as the change
        for other in MOUNTING_STAGES:
            if other in stages:
                stages[other] = {**stages[other], 'model_changed_by': result.stage}
    stages[result.stage] = {
        'created': calibration_file.now_iso(),
        'bags': [dict(s) for s in sources],
        'samples_used': int(result.samples_used),
        'samples_rejected': int(result.samples_rejected),
        'residuals': {k: float(v) for k, v in result.residuals.items()},
        'updated': sorted(_flat_keys(result.updates)),
    }
    if errors:
        stages[result.stage]['standard_errors'] = errors
    if result.covariance:
        stages[result.stage]['covariance'] = _checked_covariance(result, merged)
    u1 = (result.extra.get('coverage') or {}).get('u1_V')
    if u1:  # where the stage's views looked (G1 voltages), for coverage maps
        stages[result.stage]['views_u1_V'] = [[float(a), float(b)] for a, b in u1]
    if mounting is not None:
        stages[result.stage].update({k: v for k, v in mounting.items() if k != 'cell_T_v0'})
    if result.extra.get('nodes'):  # per-view figures of a stage, for reports
        keep = ('pose_index', 'u1_pan', 'u1_tilt', 'status', 'error1_rms_m', 'error2_rms_m',
                'error3_rms_m')
        stages[result.stage]['nodes'] = [
            {k: (float(v) if isinstance(v, (int, float)) and k != 'pose_index' else v)
             for k, v in node.items() if k in keep} for node in result.extra['nodes']]
    if 'joint_correction' in result.extra:
        jc = result.extra['joint_correction']
    elif 'joint_correction_not_installed' in result.extra:
        jc = None  # measured, reported, and deliberately not applied
        stages[result.stage]['not_installed'] = str(result.extra['joint_correction_not_installed'])
    elif result.updates:
        jc = None  # a table measured with the old model would be stale
    else:
        jc = calibration.joint_correction
    return calibration_file.Calibration(model=model, source='calibrated', stages=stages,
                                        joint_correction=jc, cell_T_v0=cell_T_v0)


def _flat_errors(d, prefix='') -> dict:
    """Standard errors as flat dotted keys with plain floats (lists stay lists)."""
    out = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_flat_errors(value, f'{prefix}{key}.'))
        elif isinstance(value, (list, tuple, np.ndarray)):
            out[f'{prefix}{key}'] = [float(v) for v in np.asarray(value, dtype=float).ravel()]
        else:
            out[f'{prefix}{key}'] = float(value)
    return out


def _check_errors(errors: dict, result: StageResult) -> None:
    """Standard errors must name updated parameters and be finite and >= 0."""
    updated = set(_flat_keys(result.updates))
    for key, value in errors.items():
        if key not in updated:
            raise ValueError(f'{result.stage}: standard error of {key}, which the stage does '
                             f'not update')
        v = np.asarray(value, dtype=np.float64)
        if not (np.isfinite(v).all() and (v >= 0).all()):
            raise ValueError(f'{result.stage}: standard error of {key} must be finite and '
                             f'>= 0, got {value}')


def _checked_covariance(result: StageResult, merged: dict) -> dict:
    """The stage's covariance record, checked: it names parameters the stage updated (or
    elements of them), and inputs the model has."""
    from reconstructor.model import RigModel
    from reconstructor.uncertainty import covariance_record, parameter_value

    rec = result.covariance
    try:
        out = covariance_record(rec.get('names', ()), rec.get('matrix', ()),
                                rec.get('inputs', ()), rec.get('sensitivity'),
                                rec.get('priors'))
    except (TypeError, AttributeError) as exc:
        raise ValueError(f'{result.stage}: covariance: {exc}') from exc
    except ValueError as exc:
        raise ValueError(f'{result.stage}: {exc}') from exc
    updated = set(_flat_keys(result.updates))
    for name in out['names']:
        if name.split('[')[0] not in updated:
            raise ValueError(f'{result.stage}: covariance of {name}, which the stage does not '
                             f'update')
    model = RigModel.from_dict(merged)
    for name in out['names'] + out.get('inputs', []):
        parameter_value(model, name)  # raises, naming a parameter the model lacks
    return out


def _flat_keys(d, prefix=''):
    for key, value in d.items():
        if isinstance(value, dict):
            yield from _flat_keys(value, f'{prefix}{key}.')
        else:
            yield f'{prefix}{key}'
