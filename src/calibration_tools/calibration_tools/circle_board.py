"""Circle-board detection and identification (docs/design.md section 3, step 2). No rclpy.

Detection (:func:`detect_circles`): Otsu threshold, connected components, then for each blob
sub-pixel edge points where rays from its centroid cross the level midway between the
blob's inside and outside grey levels, and an algebraic ellipse fit to those points. Blobs
that touch the image border, that are not elliptic, or whose edge cannot be followed are
rejected with a reason. A view shows at most one 15 mm circle (they are 140 mm apart and
a view is ~60 mm wide), so a circle is large when its radius exceeds the smallest radius in
its view by ``large_ratio``; with a single circle the size is known only from an expected
small-circle radius.

Identification (:func:`identify_view`): the detected centres are mapped onto the board plane
with the approximate model (pixel rays from the G1 voltages, approximate board pose) and
read off as fractional lattice ``(row, col)``. The common fractional offset of the view is
the prediction error. A visible large circle pins the labels modulo the 7-circle period; a
view without one is labelled by rounding, accepted only when the offset is well inside half
a pitch. Every view is then verified: labels unique and on the board, large flags matching
the board, and the reprojection of the labelled circles within a pixel tolerance. Anything
else is rejected with a reason. :func:`calibration_tools.board_identify.identify_views` runs
this over all views while refining the model, so the final check uses an accurate model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from reconstructor.model import RigModel

from .board_geometry import pixels_to_board, project_circle_centres, view_T_board
from .board_layout import CircleBoard


@dataclass(frozen=True)
class CircleDetections:
    """Circles found in one image.

    Attributes
    ----------
    centres : ndarray, shape (n, 2), pixels
        Ellipse centres (sub-pixel).
    radii : ndarray, shape (n,), pixels
        Geometric mean of the semi-axes.
    axes : ndarray, shape (n, 2), pixels
        Semi-major and semi-minor axes.
    angles : ndarray, shape (n,), radians
        Direction of the major axis from the image u axis.
    large : ndarray of bool, shape (n,)
        True for a large (15 mm) circle; meaningful only where ``size_known``.
    size_known : ndarray of bool, shape (n,)
    fit_rms_px : ndarray, shape (n,), pixels
        RMS distance of the edge points from the fitted ellipse.
    rejected : list of str
        One line per rejected blob with the reason.
    """

    centres: np.ndarray
    radii: np.ndarray
    axes: np.ndarray
    angles: np.ndarray
    large: np.ndarray
    size_known: np.ndarray
    fit_rms_px: np.ndarray
    rejected: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.centres)


def _empty(rejected) -> CircleDetections:
    z = np.zeros(0)
    b = np.zeros(0, dtype=bool)
    return CircleDetections(np.zeros((0, 2)), z, np.zeros((0, 2)), z, b, b, z, rejected)


def fit_ellipse(points) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Least-squares ellipse through points (normalised direct fit, Fitzgibbon et al. 1999).

    Parameters
    ----------
    points : array_like, shape (n, 2), pixels, n >= 6

    Returns
    -------
    centre : ndarray, shape (2,), pixels
    axes : ndarray, shape (2,), pixels
        Semi-major, semi-minor.
    angle : float, radians
        Major-axis direction.
    rms : float, pixels
        RMS of the approximate geometric distances (algebraic distance / gradient norm).

    Raises
    ------
    ValueError
        When fewer than 6 points are given or the best conic is not an ellipse.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 6:
        raise ValueError(f"points must have shape (n >= 6, 2), got {p.shape}")
    m = p.mean(axis=0)
    s = np.sqrt(((p - m) ** 2).sum(axis=1).mean())
    if not s > 0:
        raise ValueError("points are degenerate")
    q = (p - m) / s
    x, y = q[:, 0], q[:, 1]
    D1 = np.column_stack([x * x, x * y, y * y])
    D2 = np.column_stack([x, y, np.ones_like(x)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    T = -np.linalg.solve(S3, S2.T)
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    w, v = np.linalg.eig(M)
    v = np.real(v)
    cond = 4.0 * v[0] * v[2] - v[1] ** 2
    good = np.flatnonzero(cond > 0)
    if good.size == 0:
        raise ValueError("points do not lie on an ellipse")
    a1 = v[:, good[0]]
    A, B, C = a1
    Dq, Eq, Fq = T @ a1
    # Conic in normalised coordinates -> centre and axes.
    den = B * B - 4.0 * A * C
    xc = (2.0 * C * Dq - B * Eq) / den
    yc = (2.0 * A * Eq - B * Dq) / den
    F0 = A * xc * xc + B * xc * yc + C * yc * yc + Dq * xc + Eq * yc + Fq
    Q = np.array([[A, B / 2.0], [B / 2.0, C]])
    ev, evec = np.linalg.eigh(Q)
    with np.errstate(all="ignore"):
        semi = np.sqrt(-F0 / ev)
    if not np.all(np.isfinite(semi)) or np.any(semi <= 0):
        raise ValueError("points do not lie on an ellipse")
    order = np.argsort(semi)[::-1]
    semi = semi[order]
    major = evec[:, order[0]]
    angle = float(np.arctan2(major[1], major[0]))
    # Approximate geometric residual: algebraic value over gradient norm.
    val = A * x * x + B * x * y + C * y * y + Dq * x + Eq * y + Fq
    gx = 2.0 * A * x + B * y + Dq
    gy = B * x + 2.0 * C * y + Eq
    with np.errstate(all="ignore"):
        dist = val / np.hypot(gx, gy)
    rms = float(np.sqrt(np.mean(dist * dist))) * s
    centre = np.array([xc, yc]) * s + m
    return centre, semi * s, angle, rms


def _edge_points(img, c0, r0, level, dark, n_rays, step):
    """Sub-pixel crossings of ``level`` along rays from ``c0``; returns (points, n_failed)."""
    a = np.linspace(0.0, 2.0 * np.pi, n_rays, endpoint=False)
    s = np.arange(0.35 * r0, 1.8 * r0, step)
    du, dv = np.cos(a), np.sin(a)
    u = c0[0] + du[:, None] * s[None, :]
    v = c0[1] + dv[:, None] * s[None, :]
    h, w = img.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    prof = cv2.remap(
        img, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    above = prof >= level if dark else prof <= level
    # First sample outside the blob after the start (the start is inside).
    first = np.argmax(above, axis=1)
    ok = above[np.arange(n_rays), first] & (first > 0) & ~above[:, 0]
    idx = np.clip(first, 1, len(s) - 1)
    rows = np.arange(n_rays)
    p0, p1 = prof[rows, idx - 1], prof[rows, idx]
    with np.errstate(all="ignore"):
        frac = (level - p0) / (p1 - p0)
    rad = s[idx - 1] + frac * step
    ok &= np.isfinite(rad) & inside[rows, idx] & inside[rows, idx - 1]
    pts = np.column_stack([c0[0] + du * rad, c0[1] + dv * rad])
    return pts[ok], int(n_rays - ok.sum())


@dataclass(frozen=True)
class _BlobLimits:
    """Acceptance limits of :func:`detect_circles` for one blob (pixels)."""

    dark_circles: bool
    min_radius_px: float
    max_radius_px: float
    border_margin_px: float
    max_fit_rms_px: float
    max_axis_ratio: float
    n_rays: int


def _threshold_blobs(imgf, lo: float, hi: float, dark_circles: bool):
    """Otsu threshold of the smoothed, stretched image, then 8-connected components.

    Returns ``cv2.connectedComponentsWithStats``' (n, labels, stats, centroids).
    """
    img8 = np.rint((imgf - lo) * (255.0 / (hi - lo))).astype(np.uint8)
    blur8 = cv2.GaussianBlur(img8, (5, 5), 1.0)
    thr, _ = cv2.threshold(blur8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = (blur8 < thr) if dark_circles else (blur8 > thr)
    return cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)


def _edge_level(imgf, labels, i, box, r0, kernel) -> float | None:
    """Grey level midway between inside blob ``i`` and a ring just outside it.

    None when the blob is too small to hold both samples.
    """
    x, y, bw, bh = box
    h, w = imgf.shape
    # Grey levels inside (eroded blob) and in a ring just outside (dilated blob).
    pad = int(np.ceil(0.6 * r0)) + 12
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + bw + pad, w), min(y + bh + pad, h)
    blob = (labels[y0:y1, x0:x1] == i).astype(np.uint8)
    roi = imgf[y0:y1, x0:x1]
    # 5x5 kernel: each iteration moves the boundary by 2 px. Keep 4 px away from the
    # edge on both sides, sample at least 4 px of ring.
    inner = cv2.erode(blob, kernel, iterations=max(2, int(0.15 * r0 / 2)))
    gap = cv2.dilate(blob, kernel, iterations=2)
    outer = cv2.dilate(gap, kernel, iterations=max(2, int(0.25 * r0 / 2)))
    ring = (outer > 0) & (gap == 0)
    if inner.sum() < 5 or ring.sum() < 5:
        return None
    return 0.5 * (float(np.median(roi[inner > 0])) + float(np.median(roi[ring])))


def _fit_blob_ellipse(pts, w: int, h: int, lim: _BlobLimits):
    """Ellipse through a blob's edge points: (centre, radius, axes, angle, rms) or a reason."""
    try:
        centre, axes, angle, rms = fit_ellipse(pts)
    except ValueError as exc:
        return str(exc)
    if rms > lim.max_fit_rms_px:
        return f"not an ellipse (edge rms {rms:.2f} px)"
    if axes[0] > lim.max_axis_ratio * axes[1]:
        return f"too elongated ({axes[0] / axes[1]:.1f})"
    radius = float(np.sqrt(axes[0] * axes[1]))
    if not lim.min_radius_px <= radius <= lim.max_radius_px:
        return f"radius {radius:.1f} px out of range"
    # The fitted ellipse itself must stay clear of the border.
    ext = axes[0]
    margin = lim.border_margin_px
    if (
        centre[0] - ext < margin
        or centre[1] - ext < margin
        or centre[0] + ext > w - 1 - margin
        or centre[1] + ext > h - 1 - margin
    ):
        return "ellipse reaches the image border (partial circle)"
    return centre, radius, axes, angle, rms


