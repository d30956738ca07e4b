"""Camera intrinsics by Zhang's method (OpenCV) from board images at U1 = 0 (no rclpy).

docs/design.md section 3 step 1. The targets are small boards that fit the ~60 x 45 mm view
(:class:`~calibration_tools.board_layout.Checkerboard`,
:class:`~calibration_tools.board_layout.CircleGrid`). With a 54 mm telephoto lens the field
of view is ~5 degrees, so the focal length is only determined through the perspective of
tilted boards, and Zhang's closed-form start is poor: the current (nominal) intrinsics are
used as the initial guess by default.

Outlier views: after each calibration the per-view RMS reprojection error is compared with
``outlier_factor`` times the median view and with ``max_view_rms_px``; the worst offending
view is dropped and the calibration repeated until no view offends.

Gauge of the narrow field of view. Over a 5-degree field three pairs
of parameters are nearly interchangeable, as the correlation matrix of the Jacobian shows
on the reference rig (30 tilted checkerboard views, 0.023 px noise):

- ``cx`` with ``p2`` (correlation -0.91) and ``cy`` with ``p1`` (-0.79): a shift of the
  principal point is a small rotation of the camera, which the board poses take up except
  for a term quadratic in the field angle, and that term is what decentring distortion
  looks like. Unpinned, the data give cx to +-6 px and cy to +-4.4 px; two noise draws
  gave cx 3.6 px apart;
- ``k1`` with ``k2`` (-0.96): the r**4 term moves the image corner by 0.005 px per unit of
  k2, so k2 came out 17 and 27 (+-25) against a true 4.

They are pinned by stated priors (:class:`LensPrior`), a maximum a posteriori refinement
after OpenCV's fit: the principal point lies within the lens centring tolerance of the
sensor centre, ``((width - 1) / 2, (height - 1) / 2)`` (+-10 px, 1-sigma 10/sqrt(3) px);
the decentring coefficients p1, p2 are of the reference lens's order (|p| <= 5e-4,
1-sigma 5e-4/sqrt(3)); k2 of the reference order (|k2| <= 8, 1-sigma 8/sqrt(3)); k3 is not
estimated. These are lens-data tolerances, the same for every rig of the family (35-75 mm
lenses): where the field of view determines a parameter better than its prior (shorter
lenses, wider fields), the data win and the prior does nothing; where it does not, the
parameter stays within its prior instead of drifting with the noise. The prior is centred
on the sensor centre, never on the starting calibration's value. Standard errors of every
estimated parameter come from the Jacobian of the reprojection residuals at the solution,
board poses included (:func:`calibration_tools.stages.covariance_from_jacobian`); OpenCV's
own figures are not used (they ignore the correlations with the board poses).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from reconstructor.model import CameraIntrinsics

from .board_layout import Checkerboard, CircleGrid
from .circle_board import detect_circles
from .small_board import as_uint8_image, detect_board
from .stages import CaptureView, StageResult, correlation, covariance_from_jacobian

#: Distortion models: which plumb_bob coefficients are estimated.
DIST_MODELS = ("none", "k1", "k1k2", "k1k2p1p2", "full")
#: The intrinsic parameters, in the order of OpenCV's ``projectPoints`` Jacobian columns.
INTRINSIC_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_FREE = {
    "none": ("fx", "fy", "cx", "cy"),
    "k1": ("fx", "fy", "cx", "cy", "k1"),
    "k1k2": ("fx", "fy", "cx", "cy", "k1", "k2"),
    "k1k2p1p2": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "full": INTRINSIC_PARAMS,
}


def _dist_flags(dist_model: str) -> int:
    if dist_model not in DIST_MODELS:
        raise ValueError(f"dist_model must be one of {DIST_MODELS}, got {dist_model!r}")
    flags = {
        "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
        | cv2.CALIB_ZERO_TANGENT_DIST,
        "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
        "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
        "k1k2p1p2": cv2.CALIB_FIX_K3,
        "full": 0,
    }
    return flags[dist_model]


@dataclass(frozen=True)
class LensPrior:
    """Prior knowledge of the lens that pins the gauge of a narrow field (module docstring).

    Attributes
    ----------
    principal_point_sigma_px : float, pixels
        1-sigma of cx and cy about the sensor centre (lens centring tolerance +-10 px).
    tangential_sigma : float
        1-sigma of p1 and p2 about 0 (decentring of the reference order, |p| <= 5e-4).
    k2_sigma : float
        1-sigma of k2 about 0 (radial distortion of the reference order, |k2| <= 8).
    """

    principal_point_sigma_px: float = 10.0 / math.sqrt(3.0)
    tangential_sigma: float = 5e-4 / math.sqrt(3.0)
    k2_sigma: float = 8.0 / math.sqrt(3.0)

    def __post_init__(self):
        for name in ("principal_point_sigma_px", "tangential_sigma", "k2_sigma"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"LensPrior.{name} must be > 0 (inf: no prior), got {v!r}")

    def mean_sigma(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Prior mean and 1-sigma of :data:`INTRINSIC_PARAMS`, each shape (9,) (inf: none)."""
        mean = np.array([0.0, 0.0, (width - 1) / 2.0, (height - 1) / 2.0, 0, 0, 0, 0, 0])
        pp, t = self.principal_point_sigma_px, self.tangential_sigma
        sigma = np.array([np.inf, np.inf, pp, pp, np.inf, self.k2_sigma, t, t, np.inf])
        return mean, sigma


