"""Detection of the small calibration boards that fit the 60 x 45 mm view (no rclpy).

The boards themselves are :class:`calibration_tools.board_layout.Checkerboard` (inner corners,
``findChessboardCornersSB``, sub-pixel by construction) and
:class:`calibration_tools.board_layout.CircleGrid` (dark circles on light, symmetric grid,
``findCirclesGrid``). Features come back in the board's ``object_points()`` order. Only the
board's plane is used by the laser stages, and it does not depend on which of the symmetric
labellings OpenCV picks.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration_tools.board_layout import Checkerboard, CircleGrid

SMALL_BOARDS = (Checkerboard, CircleGrid)


def check_small_board(board, name: str = 'board'):
    """Raise ValueError unless ``board`` is a Checkerboard or a CircleGrid."""
    if not isinstance(board, SMALL_BOARDS):
        raise ValueError(f'{name} must be a board_layout.Checkerboard or CircleGrid, got '
                         f'{type(board).__name__}')


def as_uint8_image(image) -> np.ndarray:
    """A grey image as uint8; ValueError for other shapes or types.

    A uint16 image keeps the 8 bits below its highest bit in use: Mono10/12 arrive unpacked
    (codes below 2**10 or 2**12) and Mono16 uses the whole range.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16

    Returns
    -------
    ndarray, shape (H, W), uint8
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f'image must have shape (H, W), got {img.shape}')
    if img.dtype == np.uint16:
        img = (img >> max(int(img.max(initial=0)).bit_length() - 8, 0)).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f'image must be uint8 or uint16, got {img.dtype}')
    return img


def detect_board(board, image, fast: bool = False) -> np.ndarray | None:
    """Find a small board's features in an image.

    Parameters
    ----------
    board : Checkerboard or CircleGrid
    image : ndarray, shape (H, W), uint8 or uint16
    fast : bool
        A checkerboard: OpenCV's plain search first (about a fifth of the time of its
        exhaustive, accurate one; its corners within a few hundredths of a pixel, so
        refine them: :func:`~calibration_tools.intrinsics.detect_target` does), the
        exhaustive one only when it finds nothing.

    Returns
    -------
    ndarray, shape (cols * rows, 2), pixels, or None
        Sub-pixel feature positions in ``board.object_points()`` order; None when the whole
        grid is not found.
    """
    check_small_board(board)
    img = as_uint8_image(image)
    size = (board.cols, board.rows)
    if isinstance(board, Checkerboard):
        found, corners = (cv2.findChessboardCornersSB(img, size, flags=0) if fast
                          else (False, None))
        if not found:
            flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            found, corners = cv2.findChessboardCornersSB(img, size, flags=flags)
    else:
        found, corners = cv2.findCirclesGrid(img, size, flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    if not found or corners is None:
        return None
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def away_from_pattern_edges(board, points_b, margin: float) -> np.ndarray:
    """Which board points are at least ``margin`` from every albedo edge of the pattern.

    A laser stripe that straddles an edge between dark and light parts of the pattern has a
    skewed profile, so its centre is biased; the laser stages drop those points.

    Parameters
    ----------
    board : Checkerboard or CircleGrid
    points_b : array_like, shape (n, 2) or (n, 3), metres
        Points in the board frame (x, y on the board; z ignored).
    margin : float, metres
        For a checkerboard: distance to the nearest square edge (grid line through the
        inner corners). For a circle grid: distance outside the nearest circle's rim.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    check_small_board(board)
    q = np.asarray(points_b, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] not in (2, 3):
        raise ValueError(f'points_b must have shape (n, 2) or (n, 3), got {q.shape}')
    if not margin >= 0.0:
        raise ValueError(f'margin must be >= 0 m, got {margin!r}')
    if isinstance(board, Checkerboard):
        s = board.square
        dx = np.abs(q[:, 0] / s - np.round(q[:, 0] / s)) * s
        dy = np.abs(q[:, 1] / s - np.round(q[:, 1] / s)) * s
        return (dx >= margin) & (dy >= margin)
    p = board.pitch
    i = np.clip(np.round(q[:, 0] / p), 0, board.cols - 1)
    j = np.clip(np.round(q[:, 1] / p), 0, board.rows - 1)
    r = np.hypot(q[:, 0] - i * p, q[:, 1] - j * p)
    return r >= 0.5 * board.diameter + margin


def inside_convex_hull(points, hull_points, margin: float = 0.0) -> np.ndarray:
    """Which 2-D points lie inside the convex hull of others (shrunk by ``margin``).

    Parameters
    ----------
    points : array_like, shape (n, 2), pixels
    hull_points : array_like, shape (m, 2), pixels, m >= 3
    margin : float, pixels
        Points closer than this to the hull's boundary count as outside.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(hull_points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f'points must have shape (n, 2), got {p.shape}')
    if h.ndim != 2 or h.shape[1] != 2 or h.shape[0] < 3:
        raise ValueError(f'hull_points must have shape (m >= 3, 2), got {h.shape}')
    hull = cv2.convexHull(h.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    inside = np.ones(p.shape[0], dtype=bool)
    # cv2.convexHull returns the vertices in a consistent order; test every edge.
    area = 0.0
    for k in range(hull.shape[0]):
        a, b = hull[k], hull[(k + 1) % hull.shape[0]]
        area += a[0] * b[1] - a[1] * b[0]
    sign = 1.0 if area > 0 else -1.0
    for k in range(hull.shape[0]):
        a, b = hull[k], hull[(k + 1) % hull.shape[0]]
        edge = b - a
        length = float(np.hypot(*edge))
        if length == 0.0:
            continue
        cross = sign * (edge[0] * (p[:, 1] - a[1]) - edge[1] * (p[:, 0] - a[0])) / length
        inside &= cross >= margin
    return inside