def _measure_blob(imgf, labels, i, stat, c0, kernel, lim: _BlobLimits):
    """Sub-pixel ellipse of blob ``i``: (centre, radius, axes, angle, rms) or a reason."""
    x, y, bw, bh, area = stat
    h, w = imgf.shape
    margin = lim.border_margin_px
    if x <= margin or y <= margin or x + bw - 1 >= w - 1 - margin or y + bh - 1 >= h - 1 - margin:
        return "touches the image border (partial circle)"
    r0 = float(np.sqrt(area / np.pi))
    if r0 > lim.max_radius_px:
        return f"radius {r0:.0f} px above max_radius_px"
    level = _edge_level(imgf, labels, i, (x, y, bw, bh), r0, kernel)
    if level is None:
        return "too small to measure"
    pts, failed = _edge_points(imgf, c0, r0, level, lim.dark_circles, lim.n_rays, 0.25)
    if failed > 0.1 * lim.n_rays or len(pts) < 12:
        return f"edge not closed inside the image ({failed} rays lost)"
    return _fit_blob_ellipse(pts, w, h, lim)


def _size_classes(radii, large_ratio, expected_small_radius_px, rejected):
    """(large, size_known) per circle from the radii of one view; notes a conflict."""
    large = np.zeros(len(radii), dtype=bool)
    known = np.zeros(len(radii), dtype=bool)
    if len(radii) >= 2:
        large = radii > large_ratio * radii.min()
        if large.sum() <= 1:
            known[:] = True
        else:
            rejected.append(f"{int(large.sum())} large circles in one view: sizes unknown")
            large[:] = False
    elif expected_small_radius_px is not None:
        large[:] = radii > large_ratio * float(expected_small_radius_px)
        known[:] = True
    return large, known


