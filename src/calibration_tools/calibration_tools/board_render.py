"""Synthetic board images rendered through the geometric model (tests, demos, benchmarks).

These images are made with :mod:`reconstructor.model` (pinhole + plumb_bob through the ideal
dynamic-camera model), not by the physical simulator. They exercise the detectors and the
identification with exact, known ground truth; accuracy claims about the rig belong to the
simulator (``galvoscan_sim``).

Edges are anti-aliased analytically: each pixel centre is mapped onto the board, the signed
distance to the nearest edge is converted to pixels with the local Jacobian of the
pixel-to-board map, and the pixel's coverage is ``clip(0.5 - distance_px, 0, 1)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from reconstructor.model import CameraIntrinsics, RigModel, project_points, undistort_points

from .board_geometry import project_circle_centres, view_T_board
from .board_layout import Checkerboard, CircleBoard, CircleGrid


@dataclass(frozen=True)
class RenderedView:
    """A rendered image and its ground truth.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8
    index : ndarray, shape (m,), int
        Circle indices (circle board) or feature indices (intrinsics targets) near the view.
    uv : ndarray, shape (m, 2), pixels
        True ellipse centres (circles) or corners (checkerboard), distorted pixels.
    complete : ndarray of bool, shape (m,)
        True where the whole circle (or the corner) lies inside the image.
    V_T_W : ndarray, shape (4, 4)
        Board pose in the (virtual) camera, metres.
    """

    image: np.ndarray
    index: np.ndarray
    uv: np.ndarray
    complete: np.ndarray
    V_T_W: np.ndarray


_MAP_STEP = 4  # the pixel-to-board map is smooth: exact on a 4 px grid, bilinear in between


def _upsample(a: np.ndarray, step: int, h: int, w: int) -> np.ndarray:
    """Bilinear interpolation of a (Hc, Wc, k) grid sampled every ``step`` px to (h, w, k)."""
    v = np.arange(h)
    iv, tv = np.minimum(v // step, a.shape[0] - 2), (v - np.minimum(v // step, a.shape[0] - 2)
                                                      * step) / step
    rows = a[iv] * (1.0 - tv)[:, None, None] + a[iv + 1] * tv[:, None, None]
    u = np.arange(w)
    iu = np.minimum(u // step, a.shape[1] - 2)
    tu = (u - iu * step) / step
    return rows[:, iu] * (1.0 - tu)[None, :, None] + rows[:, iu + 1] * tu[None, :, None]


def _pixel_board_map(intr: CameraIntrinsics, V_T_W: np.ndarray):
    """Board (x, y) of every pixel centre and the Jacobian d(x, y)/d(u, v); shapes (H, W, 2)."""
    h, w = intr.height, intr.width
    s = _MAP_STEP
    vs = np.arange(0, h - 1 + 2 * s, s, dtype=np.float64)
    us = np.arange(0, w - 1 + 2 * s, s, dtype=np.float64)
    uu, vv = np.meshgrid(us, vs)
    xy = undistort_points(intr, np.column_stack([uu.ravel(), vv.ravel()]))
    W_T_V = np.linalg.inv(V_T_W)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ W_T_V[:3, :3].T
    o = W_T_V[:3, 3]
    with np.errstate(all="ignore"):
        lam = -o[2] / rays[:, 2]
        b = o[:2] + lam[:, None] * rays[:, :2]
    b[~(lam > 0.0)] = np.nan
    b = b.reshape(len(vs), len(us), 2)
    dbu = np.gradient(b, s, axis=1)  # d(x, y)/du
    dbv = np.gradient(b, s, axis=0)  # d(x, y)/dv
    return _upsample(b, s, h, w), _upsample(dbu, s, h, w), _upsample(dbv, s, h, w)


def _edge_distance_px(sd_m, grad_dir, dbu, dbv):
    """Signed distance in pixels from a board-metric distance and its board-plane gradient."""
    gu = grad_dir[..., 0] * dbu[..., 0] + grad_dir[..., 1] * dbu[..., 1]
    gv = grad_dir[..., 0] * dbv[..., 0] + grad_dir[..., 1] * dbv[..., 1]
    with np.errstate(all="ignore"):
        return sd_m / np.hypot(gu, gv)


def _disc_coverage(b, cx, cy, radius, on, dbu, dbv):
    """Pixel coverage, shape (H, W), of the disc of ``radius`` (metres) centred at (cx, cy).

    ``b`` is the board (x, y) of each pixel; zero where ``on`` is False.
    """
    dx, dy = b[..., 0] - cx, b[..., 1] - cy
    dist = np.hypot(dx, dy)
    sd_m = dist - radius
    with np.errstate(all="ignore"):
        direction = np.stack([dx / dist, dy / dist], axis=-1)
    sd_px = _edge_distance_px(sd_m, direction, dbu, dbv)
    return np.where(on, np.clip(0.5 - np.nan_to_num(sd_px, nan=1.0), 0.0, 1.0), 0.0)


def _finish(coverage_dark, inside_board, levels, background, blur_sigma_px, noise_std, rng):
    dark, light = levels
    img = light - (light - dark) * coverage_dark
    img = np.where(inside_board, img, background).astype(np.float32)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_std > 0:
        rng = np.random.default_rng(rng)
        img = img + rng.normal(0.0, noise_std, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _circle_complete(intr, V_T_W, centres, radii, margin=0.5):
    """True where the whole rim of each circle projects inside the image."""
    a = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    rim = centres[:, None, :2] + radii[:, None, None] * np.stack([np.cos(a), np.sin(a)], -1)
    rim = np.concatenate([rim, np.zeros(rim.shape[:2] + (1,))], axis=-1).reshape(-1, 3)
    p = rim @ V_T_W[:3, :3].T + V_T_W[:3, 3]
    uv = project_points(intr, p).reshape(len(centres), -1, 2)
    ok = np.isfinite(uv).all(axis=(1, 2))
    with np.errstate(invalid="ignore"):
        inside = (
            (uv[..., 0] >= margin)
            & (uv[..., 0] <= intr.width - 1 - margin)
            & (uv[..., 1] >= margin)
            & (uv[..., 1] <= intr.height - 1 - margin)
        )
    return ok & inside.all(axis=1)


def render_circle_board(
    model: RigModel,
    board: CircleBoard,
    V0_T_W,
    u1_pan: float,
    u1_tilt: float,
    *,
    blur_sigma_px: float = 0.8,
    noise_std: float = 1.5,
    levels: tuple[float, float] = (35.0, 215.0),
    background: float = 90.0,
    border: float = 0.02,
    rng=None,
) -> RenderedView:
    """Render the circle board as seen by the dynamic camera at G1 voltages ``(u1_pan, u1_tilt)``.

    Parameters
    ----------
    model : RigModel
        Rig whose intrinsics and dynamic camera form the image.
    board : CircleBoard
    V0_T_W : array_like, shape (4, 4)
        Board pose in V0, metres.
    u1_pan, u1_tilt : float, volts
    blur_sigma_px, noise_std : float
        Gaussian blur (pixels) and additive noise (grey levels) of the image.
    levels : (float, float)
        Grey levels of the circles and of the board.
    background : float
        Grey level beyond the board.
    border : float
        Margin of board around the outer circle centres, metres (beyond it: background).
    rng : int or numpy Generator, optional

    Returns
    -------
    RenderedView
        Truth: every circle whose centre maps within two pitches of the view.
    """
    V_T_W = view_T_board(model, float(u1_pan), float(u1_tilt), V0_T_W)
    intr = model.intrinsics
    b, dbu, dbv = _pixel_board_map(intr, V_T_W)
    lat = board.lattice_coords(b.reshape(-1, 2)).reshape(b.shape)
    rc = np.rint(np.nan_to_num(lat, nan=-1e6))
    r_idx, c_idx = rc[..., 0], rc[..., 1]
    on_lattice = (r_idx >= 0) & (r_idx < board.rows) & (c_idx >= 0) & (c_idx < board.cols)
    cx = (c_idx - board.centre_col) * board.pitch
    cy = (r_idx - board.centre_row) * board.pitch
    radius = np.where(board.is_large_rc(r_idx, c_idx), board.large_diameter, board.small_diameter)
    coverage = _disc_coverage(b, cx, cy, radius / 2.0, on_lattice, dbu, dbv)
    half_x = board.centre_col * board.pitch + border
    half_y = board.centre_row * board.pitch + border
    with np.errstate(invalid="ignore"):
        inside = (np.abs(b[..., 0]) <= half_x) & (np.abs(b[..., 1]) <= half_y)
    image = _finish(coverage, inside, levels, background, blur_sigma_px, noise_std, rng)

    ok = np.isfinite(lat).all(axis=-1)
    if ok.any():
        lo = np.floor(lat[ok].min(axis=0)) - 2
        hi = np.ceil(lat[ok].max(axis=0)) + 2
        rows = np.arange(max(lo[0], 0), min(hi[0], board.rows - 1) + 1, dtype=np.int64)
        cols = np.arange(max(lo[1], 0), min(hi[1], board.cols - 1) + 1, dtype=np.int64)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        index = board.index_of(rr.ravel(), cc.ravel())
    else:
        index = np.zeros(0, dtype=np.int64)
    centres = board.points(index)
    radii = board.radius(index)
    uv = project_circle_centres(intr, V_T_W, centres, radii)
    complete = _circle_complete(intr, V_T_W, centres, radii)
    with np.errstate(invalid="ignore"):
        near = np.isfinite(uv).all(axis=1) & (
            (uv[:, 0] > -intr.width) & (uv[:, 0] < 2 * intr.width)
            & (uv[:, 1] > -intr.height) & (uv[:, 1] < 2 * intr.height)
        )
    return RenderedView(image, index[near], uv[near], complete[near], V_T_W)


def _checkerboard_coverage(board: Checkerboard, b, dbu, dbv):
    """Dark coverage of each pixel and the pixels on the target, both shape (H, W)."""
    s = board.square
    # Squares span [-s, cols*s] x [-s, rows*s]; one white square of margin around them.
    fx, fy = b[..., 0] / s, b[..., 1] / s
    dist_x = (fx - np.rint(fx)) * s  # signed distance to the nearest vertical edge line
    dist_y = (fy - np.rint(fy)) * s
    ones = np.ones_like(dist_x)
    zeros = np.zeros_like(dist_x)
    px_x = np.abs(_edge_distance_px(dist_x, np.stack([ones, zeros], -1), dbu, dbv))
    px_y = np.abs(_edge_distance_px(dist_y, np.stack([zeros, ones], -1), dbu, dbv))
    # Squares k = -1 .. cols (x) and -1 .. rows (y); the stripe sign is +1 for even k.
    px_x = np.nan_to_num(px_x, nan=1.0)
    px_y = np.nan_to_num(px_y, nan=1.0)
    sign_x = np.where(np.mod(np.floor(fx), 2) == 0, 1.0, -1.0)
    sign_y = np.where(np.mod(np.floor(fy), 2) == 0, 1.0, -1.0)
    # Inner lines: smooth each stripe pattern over +-0.5 px. Outer lines (the border of
    # the squares, next to the white margin): the stripe keeps the inner square's sign
    # and the pixel's coverage of the squares region scales the result.
    with np.errstate(invalid="ignore"):
        lx, ly = np.rint(fx), np.rint(fy)
        outer_x = (lx == -1) | (lx == board.cols)
        outer_y = (ly == -1) | (ly == board.rows)
        in_x = (fx >= -1) & (fx <= board.cols)
        in_y = (fy >= -1) & (fy <= board.rows)
    kx = np.where(lx == -1, -1, board.cols - 1)
    ky = np.where(ly == -1, -1, board.rows - 1)
    inner_sx = np.where(np.mod(kx, 2) == 0, 1.0, -1.0)
    inner_sy = np.where(np.mod(ky, 2) == 0, 1.0, -1.0)
    ax = np.where(outer_x, inner_sx, sign_x * np.clip(px_x * 2.0, 0.0, 1.0))
    ay = np.where(outer_y, inner_sy, sign_y * np.clip(px_y * 2.0, 0.0, 1.0))
    wx = np.where(outer_x, np.clip(0.5 + np.where(in_x, px_x, -px_x), 0.0, 1.0),
                  in_x.astype(float))
    wy = np.where(outer_y, np.clip(0.5 + np.where(in_y, px_y, -px_y), 0.0, 1.0),
                  in_y.astype(float))
    with np.errstate(invalid="ignore"):
        inside = (fx >= -2) & (fx <= board.cols + 1) & (fy >= -2) & (fy <= board.rows + 1)
    # Square (-1, -1), the board's first corner square, is dark.
    coverage = wx * wy * (0.5 + 0.5 * ax * ay)
    return coverage, inside


def _checkerboard_corners(intrinsics: CameraIntrinsics, V_T_W, obj):
    """Pixels of the inner corners, shape (m, 2), and whether each lies in the image."""
    p = obj @ V_T_W[:3, :3].T + V_T_W[:3, 3]
    uv = project_points(intrinsics, p)
    with np.errstate(invalid="ignore"):
        complete = (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= 0) & (uv[:, 0] <= intrinsics.width - 1)
            & (uv[:, 1] >= 0) & (uv[:, 1] <= intrinsics.height - 1)
        )
    return uv, complete


def _circle_grid_coverage(board: CircleGrid, b, dbu, dbv):
    """Dark coverage of each pixel and the pixels on the target, both shape (H, W)."""
    p_ = board.pitch
    fx, fy = b[..., 0] / p_, b[..., 1] / p_
    cx, cy = np.rint(fx) * p_, np.rint(fy) * p_
    with np.errstate(invalid="ignore"):
        on_grid = (
            (np.rint(fx) >= 0) & (np.rint(fx) < board.cols)
            & (np.rint(fy) >= 0) & (np.rint(fy) < board.rows)
        )
        inside = (
            (fx >= -1.5) & (fx <= board.cols + 0.5) & (fy >= -1.5) & (fy <= board.rows + 0.5)
        )
    coverage = _disc_coverage(b, cx, cy, board.diameter / 2.0, on_grid, dbu, dbv)
    return coverage, inside


def render_target(
    intrinsics: CameraIntrinsics,
    board: Checkerboard | CircleGrid,
    V_T_W,
    *,
    blur_sigma_px: float = 0.8,
    noise_std: float = 1.5,
    levels: tuple[float, float] = (35.0, 215.0),
    background: float = 90.0,
    rng=None,
) -> RenderedView:
    """Render an intrinsics target (checkerboard or circle grid) seen by a camera.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
    board : Checkerboard or CircleGrid
    V_T_W : array_like, shape (4, 4)
        Target pose in the camera, metres.
    blur_sigma_px, noise_std, levels, background, rng
        As :func:`render_circle_board`.

    Returns
    -------
    RenderedView
        ``index`` and ``uv`` list every corner (checkerboard) or circle centre (grid) in the
        order of ``board.object_points()``; circle-grid ``uv`` are ellipse centres.
    """
    V_T_W = np.asarray(V_T_W, dtype=np.float64)
    if V_T_W.shape != (4, 4):
        raise ValueError(f"V_T_W must have shape (4, 4), got {V_T_W.shape}")
    b, dbu, dbv = _pixel_board_map(intrinsics, V_T_W)
    obj = board.object_points()
    if isinstance(board, Checkerboard):
        coverage, inside = _checkerboard_coverage(board, b, dbu, dbv)
        uv, complete = _checkerboard_corners(intrinsics, V_T_W, obj)
    elif isinstance(board, CircleGrid):
        coverage, inside = _circle_grid_coverage(board, b, dbu, dbv)
        radii = np.full(len(obj), board.diameter / 2.0)
        uv = project_circle_centres(intrinsics, V_T_W, obj, radii)
        complete = _circle_complete(intrinsics, V_T_W, obj, radii)
    else:
        raise ValueError(f"board must be a Checkerboard or CircleGrid, got {type(board).__name__}")
    image = _finish(coverage, inside, levels, background, blur_sigma_px, noise_std, rng)
    return RenderedView(image, np.arange(len(obj)), uv, complete, V_T_W)
