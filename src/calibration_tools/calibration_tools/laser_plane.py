"""Laser plane at U2 = 0 (docs/design.md §3 step 3): board plane by PnP, stripe back-projection,
SVD plane fit with outlier rejection. No rclpy.

Building blocks
---------------
- :func:`fit_plane_svd`: (weighted) least-squares plane (SVD of the centred points) with
  iterative rejection of points farther than ``k_sigma`` robust standard deviations
  (1.4826 MAD) from the plane; optionally a robust start (least median of squares).
- :func:`fit_line_trimmed`: the same for a 3-D line (one stripe on one board).
- :func:`board_plane_from_pnp`: board pose and plane in the camera frame from detected
  features (OpenCV IPPE, then Levenberg-Marquardt refinement).
- :func:`backproject_to_plane`: intersect the (undistorted) pixel rays with a plane.
- :func:`board_stripe_points`: the data pipeline shared with the laser-axis stage. For each
  laser-on view it finds the board plane from a laser-off view of the same board pose and
  G1 voltages (or, failing that, from the laser-on view itself), extracts the stripe with
  :mod:`stripe_extractor`, keeps the stripe pixels inside the detected board, back-projects
  them onto the board plane in V, drops those near the pattern's albedo edges (where the
  stripe's profile is skewed) and off the stripe's line, and maps them to V0 with the
  current model.
- :func:`plane_from_stripes`: one plane from the stripes of several board poses, every pose
  weighted the same (its error is mostly a shift of its whole line).

Stage
-----
:func:`run_laser_plane` fits ``laser_plane_v0`` from views with U2_tilt = 0.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration_tools.small_board import (
    away_from_pattern_edges,
    check_small_board,
    detect_board,
    inside_convex_hull,
)
from calibration_tools.sphere_fit import finite_rows
from calibration_tools.stages import (
    VOLTAGE_TOL,
    CaptureView,
    StageResult,
    covariance_from_jacobian,
)

log = logging.getLogger('galvoscan.calibration.laser_plane')



# ----------------------------------------------------------------------------- plane fit
@dataclass(frozen=True)
class PlaneFit:
    """A fitted plane.

    Attributes
    ----------
    plane : ndarray, shape (4,)
        (a, b, c, e) with unit normal, e in metres.
    rms : float, metres
        RMS point-to-plane distance of the inliers.
    max_abs : float, metres
        Largest inlier distance.
    inliers : ndarray of bool, shape (n,)
    singular_values : ndarray, shape (3,), metres
        Of the centred inliers divided by sqrt(n): the spread along the plane's two in-plane
        directions and its normal (a tiny middle value means the points are nearly collinear).
    """

    plane: np.ndarray
    rms: float
    max_abs: float
    inliers: np.ndarray
    singular_values: np.ndarray

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def _svd_plane(p: np.ndarray, w: np.ndarray | None = None):
    if w is None:
        c = p.mean(axis=0)
        _, s, vt = np.linalg.svd(p - c, full_matrices=False)
        return np.append(vt[2], -vt[2] @ c), s / np.sqrt(p.shape[0])
    w = w / w.sum()
    c = w @ p
    _, s, vt = np.linalg.svd((p - c) * np.sqrt(w)[:, None], full_matrices=False)
    return np.append(vt[2], -vt[2] @ c), s


def fit_plane_svd(points, *, weights=None, k_sigma: float = 4.0,
                  min_threshold: float = 1e-6, max_iter: int = 20, robust_start: bool = False,
                  orient=None, seed: int = 0) -> PlaneFit:
    """Fit a plane to 3-D points with outlier rejection.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres
        n >= 3, not all collinear.
    weights : array_like, shape (n,), optional
        Non-negative weights of the least-squares fit (e.g. one over the number of points of
        each board pose, so that every pose counts the same). Rejection ignores them.
    k_sigma : float
        Points farther than ``max(k_sigma * 1.4826 * MAD, min_threshold)`` from the plane are
        rejected; the fit is repeated until the inlier set stops changing.
    min_threshold : float, metres
        Floor of the rejection distance (keeps noise-free data from being trimmed).
    max_iter : int
    robust_start : bool
        Start from the least-median-of-squares plane through random point triples instead of
        the plain least-squares plane (resists up to about 50 % gross outliers). Do not use
        it on points from few stripes: a plane through one stripe holding half of the points
        has a zero median residual.
    orient : array_like, shape (3,), optional
        Sign convention: the normal is flipped to have a non-negative dot product with this.
        By default the plane's offset e is made <= 0 (normal pointing away from the origin).
    seed : int
        Seed of the random triples (the result is deterministic).

    Returns
    -------
    PlaneFit
    """
    p = finite_rows(points, 'points', 3)
    if not k_sigma > 0:
        raise ValueError(f'k_sigma must be > 0, got {k_sigma}')
    n = p.shape[0]
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
            raise ValueError(f'weights must be finite, >= 0, not all 0, shape ({n},)')
    plane, s = _svd_plane(p)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError('points are collinear (or coincident): the plane is undetermined')
    if robust_start and n > 6:
        rng = np.random.default_rng(seed)
        best, best_med = plane, np.median(np.abs(p @ plane[:3] + plane[3]))
        trials = rng.integers(0, n, size=(min(300, 10 * n), 3))
        a, b, c = p[trials[:, 0]], p[trials[:, 1]], p[trials[:, 2]]
        normals = np.cross(b - a, c - a)
        norms = np.linalg.norm(normals, axis=1)
        good = norms > 1e-12 * max(s[0], 1e-300) ** 2
        for nv, pa in zip(normals[good] / norms[good, None], a[good], strict=True):
            med = np.median(np.abs(p @ nv - nv @ pa))
            if med < best_med:
                best, best_med = np.append(nv, -nv @ pa), med
        plane = best
    inliers = np.ones(n, dtype=bool)
    for _ in range(max_iter):
        r = p @ plane[:3] + plane[3]
        # Centred on the median: a start pulled aside by outliers still keeps the bulk.
        centre = np.median(r)
        sigma = 1.4826 * np.median(np.abs(r - centre))
        new = np.abs(r - centre) <= max(k_sigma * sigma, min_threshold)
        if new.sum() < 3 or (w is not None and not w[new].sum() > 0):
            break
        plane, s = _svd_plane(p[new], None if w is None else w[new])
        if np.array_equal(new, inliers):
            break
        inliers = new
    r = p[inliers] @ plane[:3] + plane[3]
    if orient is not None:
        o = np.asarray(orient, dtype=np.float64)
        if o.shape != (3,):
            raise ValueError(f'orient must have shape (3,), got {o.shape}')
        flip = plane[:3] @ o < 0.0
    else:
        flip = plane[3] > 0.0
    if flip:
        plane = -plane
    return PlaneFit(plane=plane, rms=float(np.sqrt(np.mean(r * r))),
                    max_abs=float(np.abs(r).max()), inliers=inliers, singular_values=s)


def fit_line_trimmed(points, *, k_sigma: float = 4.0, min_threshold: float = 1e-6,
                     max_iter: int = 20):
    """Fit a 3-D line with iterative outlier rejection.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres, n >= 2
    k_sigma : float
        Points farther than ``max(k_sigma * 1.4826 * median distance, min_threshold)`` from
        the line are rejected, repeatedly until the inlier set is stable.
    min_threshold : float, metres
    max_iter : int

    Returns
    -------
    centroid : ndarray, shape (3,), metres
    direction : ndarray, shape (3,)
    inliers : ndarray of bool, shape (n,)
    rms : float, metres
        RMS distance of the inliers from the line.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
        raise ValueError(f'points must have shape (n >= 2, 3), got {p.shape}')
    inliers = np.ones(p.shape[0], dtype=bool)
    for _ in range(max_iter):
        c = p[inliers].mean(axis=0)
        d = np.linalg.svd(p[inliers] - c, full_matrices=False)[2][0]
        q = p - c
        r = np.linalg.norm(q - np.outer(q @ d, d), axis=1)
        # Stripe points back-projected onto a board lie in its plane, so their offsets from
        # the line are one-dimensional: median |offset| = 0.6745 sigma.
        sigma = 1.4826 * np.median(r[inliers])
        new = r <= max(k_sigma * sigma, min_threshold)
        if new.sum() < 2 or np.array_equal(new, inliers):
            break
        inliers = new
    c = p[inliers].mean(axis=0)
    d = np.linalg.svd(p[inliers] - c, full_matrices=False)[2][0]
    q = p[inliers] - c
    r = np.linalg.norm(q - np.outer(q @ d, d), axis=1)
    return c, d, inliers, float(np.sqrt(np.mean(r * r)))


