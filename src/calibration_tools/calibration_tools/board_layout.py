"""Calibration boards: the paper's large circle board and small intrinsics targets (no rclpy).

Board frame W (OpenCV object convention): the board is the plane z = 0, x runs along a row
(increasing column index), y along a column (increasing row index) and z points into the
board, away from a camera that sees the printed side with x right and y down.

The circle board (docs/design.md section 3): 35 x 35 circles at 20 mm pitch in 25 sub-patterns of
7 x 7; the centre circle of each sub-pattern is 15 mm across, the others 10 mm. Circle
``(row, col)`` has index ``row * cols + col`` and sits at
``((col - centre_col) * pitch, (row - centre_row) * pitch, 0)``: the origin of W is the
centre circle of the whole board (itself a large circle).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class CircleBoard:
    """A square lattice of circles with one large circle per sub-pattern.

    Parameters
    ----------
    rows, cols : int
        Number of circle rows and columns.
    pitch : float
        Centre-to-centre spacing, metres.
    sub_pattern : int
        Side of a sub-pattern in circles (odd); its centre circle is the large one.
    small_diameter, large_diameter : float
        Circle diameters, metres.
    """

    rows: int = 35
    cols: int = 35
    pitch: float = 0.020
    sub_pattern: int = 7
    small_diameter: float = 0.010
    large_diameter: float = 0.015

    def __post_init__(self):
        for name in ("rows", "cols", "sub_pattern"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.sub_pattern % 2 != 1:
            raise ValueError(f"sub_pattern must be odd, got {self.sub_pattern}")
        if self.rows % self.sub_pattern or self.cols % self.sub_pattern:
            raise ValueError("rows and cols must be multiples of sub_pattern")
        for name in ("pitch", "small_diameter", "large_diameter"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value <= 0.0:
                raise ValueError(f"{name} must be a positive length in metres, got {value!r}")
            object.__setattr__(self, name, value)
        if self.pitch > 1.0:
            raise ValueError(f"pitch must be in metres (got {self.pitch}; millimetres?)")
        if not self.small_diameter < self.large_diameter < self.pitch:
            raise ValueError("need small_diameter < large_diameter < pitch")

    @property
    def n_circles(self) -> int:
        """Number of circles on the board."""
        return self.rows * self.cols

    @property
    def centre_row(self) -> float:
        """Row coordinate of the board frame origin."""
        return (self.rows - 1) / 2.0

    @property
    def centre_col(self) -> float:
        """Column coordinate of the board frame origin."""
        return (self.cols - 1) / 2.0

    @cached_property
    def _points(self) -> np.ndarray:
        r, c = np.divmod(np.arange(self.n_circles), self.cols)
        pts = np.zeros((self.n_circles, 3))
        pts[:, 0] = (c - self.centre_col) * self.pitch
        pts[:, 1] = (r - self.centre_row) * self.pitch
        pts.flags.writeable = False
        return pts

    def points(self, index=None) -> np.ndarray:
        """Circle centres in the board frame.

        Parameters
        ----------
        index : array_like of int, shape (m,), optional
            Circle indices; all circles when omitted.

        Returns
        -------
        ndarray, shape (m, 3), metres
        """
        if index is None:
            return self._points.copy()
        return self._points[self._check_index(index)]

    def row_col(self, index) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of circle indices, each shape (m,)."""
        return np.divmod(self._check_index(index), self.cols)

    def index_of(self, row, col) -> np.ndarray:
        """Circle index of ``(row, col)``, -1 where outside the board; shape of the inputs."""
        r = np.asarray(row)
        c = np.asarray(col)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        return np.where(inside, r * self.cols + c, -1).astype(np.int64)

    def is_large_rc(self, row, col) -> np.ndarray:
        """True where lattice position ``(row, col)`` is a sub-pattern centre (any integers)."""
        h = self.sub_pattern // 2
        return (np.mod(row, self.sub_pattern) == h) & (np.mod(col, self.sub_pattern) == h)

    def is_large(self, index) -> np.ndarray:
        """True for the large (sub-pattern centre) circles; shape (m,)."""
        r, c = self.row_col(index)
        return self.is_large_rc(r, c)

    def radius(self, index) -> np.ndarray:
        """Circle radii, shape (m,), metres."""
        big = self.is_large(index)
        return np.where(big, self.large_diameter / 2.0, self.small_diameter / 2.0)

    def lattice_coords(self, xy) -> np.ndarray:
        """Fractional ``(row, col)`` of board-plane points.

        Parameters
        ----------
        xy : array_like, shape (m, 2), metres
            Board-frame (x, y).

        Returns
        -------
        ndarray, shape (m, 2)
        """
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy must have shape (m, 2), got {xy.shape}")
        return np.stack(
            [xy[:, 1] / self.pitch + self.centre_row, xy[:, 0] / self.pitch + self.centre_col],
            axis=1,
        )

    def _check_index(self, index) -> np.ndarray:
        idx = np.asarray(index)
        if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"index must be a 1-D integer array, got {idx.dtype} {idx.shape}")
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_circles):
            raise ValueError(
                f"index must be in [0, {self.n_circles}), got {idx.min()}..{idx.max()}"
            )
        return idx.astype(np.int64)


#: The paper's 740 x 740 mm board (docs/design.md section 3).
PAPER_CIRCLE_BOARD = CircleBoard()


@dataclass(frozen=True)
class Checkerboard:
    """Chessboard target for the intrinsics stage.

    Parameters
    ----------
    cols, rows : int
        Inner corners per row and per column (OpenCV ``patternSize = (cols, rows)``).
    square : float
        Square side, metres.
    """

    cols: int
    rows: int
    square: float

    def __post_init__(self):
        _check_grid(self.cols, self.rows, self.square, "square")

    def object_points(self) -> np.ndarray:
        """Inner corners in the board frame, OpenCV order (row-major), shape (n, 3), metres."""
        r, c = np.divmod(np.arange(self.cols * self.rows), self.cols)
        return np.stack([c * self.square, r * self.square, np.zeros(r.size)], axis=1)


@dataclass(frozen=True)
class CircleGrid:
    """Symmetric circle grid target for the intrinsics stage (dark circles on light).

    Parameters
    ----------
    cols, rows : int
        Circles per row and per column (OpenCV ``patternSize = (cols, rows)``).
    pitch : float
        Centre spacing, metres.
    diameter : float
        Circle diameter, metres.
    """

    cols: int
    rows: int
    pitch: float
    diameter: float

    def __post_init__(self):
        _check_grid(self.cols, self.rows, self.pitch, "pitch")
        if not 0.0 < float(self.diameter) < float(self.pitch):
            raise ValueError(f"diameter must be in (0, pitch), got {self.diameter!r}")

    def object_points(self) -> np.ndarray:
        """Circle centres in the board frame, OpenCV order (row-major), shape (n, 3), metres."""
        r, c = np.divmod(np.arange(self.cols * self.rows), self.cols)
        return np.stack([c * self.pitch, r * self.pitch, np.zeros(r.size)], axis=1)


def _check_grid(cols, rows, spacing, name):
    for key, value in (("cols", cols), ("rows", rows)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
            raise ValueError(f"{key} must be an integer >= 2, got {value!r}")
    s = float(spacing)
    if not np.isfinite(s) or s <= 0.0:
        raise ValueError(f"{name} must be a positive length in metres, got {spacing!r}")
    if s > 0.5:
        raise ValueError(f"{name} must be in metres (got {spacing}; millimetres?)")
