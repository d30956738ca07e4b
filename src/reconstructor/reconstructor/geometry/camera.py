"""Pinhole camera with OpenCV plumb_bob distortion: intrinsics, projection and undistortion.

Normalised image coordinates are ``x = X/Z, y = Y/Z`` in the optical camera frame (z forward,
x right, y down). The plumb_bob model (OpenCV, ROS CameraInfo ``d``) maps undistorted
``(x, y)`` to distorted ``(xd, yd)``::

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx xd + cx,  v = fy yd + cy

The inverse has no closed form. :func:`undistort_points` runs the fixed-point iteration
``x <- (xd - tangential(x)) / radial(x)`` (the same iteration as OpenCV), started either at
``xd`` or at a cheap approximate inverse (series inverse of the radial part minus the
tangential term). The iteration is a contraction with a small constant rho for this rig's
telephoto lens, so after a step of size s the remaining error is at most
``rho / (1 - rho) * s``.

Once per :class:`CameraIntrinsics` a polar grid over the "disk" (centred on the principal
point, radius 5 % beyond the farthest image corner in distorted normalised coordinates; the
bare corner radius if the distortion folds within that margin) fixes rho (twice the largest
observed step ratio), the last-step size that guarantees ``UNDISTORT_TARGET_ERROR``, the start
and the number of steps every grid point needs to get there.

At run time a batch whose points all lie in the disk (one reduction over ``|xd|^2``) runs
exactly that fixed number of steps: the hot path. Otherwise the last step of each point is
checked, and points that fail restart from ``xd`` and iterate until their step is below
``UNDISTORT_STEP_TOL``, up to ``UNDISTORT_MAX_ITER`` steps; points that still have not
converged (beyond the fold of the distortion polynomial) are reported as not converged.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from types import SimpleNamespace

import numpy as np

from .checks import as_points, finite_scalar, finite_vector

#: Error bound the fixed-count undistortion guarantees inside the image, normalised units
#: (1e-13 is about 1e-9 px at f = 7800 px).
UNDISTORT_TARGET_ERROR = 1e-13
#: Convergence threshold on the last step for points outside the calibrated grid, normalised.
UNDISTORT_STEP_TOL = 1e-14
#: Iteration cap of the iterative undistortion.
UNDISTORT_MAX_ITER = 200
# Disk radii tried for the fixed-count hot path, as multiples of the farthest-corner radius.
_DISK_SCALES = (1.05, 1.0)


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics with plumb_bob distortion.

    Parameters
    ----------
    fx, fy : float
        Focal lengths, pixels (> 0).
    cx, cy : float
        Principal point, pixels.
    dist : tuple of 5 float
        Plumb_bob coefficients ``(k1, k2, p1, p2, k3)``, dimensionless (OpenCV order).
    width, height : int
        Image size, pixels (> 0).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float]
    width: int
    height: int

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, finite_scalar(getattr(self, name), name))
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        dist = finite_vector(self.dist, "dist", 5)
        object.__setattr__(self, "dist", tuple(float(x) for x in dist))
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not float(value).is_integer() or value <= 0:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))

    def matrix(self) -> np.ndarray:
        """Return the camera matrix K, shape (3, 3), pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @cached_property
    def _plan(self) -> SimpleNamespace:
        """Constants of the undistortion and projection hot paths (depend on self only)."""
        k1, k2, p1, p2, k3 = self.dist
        plan = SimpleNamespace(
            c=np.array([[self.cx], [self.cy]]),
            f=np.array([[self.fx], [self.fy]]),
            finv=np.array([[1.0 / self.fx], [1.0 / self.fy]]),
            k1=k1,
            k2=k2,
            k3=k3,
            has_k3=k3 != 0.0,
            has_tangential=p1 != 0.0 or p2 != 0.0,
            p_row2=np.array([2.0 * p2, 2.0 * p1]),
            p_col=np.array([[p2], [p1]]),
            distorted=any(v != 0.0 for v in self.dist),
            b1=-k1,
            b2=3.0 * k1 * k1 - k2,
            b3=-12.0 * k1**3 + 8.0 * k1 * k2 - k3,
            use_guess=False,
            n_fast=0,
            fast_tol=UNDISTORT_STEP_TOL,
        )
        # The hot-path disk. If some grid point of the disk does not converge (strong
        # distortion folding near the corners), retry with the bare corner radius; if that
        # fails too there is no hot path.
        corners = (np.array([[0.0, self.width], [0.0, self.height]]) - plan.c) * plan.finv
        r_corner = float(np.hypot(np.abs(corners[0]).max(), np.abs(corners[1]).max()))
        plan.s_max = -1.0  # |xd|^2 bound of the disk; negative: no hot path
        radius = np.linspace(0.0, 1.0, 41) ** 0.5  # denser towards the rim
        angle = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
        rr, aa = np.meshgrid(radius, angle)
        unit = np.stack([(rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel()])
        x = None
        for scale in _DISK_SCALES:
            xd = scale * r_corner * unit
            if plan.distorted:
                use_guess, n_fast, fast_tol, x = _fixed_iteration_plan(plan, xd)
                plan.fast_tol = fast_tol
                if x is None:
                    continue
                plan.use_guess, plan.n_fast = use_guess, n_fast
            else:
                x = xd
            plan.s_max = (scale * r_corner) ** 2 * (1.0 - 1e-12)
            break
        if x is None:
            x = np.zeros((2, 1))
        # Largest ray length sqrt(1 + r2) in the disk (with 1 % slack), for the angle test.
        r2 = x[0] * x[0] + x[1] * x[1]
        plan.ray_norm_max = 1.01 * float(np.sqrt(1.0 + np.nanmax(r2)))
        # the same constants as plain scalars, in the order the compiled triangulation pass
        # takes them (triangulation._hot_path)
        plan.kernel_args = (
            float(plan.c[0, 0]), float(plan.c[1, 0]), float(plan.finv[0, 0]),
            float(plan.finv[1, 0]), float(plan.s_max), bool(plan.distorted),
            bool(plan.use_guess), int(plan.n_fast), float(k1), float(k2), float(k3),
            float(p1), float(p2), float(plan.b1), float(plan.b2), float(plan.b3))
        return plan


def _iterate(plan: SimpleNamespace, xd: np.ndarray, x: np.ndarray) -> np.ndarray:
    """One fixed-point undistortion step; ``xd`` and ``x`` shape (2, n)."""
    x2 = x * x
    r2 = x2[0] + x2[1]
    if plan.has_k3:
        radial = 1.0 + r2 * (plan.k1 + r2 * (plan.k2 + r2 * plan.k3))
    else:
        radial = 1.0 + r2 * (plan.k1 + r2 * plan.k2)
    if plan.has_tangential:
        # tangential(x) = r2 p + 2 (p . x) x with p = (p2, p1)
        delta = (plan.p_row2 @ x) * x
        delta += r2 * plan.p_col
        return (xd - delta) / radial
    return xd / radial


def _distort(plan: SimpleNamespace, x: np.ndarray) -> np.ndarray:
    """Apply plumb_bob distortion to normalised points ``x`` shape (2, n); return shape (2, n)."""
    x2 = x * x
    r2 = x2[0] + x2[1]
    radial = 1.0 + r2 * (plan.k1 + r2 * (plan.k2 + r2 * plan.k3))
    return x * radial + (plan.p_row2 @ x) * x + r2 * plan.p_col


def _initial_guess(plan: SimpleNamespace, xd: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Approximate inverse: series inverse of the radial part minus the tangential term at xd.

    ``xd (1 + b1 s + b2 s^2 + b3 s^3) - tangential(xd)``, ``s = |xd|^2`` (given), with
    ``b1 = -k1, b2 = 3 k1^2 - k2, b3 = -12 k1^3 + 8 k1 k2 - k3``.
    """
    x = xd * (1.0 + s * (plan.b1 + s * (plan.b2 + s * plan.b3)))
    if plan.has_tangential:
        delta = (plan.p_row2 @ xd) * xd
        delta += s * plan.p_col
        x -= delta
    return x


def _sq_norm(x: np.ndarray) -> np.ndarray:
    x2 = x * x
    return x2[0] + x2[1]


def _iterate_until_converged(plan, xd, max_iter):
    """Iterate from ``xd`` until each step is below tolerance; return (x, converged)."""
    n = xd.shape[1]
    converged = np.zeros(n, dtype=bool)
    active = np.arange(n)
    x = xd.copy()
    with np.errstate(all="ignore"):
        for _ in range(max_iter):
            if not active.size:
                break
            x_new = _iterate(plan, xd[:, active], x[:, active])
            step = np.abs(x_new - x[:, active]).max(axis=0)
            x[:, active] = x_new
            done = step <= UNDISTORT_STEP_TOL
            converged[active[done]] = True
            # Drop converged columns and columns that blew up.
            active = active[~done & np.isfinite(step)]
    left = np.flatnonzero(~converged)
    if left.size:
        # slow or oscillating near the fold: Newton, from the last iterate where it is finite
        start = x[:, left]
        start = np.where(np.isfinite(start), start, xd[:, left])
        x_n, ok = _newton_inverse(plan, xd[:, left], start)
        x[:, left[ok]] = x_n[:, ok]
        converged[left[ok]] = True
    return x, converged


def _distortion_jacobian(plan: SimpleNamespace, x: np.ndarray) -> np.ndarray:
    """d distort(x) / dx of plumb_bob at ``x`` shape (2, n); returns shape (n, 2, 2)."""
    a, b = x
    r2 = a * a + b * b
    radial = 1.0 + r2 * (plan.k1 + r2 * (plan.k2 + r2 * plan.k3))
    d_radial = plan.k1 + r2 * (2.0 * plan.k2 + 3.0 * r2 * plan.k3)
    p2, p1 = plan.p_col[:, 0]
    cross = 2.0 * a * b * d_radial + 2.0 * p1 * a + 2.0 * p2 * b
    J = np.empty((x.shape[1], 2, 2))
    J[:, 0, 0] = radial + 2.0 * a * a * d_radial + 2.0 * p1 * b + 6.0 * p2 * a
    J[:, 0, 1] = cross
    J[:, 1, 0] = cross
    J[:, 1, 1] = radial + 2.0 * b * b * d_radial + 6.0 * p1 * b + 2.0 * p2 * a
    return J


def _newton_inverse(plan: SimpleNamespace, xd: np.ndarray, x0: np.ndarray, max_iter: int = 50):
    """Solve ``distort(x) = xd`` by Newton from ``x0`` (both shape (2, n)).

    The fixed-point iteration (OpenCV's) contracts slowly or oscillates near the corners of
    strongly distorted lenses, where a true inverse still exists. A point counts as inverted
    when the distortion of the answer reproduces ``xd`` to ``UNDISTORT_TARGET_ERROR`` and the
    distortion map's Jacobian is positive definite there (the answer lies before the fold, on
    the branch the lens really images, not on a mirrored one). Returns (x, ok).
    """
    x = x0.copy()
    with np.errstate(all="ignore"):
        for _ in range(max_iter):
            r = _distort(plan, x) - xd
            J = _distortion_jacobian(plan, x)
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            dx = np.stack([(J[:, 1, 1] * r[0] - J[:, 0, 1] * r[1]) / det,
                           (J[:, 0, 0] * r[1] - J[:, 1, 0] * r[0]) / det])
            x = x - np.where(np.isfinite(dx), dx, 0.0)
            if np.all(np.abs(dx) <= UNDISTORT_STEP_TOL):
                break
        J = _distortion_jacobian(plan, x)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        residual = np.abs(_distort(plan, x) - xd).max(axis=0)
        # J is symmetric: positive definite = before the fold, not on a mirrored branch
        ok = (residual <= UNDISTORT_TARGET_ERROR * 100.0) & (det > 0.0) & (J[:, 0, 0] > 0.0) \
            & np.isfinite(x).all(0)
    return x, ok


def _grid_steps(plan: SimpleNamespace, xd: np.ndarray, x: np.ndarray):
    """Step sizes, shape (iterations, points), iterating until every point has converged."""
    steps = []
    with np.errstate(all="ignore"):
        for _ in range(UNDISTORT_MAX_ITER):
            x_new = _iterate(plan, xd, x)
            steps.append(np.abs(x_new - x).max(axis=0))
            x = x_new
            if not np.any(steps[-1] > UNDISTORT_STEP_TOL):
                break
    return np.array(steps), x


def _fixed_iteration_plan(plan: SimpleNamespace, xd: np.ndarray):
    """Choose the start, fixed step count and last-step tolerance on the disk grid ``xd``.

    Returns (use_guess, n_fast, fast_tol, x) with x the converged grid, or x None when no grid
    point converges.
    """
    variants = {
        False: _grid_steps(plan, xd, xd),
        True: _grid_steps(plan, xd, _initial_guess(plan, xd, _sq_norm(xd))),
    }
    # Contraction estimate from consecutive steps well above round-off (same map for both).
    rho_obs = 0.0
    for steps, _ in variants.values():
        good = steps[-1] <= UNDISTORT_STEP_TOL  # grid points beyond the fold never converge
        prev, cur = steps[:-1, good], steps[1:, good]
        usable = prev > 1e-12
        if usable.any():
            rho_obs = max(rho_obs, float((cur[usable] / prev[usable]).max()))
    rho = min(max(2.0 * rho_obs, 1e-6), 0.99)
    tol = min(max(UNDISTORT_TARGET_ERROR * (1.0 - rho) / rho, UNDISTORT_STEP_TOL), 1e-8)
    needed = {}
    for use_guess, (steps, _) in variants.items():
        good = steps[-1] <= UNDISTORT_STEP_TOL
        # Every grid point must converge for the fixed count to cover the disk.
        needed[use_guess] = (
            int((np.argmax(steps <= tol, axis=0) + 1).max()) if good.all() else None
        )
    if needed[False] is None and needed[True] is None:
        return False, 0, tol, None
    # The guess costs about one step: use it only when it saves more than that.
    if needed[False] is None:
        use_guess = True
    elif needed[True] is None:
        use_guess = False
    else:
        use_guess = needed[True] + 1 < needed[False]
    return use_guess, needed[use_guess], tol, variants[use_guess][1]


def undistort_normalised(intr: CameraIntrinsics, xd: np.ndarray):
    """Undistort distorted normalised points (the core of :func:`undistort_points`).

    Parameters
    ----------
    intr : CameraIntrinsics
    xd : ndarray, shape (2, n), normalised image units
        Distorted normalised coordinates ``((u - cx)/fx, (v - cy)/fy)``. Modified in place
        where non-finite (set to 0).

    Returns
    -------
    x : ndarray, shape (2, n)
        Undistorted normalised coordinates; 0 where the input is non-finite, meaningless where
        not converged.
    finite : ndarray of bool, shape (n,), or None
        None when every input is finite.
    converged : ndarray of bool, shape (n,), or None
        None when every point converged.
    in_disk : bool
        True when every point lies in the hot-path disk (then both masks are None).
    """
    plan = intr._plan
    if xd.shape[1] == 0:
        return xd, None, None, False
    s = _sq_norm(xd)
    s_max = float(s.max())
    if s_max <= plan.s_max:  # False with NaN
        if not plan.distorted:
            return xd, None, None, True
        x = _initial_guess(plan, xd, s) if plan.use_guess else xd
        for _ in range(plan.n_fast):
            x = _iterate(plan, xd, x)
        return x, None, None, True
    finite = None
    if not np.isfinite(s_max):
        finite = np.isfinite(xd).all(axis=0)
        xd[:, ~finite] = 0.0
        s[~finite] = 0.0
        if finite.all():  # only overflow in |xd|^2
            finite = None
    if not plan.distorted:
        return xd, finite, None, False
    with np.errstate(all="ignore"):
        x = _initial_guess(plan, xd, s) if plan.use_guess else xd
        x_prev = x
        for _ in range(plan.n_fast):
            x_prev = x
            x = _iterate(plan, xd, x)
        if plan.n_fast:
            step_ok = (np.abs(x - x_prev) <= plan.fast_tol).all(axis=0)
            if step_ok.all():
                return x, finite, None, False
            bad = np.flatnonzero(~step_ok)
        else:  # no fixed-count plan: every point takes the slow path
            bad = np.arange(xd.shape[1])
        # Points that need more steps (outside the image) restart from xd, the most robust
        # start, and iterate to the strict tolerance; some never converge (no preimage).
        x = x.copy()
        x[:, bad], conv_b = _iterate_until_converged(plan, xd[:, bad], UNDISTORT_MAX_ITER)
    converged = np.ones(xd.shape[1], dtype=bool)
    converged[bad] = conv_b
    return x, finite, converged, False


def undistort_points(intr: CameraIntrinsics, uv) -> np.ndarray:
    """Undistort pixel coordinates into normalised image coordinates (rays ``(x, y, 1)``).

    Parameters
    ----------
    intr : CameraIntrinsics
    uv : array_like, shape (n, 2), pixels
        Observed (distorted) pixel coordinates.

    Returns
    -------
    ndarray, shape (n, 2), normalised image units
        Undistorted ``(x, y)`` with ``x = X/Z, y = Y/Z``. Rows whose input is non-finite or
        whose iteration did not converge (no preimage under the distortion) are NaN.
    """
    uv = as_points(uv, "uv", 2)
    plan = intr._plan
    xd = np.subtract(uv.T, plan.c, order="C")
    xd *= plan.finv
    x, finite, converged, _ = undistort_normalised(intr, xd)
    out = x.T.copy()
    if finite is not None:
        out[~finite] = np.nan
    if converged is not None:
        out[~converged] = np.nan
    return out


def distort_normalised(intr: CameraIntrinsics, x: np.ndarray) -> np.ndarray:
    """Apply plumb_bob distortion; ``x`` shape (2, n) normalised, returns shape (2, n)."""
    return _distort(intr._plan, x)


def project_points(intr: CameraIntrinsics, p_C) -> np.ndarray:
    """Project points in the camera frame to pixels, with distortion.

    Parameters
    ----------
    intr : CameraIntrinsics
    p_C : array_like, shape (n, 3), metres
        Points in the optical camera frame (z forward).

    Returns
    -------
    ndarray, shape (n, 2), pixels
        Distorted pixel coordinates. Rows with ``Z <= 0`` or non-finite input are NaN. Points
        far outside the field of view may land inside the image (the distortion polynomial
        folds back); check bounds against the undistorted field of view where that matters.
    """
    p_C = as_points(p_C, "p_C", 3)
    plan = intr._plan
    z = p_C[:, 2]
    ok = (z > 0.0) & np.isfinite(p_C).all(axis=1)
    with np.errstate(all="ignore"):
        x = p_C[:, :2].T / z
        xd = _distort(plan, x) if plan.distorted else x
        uv = (xd * plan.f + plan.c).T.copy()
    uv[~ok] = np.nan
    return uv