# ----------------------------------------------------------------------------- board pose
@dataclass(frozen=True)
class BoardPose:
    """Board pose from PnP.

    Attributes
    ----------
    V_T_B : ndarray, shape (4, 4)
        Board frame to camera (virtual camera) frame, metres.
    plane : ndarray, shape (4,)
        The board plane z_B = 0 in the camera frame, ``B_T_V.T @ (0, 0, 1, 0)``: unit normal
        along the board's z axis (pointing into the board, away from the camera), e in m.
    reprojection_rms_px : float
    n_points : int
    """

    V_T_B: np.ndarray
    plane: np.ndarray
    reprojection_rms_px: float
    n_points: int


def board_plane_from_pnp(image_points, object_points, intrinsics) -> BoardPose:
    """Pose and plane of a planar board from its detected features.

    Parameters
    ----------
    image_points : array_like, shape (n, 2), pixels
        Detected (distorted) feature positions, n >= 4.
    object_points : array_like, shape (n, 3), metres
        The same features in the board frame, all with z = 0.
    intrinsics : reconstructor.model.CameraIntrinsics

    Returns
    -------
    BoardPose
    """
    uv = np.asarray(image_points, dtype=np.float64)
    obj = np.asarray(object_points, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or uv.shape[0] < 4:
        raise ValueError(f'image_points must have shape (n >= 4, 2), got {uv.shape}')
    if obj.shape != (uv.shape[0], 3):
        raise ValueError(f'object_points must have shape ({uv.shape[0]}, 3), got {obj.shape}')
    if not (np.all(np.isfinite(uv)) and np.all(np.isfinite(obj))):
        raise ValueError('image_points and object_points must be finite')
    if np.abs(obj[:, 2]).max() > 1e-12:
        raise ValueError('object_points must lie on the board plane z = 0')
    K = intrinsics.matrix()
    dist = np.asarray(intrinsics.dist, dtype=np.float64)
    ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok or len(rvecs) == 0:
        raise ValueError('PnP failed for these points')
    best = None
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        rvec, tvec = cv2.solvePnPRefineLM(obj, uv, K, dist, rvec.copy(), tvec.copy(),
                                          (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT,
                                           100, 1e-12))
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, axis=1))))
        if tvec.ravel()[2] > 0 and (best is None or rms < best[2]):
            best = (rvec, tvec, rms)
    if best is None:
        raise ValueError('PnP put the board behind the camera')
    rvec, tvec, rms = best
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    normal = T[:3, 2]
    plane = np.append(normal, -normal @ T[:3, 3])
    return BoardPose(V_T_B=T, plane=plane, reprojection_rms_px=rms, n_points=uv.shape[0])


