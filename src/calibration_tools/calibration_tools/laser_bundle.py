"""The laser's bundle adjustment: every stripe point on the boards at once.

The staged laser calibration fits a plane to each G2 voltage's stripes, then a cone (or the
paper's line) to the planes, then G2's response to the planes' turns, and takes the laser
plane at U2 = 0 from another stage's boards. Each step passes on only what the one before
kept, and the U2 = 0 plane and the axis are never made to agree.

Here the physical model's laser is fitted to the stripe points themselves: the U2 = 0 plane
``laser_plane_v0``, the G2 tilt axis (``laser_axis_dir``, ``laser_axis_point``) and G2's
response (``g2_tilt.k`` and ``g2_tilt.poly``), in one robust least squares whose residual is
each point's distance to the model's laser plane at its voltage
(:func:`reconstructor.model.laser_plane_v0`). The camera (intrinsics and dynamic camera)
is held: its uncertainty enters through the sensitivity of the result to it, as for every
stage (:func:`reconstructor.uncertainty.remeasured_sensitivity`).

Parameters are moved in a minimal form: two turns and a shift of the U2 = 0 plane, two turns
of the axis, two shifts of its point across it, the gain and the polynomial. The point is
reported as the axis point nearest V0's origin (where along the axis it sits means nothing),
as the staged fit reports it. Every view counts the same (its points weighted by one over the
square root of their number): a view's error is mostly one shift of its whole line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: G2's response in the bundle: gain, square and cube. The staged fit to plane turns keeps
#: the square only (the cube made three of seven rigs worse there); fitted to the points, the
#: cube took the reference rig from 0.060 to 0.053 mm and a drawn rig from 0.198 to 0.120 mm
#: (exact camera), and cost the others 1-2 um.
BUNDLE_POLY_DEGREE = 3
#: Robust loss scale, in robust sigmas of the starting residuals (soft L1 beyond it).
ROBUST_SIGMAS = 2.5
#: Largest condition number of the scaled normal matrix: beyond it the views do not
#: determine every parameter, and the highest polynomial term is dropped (then refused).
MAX_CONDITION = 1e10
#: Typical sizes of the minimal parameters (x_scale of the solver): plane and axis turns
#: [rad], plane shift [m], point shifts [m], gain [rad/V], square [rad/V^2], cube [rad/V^3].
_SCALES = (1e-4, 1e-4, 1e-5, 1e-4, 1e-4, 1e-4, 1e-4, 1e-5, 1e-6, 1e-7)


@dataclass(frozen=True)
class LaserBundle:
    """Result of :func:`fit_laser_bundle`.

    Attributes
    ----------
    updates : dict
        ``laser_plane_v0`` (4), ``laser_axis_dir`` (3), ``laser_axis_point`` (3) and
        ``g2_tilt: {'k', 'poly'}``, as a stage's updates.
    names : list of str
        The flat parameter names of ``covariance``.
    covariance : ndarray
        Their covariance from the points' scatter (camera held), SI units.
    sensitivity_of : callable
        ``f(list of moved point arrays) -> values in names' order``: the bundle solved again,
        to first order, for stripe points measured otherwise (same groups as ``groups``).
    groups : list of (ndarray, float, float)
        Per stripe: its points in V0 and the G1 voltages it was seen at.
    rms_m : float
        RMS point-to-plane distance at the solution (inliers of the robust loss), metres.
    rms_start_m : float
        The same for the starting (staged) laser.
    points, views : int
    poly_degree : int
        Of G2's response as fitted (1 gain, 2 square, 3 cube).
    frame_noise_u2_V : float
        G2's per-frame noise [V, 1 sigma] (:func:`_g2_frame_noise`); NaN when too few views
        tell.
    """

    updates: dict
    names: list
    covariance: np.ndarray
    sensitivity_of: object
    groups: list
    rms_m: float
    rms_start_m: float
    points: int
    views: int
    poly_degree: int
    frame_noise_u2_V: float = float('nan')

    def standard_errors(self) -> dict:
        sd = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        by = dict(zip(self.names, (float(v) for v in sd), strict=True))
        return {'laser_plane_v0': [by[f'laser_plane_v0[{j}]'] for j in range(4)],
                'laser_axis_dir': [by[f'laser_axis_dir[{j}]'] for j in range(3)],
                'laser_axis_point': [by[f'laser_axis_point[{j}]'] for j in range(3)],
                'g2_tilt': {'k': by['g2_tilt.k'],
                            'poly': [by[n] for n in self.names if n.startswith('g2_tilt.poly')]}}


def _perp(v) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``v`` and to each other."""
    v = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    a = np.cross(v, np.eye(3)[int(np.argmin(np.abs(v)))])
    a /= np.linalg.norm(a)
    return a, np.cross(v, a)


