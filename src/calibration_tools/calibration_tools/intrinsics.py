"""Camera intrinsics by Zhang's method (OpenCV) from board images at U1 = 0 (no rclpy).

DESIGN.md section 3 step 1. The targets are small boards that fit the ~60 x 45 mm view
(:class:`~calibration_tools.board_layout.Checkerboard`,
:class:`~calibration_tools.board_layout.CircleGrid`). With a 54 mm telephoto lens the field
of view is ~5 degrees, so the focal length is only determined through the perspective of
tilted boards, and Zhang's closed-form start is poor: the current (nominal) intrinsics are
used as the initial guess by default.

Outlier views: after each calibration the per-view RMS reprojection error is compared with
``outlier_factor`` times the median view and with ``max_view_rms_px``; the worst offending
view is dropped and the calibration repeated until no view offends.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from reconstructor.model import CameraIntrinsics

from .board_layout import Checkerboard, CircleGrid
from .circle_board import detect_circles
from .small_board import as_uint8_image, detect_board
from .stages import CaptureView, StageResult

#: Distortion models: which plumb_bob coefficients are estimated.
DIST_MODELS = ("none", "k1", "k1k2", "k1k2p1p2", "full")


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


def detect_target(image, board) -> np.ndarray | None:
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

    Returns
    -------
    ndarray, shape (cols * rows, 2), pixels, or None when the whole target is not found
    """
    if isinstance(board, Checkerboard):
        corners = detect_board(board, image)
        if corners is None:
            return None
        # Symmetry refinement over a window of ~0.4 square sides (from the corner spacing).
        grid = corners.reshape(board.rows, board.cols, 2)
        side = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
        img = np.asarray(image)
        img = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else img
        return refine_corners_symmetric(img, corners, radius_px=max(2.0, 0.4 * side))
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
        Standard deviations reported by OpenCV (fx, fy, cx, cy px; k1, k2, p1, p2, k3).
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: np.ndarray
    used: np.ndarray
    rejected: dict = field(default_factory=dict)
    std: dict = field(default_factory=dict)


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
        rms, K, dist, rvecs, tvecs, std_i, _, _ = cv2.calibrateCameraExtended(
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
    view_rms = _all_view_rms(obj, img, idx, vr, used, K, dist)
    d = np.zeros(5)
    d[: min(5, dist.size)] = np.asarray(dist).ravel()[:5]
    intr = CameraIntrinsics(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        dist=tuple(float(v) for v in d), width=w, height=h,
    )
    s = np.asarray(std_i).ravel()
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    std = {k: float(v) for k, v in zip(names, s[: len(names)], strict=False)}
    return IntrinsicsResult(intr, float(rms), view_rms, used, rejected, std)


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
    outlier_factor, max_view_rms_px, min_views
        As :func:`calibrate_intrinsics`.
    progress : callable, optional
        ``progress(done, total, message)``.

    Returns
    -------
    StageResult
        ``updates['intrinsics']`` = fx, fy, cx, cy, dist, width, height. Residuals:
        ``reprojection_rms_px``, ``worst_view_rms_px``. ``extra['intrinsics']``: per-view
        RMS, standard deviations.
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
        min_views=min_views,
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
            "dist_model": dist_model,
        }},
    )