def backproject_to_plane(uv, plane, intrinsics, *, min_angle: float = 1e-3):
    """Intersect pixel rays with a plane in the camera frame.

    Parameters
    ----------
    uv : array_like, shape (n, 2), pixels
        Distorted pixel coordinates (undistorted here with the intrinsics' distortion).
    plane : array_like, shape (4,)
        (a, b, c, e) in the camera frame, e in metres.
    intrinsics : reconstructor.model.CameraIntrinsics
    min_angle : float, radians
        Rays closer than this to parallel with the plane are invalid.

    Returns
    -------
    points : ndarray, shape (n, 3), metres
        Intersections in the camera frame (0 where invalid).
    valid : ndarray of bool, shape (n,)
        False for non-finite pixels, nearly parallel rays and points behind the camera.
    """
    from reconstructor.model import undistort_points

    pl = np.asarray(plane, dtype=np.float64)
    if pl.shape != (4,) or not np.all(np.isfinite(pl)):
        raise ValueError(f'plane must be a finite vector of shape (4,), got {pl.shape}')
    norm = np.linalg.norm(pl[:3])
    if norm < 1e-12:
        raise ValueError('plane must have a non-zero normal')
    pl = pl / norm
    xy = undistort_points(intrinsics, uv)
    rays = np.column_stack([xy, np.ones(xy.shape[0])])
    with np.errstate(all='ignore'):
        denom = rays @ pl[:3]
        ok = np.isfinite(denom) & (np.abs(denom) >= np.sin(min_angle) * np.linalg.norm(rays,
                                                                                   axis=1))
        Z = np.where(ok, -pl[3] / np.where(ok, denom, 1.0), 0.0)
    ok &= Z > 0.0
    pts = np.where(ok[:, None], rays * Z[:, None], 0.0)
    return pts, ok