class LaserParameters:
    """The laser's minimal parameters about a starting model (module docstring), and the
    models they give: ``values(x)`` the laser's fields, ``model_at(x)`` the whole model,
    ``scale`` their typical sizes (:data:`_SCALES`)."""

    def __init__(self, model, poly_degree: int) -> None:
        from reconstructor.model import RigModel

        self.RigModel = RigModel
        self.model = model
        self.data = model.to_dict()
        pl = np.asarray(model.laser_plane_v0, dtype=np.float64)
        self.n0, self.e0 = pl[:3] / np.linalg.norm(pl[:3]), float(pl[3] / np.linalg.norm(pl[:3]))
        self.t = _perp(self.n0)
        self.n = np.asarray(model.laser_axis_dir, dtype=np.float64)
        self.u = _perp(self.n)
        self.P = np.asarray(model.laser_axis_point, dtype=np.float64)
        self.k = float(model.g2_tilt.k)
        poly = list(model.g2_tilt.poly)[:poly_degree - 1]
        self.poly = np.array(poly + [0.0] * (poly_degree - 1 - len(poly)), dtype=np.float64)
        self.size = 8 + len(self.poly)
        self.scale = np.array(_SCALES[:self.size])

    def values(self, x) -> dict:
        x = np.asarray(x, dtype=np.float64)
        n0 = self.n0 + x[0] * self.t[0] + x[1] * self.t[1]
        s = float(np.linalg.norm(n0))
        n = self.n + x[3] * self.u[0] + x[4] * self.u[1]
        n = n / np.linalg.norm(n)
        P = self.P + x[5] * self.u[0] + x[6] * self.u[1]
        P = P - float(P @ n) * n  # the axis point nearest V0's origin, as the staged fit's
        return {'laser_plane_v0': [*(n0 / s), (self.e0 + x[2])],
                'laser_axis_dir': list(n),
                'laser_axis_point': list(P),
                'g2_tilt': {'k': self.k + x[7], 'poly': list(self.poly + x[8:])}}

    def vector(self, x) -> np.ndarray:
        v = self.values(x)
        return np.array([*v['laser_plane_v0'], *v['laser_axis_dir'], *v['laser_axis_point'],
                         v['g2_tilt']['k'], *v['g2_tilt']['poly']], dtype=np.float64)

    def names(self) -> list:
        return ([f'laser_plane_v0[{j}]' for j in range(4)]
                + [f'laser_axis_dir[{j}]' for j in range(3)]
                + [f'laser_axis_point[{j}]' for j in range(3)]
                + ['g2_tilt.k'] + [f'g2_tilt.poly[{j}]' for j in range(len(self.poly))])

    def model_at(self, x):
        v = self.values(x)
        data = dict(self.data)
        data['laser_plane_v0'] = [float(a) for a in v['laser_plane_v0']]
        data['laser_axis_dir'] = [float(a) for a in v['laser_axis_dir']]
        data['laser_axis_point'] = [float(a) for a in v['laser_axis_point']]
        data['g2_tilt'] = {**self.data['g2_tilt'], 'k': float(v['g2_tilt']['k']),
                           'poly': [float(a) for a in v['g2_tilt']['poly']]}
        return self.RigModel.from_dict(data, correction=self.model.correction)


