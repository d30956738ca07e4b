"""Joint correction of the dynamic camera and dynamic laser (paper's Algorithm 1, docs/design.md §3
step 5). No rclpy.

With G2 held still, the laser stripe on a calibration sphere is one fixed physical curve;
every G1 view of it should reconstruct to the same points in V0. The model's residual errors
make the clouds disagree. For every G1 voltage pair (a *node*) the cloud is registered to the
cloud of the reference node; the registration ``T`` (node cloud -> reference cloud) is the
correction ``V0c_T_V0`` at that node. The corrections form a
:class:`reconstructor.correction.CorrectionTable`, interpolated at run time.

Registration, per node:

1. sphere-centre fitting (closed form, no correspondences; the calibration sphere's radius is
   known, so one planar stripe arc fixes the centre) gives the translation;
2. point-to-point ICP (open3d), started from that translation, then refined point-to-line
   against the reference stripe densified along the curve (Gauss-Newton; point-to-point ICP
   barely moves along a curve's weak directions), gives the full rigid transform
   (``registration='icp'``, default). ``registration='sphere'`` keeps the translation only.

A stripe that also crosses the background next to the sphere (the sphere stands on a plate or
in front of a wall, as in the paper's Fig. 2) pins the rotation about the stripe-plane normal,
which the sphere arc alone leaves free.

Several sphere positions (``pose_index``) chain: a position whose reference node has the G1
voltages of a node already corrected from an earlier position is registered to that node, and
its corrections are composed with that node's (the paper's ``M``).

Checks, each skipping the node with a logged reason (never registered blindly): too few
points; no sphere fit, or a poor one (points off the sphere: something in front of it); the
sphere arc incomplete with respect to the reference's (partly occluded or out of view); ICP
not converged or with too small an overlap (reported, correction not stored).

Errors as the paper reports them (per point, over the pairs the registration matched):
Error1 = nearest-neighbour distance before, Error2 = pair distance after, Error3 = pair
distance before.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from calibration_tools.laser_plane import stripe_extractor_config, view_voltages
from calibration_tools.registration import (
    RegistrationErrors,
    apply_transform,
    densify_polylines,
    nearest_neighbours,
    register_icp,
    register_sphere_centres,
    registration_errors,
)
from calibration_tools.sphere_fit import fit_sphere
from calibration_tools.stages import VOLTAGE_TOL, StageResult

log = logging.getLogger('galvoscan.calibration.joint_correction')

REGISTRATIONS = ('icp', 'sphere')


@dataclass
class NodeCloud:
    """The reconstructed stripe points of one G1 voltage pair at one sphere position.

    Attributes
    ----------
    pose_index : int
        Sphere position.
    u1_pan, u1_tilt : float, volts
    points : ndarray, shape (n, 3), metres
        In V0, triangulated by the model without any joint correction; each frame's points
        consecutive and in stripe order.
    frame_ids : ndarray of int, shape (n,)
        Index of the view each point came from.
    """

    pose_index: int
    u1_pan: float
    u1_tilt: float
    points: np.ndarray
    frame_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def view_indices(self) -> list:
        return sorted(set(int(i) for i in self.frame_ids))

    @property
    def key(self) -> tuple:
        return (round(self.u1_pan / VOLTAGE_TOL), round(self.u1_tilt / VOLTAGE_TOL))


@dataclass
class NodeResult:
    """What happened to one node.

    Attributes
    ----------
    pose_index : int
    u1_pan, u1_tilt : float, volts
    status : str
        ``'reference'``, ``'registered'``, ``'skipped'`` or ``'not_converged'``.
    reason : str
        Why it was skipped or not converged ('' otherwise).
    transform : ndarray, shape (4, 4), or None
        The stored correction ``V0c_T_V0`` (None unless reference or registered).
    registration : ndarray, shape (4, 4), or None
        Node cloud -> reference cloud (before chaining).
    n_points : int
    sphere_centre : ndarray, shape (3,), or None
    sphere_rms : float or None, metres
    coverage : float or None
        Smaller of the two arc coverages (node of reference, reference of node).
    icp_fitness, icp_rmse : float or None
    icp_vs_sphere : float or None, metres
        Distance between the sphere centre moved by the ICP result and the reference centre
        (how much the two registrations disagree at the sphere).
    errors : RegistrationErrors or None
        The paper's errors against the reference cloud as sampled.
    errors_dense : RegistrationErrors or None
        The same against the reference stripes densified along the curve
        (:func:`registration.densify_polylines`): misalignment without the sampling.
    """

    pose_index: int
    u1_pan: float
    u1_tilt: float
    status: str
    reason: str = ''
    transform: np.ndarray | None = None
    registration: np.ndarray | None = None
    n_points: int = 0
    sphere_centre: np.ndarray | None = None
    sphere_rms: float | None = None
    coverage: float | None = None
    icp_fitness: float | None = None
    icp_rmse: float | None = None
    icp_vs_sphere: float | None = None
    errors: RegistrationErrors | None = None
    errors_dense: RegistrationErrors | None = None

    def summary(self) -> dict:
        """Plain floats/str for reports (metres, volts)."""
        out = {'pose_index': self.pose_index, 'u1_pan': self.u1_pan, 'u1_tilt': self.u1_tilt,
               'status': self.status, 'reason': self.reason, 'n_points': self.n_points}
        for name in ('sphere_rms', 'coverage', 'icp_fitness', 'icp_rmse', 'icp_vs_sphere'):
            v = getattr(self, name)
            if v is not None:
                out[name] = float(v)
        for suffix, errs in (('', self.errors), ('_dense', self.errors_dense)):
            if errs is not None:
                for name in ('error1', 'error2', 'error3'):
                    out[f'{name}{suffix}_rms_m'] = RegistrationErrors.rms(getattr(errs, name))
        if self.transform is not None:
            out['translation_m'] = [float(v) for v in self.transform[:3, 3]]
        return out


@dataclass
class JointCorrectionResult:
    """Output of :func:`compute_joint_correction`.

    Attributes
    ----------
    table : reconstructor.correction.CorrectionTable
    nodes : list of NodeResult
    errors : dict
        ``error1_rms_m``, ``error2_rms_m``, ``error3_rms_m`` (the paper's definitions) and
        the same with ``_dense`` (against the densified reference), RMS over all registered
        nodes' points (reference excluded).
    """

    table: object
    nodes: list
    errors: dict


# ----------------------------------------------------------------------------- reconstruction
def reconstruct_nodes(views, model, *, extractor_config=None, min_points: int = 1,
                      use_correction: bool = False):
    """Extract and triangulate laser-on views, grouped into nodes (pose, G1 voltages).

    Parameters
    ----------
    views : list of CaptureView
        Laser-off views are ignored.
    model : reconstructor.model.RigModel
        Used without its joint correction (the correction is what is being measured),
        unless ``use_correction``.
    extractor_config : stripe_extractor.extractor.ExtractorConfig, optional
    min_points : int
        Views with fewer triangulated points contribute nothing (logged).

    Returns
    -------
    list of NodeCloud
        Sorted by (pose_index, u1_pan, u1_tilt).
    """
    from reconstructor.model import triangulate
    from stripe_extractor.extractor import extract

    if not isinstance(views, (list, tuple)):
        raise ValueError(f'views must be a list of CaptureView, got {type(views).__name__}')
    plain = model if use_correction else dataclasses.replace(model, correction=None)
    extractor_config = stripe_extractor_config(model, extractor_config)
    groups: dict[tuple, NodeCloud] = {}
    for i, view in enumerate(views):
        volts = view_voltages(i, view)
        if not view.laser_on:
            continue
        stripe = extract(np.ascontiguousarray(view.image), extractor_config)
        uv = np.column_stack([stripe.u, stripe.v]).astype(np.float64)
        res = triangulate(plain, uv, volts[0], volts[1], volts[3])
        pts = res.p_v0[res.valid]
        if pts.shape[0] < min_points:
            log.warning('view %d: %d stripe points, ignored', i, pts.shape[0])
            continue
        key = (int(view.pose_index), round(volts[0] / VOLTAGE_TOL), round(volts[1] / VOLTAGE_TOL))
        node = groups.get(key)
        if node is None:
            node = groups[key] = NodeCloud(int(view.pose_index), float(volts[0]),
                                           float(volts[1]), np.zeros((0, 3)))
        node.points = np.vstack([node.points, pts])
        node.frame_ids = np.concatenate([node.frame_ids, np.full(pts.shape[0], i)])
    return [groups[k] for k in sorted(groups)]


# ----------------------------------------------------------------------------- registration
@dataclass
class _Fit:
    centre: np.ndarray
    rms: float
    sphere_points: np.ndarray


def _coverage(a: np.ndarray, b: np.ndarray, tol: float) -> float:
    """Fraction of points of ``a`` with a point of ``b`` within ``tol``."""
    d, _ = nearest_neighbours(a, b)
    return float(np.mean(d <= tol))


#: Distances of the fit and registration: a fraction of the sphere's radius, at most the
#: value the stage was tuned with on the reference kit's 10 mm sphere, ``(fraction, cap
#: [m])``. The plans choose the sphere for the view (``capture_plans.SPHERE_FILL``), so a
#: short-range rig gets a small sphere; absolute distances would then let the sphere's cap
#: be fitted to the wall behind it: a straight stripe stays within a tolerance t of a sphere
#: of radius R over 2 sqrt(2 R t), which at R = 1 mm and t = 0.2 mm is longer than the arc
#: the stripe draws on the sphere.
RELATIVE_TOLERANCES = {'sphere_inlier_tol': (0.02, 2e-4), 'max_sphere_rms': (0.02, 1e-4),
                       'coverage_tol': (0.03, 3e-4), 'icp_max_distance': (0.02, 2e-4)}


def compute_joint_correction(nodes, *, sphere_radius: float, reference_voltages=(0.0, 0.0),
                             registration: str = 'icp', min_points: int = 100,
                             min_sphere_points: int = 50, sphere_inlier_tol: float | None = None,
                             max_sphere_rms: float | None = None, max_off_sphere: float = 0.5,
                             coverage_tol: float | None = None, min_coverage: float = 0.9,
                             icp_max_distance: float | None = None,
                             icp_max_iterations: int = 100,
                             min_fitness: float = 0.6, icp_tolerance: float = 1e-7,
                             viewpoint=(0.0, 0.0, 0.0)) -> JointCorrectionResult:
    """Register every node to its position's reference node and build the correction table.

    Parameters
    ----------
    nodes : list of NodeCloud
    sphere_radius : float, metres
        Known radius of the calibration sphere.
    reference_voltages : (float, float), volts
        G1 voltages of the reference node (its correction is the identity).
    registration : {'icp', 'sphere'}
        Full rigid ICP started from the sphere-centre translation, or the translation only.
    min_points : int
        Nodes with fewer points are skipped.
    min_sphere_points : int
        Nodes with fewer points on the fitted sphere are skipped.
    sphere_inlier_tol : float, metres
        Inlier distance of the sphere fit (default: :data:`RELATIVE_TOLERANCES` of the
        radius).
    max_sphere_rms : float, metres
        Nodes whose sphere fit RMS is larger are skipped (default: relative, likewise).
    max_off_sphere : float
        Largest accepted fraction of the node's points off the sphere that have no
        counterpart in the reference cloud (after the sphere-centre alignment); more means
        something stands in front of the sphere or the view sees another scene.
    coverage_tol : float, metres
        Matching distance of the arc-coverage check.
    min_coverage : float
        Nodes whose sphere arc covers less of the reference arc (or is covered less by it)
        are skipped as partly occluded or out of view.
    icp_max_distance : float, metres
        ICP correspondence distance (after the sphere-centre alignment), and the pairing
        distance of the errors. Small, so that the parts of the stripe that only one of the
        two views sees (beyond the other's field of view) find no partner.
    icp_max_iterations : int
    min_fitness : float
        ICP results matching a smaller fraction of the node's points are not stored (the
        node is skipped: too little overlap).
    icp_tolerance : float, metres
        Convergence tolerance of :func:`registration.register_icp`.
    viewpoint : array_like, shape (3,), metres
        For the sphere fit (V0 origin).

    Returns
    -------
    JointCorrectionResult

    Raises
    ------
    ValueError
        Bad arguments, or no node registered (the reasons are in the message).
    """
    ref_key = _check_arguments(nodes, registration, sphere_radius, reference_voltages)
    given = {'sphere_inlier_tol': sphere_inlier_tol, 'max_sphere_rms': max_sphere_rms,
             'coverage_tol': coverage_tol, 'icp_max_distance': icp_max_distance}
    tol = {k: min(RELATIVE_TOLERANCES[k][0] * float(sphere_radius), RELATIVE_TOLERANCES[k][1])
           if v is None else float(v) for k, v in given.items()}
    sphere_inlier_tol, max_sphere_rms = tol['sphere_inlier_tol'], tol['max_sphere_rms']
    coverage_tol, icp_max_distance = tol['coverage_tol'], tol['icp_max_distance']
    results: dict[int, NodeResult] = {}

    def skip(i, why, status='skipped'):
        n = nodes[i]
        log.warning('joint correction: node pose %d U1 = (%.4f, %.4f) V %s: %s',
                    n.pose_index, n.u1_pan, n.u1_tilt, status.replace('_', ' '), why)
        r = results[i]
        r.status, r.reason = status, why

    fits = _fit_spheres(nodes, results, skip, sphere_radius=sphere_radius, viewpoint=viewpoint,
                        min_points=min_points, min_sphere_points=min_sphere_points,
                        sphere_inlier_tol=sphere_inlier_tol, max_sphere_rms=max_sphere_rms)
    table = _chain_positions(nodes, ref_key, fits, results, skip,
                             registration=registration, sphere_radius=sphere_radius,
                             sphere_inlier_tol=sphere_inlier_tol,
                             max_off_sphere=max_off_sphere,
                             coverage_tol=coverage_tol, min_coverage=min_coverage,
                             icp_max_distance=icp_max_distance,
                             icp_max_iterations=icp_max_iterations,
                             min_fitness=min_fitness, icp_tolerance=icp_tolerance)
    registered = _registered(results)
    ordered = [results[i] for i in range(len(nodes))]
    return JointCorrectionResult(table=_correction_table(nodes, table), nodes=ordered,
                                 errors=_error_figures(registered))


def _check_arguments(nodes, registration, sphere_radius, reference_voltages) -> tuple:
    """Check :func:`compute_joint_correction`'s arguments; the reference G1 voltages' key."""
    if registration not in REGISTRATIONS:
        raise ValueError(f'registration must be one of {REGISTRATIONS}, got {registration!r}')
    if not sphere_radius > 0:
        raise ValueError(f'sphere_radius must be > 0 m, got {sphere_radius!r}')
    ref_v = np.asarray(reference_voltages, dtype=np.float64)
    if ref_v.shape != (2,) or not np.all(np.isfinite(ref_v)):
        raise ValueError(f'reference_voltages must be 2 finite volts, got {reference_voltages!r}')
    ref_key = (round(ref_v[0] / VOLTAGE_TOL), round(ref_v[1] / VOLTAGE_TOL))
    for i, n in enumerate(nodes):
        if not isinstance(n, NodeCloud):
            raise ValueError(f'nodes[{i}] must be a NodeCloud, got {type(n).__name__}')
    return ref_key


def _registered(results) -> list:
    """The results of the registered nodes (ValueError with every reason when none is)."""
    registered = [r for r in results.values() if r.status == 'registered']
    if not registered:
        reasons = [f'pose {r.pose_index} U1 ({r.u1_pan:.4f}, {r.u1_tilt:.4f}) V: {r.reason}'
                   for r in results.values() if r.reason]
        raise ValueError(f'joint_correction: no node could be registered; {reasons}')
    return registered


def _fit_spheres(nodes, results, skip, *, sphere_radius, viewpoint, min_points,
                 min_sphere_points, sphere_inlier_tol, max_sphere_rms) -> dict:
    """Quality of every node on its own: its sphere fit, or the reason it is skipped."""
    fits: dict[int, _Fit] = {}
    for i, n in enumerate(nodes):
        results[i] = NodeResult(n.pose_index, n.u1_pan, n.u1_tilt, 'pending',
                                n_points=int(n.points.shape[0]))
        if n.points.shape[0] < min_points:
            skip(i, f'{n.points.shape[0]} points < {min_points}')
            continue
        try:
            sf = fit_sphere(n.points, radius=sphere_radius, viewpoint=viewpoint,
                            inlier_tol=sphere_inlier_tol, sample_window=200)
        except ValueError as exc:
            skip(i, f'no sphere in the points ({exc})')
            continue
        results[i].sphere_centre = sf.centre
        results[i].sphere_rms = sf.rms
        if sf.n_inliers < min_sphere_points:
            skip(i, f'{sf.n_inliers} points on the sphere < {min_sphere_points}')
            continue
        if sf.rms > max_sphere_rms:
            skip(i, f'sphere fit RMS {sf.rms * 1e6:.1f} um > {max_sphere_rms * 1e6:.1f} um')
            continue
        fits[i] = _Fit(sf.centre, sf.rms, n.points[sf.inliers])
    return fits


def _chain_positions(nodes, ref_key, fits, results, skip, **register_kw) -> dict:
    """Register the sphere positions in chaining order: key -> (T, pan, tilt)."""
    table: dict[tuple, tuple] = {}
    by_pose: dict[int, list] = {}
    for i, n in enumerate(nodes):
        by_pose.setdefault(n.pose_index, []).append(i)
    pending = sorted(by_pose)
    progress = True
    while pending and progress:
        progress = False
        for pose in list(pending):
            idx = by_pose[pose]
            ref = next((i for i in idx if nodes[i].key == ref_key and not table), None)
            if ref is None:
                ref = next((i for i in idx if nodes[i].key in table), None)
            if ref is None:
                continue
            pending.remove(pose)
            progress = True
            _register_position(nodes, idx, ref, fits, results, table, skip, **register_kw)
    for pose in pending:
        for i in by_pose[pose]:
            if results[i].status == 'pending':
                skip(i, f'sphere position {pose} has no node at the reference voltages or at '
                        f'an already corrected G1 voltage to chain to')
    return table


def _correction_table(nodes, table):
    """The registered transforms on the G1 grid of the nodes' voltages."""
    from reconstructor.correction import CorrectionTable

    pans = _axis_values([n.u1_pan for n in nodes])
    tilts = _axis_values([n.u1_tilt for n in nodes])
    T = np.tile(np.eye(4), (len(pans), len(tilts), 1, 1))
    valid = np.zeros((len(pans), len(tilts)), dtype=bool)
    for (Tn, pan, tilt) in table.values():
        a = int(np.argmin(np.abs(pans - pan)))
        b = int(np.argmin(np.abs(tilts - tilt)))
        T[a, b] = Tn
        valid[a, b] = True
    return CorrectionTable(pans, tilts, T, valid)


def _error_figures(registered) -> dict:
    """RMS of the three registration errors over the registered nodes [m]."""
    def cat(attr, name):
        arrs = [getattr(getattr(r, attr), name) for r in registered
                if getattr(r, attr) is not None]
        return np.concatenate(arrs) if arrs else np.zeros(0)

    errors = {}
    for attr, suffix in (('errors', ''), ('errors_dense', '_dense')):
        for name in ('error1', 'error2', 'error3'):
            errors[f'{name}{suffix}_rms_m'] = RegistrationErrors.rms(cat(attr, name))
    return errors


def _axis_values(values) -> np.ndarray:
    """Distinct voltages (within VOLTAGE_TOL), sorted."""
    out: list[float] = []
    for v in sorted(values):
        if not out or v - out[-1] > VOLTAGE_TOL:
            out.append(float(v))
    return np.array(out)


def _register_position(nodes, idx, ref, fits, results, table, skip, *, registration,
                       sphere_radius, sphere_inlier_tol, max_off_sphere, coverage_tol,
                       min_coverage, icp_max_distance, icp_max_iterations, min_fitness,
                       icp_tolerance):
    """Register the nodes ``idx`` of one sphere position to its reference node ``ref``."""
    rn = nodes[ref]
    if ref not in fits:
        why = results[ref].reason or 'unusable'
        for i in idx:
            if results[i].status == 'pending':
                skip(i, f'the reference node of sphere position {rn.pose_index} is unusable '
                        f'({why})')
        return
    C_ref = table[rn.key][0] if rn.key in table else np.eye(4)
    if rn.key not in table:
        table[rn.key] = (C_ref, rn.u1_pan, rn.u1_tilt)
    rr = results[ref]
    rr.status, rr.transform, rr.registration = 'reference', C_ref, np.eye(4)
    rf = fits[ref]
    target, tangents = densify_polylines(rn.points, rn.frame_ids)
    for i in idx:
        if i == ref or results[i].status != 'pending':
            continue
        n, f, r = nodes[i], fits.get(i), results[i]
        if f is None:  # already skipped with its reason
            continue
        if np.linalg.norm(f.centre - rf.centre) > 0.5 * sphere_radius:
            # A planar arc fits two mirror-image centres: take the one next to the reference.
            sf = fit_sphere(n.points, radius=sphere_radius, centre_hint=rf.centre,
                            inlier_tol=sphere_inlier_tol, sample_window=200)
            f = fits[i] = _Fit(sf.centre, sf.rms, n.points[sf.inliers])
            r.sphere_centre = sf.centre
        T0 = register_sphere_centres(f.centre, rf.centre)
        moved_sphere = apply_transform(T0, f.sphere_points)
        # Matching distances never below the two clouds' own noise (their sphere fits'
        # RMS): at short range the points scatter by more than a fraction of a small
        # sphere's radius. On the reference kit the tuned distances are the larger.
        noise = float(np.hypot(f.rms, rf.rms))
        cov_tol, icp_d = max(coverage_tol, 3.0 * noise), max(icp_max_distance, 2.0 * noise)
        cov = min(_coverage(rf.sphere_points, moved_sphere, cov_tol),
                  _coverage(moved_sphere, rf.sphere_points, cov_tol))
        r.coverage = cov
        if cov < min_coverage:
            skip(i, f'sphere arc covers only {cov * 100:.0f} % of the reference arc (or is '
                    f'covered that little by it): partly occluded or out of view')
            continue
        d_all, _ = nearest_neighbours(apply_transform(T0, n.points), rn.points)
        off = float(np.mean(d_all > 10.0 * icp_d))
        if off > max_off_sphere:
            skip(i, f'{off * 100:.0f} % of the points have no counterpart in the reference '
                    f'cloud: something in front of the sphere or another scene')
            continue
        if registration == 'sphere':
            T = T0
        else:
            icp = register_icp(n.points, target, init=T0, max_distance=icp_d,
                               max_iterations=icp_max_iterations, min_fitness=min_fitness,
                               tolerance=icp_tolerance, target_tangents=tangents)
            r.icp_fitness, r.icp_rmse = icp.fitness, icp.inlier_rmse
            r.icp_vs_sphere = float(np.linalg.norm(apply_transform(icp.transform,
                                                                   f.centre[None])[0]
                                                   - rf.centre))
            if not icp.converged:
                skip(i, icp.message, status='not_converged')
                r.registration = icp.transform
                continue
            if not icp.accepted:
                skip(i, icp.message)
                continue
            T = icp.transform
        r.registration = T
        r.errors = registration_errors(n.points, rn.points, T, max_distance=icp_d)
        r.errors_dense = registration_errors(n.points, target, T, max_distance=icp_d)
        C = C_ref @ T
        r.transform = C
        r.status = 'registered'
        if n.key not in table:
            table[n.key] = (C, n.u1_pan, n.u1_tilt)


# ----------------------------------------------------------------------------- stage
def run_joint_correction(views, calibration, *, sphere_radius: float,
                         extractor_config=None, install: bool | None = None,
                         **options) -> StageResult:
    """The joint-correction stage: views of the sphere -> correction table.

    Parameters
    ----------
    views : list of CaptureView
        Laser-on views of the calibration sphere, G2 fixed per sphere position
        (``pose_index``), G1 stepped over a grid of voltages that includes the reference
        voltages (default 0, 0) at the first position.
    calibration : reconstructor.calibration_file.Calibration
        Current calibration; its model is used without any existing joint correction (the
        new table replaces the old one).
    sphere_radius : float, metres
    extractor_config : stripe_extractor.extractor.ExtractorConfig, optional
    install : bool or None
        Whether the table goes into the calibration. Default: with the paper's model yes
        (its Algorithm 1); with the physical model no. The stage then still measures the
        errors before and after (its residuals) and says why in ``extra``. The table is
        measured along one row of G1 voltages (pan +-2.2 V, tilt +-0.1 V on the reference
        rig), chained from position to position, and held at its edge beyond. On the
        reference rig with the physical model, applying it made the whole-plate RMSE and the
        off-nominal stair figures worse (see :data:`NOT_INSTALLED`).
    **options
        Passed to :func:`compute_joint_correction`.

    Returns
    -------
    StageResult
        No model update; ``extra['joint_correction']`` is the table's ``to_dict()``;
        ``extra['nodes']`` the per-node summaries. Residuals: ``error1_rms_m``,
        ``error2_rms_m``, ``error3_rms_m``, ``nodes_registered``, ``nodes_skipped``,
        ``nodes_not_converged``, ``sphere_rms_max_m``, ``icp_vs_sphere_max_m``.
    """
    if install is None:
        install = calibration.model.physical is None
    nodes = reconstruct_nodes(views, calibration.model, extractor_config=extractor_config)
    try:
        if not nodes:
            raise ValueError('joint_correction: no laser-on view gave stripe points')
        res = compute_joint_correction(nodes, sphere_radius=sphere_radius, **options)
    except ValueError as exc:
        if install:
            raise
        # nothing to install: a diagnostic that could not be measured stops nothing
        log.warning('joint correction not measured (the physical model installs no table): '
                    '%s', exc)
        return StageResult(stage='joint_correction', samples_rejected=len(views),
                           rejected=[str(exc)],
                           extra={'joint_correction_not_installed':
                                  f'{NOT_INSTALLED}; not measured either: {exc}'})
    counts = {s: sum(1 for r in res.nodes if r.status == s)
              for s in ('registered', 'skipped', 'not_converged')}
    residuals = dict(res.errors)
    residuals.update({f'nodes_{k}': float(v) for k, v in counts.items()})
    rms = [r.sphere_rms for r in res.nodes if r.sphere_rms is not None]
    if rms:
        residuals['sphere_rms_max_m'] = float(max(rms))
    dev = [r.icp_vs_sphere for r in res.nodes
           if r.icp_vs_sphere is not None and r.status == 'registered']
    if dev:
        residuals['icp_vs_sphere_max_m'] = float(max(dev))
    rejected = [f'pose {r.pose_index} U1 = ({r.u1_pan:.4f}, {r.u1_tilt:.4f}) V: {r.status}: '
                f'{r.reason}' for r in res.nodes if r.status in ('skipped', 'not_converged')]
    return StageResult(
        stage='joint_correction',
        updates={},
        residuals=residuals,
        samples_used=counts['registered'] + sum(1 for r in res.nodes
                                                if r.status == 'reference'),
        samples_rejected=counts['skipped'] + counts['not_converged'],
        rejected=rejected,
        extra={**({'joint_correction': res.table.to_dict()} if install
                  else {'joint_correction_not_installed': NOT_INSTALLED}),
               'nodes': [r.summary() for r in res.nodes]},
    )


#: Why the physical model's calibration keeps no joint-correction table.
NOT_INSTALLED = (
    'measured, not installed: the physical mirror model leaves no systematic error for a '
    'table to take out, and the table (one row of G1 voltages, chained from position to '
    'position, held at its edge beyond) moved points elsewhere by up to a few tenths of a '
    'millimetre')