def refine_corners_symmetric(image, corners, radius_px: float = 10.0, iterations: int = 8):
    """Sub-pixel checkerboard corners as centres of point symmetry.

    Around an X-corner the image is point-symmetric, ``I(c + d) = I(c - d)``, under any
    local affine map (perspective to first order) and any symmetric blur. Each corner is
    moved by Gauss-Newton to minimise the Gaussian-weighted sum of squared differences over
    a disc of radius ``radius_px``.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    corners : array_like, shape (n, 2), pixels
        Starting positions (within ~1 px).
    radius_px : float
        Half-size of the symmetric window, pixels (keep it below ~0.45 square sides).
    iterations : int

    Returns
    -------
    ndarray, shape (n, 2), pixels
        Refined corners; a corner whose step exceeds ``radius_px / 2`` keeps its start.
    """
    img = np.asarray(image, dtype=np.float32)
    c0 = np.asarray(corners, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must have shape (H, W), got {img.shape}")
    if c0.ndim != 2 or c0.shape[1] != 2:
        raise ValueError(f"corners must have shape (n, 2), got {c0.shape}")
    if not radius_px >= 2.0:
        raise ValueError(f"radius_px must be >= 2, got {radius_px}")
    g = np.arange(-np.floor(radius_px), np.floor(radius_px) + 1.0)
    dx, dy = np.meshgrid(g, g)
    half = (dx**2 + dy**2 <= radius_px**2) & ((dy > 0) | ((dy == 0) & (dx > 0)))
    dx, dy = dx[half], dy[half]
    w = np.exp(-(dx**2 + dy**2) / (2.0 * (radius_px / 2.0) ** 2))
    c = c0.copy()
    h = 0.05  # finite-difference step of the Jacobian, pixels

    def residual(cu, cv):
        a = cv2.remap(img, (cu + dx).astype(np.float32), (cv + dy).astype(np.float32),
                      cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        b = cv2.remap(img, (cu - dx).astype(np.float32), (cv - dy).astype(np.float32),
                      cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return w * (a.astype(np.float64) - b.astype(np.float64))

    for _ in range(iterations):
        cu, cv = c[:, :1], c[:, 1:]
        r = residual(cu, cv)
        ju = (residual(cu + h, cv) - residual(cu - h, cv)) / (2.0 * h)
        jv = (residual(cu, cv + h) - residual(cu, cv - h)) / (2.0 * h)
        a11, a12, a22 = (ju * ju).sum(1), (ju * jv).sum(1), (jv * jv).sum(1)
        b1, b2 = (ju * r).sum(1), (jv * r).sum(1)
        det = a11 * a22 - a12 * a12
        with np.errstate(all="ignore"):
            step = -np.column_stack([a22 * b1 - a12 * b2, a11 * b2 - a12 * b1]) / det[:, None]
        step = np.where(np.isfinite(step), step, 0.0)
        c = c + step
        if np.abs(step).max() < 1e-5:
            break
    bad = ~(np.linalg.norm(c - c0, axis=1) <= radius_px / 2.0)
    c[bad] = c0[bad]
    return c


def detect_target(image, board, fast: bool = False) -> np.ndarray | None:
    """Features of an intrinsics target, in ``board.object_points()`` order.

    Checkerboards use ``findChessboardCornersSB``, refined by
    :func:`refine_corners_symmetric`. Circle grids are ordered by
    ``findCirclesGrid`` with a blob detector sized for large circles, then each centre is
    replaced by the sub-pixel ellipse centre of :func:`~calibration_tools.circle_board.
    detect_circles`.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16
    board : Checkerboard or CircleGrid
    fast : bool
        A checkerboard: OpenCV's plain search first, the exhaustive one when that finds
        nothing (:func:`~calibration_tools.small_board.detect_board`). After the refinement
        the corners agree with the exhaustive search's to 6e-5 px on the reference rig's
        intrinsics plan, in a fifth of the time; for finding a board and gating its views
        (a stage's data keep the exhaustive search, whose result repeats bit for bit).

    Returns
    -------
    ndarray, shape (cols * rows, 2), pixels, or None when the whole target is not found
    """
    if isinstance(board, Checkerboard):
        corners = detect_board(board, image, fast=fast)
        if corners is None:
            return None
        # Symmetry refinement over a window of ~0.4 square sides (from the corner spacing).
        grid = corners.reshape(board.rows, board.cols, 2)
        side = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
        return refine_corners_symmetric(as_uint8_image(image), corners,
                                        radius_px=max(2.0, 0.4 * side))
    if not isinstance(board, CircleGrid):
        raise ValueError(f"board must be a Checkerboard or CircleGrid, got {type(board).__name__}")
    img = as_uint8_image(image)
    dets = detect_circles(img, min_radius_px=3.0)
    if len(dets) < board.cols * board.rows:
        return None
    r = float(np.median(dets.radii))
    params = cv2.SimpleBlobDetector_Params()
    params.minArea = 0.3 * np.pi * r * r
    params.maxArea = 3.0 * np.pi * r * r
    params.minDistBetweenBlobs = r
    params.filterByColor = True
    params.blobColor = 0
    params.filterByConvexity = False
    params.filterByInertia = False
    params.filterByCircularity = False
    detector = cv2.SimpleBlobDetector_create(params)
    found, centres = cv2.findCirclesGrid(
        img, (board.cols, board.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID, blobDetector=detector
    )
    if not found or centres is None:
        return None
    rough = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    dist = np.linalg.norm(rough[:, None, :] - dets.centres[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)
    if np.any(dist[np.arange(len(rough)), nearest] > 0.5 * r) or len(set(nearest)) != len(rough):
        return None
    return dets.centres[nearest]


@dataclass
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    rms_px : float
        RMS reprojection error over the used views, pixels.
    view_rms_px : ndarray, shape (n,), pixels
        Per-view RMS reprojection error (of the final calibration, for every view).
    used : ndarray of bool, shape (n,)
    rejected : dict of int to str
        View index to reason.
    std : dict of str to float
        1-sigma standard errors of the estimated parameters (fx, fy, cx, cy in px; k1, k2,
        p1, p2, k3 as estimated), from the Jacobian at the solution with the priors.
    correlation : ndarray, shape (p, p)
        Correlation matrix of the estimated parameters, in ``std`` order.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: np.ndarray
    used: np.ndarray
    rejected: dict = field(default_factory=dict)
    std: dict = field(default_factory=dict)
    correlation: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))


def projection_jacobian(obj, img, K, dist, rvecs, tvecs) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals and their Jacobian over all views of a Zhang calibration.

    Parameters
    ----------
    obj : sequence of ndarray, each shape (m_i, 3), metres
        Target points per view.
    img : sequence of ndarray, each shape (m_i, 2), pixels
        Detected points per view.
    K : ndarray, shape (3, 3), pixels
    dist : array_like, shape (5,)
        (k1, k2, p1, p2, k3).
    rvecs, tvecs : sequence of array_like, each shape (3,) (radians, metres)
        Target pose per view.

    Returns
    -------
    residuals : ndarray, shape (2N,), pixels
        Projected minus detected, (u, v) interleaved, N the points of all views.
    jac : ndarray, shape (2N, 9 + 6n)
        Derivatives with respect to :data:`INTRINSIC_PARAMS` (px per px, px per unit
        coefficient), then (rvec [px/rad], tvec [px/m]) of each of the n views.
    """
    n = len(obj)
    d5 = np.zeros(5)
    d5[: min(5, np.size(dist))] = np.asarray(dist, dtype=np.float64).ravel()[:5]
    res, jac = [], []
    for i, (o, p, r, t) in enumerate(zip(obj, img, rvecs, tvecs, strict=True)):
        proj, j = cv2.projectPoints(np.asarray(o, dtype=np.float64),
                                    np.asarray(r, dtype=np.float64),
                                    np.asarray(t, dtype=np.float64), K, d5)
        block = np.zeros((j.shape[0], 9 + 6 * n))
        block[:, :9] = j[:, 6:15]
        block[:, 9 + 6 * i: 15 + 6 * i] = j[:, :6]
        res.append((proj.reshape(-1, 2) - np.asarray(p, dtype=np.float64)).ravel())
        jac.append(block)
    return np.concatenate(res), np.vstack(jac)


def _intrinsic_vector(K, dist) -> np.ndarray:
    """(fx, fy, cx, cy, k1, k2, p1, p2, k3) of a camera matrix and distortion, shape (9,)."""
    d5 = np.zeros(5)
    d5[: min(5, np.size(dist))] = np.asarray(dist, dtype=np.float64).ravel()[:5]
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d5])


def _camera(v) -> tuple[np.ndarray, np.ndarray]:
    """Camera matrix (3, 3) and distortion (5,) of an intrinsic vector (9,)."""
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return K, np.array(v[4:9], dtype=np.float64)


@dataclass
class _MapFit:
    """Result of :func:`_map_refine`: the solution and its covariance."""

    vector: np.ndarray  # shape (9,), INTRINSIC_PARAMS order
    rvecs: np.ndarray  # shape (n, 3)
    tvecs: np.ndarray  # shape (n, 3)
    free: tuple  # names of the estimated intrinsics
    cov: np.ndarray  # shape (len(free), len(free)), their covariance
    residuals: np.ndarray  # shape (2N,), pixels


def _map_refine(obj, img, K, dist, rvecs, tvecs, free, prior, size) -> _MapFit:
    """Maximum a posteriori bundle over the free intrinsics and every board pose.

    Starts from OpenCV's solution; the prior terms weigh ``(x - mean) / sigma`` against the
    reprojection residuals scaled by their standard deviation ``s``, so that the covariance
    is ``inv(J.T J / s**2 + diag(1 / sigma**2))``. Without a prior it only polishes the fit
    and gives the Jacobian's covariance.
    """
    n = len(obj)
    v0 = _intrinsic_vector(K, dist)
    fi = np.array([INTRINSIC_PARAMS.index(k) for k in free])
    mean, sigma = prior.mean_sigma(*size) if prior is not None else (np.zeros(9),
                                                                      np.full(9, np.inf))
    mean, sigma = mean[fi], sigma[fi]
    has = np.flatnonzero(np.isfinite(sigma))
    poses0 = np.column_stack([np.reshape(rvecs, (n, 3)), np.reshape(tvecs, (n, 3))])
    z0 = np.concatenate([v0[fi], poses0.ravel()])
    cols = np.concatenate([fi, np.arange(9, 9 + 6 * n)])

    def data(z):
        v = v0.copy()
        v[fi] = z[: len(fi)]
        poses = z[len(fi):].reshape(n, 6)
        Kz, dz = _camera(v)
        r, J = projection_jacobian(obj, img, Kz, dz, poses[:, :3], poses[:, 3:])
        return r, J[:, cols]

    r0, _ = data(z0)
    w = math.sqrt(float(r0 @ r0) / max(len(r0) - len(z0), 1)) / sigma[has]
    z = _gauss_newton(data, z0, has, w, mean[has])
    r, J = data(z)
    cov, _ = covariance_from_jacobian(J, r, prior_sigma=np.concatenate(
        [sigma, np.full(6 * n, np.inf)]))
    v = v0.copy()
    v[fi] = z[: len(fi)]
    poses = z[len(fi):].reshape(n, 6)
    return _MapFit(v, poses[:, :3], poses[:, 3:], tuple(free), cov[: len(fi), : len(fi)], r)


def _gauss_newton(data, z0, has, w, mean, iterations: int = 30) -> np.ndarray:
    """Levenberg-damped Gauss-Newton on ``|r(z)|**2 + |w (z[has] - mean)|**2``.

    ``data(z) -> (r, J)``; the normal equations are small (free intrinsics plus six
    parameters per view), so this is much cheaper than a dense SVD of the whole Jacobian.
    """
    z = z0.copy()
    r, J = data(z)
    cost = float(r @ r) + float(np.sum((w * (z[has] - mean)) ** 2))
    lam = 1e-6
    for _ in range(iterations):
        A = J.T @ J
        g = J.T @ r
        A[has, has] += w**2
        g[has] += w**2 * (z[has] - mean)
        dA = np.sqrt(np.diag(A))
        dA = np.where(dA > 0, dA, 1.0)
        An = A / np.outer(dA, dA)
        step = -np.linalg.solve(An + lam * np.eye(len(z)), g / dA) / dA
        z_new = z + step
        r_new, J_new = data(z_new)
        cost_new = float(r_new @ r_new) + float(np.sum((w * (z_new[has] - mean)) ** 2))
        if cost_new <= cost:
            done = cost - cost_new <= 1e-12 * cost
            z, r, J, cost, lam = z_new, r_new, J_new, cost_new, max(lam / 10.0, 1e-9)
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return z


def _view_rms(obj, img, K, dist, rvecs, tvecs):
    out = []
    for o, p, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p) ** 2, axis=1)))))
    return np.array(out)


def _view_points(image_points, object_points) -> tuple[list, list]:
    """Per-view image points (m_i, 2) and object points (m_i, 3) as float64, checked."""
    img = [np.asarray(p, dtype=np.float64) for p in image_points]
    n = len(img)
    if isinstance(object_points, np.ndarray) and object_points.ndim == 2:
        obj = [np.asarray(object_points, dtype=np.float64)] * n
    else:
        obj = [np.asarray(o, dtype=np.float64) for o in object_points]
    if len(obj) != n:
        raise ValueError(f"object_points must have one entry per view ({n}), got {len(obj)}")
    for i, (o, p) in enumerate(zip(obj, img, strict=True)):
        if p.ndim != 2 or p.shape[1] != 2 or o.shape != (len(p), 3) or len(p) < 4:
            raise ValueError(f"image_points[{i}] shape {p.shape} and object_points shape "
                             f"{o.shape} must be (m >= 4, 2) and (m, 3)")
        if not (np.isfinite(p).all() and np.isfinite(o).all()):
            raise ValueError(f"image_points[{i}] or its object points are not finite")
    return img, obj


def _all_view_rms(obj, img, idx, vr, used, K, dist) -> np.ndarray:
    """Per-view errors for every view (rejected ones through their own PnP)."""
    view_rms = np.full(len(img), np.nan)
    view_rms[idx] = vr
    for i in np.flatnonzero(~used):
        ok, rv, tv = cv2.solvePnP(obj[i], img[i], K, dist)
        if ok:
            view_rms[i] = _view_rms([obj[i]], [img[i]], K, dist, [rv], [tv])[0]
    return view_rms


def _detect_views(views, board, current, max_abs_u1, progress) -> tuple[list, list, list]:
    """Target points of the usable views, their input indices, and why the others are not."""
    size = (current.width, current.height)
    rejected: list[str] = []
    pts, keep = [], []
    for i, view in enumerate(views):
        v = np.asarray(view.voltages, dtype=np.float64)
        if v.shape != (4,) or not np.isfinite(v).all():
            rejected.append(f"view {i}: voltages must be 4 finite values")
            continue
        if np.abs(v[:2]).max() > max_abs_u1:
            rejected.append(f"view {i}: U1 = ({v[0]:+.4f}, {v[1]:+.4f}) V is not at 0")
            continue
        if view.laser_on:
            rejected.append(f"view {i}: laser on")
            continue
        img = np.asarray(view.image)
        if img.shape != (current.height, current.width):
            rejected.append(f"view {i}: image shape {img.shape} is not {size[::-1]}")
            continue
        p = detect_target(img, board)
        if p is None:
            rejected.append(f"view {i}: target not found")
        else:
            pts.append(p)
            keep.append(i)
        if progress is not None:
            progress(i + 1, len(views), "detecting the target")
    return pts, keep, rejected


def _initial_guess(initial, dist_model: str) -> tuple[np.ndarray, np.ndarray, int]:
    """OpenCV's start: camera matrix (3, 3), distortion (5,) and calibration flags."""
    flags = _dist_flags(dist_model)
    if initial is not None:
        K0 = initial.matrix()
        d0 = np.array(initial.dist, dtype=np.float64)
        if dist_model == "none":
            d0[:] = 0.0
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    else:
        K0 = np.eye(3)
        d0 = np.zeros(5)
    return K0, d0, flags


def calibrate_intrinsics(
    image_points: Sequence,
    object_points,
    image_size: tuple[int, int],
    *,
    initial: CameraIntrinsics | None = None,
    dist_model: str = "k1k2p1p2",
    outlier_factor: float = 3.0,
    max_view_rms_px: float = 1.0,
    min_views: int = 4,
    prior: LensPrior | None = LensPrior(),
) -> IntrinsicsResult:
    """Zhang's calibration with per-view errors and outlier-view rejection.

    Parameters
    ----------
    image_points : sequence of array_like, each shape (m_i, 2), pixels
    object_points : array_like shape (m, 3) for all views, or sequence of shape (m_i, 3),
        metres
    image_size : (int, int)
        (width, height), pixels.
    initial : CameraIntrinsics, optional
        Initial guess (recommended for narrow fields of view); Zhang's closed form if None.
    dist_model : str
        One of :data:`DIST_MODELS`.
    outlier_factor : float
        A view is an outlier above ``outlier_factor`` times the median view RMS ...
    max_view_rms_px : float
        ... or above this absolute RMS, pixels (whichever is larger is not the rule: a view
        must pass both the relative test, floored at 0.05 px, and the absolute one).
    min_views : int
        Fewer usable views raise ValueError.
    prior : LensPrior or None
        Priors that pin the parameters a narrow field cannot separate (module docstring);
        None: OpenCV's least-squares solution (standard errors from the Jacobian still).

    Returns
    -------
    IntrinsicsResult
    """
    img, obj = _view_points(image_points, object_points)
    n = len(img)
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size must be positive (width, height), got {image_size}")
    if outlier_factor <= 1.0 or max_view_rms_px <= 0.0:
        raise ValueError("outlier_factor must be > 1 and max_view_rms_px > 0")
    if prior is not None and not isinstance(prior, LensPrior):
        raise ValueError(f"prior must be a LensPrior or None, got {type(prior).__name__}")
    K0, d0, flags = _initial_guess(initial, dist_model)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    used = np.ones(n, dtype=bool)
    rejected: dict[int, str] = {}
    while True:
        idx = np.flatnonzero(used)
        if len(idx) < min_views:
            raise ValueError(f"only {len(idx)} usable views, need {min_views} "
                             f"({len(rejected)} rejected as outliers)")
        o_sel = [obj[i].astype(np.float32) for i in idx]
        p_sel = [img[i].astype(np.float32).reshape(-1, 1, 2) for i in idx]
        _, K, dist, rvecs, tvecs, _, _, _ = cv2.calibrateCameraExtended(
            o_sel, p_sel, (w, h), K0.copy(), d0.copy(), flags=flags, criteria=criteria
        )
        vr = _view_rms([obj[i] for i in idx], [img[i] for i in idx], K, dist, rvecs, tvecs)
        limit = min(max(outlier_factor * float(np.median(vr)), 0.05), max_view_rms_px)
        worst = int(np.argmax(vr))
        if vr[worst] <= limit:
            break
        used[idx[worst]] = False
        rejected[int(idx[worst])] = (f"outlier view: reprojection rms {vr[worst]:.3f} px > "
                                     f"{limit:.3f} px")
    fit = _map_refine([obj[i] for i in idx], [img[i] for i in idx], K, dist, rvecs, tvecs,
                      _FREE[dist_model], prior, (w, h))
    K, dist = _camera(fit.vector)
    vr = _view_rms([obj[i] for i in idx], [img[i] for i in idx], K, dist, fit.rvecs,
                   fit.tvecs)
    view_rms = _all_view_rms(obj, img, idx, vr, used, K, dist)
    rms = math.sqrt(float(fit.residuals @ fit.residuals) / (len(fit.residuals) // 2))
    v = fit.vector
    intr = CameraIntrinsics(
        fx=float(v[0]), fy=float(v[1]), cx=float(v[2]), cy=float(v[3]),
        dist=tuple(float(x) for x in v[4:9]), width=w, height=h,
    )
    std = {k: float(x) for k, x in zip(fit.free, np.sqrt(np.diag(fit.cov)), strict=True)}
    return IntrinsicsResult(intr, float(rms), view_rms, used, rejected, std,
                            correlation(fit.cov))


def run_intrinsics(
    views: Sequence[CaptureView],
    calibration,
    board: Checkerboard | CircleGrid,
    *,
    max_abs_u1: float = 0.002,
    dist_model: str = "k1k2p1p2",
    use_initial_guess: bool = True,
    outlier_factor: float = 3.0,
    max_view_rms_px: float = 1.0,
    min_views: int = 4,
    prior: LensPrior | None = LensPrior(),
    progress: Callable | None = None,
) -> StageResult:
    """The intrinsics stage: Zhang's method on target views taken at U1 = 0.

    Parameters
    ----------
    views : sequence of CaptureView
        Target images; views with ``|U1| > max_abs_u1`` or the laser on are rejected.
    calibration : reconstructor.calibration_file.Calibration
        Current calibration; its intrinsics are the initial guess and give the image size.
    board : Checkerboard or CircleGrid
    max_abs_u1 : float, volts
    dist_model : str
        One of :data:`DIST_MODELS`.
    use_initial_guess : bool
        Start from the calibration's intrinsics (recommended for the telephoto lens).
    outlier_factor, max_view_rms_px, min_views, prior
        As :func:`calibrate_intrinsics`.
    progress : callable, optional
        ``progress(done, total, message)``.

    Returns
    -------
    StageResult
        ``updates['intrinsics']`` = fx, fy, cx, cy, dist, width, height. Residuals:
        ``reprojection_rms_px``, ``worst_view_rms_px``. ``extra['intrinsics']``: per-view
        RMS, standard errors, their correlation, the priors and the coefficients held at 0.
        ``standard_errors['intrinsics']``: fx, fy, cx, cy (px) and dist (five, 0 for a
        coefficient the distortion model holds at 0).
    """
    if not isinstance(board, (Checkerboard, CircleGrid)):
        raise ValueError(f"board must be a Checkerboard or CircleGrid, got {type(board).__name__}")
    if max_abs_u1 < 0:
        raise ValueError(f"max_abs_u1 must be >= 0, got {max_abs_u1}")
    current = calibration.model.intrinsics
    size = (current.width, current.height)
    pts, keep, rejected = _detect_views(views, board, current, max_abs_u1, progress)
    if len(pts) < min_views:
        raise ValueError(f"intrinsics: only {len(pts)} views with the target found, need "
                         f"{min_views} ({'; '.join(rejected[:5])})")
    res = calibrate_intrinsics(
        pts, board.object_points(), size, initial=current if use_initial_guess else None,
        dist_model=dist_model, outlier_factor=outlier_factor, max_view_rms_px=max_view_rms_px,
        min_views=min_views, prior=prior,
    )
    for j, reason in sorted(res.rejected.items()):
        rejected.append(f"view {keep[j]}: {reason}")
    intr = res.intrinsics
    used_rms = res.view_rms_px[res.used]
    return StageResult(
        stage="intrinsics",
        updates={"intrinsics": {
            "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
            "dist": list(intr.dist), "width": intr.width, "height": intr.height,
        }},
        residuals={
            "reprojection_rms_px": res.rms_px,
            "worst_view_rms_px": float(np.max(used_rms)),
        },
        samples_used=int(res.used.sum()),
        samples_rejected=len(views) - int(res.used.sum()),
        rejected=rejected,
        extra={"intrinsics": {
            "view_rms_px": {int(keep[j]): float(r) for j, r in enumerate(res.view_rms_px)},
            "std": res.std,
            "correlation": np.round(res.correlation, 4).tolist(),
            "dist_model": dist_model,
            "fixed_at_zero": [k for k in INTRINSIC_PARAMS[4:] if k not in res.std],
            "prior": None if prior is None else dataclasses.asdict(prior),
        }},
        standard_errors={"intrinsics": {
            **{k: res.std[k] for k in ("fx", "fy", "cx", "cy")},
            "dist": [res.std.get(k, 0.0) for k in INTRINSIC_PARAMS[4:]],
        }},
        covariance=intrinsics_covariance(res),
    )


#: Model key of each intrinsic parameter (distortion in OpenCV's k1, k2, p1, p2, k3 order).
_MODEL_KEY = {**{k: f"intrinsics.{k}" for k in ("fx", "fy", "cx", "cy")},
              **{k: f"intrinsics.dist[{j}]" for j, k in enumerate(INTRINSIC_PARAMS[4:])}}


def intrinsics_covariance(res: IntrinsicsResult) -> dict:
    """The covariance record (``StageResult.covariance``) of a calibration's estimated
    intrinsics: standard errors and correlation joined, named by model key."""
    from reconstructor.uncertainty import covariance_record

    names = list(res.std)
    sd = np.array([res.std[k] for k in names])
    corr = np.nan_to_num(np.asarray(res.correlation, dtype=np.float64))
    return covariance_record([_MODEL_KEY[k] for k in names], corr * np.outer(sd, sd))