def fit_laser_bundle(model, stripes, *, poly_degree: int = BUNDLE_POLY_DEGREE,
                     g1_frame_noise_v: dict | None = None) -> LaserBundle:
    """Fit the physical model's laser to stripe points on boards (module docstring).

    Parameters
    ----------
    model : reconstructor.model.RigModel
        ``model: physical``, with the staged laser as the starting point; its camera is held.
    stripes : sequence of (ndarray (n, 3), float, float, float)
        Per stripe (one view of one board): its points in V0 [m], the G2 tilt voltage and
        the G1 voltages (pan, tilt) it was seen at.
    poly_degree : int
        Of G2's response (1: gain only). Lowered while the views cannot determine the highest
        term (:data:`MAX_CONDITION`).
    g1_frame_noise_v : dict, optional
        G1's per-frame noise ``{'u1_pan': V, 'u1_tilt': V}`` as the dynamic camera measured
        it (:func:`reconstructor.uncertainty.frame_noise`): its share of the views' offsets
        is taken out of G2's (:func:`_g2_frame_noise`).

    Returns
    -------
    LaserBundle

    Raises
    ------
    ValueError
        Not a physical model, too few views, or a response the views cannot determine even as
        a gain alone.
    """
    from scipy.optimize import least_squares

    from reconstructor.model import laser_plane_v0

    if model.kind != 'physical':
        raise ValueError('the laser bundle needs model: physical')
    if not isinstance(poly_degree, int) or not 1 <= poly_degree <= 4:
        raise ValueError(f'poly_degree must be an integer 1..4, got {poly_degree!r}')
    groups = [(np.asarray(p, dtype=np.float64), float(u1p), float(u1t))
              for p, _, u1p, u1t in stripes if len(p)]
    u2 = [float(u) for p, u, _, _ in stripes if len(p)]
    if len(groups) < 12:
        raise ValueError(f'{len(groups)} stripe views; the laser bundle needs at least 12')
    counts = np.array([len(g[0]) for g in groups])
    w = np.repeat(1.0 / np.sqrt(counts), counts)
    volts = np.repeat(np.array(u2), counts)
    uu, inv = np.unique(np.round(volts, 6), return_inverse=True)

    def residual_fn(laser, points):
        def f(x):
            pl = laser_plane_v0(laser.model_at(x), uu)[inv]
            return w * (np.einsum('ij,ij->i', pl[:, :3], points) + pl[:, 3])
        return f

    P = np.concatenate([g[0] for g in groups])
    while True:
        laser = LaserParameters(model, poly_degree)
        f = residual_fn(laser, P)
        x0 = np.zeros(laser.size)
        r0 = f(x0)
        sigma = 1.4826 * float(np.median(np.abs(r0 - np.median(r0))))
        sol = least_squares(f, x0, x_scale=laser.scale, loss='soft_l1',
                            f_scale=max(ROBUST_SIGMAS * sigma, 1e-12), method='trf')
        J = _jacobian(f, sol.x, laser.scale)
        JtJ = J.T @ J
        D = np.sqrt(np.diag(JtJ))
        ok = np.all(D > 0) and np.linalg.cond(JtJ / np.outer(D, D)) < MAX_CONDITION
        if ok or poly_degree == 1:
            break
        poly_degree -= 1
    if not ok:
        raise ValueError('laser bundle: the views do not determine the laser (normal matrix '
                         'singular even with a linear response); spread the G2 rows')
    r = f(sol.x)
    inlier = np.abs(r) <= 3.0 * ROBUST_SIGMAS * sigma
    dof = len(groups) - laser.size
    if dof <= 0:
        raise ValueError(f'{len(groups)} stripe views for {laser.size} laser parameters')
    cov_x = _clustered_covariance(J, np.where(inlier, r, 0.0), groups, counts, JtJ)
    G = _jacobian(laser.vector, sol.x, laser.scale)
    cov = G @ cov_x @ G.T
    cov = 0.5 * (cov + cov.T)
    step = np.linalg.solve(JtJ, J.T)  # first-order re-solve for moved points

    def sensitivity_of(moved):
        Pm = np.concatenate([np.asarray(m, dtype=np.float64) for m in moved])
        return laser.vector(sol.x - step @ residual_fn(laser, Pm)(sol.x))

    raw = r / w
    raw0 = r0 / w
    noise = _g2_frame_noise(laser.model_at(sol.x), groups, u2, raw, inlier, laser.size,
                            g1_frame_noise_v)
    return LaserBundle(
        updates=laser.values(sol.x), names=laser.names(), covariance=cov,
        sensitivity_of=sensitivity_of, groups=groups,
        rms_m=float(np.sqrt(np.mean(raw[inlier] ** 2))),
        rms_start_m=float(np.sqrt(np.mean(raw0 ** 2))),
        points=int(len(P)), views=len(groups), poly_degree=poly_degree,
        frame_noise_u2_V=noise)


def _clustered_covariance(J, r, groups, counts, JtJ) -> np.ndarray:
    """The solution's covariance with the views of one board taken as one sample.

    A board's pose comes from one laser-off frame (G1's scatter in that frame, the pose fit's
    noise), and every lit frame of the board carries that error alike: its views are not
    independent, and more lit frames of the same boards would not make the laser better
    known. The covariance is the cluster-robust sandwich over boards (their G1 voltages;
    :func:`calibration_tools.stages.clustered_covariance`); with too few boards for that,
    one mean square residual per view (``s2 inv(J.T J)``).

    Taking each view as its own sample would shrink the stated error by sqrt(3) with three
    times the lit frames while the true error stays; one sample per board with the boards'
    mean square residuals would overstate it (the frames' own scatter counted as the
    board's). This sandwich assumes nothing about the errors within a board.
    """
    from .stages import clustered_covariance

    keys: dict = {}
    board = np.array([keys.setdefault((round(a, 4), round(b, 4)), len(keys))
                      for _, a, b in groups])
    out = clustered_covariance(J, r, np.repeat(board, counts))
    if out is None:
        return float(np.sum(r ** 2)) / (len(groups) - J.shape[1]) * np.linalg.inv(JtJ)
    return out