# ----------------------------------------------------------------------------- data pipeline
@dataclass
class StripeOnBoard:
    """Stripe points of one laser-on view, back-projected onto the board.

    Attributes
    ----------
    view_index : int
        Index of the laser-on view in the input list.
    pose_index : int
    u2_tilt : float, volts
    points_v0 : ndarray, shape (n, 3), metres
        Stripe points in V0 (through the current model's ``V0_T_V``).
    pnp_rms_px : float
        Reprojection RMS of the board pose used.
    line_rms : float, metres
        RMS distance of the kept points from their best-fit line (stripe noise).
    n_trimmed : int
        Points dropped as off the stripe's line (extraction outliers).
    """

    view_index: int
    pose_index: int
    u2_tilt: float
    points_v0: np.ndarray
    pnp_rms_px: float
    line_rms: float = 0.0
    n_trimmed: int = 0
    u1: tuple = (0.0, 0.0)


@dataclass
class StripeCollection:
    """Output of :func:`board_stripe_points`: accepted views and rejection reasons."""

    stripes: list = field(default_factory=list)
    rejected: list = field(default_factory=list)


def _same_g1(a: CaptureView, b: CaptureView) -> bool:
    va, vb = np.asarray(a.voltages, float), np.asarray(b.voltages, float)
    return bool(np.all(np.abs(va[:2] - vb[:2]) <= VOLTAGE_TOL))


def _reject(collection: StripeCollection, message: str):
    log.warning('rejected: %s', message)
    collection.rejected.append(message)


def view_voltages(i: int, view) -> np.ndarray:
    """The voltages of ``views[i]``, shape (4,), volts, after checking that it is a
    :class:`CaptureView` with 4 finite voltages (else ValueError naming ``views[i]``)."""
    if not isinstance(view, CaptureView):
        raise ValueError(f'views[{i}] must be a CaptureView, got {type(view).__name__}')
    volts = np.asarray(view.voltages, dtype=np.float64)
    if volts.shape != (4,) or not np.all(np.isfinite(volts)):
        raise ValueError(f'views[{i}].voltages must be 4 finite volts, got {view.voltages!r}')
    return volts


def _check_views(views):
    if not isinstance(views, (list, tuple)):
        raise ValueError(f'views must be a list of CaptureView, got {type(views).__name__}')
    for i, v in enumerate(views):
        view_voltages(i, v)
        img = np.asarray(v.image)
        if img.ndim != 2:
            raise ValueError(f'views[{i}].image must have shape (H, W), got {img.shape}')