def detect_circles(
    image,
    *,
    dark_circles: bool = True,
    min_radius_px: float = 8.0,
    max_radius_px: float | None = None,
    border_margin_px: float = 2.0,
    max_fit_rms_px: float = 0.35,
    max_axis_ratio: float = 3.0,
    large_ratio: float = 1.25,
    expected_small_radius_px: float | None = None,
    n_rays: int = 120,
) -> CircleDetections:
    """Find complete circles in an image with sub-pixel centres and tell large from small.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16 (or float)
    dark_circles : bool
        Circles darker than the board (True) or brighter.
    min_radius_px, max_radius_px : float
        Accepted blob radius range, pixels (max defaults to half the image height).
    border_margin_px : float
        Blobs whose pixels come this close to the image border are rejected as partial.
    max_fit_rms_px : float
        Largest RMS edge-to-ellipse distance of an accepted circle, pixels.
    max_axis_ratio : float
        Largest accepted major/minor axis ratio.
    large_ratio : float
        A circle is large when its radius exceeds the view's smallest by this factor
        (the board's ratio is 1.5).
    expected_small_radius_px : float, optional
        Radius of a small circle predicted by the caller; tells the size of a lone circle.
    n_rays : int
        Edge samples per circle.

    Returns
    -------
    CircleDetections
    """
    img = np.asarray(image)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ValueError(f"image must have shape (H, W), got {img.shape}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise ValueError(f"image must be numeric, got {img.dtype}")
    h, w = img.shape
    imgf = img.astype(np.float32)
    if max_radius_px is None:
        max_radius_px = 0.5 * min(h, w)
    lo, hi = float(imgf.min()), float(imgf.max())
    rejected: list[str] = []
    if hi - lo < 1e-6:
        return _empty(rejected)
    n, labels, stats, cents = _threshold_blobs(imgf, lo, hi, dark_circles)
    lim = _BlobLimits(dark_circles, min_radius_px, max_radius_px, border_margin_px,
                      max_fit_rms_px, max_axis_ratio, n_rays)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    out = []
    min_area = np.pi * min_radius_px**2 * 0.5
    for i in range(1, n):
        c0 = cents[i]
        if stats[i][4] < min_area:
            continue  # specks: not worth a line in the report
        got = _measure_blob(imgf, labels, i, stats[i], c0, kernel, lim)
        if isinstance(got, str):
            rejected.append(f"blob at ({c0[0]:.0f}, {c0[1]:.0f}) px: {got}")
        else:
            out.append(got)
    if not out:
        return _empty(rejected)
    centres = np.array([o[0] for o in out])
    radii = np.array([o[1] for o in out])
    axes = np.array([o[2] for o in out])
    angles = np.array([o[3] for o in out])
    rms = np.array([o[4] for o in out])
    large, known = _size_classes(radii, large_ratio, expected_small_radius_px, rejected)
    return CircleDetections(centres, radii, axes, angles, large, known, rms, rejected)


# --------------------------------------------------------------------------- identification
@dataclass(frozen=True)
class ViewIdentification:
    """Which board circle each detected circle of one view is.

    Attributes
    ----------
    accepted : bool
    index : ndarray, shape (n,), int
        Board circle index per detection (-1 where unknown; all -1 when not accepted).
    reason : str
        Why the view was rejected ('' when accepted).
    mode : str
        'large' (anchored by a visible 15 mm circle) or 'model' (by prediction alone).
    offset_pitch : ndarray, shape (2,)
        Prediction error of the view in pitches (row, col): labelled minus predicted.
    spread_pitch : float
        Largest deviation of a circle from the view's common offset, pitches.
    residual_px : ndarray, shape (n,), pixels
        Distance between each detection and the model reprojection of its label (NaN when
        not computed).
    """

    accepted: bool
    index: np.ndarray
    reason: str = ""
    mode: str = "model"
    offset_pitch: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    spread_pitch: float = float("nan")
    residual_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _reject(n, reason, **kw) -> ViewIdentification:
    return ViewIdentification(False, np.full(n, -1, dtype=np.int64), reason, **kw)


def _large_circle_offset(frac, large, board: CircleBoard) -> np.ndarray:
    """Offset, shape (2,) pitches, moving the view's one large circle onto the nearest site."""
    # The large circle sits at (row, col) = h (mod period); pick the nearest such site.
    h = board.sub_pattern // 2
    per = board.sub_pattern
    f = frac[np.flatnonzero(large)[0]]
    site = np.round((f - h) / per) * per + h
    return site - f


def _common_offset(frac) -> np.ndarray:
    """Common offset of the view, shape (2,) pitches: minus the circular mean of ``frac``."""
    ang = 2.0 * np.pi * frac
    mean = np.arctan2(np.sin(ang).mean(axis=0), np.cos(ang).mean(axis=0)) / (2.0 * np.pi)
    return -mean


def _round_to_lattice(frac, offset):
    """Labels (rounded ``frac + offset``, float (n, 2)) and the largest rounding, pitches."""
    shifted = frac + offset
    labels = np.rint(shifted)
    spread = float(np.abs(shifted - labels).max())
    return labels, spread


def _board_index(detections: CircleDetections, labels, board: CircleBoard):
    """Board index of each label and why the labels are impossible ('' when they are not)."""
    known = detections.size_known
    rows, cols = labels[:, 0].astype(np.int64), labels[:, 1].astype(np.int64)
    index = board.index_of(rows, cols)
    if np.any(index < 0):
        return index, "labels fall outside the board"
    if len(np.unique(index)) != len(detections):
        return index, "two detections got the same label"
    board_large = board.is_large(index)
    if np.any(board_large[known] != detections.large[known]):
        return index, "circle sizes do not match the board at these labels"
    return index, ""


def _reprojection_residual(detections, u1_pan, u1_tilt, model, V0_T_W, board, index):
    """Distance of each detection from the model reprojection of its label, shape (n,), px."""
    V_T_W = view_T_board(model, float(u1_pan), float(u1_tilt), V0_T_W)
    uv = project_circle_centres(
        model.intrinsics, V_T_W, board.points(index), board.radius(index)
    )
    return np.linalg.norm(uv - detections.centres, axis=1)


def identify_view(
    detections: CircleDetections,
    u1_pan: float,
    u1_tilt: float,
    model: RigModel,
    V0_T_W,
    board: CircleBoard,
    *,
    max_offset_pitch: float = 0.25,
    max_anchor_offset_pitch: float = 3.4,
    max_spread_pitch: float = 0.12,
    max_residual_px: float | None = None,
    use_large: bool = True,
) -> ViewIdentification:
    """Label the circles of one view with board indices, or reject the view with a reason.

    Parameters
    ----------
    detections : CircleDetections
    u1_pan, u1_tilt : float, volts
        G1 voltages of the view.
    model : RigModel
        Approximate (or refined) rig model.
    V0_T_W : array_like, shape (4, 4)
        Approximate board pose in V0, metres.
    board : CircleBoard
    max_offset_pitch : float
        Largest accepted prediction error of a view without a large circle, pitches per axis
        (a wrong label needs an error of at least ``1 - max_offset_pitch``).
    max_anchor_offset_pitch : float
        Largest accepted prediction error of a view anchored by a large circle (< 3.5, half
        the sub-pattern period).
    max_spread_pitch : float
        Largest deviation of one circle from the view's common offset, pitches (catches
        spurious blobs and a wrong board orientation).
    max_residual_px : float, optional
        Reprojection tolerance of the verification step, pixels; skipped when None.
    use_large : bool
        Anchor views on visible large circles.

    Returns
    -------
    ViewIdentification
    """
    n = len(detections)
    if n == 0:
        return _reject(0, "no circles detected")
    if not 0.0 < max_offset_pitch < 0.5:
        raise ValueError(f"max_offset_pitch must be in (0, 0.5), got {max_offset_pitch}")
    half_period = board.sub_pattern / 2.0
    if not 0.0 < max_anchor_offset_pitch < half_period:
        raise ValueError(f"max_anchor_offset_pitch must be in (0, {half_period})")
    xy = pixels_to_board(model, detections.centres, u1_pan, u1_tilt, V0_T_W)
    if not np.isfinite(xy).all():
        return _reject(n, "pixel rays miss the board plane of the approximate pose")
    frac = board.lattice_coords(xy)  # (n, 2) fractional (row, col)
    large = detections.large & detections.size_known
    mode = "model"
    if use_large and large.sum() == 1:
        offset = _large_circle_offset(frac, large, board)
        mode = "large"
        if np.abs(offset).max() > max_anchor_offset_pitch:
            return _reject(n, f"prediction off by {np.abs(offset).max():.2f} pitch even with "
                              "a large circle", mode=mode, offset_pitch=offset)
        labels, spread = _round_to_lattice(frac, offset)
    else:
        offset = _common_offset(frac)
        labels, spread = _round_to_lattice(frac, offset)
        if np.abs(offset).max() > max_offset_pitch:
            return _reject(n, f"ambiguous: prediction off by {np.abs(offset).max():.2f} pitch "
                              "and no large circle", mode=mode, offset_pitch=offset,
                           spread_pitch=spread)
    if spread > max_spread_pitch:
        return _reject(n, f"circles do not fit one lattice offset (spread {spread:.2f} pitch)",
                       mode=mode, offset_pitch=offset, spread_pitch=spread)
    common = dict(mode=mode, offset_pitch=offset, spread_pitch=spread)
    index, reason = _board_index(detections, labels, board)
    if reason:
        return _reject(n, reason, **common)
    residual = np.full(n, np.nan)
    if max_residual_px is not None:
        residual = _reprojection_residual(detections, u1_pan, u1_tilt, model, V0_T_W, board,
                                          index)
        worst = float(np.nanmax(residual)) if np.isfinite(residual).any() else np.inf
        if not worst <= max_residual_px:
            return _reject(n, f"reprojection check failed ({worst:.1f} px > "
                              f"{max_residual_px:.1f} px)", residual_px=residual, **common)
    return ViewIdentification(True, index, "", residual_px=residual, **common)