def _g2_frame_noise(model, groups, u2, raw, inlier, n_params: int,
                    g1_noise_v: dict | None = None, step_v: float = 1e-3) -> float:
    """G2's per-frame noise [V, 1 sigma] from the views' common offsets the bundle leaves.

    A galvo's angle scatters from frame to frame about its response (its repeatability):
    the whole sheet of one frame then lies where a slightly other voltage would put it, and
    every stripe point of the view sits off the fitted plane by about the same distance.
    Per view, the mean distance of its inlying points over the distance's derivative with
    respect to U2 is that voltage offset; the noise of the mean (the points' scatter over
    their number) is subtracted and the fit's share (its parameters over the views) put
    back. The offsets hold G1's frame noise too (the points were measured through G1):
    with ``g1_noise_v`` its share is taken out, to first order as if the view had moved
    with its points (the points as the view at U1 +- 1 sigma would have measured them);
    without it the estimate is G2's and G1's together, an upper bound.
    """
    from reconstructor.model import laser_plane_v0, v0_T_v

    counts = [len(g[0]) for g in groups]
    noise_g1 = g1_noise_v or {}
    offsets, floors = [], []
    start = 0
    for (p, a, b), u, n in zip(groups, u2, counts, strict=True):
        sel = slice(start, start + n)
        start += n
        keep = inlier[sel]
        if keep.sum() < 5:
            continue
        q = p[keep]
        d = raw[sel][keep]
        plus, minus = laser_plane_v0(model, np.array([u + step_v, u - step_v]))
        slope = float(np.mean((q @ plus[:3] + plus[3]) - (q @ minus[:3] + minus[3]))) / (
            2.0 * step_v)
        if not abs(slope) > 0:
            continue
        offsets.append(float(np.mean(d)) / slope)
        share = 0.0
        g1 = (noise_g1.get('u1_pan', 0.0), noise_g1.get('u1_tilt', 0.0))
        if any(sd > 0 for sd in g1):  # once per view: the sheet at u, the view at U1
            pl = laser_plane_v0(model, np.array([u]))[0]
            base = np.linalg.inv(v0_T_v(model, a, b))
        for k, sd in enumerate(g1):
            if not sd > 0:
                continue
            moved = []
            for sign in (1.0, -1.0):
                v = [a, b]
                v[k] += sign * sd
                M = v0_T_v(model, v[0], v[1]) @ base
                moved.append(float(np.mean((q @ M[:3, :3].T + M[:3, 3]) @ pl[:3] + pl[3])))
            share += ((moved[0] - moved[1]) / 2.0 / slope) ** 2
        floors.append(float(np.var(d)) / len(d) / slope ** 2 + share)
    if len(offsets) <= n_params or len(offsets) < 3:
        return float('nan')
    dof = len(offsets) / (len(offsets) - n_params)
    var = dof * float(np.mean(np.square(offsets))) - float(np.mean(floors))
    return float(np.sqrt(max(var, 0.0)))


def _jacobian(f, x, scale) -> np.ndarray:
    """Central differences of ``f`` at ``x`` with steps of 1e-3 of ``scale``."""
    cols = []
    for j, h in enumerate(np.asarray(scale) * 1e-3):
        e = np.zeros_like(x)
        e[j] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2.0 * h))
    return np.column_stack(cols)


def bundle_covariance_record(bundle: LaserBundle, model, inputs) -> dict:
    """The stage's covariance record: the bundle's covariance and its sensitivity to the
    camera's calibrated parameters (``inputs``, name to 1 sigma): the stripe points as a
    moved camera would have measured them, the bundle solved again to first order."""
    from reconstructor.uncertainty import covariance_record, remeasured_sensitivity

    if not inputs:
        return covariance_record(bundle.names, bundle.covariance)
    S = remeasured_sensitivity(model, bundle.groups, inputs, bundle.sensitivity_of)
    return covariance_record(bundle.names, bundle.covariance, list(inputs),
                             S.reshape(len(bundle.names), len(inputs)))