def board_stripe_points(views, model, board, *, extractor_config=None,
                        max_pnp_rms_px: float = 0.5, min_stripe_points: int = 20,
                        hull_margin_px: float = 3.0, u2_tilt=None,
                        line_k_sigma: float = 4.0,
                        edge_margin: float = 0.6e-3) -> StripeCollection:
    """Back-project the stripe of every laser-on view onto its board and into V0.

    Parameters
    ----------
    views : list of CaptureView
        Laser-off views (board pattern) and laser-on views (stripe on the board). A laser-on
        view uses the laser-off view with the same ``pose_index`` and G1 voltages; without
        one, the board is detected in the laser-on image itself.
    model : reconstructor.model.RigModel
        Current calibration (intrinsics and ``V0_T_V``).
    board : board_layout.Checkerboard or board_layout.CircleGrid
    extractor_config : stripe_extractor.extractor.ExtractorConfig, optional
    max_pnp_rms_px : float
        Board poses with a larger reprojection RMS are rejected.
    min_stripe_points : int
        Views with fewer stripe points on the board are rejected.
    hull_margin_px : float
        Stripe pixels closer than this to the edge of the detected feature grid are dropped.
    u2_tilt : float, volts, optional
        When given, laser-on views at another G2 tilt voltage are rejected with a reason.
    line_k_sigma : float
        Rejection threshold of the per-view line fit (:func:`fit_line_trimmed`).
    edge_margin : float, metres
        Stripe points closer than this (on the board) to an edge of the printed pattern are
        dropped: there the stripe's profile is skewed by the albedo step and its centre biased
        (:func:`small_board.away_from_pattern_edges`).

    Returns
    -------
    StripeCollection
    """
    _check_views(views)
    check_small_board(board)
    extractor_config = stripe_extractor_config(model, extractor_config)
    out = StripeCollection()
    poses = BoardPoses(views, board, model, max_pnp_rms_px)
    for i, view in enumerate(views):
        if not view.laser_on:
            continue
        volts = np.asarray(view.voltages, dtype=np.float64)
        label = f'view {i} (pose {view.pose_index})'
        if u2_tilt is not None and abs(volts[3] - u2_tilt) > VOLTAGE_TOL:
            _reject(out, f'{label}: U2_tilt = {volts[3]:.4f} V, not {u2_tilt:g} V')
            continue
        pose, corners, why = poses.for_view(i)
        if pose is None:
            _reject(out, f'{label}: {why}')
            continue
        p_v, why = _stripe_on_board(view, pose, corners, board, model, extractor_config,
                                    hull_margin_px, edge_margin, min_stripe_points)
        if not why:
            stripe, why = _stripe_line_in_v0(i, view, pose, p_v, model, line_k_sigma,
                                             min_stripe_points)
        if why:
            _reject(out, f'{label}: {why}')
            continue
        out.stripes.append(stripe)
    return out


class BoardPoses:
    """Board pose (PnP) per view, computed once: (pose, corners, '') or (None, None, why).

    ``for_view(i)`` gives the board under laser-on view ``i`` (:func:`board_stripe_points`
    uses it; so does ``benchmarks/joint_bundle.py``)."""

    def __init__(self, views, board, model, max_pnp_rms_px: float) -> None:
        self.views, self.board, self.model = views, board, model
        self.max_pnp_rms_px = max_pnp_rms_px
        self.obj = board.object_points()
        self.cache: dict[int, tuple] = {}

    def __call__(self, view_idx: int):
        if view_idx in self.cache:
            return self.cache[view_idx]
        corners = detect_board(self.board, self.views[view_idx].image)
        result = (None, None, 'board not found')
        if corners is not None:
            try:
                pose = board_plane_from_pnp(corners, self.obj, self.model.intrinsics)
            except ValueError as exc:
                result = (None, None, f'PnP failed: {exc}')
            else:
                if pose.reprojection_rms_px > self.max_pnp_rms_px:
                    result = (None, None, f'board PnP reprojection RMS '
                              f'{pose.reprojection_rms_px:.3f} px > {self.max_pnp_rms_px} px')
                else:
                    result = (pose, corners, '')
        self.cache[view_idx] = result
        return result

    def for_view(self, i: int):
        """The board under laser-on view ``i``: from a laser-off view of the same pose and G1
        voltages, else from the laser-on image itself."""
        view = self.views[i]
        candidates = [j for j, w in enumerate(self.views) if not w.laser_on
                      and w.pose_index == view.pose_index and _same_g1(w, view)]
        pose, corners, why = None, None, 'no laser-off view of this pose and G1 voltage'
        for j in candidates:
            pose, corners, why = self(j)
            if pose is not None:
                break
        if pose is None:
            pose, corners, why2 = self(i)
            why = f'{why}; in the laser-on image: {why2}' if pose is None else ''
        return pose, corners, why


def stripe_extractor_config(model, config=None):
    """The stripe extractor's settings for a calibration's laser views: ``config`` (default
    settings when None) oriented the way the model's stripe runs
    (``reconstructor.planning.stripe_layout``: along the rows for a laser below or above
    the camera, along the columns beside it)."""
    import dataclasses as _dc

    from reconstructor.planning import stripe_layout
    from stripe_extractor.extractor import ExtractorConfig

    orientation = stripe_layout(model).orientation
    config = ExtractorConfig() if config is None else config
    return config if config.orientation == orientation else _dc.replace(
        config, orientation=orientation)


