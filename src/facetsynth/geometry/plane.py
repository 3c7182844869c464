"""The rectified sample-plane grid: the one place that maps (row, col) to (x, y).

The sample occupies [-width/2, width/2] x [-height/2, height/2] on z = 0.
A rectified image is viewed from above: column index grows with x, row index
grows with -y (row 0 is the +y edge), and cell (row, col) has its centre at

    x = -width/2  + (col + 0.5) * width  / cols
    y = +height/2 - (row + 0.5) * height / rows
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PlaneGrid:
    """A regular grid of sample points over the sample plane."""

    width: float
    height: float
    cols: int
    rows: int

    @property
    def cell_size(self) -> tuple[float, float]:
        """(dx, dy) in metres."""
        return self.width / self.cols, self.height / self.rows

    def pixel_to_plane(self) -> np.ndarray:
        """3x3 matrix A with (x, y, 1) = A (col, row, 1)."""
        dx, dy = self.cell_size
        return np.array([[dx, 0.0, -self.width / 2 + dx / 2],
                         [0.0, -dy, self.height / 2 - dy / 2],
                         [0.0, 0.0, 1.0]])

    def to_plane(self, col, row) -> np.ndarray:
        """Continuous (col, row) to (x, y) in metres, shape (..., 2)."""
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        xy1 = np.stack([col, row, np.ones_like(col)], axis=-1) @ self.pixel_to_plane().T
        return xy1[..., :2]

    def to_pixel(self, x, y) -> np.ndarray:
        """(x, y) in metres to continuous (col, row), shape (..., 2)."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        cr1 = np.stack([x, y, np.ones_like(x)], axis=-1) @ np.linalg.inv(self.pixel_to_plane()).T
        return cr1[..., :2]

    def cell_centres(self) -> np.ndarray:
        """(rows, cols, 2) sample-plane (x, y) of every cell centre."""
        cc, rr = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return self.to_plane(cc, rr)

    def points3d(self) -> np.ndarray:
        """(rows, cols, 3) world positions of the cell centres (z = 0)."""
        xy = self.cell_centres()
        return np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "cols": self.cols, "rows": self.rows,
                "pixel_to_plane": self.pixel_to_plane().tolist(),
                "convention": "x = -width/2 + (col+0.5)*width/cols; y = height/2 - (row+0.5)*height/rows"}

    @classmethod
    def from_dict(cls, d: dict) -> "PlaneGrid":
        return cls(width=float(d["width"]), height=float(d["height"]), cols=int(d["cols"]), rows=int(d["rows"]))