def _stripe_on_board(view, pose, corners, board, model, extractor_config,
                     hull_margin_px: float, edge_margin: float, min_stripe_points: int):
    """Stripe points of a laser-on view on its board, in V [m], or ``(None, why)``."""
    from stripe_extractor.extractor import extract

    stripe = extract(np.ascontiguousarray(view.image), extractor_config)
    uv = np.column_stack([stripe.u, stripe.v]).astype(np.float64)
    if uv.shape[0]:
        uv = uv[inside_convex_hull(uv, corners, hull_margin_px)]
    if uv.shape[0] < min_stripe_points:
        return None, f'{uv.shape[0]} stripe points on the board < {min_stripe_points}'
    p_v, ok = backproject_to_plane(uv, pose.plane, model.intrinsics)
    p_v = p_v[ok]
    B_T_V = np.linalg.inv(pose.V_T_B)
    p_v = p_v[away_from_pattern_edges(board, p_v @ B_T_V[:3, :3].T + B_T_V[:3, 3],
                                      edge_margin)]
    if p_v.shape[0] < min_stripe_points:
        return None, (f'{p_v.shape[0]} stripe points away from pattern edges '
                      f'< {min_stripe_points}')
    return p_v, ''


def _stripe_line_in_v0(i, view, pose, p_v, model, line_k_sigma: float,
                       min_stripe_points: int):
    """The stripe points (V, metres) on their line, taken into V0: a
    :class:`StripeOnBoard`, or ``(None, why)``."""
    from reconstructor.model import v0_T_v

    volts = np.asarray(view.voltages, dtype=np.float64)
    # A plane cuts the board in a straight line: drop stripe points off it (extraction
    # errors where the stripe crosses the pattern's edges).
    _, _, keep, line_rms = fit_line_trimmed(p_v, k_sigma=line_k_sigma)
    if keep.sum() < min_stripe_points:
        return None, f'{int(keep.sum())} stripe points on a line < {min_stripe_points}'
    T = v0_T_v(model, volts[0], volts[1])
    p_v0 = p_v[keep] @ T[:3, :3].T + T[:3, 3]
    return StripeOnBoard(view_index=i, pose_index=int(view.pose_index),
                         u2_tilt=float(volts[3]), points_v0=p_v0,
                         pnp_rms_px=pose.reprojection_rms_px, line_rms=line_rms,
                         n_trimmed=int((~keep).sum()),
                         u1=(float(volts[0]), float(volts[1]))), ''


def plane_from_stripes(stripes, *, k_sigma: float = 4.0, orient=None,
                       min_poses: int = 2, min_spread: float = 1e-3):
    """Fit one laser plane to the stripes of several board poses.

    Parameters
    ----------
    stripes : list of StripeOnBoard
        All taken at the same G2 voltage.
    k_sigma : float
        Outlier rejection of :func:`fit_plane_svd`.
    orient : array_like, shape (3,), optional
        Normal sign convention (see :func:`fit_plane_svd`).
    min_poses : int
        Distinct board poses required (one pose gives a line, not a plane).
    min_spread : float, metres
        Smallest accepted RMS spread of the points across the stripe direction (the second
        singular value); below it the points are nearly collinear.

    Returns
    -------
    PlaneFit

    Raises
    ------
    ValueError
        Too few poses, or points too close to collinear.
    """
    poses = {s.pose_index for s in stripes}
    if len(poses) < min_poses:
        raise ValueError(f'{len(poses)} board pose(s); at least {min_poses} needed for a plane')
    pts = np.concatenate([s.points_v0 for s in stripes])
    # Each view's error is mostly a rigid shift of its whole line (board-pose error): weight
    # every view the same, whatever its number of points.
    weights = np.concatenate([np.full(len(s.points_v0), 1.0 / len(s.points_v0))
                              for s in stripes])
    fit = fit_plane_svd(pts, weights=weights, k_sigma=k_sigma, orient=orient)
    if fit.singular_values[1] < min_spread:
        raise ValueError(f'stripe points span only {fit.singular_values[1] * 1e3:.3f} mm RMS '
                         f'across the stripe (< {min_spread * 1e3:.3f} mm): move the board '
                         f'between poses')
    return fit


def plane_standard_errors(points, plane, groups) -> np.ndarray:
    """1-sigma standard errors of a fitted plane's (a, b, c, e): the square roots of the
    diagonal of :func:`plane_covariance` (same arguments), shape (4,)."""
    return np.sqrt(np.clip(np.diag(plane_covariance(points, plane, groups)), 0.0, None))


def plane_covariance(points, plane, groups) -> np.ndarray:
    """Covariance of a fitted plane's (a, b, c, e), from its views' lines.

    The errors of one view (one board pose) are mostly one shift and tilt of its whole line,
    not independent per point. So each view is reduced to its line: the plane residual at
    the line's centroid, and the line's tilt out of the plane times its RMS half-length
    (both metres). The plane is parametrised about the solution by two small rotations of
    its normal (along in-plane unit vectors t1, t2) and its offset; the Jacobian of the
    2G view residuals, each kind (offset, tilt) weighed by its own spread
    ``s_k**2 = sum r_k**2 / (G - 1.5)``, gives the covariance ``inv(J.T W J)``.

    Parameters
    ----------
    points : array_like, shape (n, 3), metres
        The inlier points of the fit.
    plane : array_like, shape (4,)
        (a, b, c, e), unit normal, e in metres.
    groups : array_like, shape (n,)
        View of each point; at least 3 distinct views with 2 or more points each.

    Returns
    -------
    ndarray, shape (4, 4)
        Covariance of a, b, c (1) and e (metres).
    """
    p = np.asarray(points, dtype=np.float64)
    pl = np.asarray(plane, dtype=np.float64)
    g = np.asarray(groups)
    if p.ndim != 2 or p.shape[1] != 3 or pl.shape != (4,) or g.shape != (len(p),):
        raise ValueError('points (n, 3), plane (4,) and groups (n,) expected')
    n = pl[:3]
    t1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    rows, res = [], []
    for k in np.unique(g):
        q = p[g == k]
        if len(q) < 2:
            continue
        c = q.mean(axis=0)
        d = np.linalg.svd(q - c, full_matrices=False)[2][0]
        half = float(np.sqrt(np.mean(((q - c) @ d) ** 2)))
        rows += [[t1 @ c, t2 @ c, 1.0], [half * (t1 @ d), half * (t2 @ d), 0.0]]
        res += [n @ c + pl[3], half * (n @ d)]
    if len(res) < 6:
        raise ValueError(f'{len(res) // 2} views cannot give the spread of a plane (need 3)')
    # Offsets and tilts have their own spread: weigh each kind by its own RMS (the three
    # parameters' degrees of freedom shared between them).
    J, r = np.array(rows), np.array(res)
    G = len(r) // 2
    for k in (0, 1):
        s_k = math.sqrt(float(r[k::2] @ r[k::2]) / (G - 1.5))
        J[k::2] /= max(s_k, 1e-300)
        r[k::2] /= max(s_k, 1e-300)
    cov, _ = covariance_from_jacobian(J, r)
    M = np.zeros((4, 3))
    M[:3, 0], M[:3, 1], M[3, 2] = t1, t2, 1.0
    return M @ cov @ M.T


def inlier_groups(stripes, inliers) -> list:
    """Per stripe with inliers, ``(inlier points_v0, u1_pan, u1_tilt)``: what the camera
    measured and where it looked (``inliers``: one flag per point of all stripes, in
    order), for :func:`reconstructor.uncertainty.remeasured_sensitivity`."""
    keep = np.split(inliers, np.cumsum([len(s.points_v0) for s in stripes])[:-1])
    return [(s.points_v0[k], *s.u1) for s, k in zip(stripes, keep, strict=True) if k.any()]


def _plane_errors(stripes, fit, model, inputs) -> tuple[dict, dict]:
    """``{'laser_plane_v0': [sa, sb, sc, se]}`` of a fit and its covariance record, or
    ({}, {}) with fewer than 3 views. The record's sensitivity to the camera's calibrated
    parameters (``inputs``, name to 1 sigma) is that of the inliers' plane to the points
    as a moved camera would have measured them
    (:func:`reconstructor.uncertainty.remeasured_sensitivity`)."""
    from reconstructor.uncertainty import covariance_record, remeasured_sensitivity

    pts = np.concatenate([s.points_v0 for s in stripes])[fit.inliers]
    views = np.concatenate([np.full(len(s.points_v0), j) for j, s in enumerate(stripes)])
    try:
        cov = plane_covariance(pts, fit.plane, views[fit.inliers])
    except ValueError:
        return {}, {}
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    groups = inlier_groups(stripes, fit.inliers)

    def plane(pts):
        pl, _ = _svd_plane(np.concatenate(pts))
        return pl if pl[:3] @ fit.plane[:3] > 0 else -pl

    S = remeasured_sensitivity(model, groups, inputs, plane)
    return ({'laser_plane_v0': [float(v) for v in se]},
            covariance_record([f'laser_plane_v0[{j}]' for j in range(4)], cov,
                              list(inputs), S.reshape(4, len(inputs))))


# ----------------------------------------------------------------------------- stage
def run_laser_plane(views, calibration, *, board, extractor_config=None,
                    k_sigma: float = 4.0, max_pnp_rms_px: float = 0.5,
                    min_stripe_points: int = 20, min_poses: int = 2,
                    min_spread: float = 1e-3, edge_margin: float = 0.6e-3) -> StageResult:
    """Calibrate the laser plane at U2_tilt = 0 in V0.

    Parameters
    ----------
    views : list of CaptureView
        For each board pose (``pose_index``): a laser-off view of the board and a laser-on view
        with the stripe on it, at the same G1 voltages (normally 0 V, where V = V0) and
        U2_tilt = 0. Laser-on views at another G2 voltage are rejected with a reason.
    calibration : reconstructor.calibration_file.Calibration
        Current calibration: intrinsics and the dynamic camera are used; the sign of the
        current ``laser_plane_v0`` normal is kept.
    board : board_layout.Checkerboard or board_layout.CircleGrid
    extractor_config : stripe_extractor.extractor.ExtractorConfig, optional
    k_sigma, max_pnp_rms_px, min_stripe_points, min_poses, min_spread, edge_margin
        See :func:`board_stripe_points` and :func:`plane_from_stripes`.

    Returns
    -------
    StageResult
        ``updates = {'laser_plane_v0': [a, b, c, e]}``; residuals ``plane_rms_m``,
        ``plane_max_abs_m``, ``pnp_rms_px_max``, ``points_used``, ``points_rejected``;
        ``standard_errors`` of the four (:func:`plane_standard_errors`), from 3 views on.

    Raises
    ------
    ValueError
        When no plane can be fitted (the reasons are in the message).
    """
    model = calibration.model
    coll = board_stripe_points(views, model, board, extractor_config=extractor_config,
                               max_pnp_rms_px=max_pnp_rms_px,
                               min_stripe_points=min_stripe_points, u2_tilt=0.0,
                               edge_margin=edge_margin)
    rejected = list(coll.rejected)
    try:
        fit = plane_from_stripes(coll.stripes, k_sigma=k_sigma,
                                 orient=model.laser_plane_v0[:3], min_poses=min_poses,
                                 min_spread=min_spread)
    except ValueError as exc:
        raise ValueError(f'laser_plane: {exc}; rejected: {rejected}') from None
    n_pts = fit.inliers.shape[0]
    from reconstructor.uncertainty import camera_inputs

    errors, covariance = _plane_errors(coll.stripes, fit, model, camera_inputs(calibration))
    return StageResult(
        stage='laser_plane',
        updates={'laser_plane_v0': [float(v) for v in fit.plane]},
        standard_errors=errors,
        covariance=covariance,
        residuals={
            'plane_rms_m': fit.rms,
            'plane_max_abs_m': fit.max_abs,
            'pnp_rms_px_max': max(s.pnp_rms_px for s in coll.stripes),
            'points_used': float(fit.n_inliers),
            'points_rejected': float(n_pts - fit.n_inliers),
        },
        samples_used=len(coll.stripes),
        samples_rejected=len(rejected),
        rejected=rejected,
    )

