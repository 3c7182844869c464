"""Pinhole or orthographic camera in the OpenCV convention (DESIGN.md sec. 4).

X_cam = R X + t; x right, y down, z forward; pixel (0, 0) is the centre of the
top-left pixel. The sample plane is z = 0 in world coordinates. A pinhole
(``perspective``) camera divides by the depth; an ``orthographic`` one does not:
(col, row, 1) = K (X_cam_x, X_cam_y, 1), fx and fy in pixels per metre, t_z unused.
That is an RTI light dome's camera: far above a small object, looking straight down.
Its centre is at infinity: :attr:`Camera.view_point` is homogeneous, (C, 1) for a
pinhole and (-r3, 0), the direction towards the camera, for an orthographic one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole camera: image size, intrinsics K, extrinsics R, t."""

    width: int
    height: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    projection: str = "perspective"

    @property
    def orthographic(self) -> bool:
        return self.projection == "orthographic"

    @property
    def centre(self) -> np.ndarray:
        """Camera position in world coordinates, C = -R^T t (the paper's V); pinhole cameras only."""
        if self.orthographic:
            raise ValueError("an orthographic camera has no centre: use view_point")
        return -self.R.T @ self.t

    @property
    def view_point(self) -> np.ndarray:
        """The camera as a homogeneous world point (4,): (C, 1), or (-r3, 0) for an orthographic camera
        (the direction towards it; r3 the third row of R). :func:`facetsynth.models.render.towards` takes it."""
        if self.orthographic:
            return np.append(-self.R[2], 0.0)
        return np.append(self.centre, 1.0)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) to pixel coordinates (..., 2) as (col, row).

        Applies the OpenCV lens distortion (k1, k2, p1, p2, k3) when present.
        """
        xc = points @ self.R.T + self.t
        depth = 1.0 if self.orthographic else xc[..., 2]
        x, y = xc[..., 0] / depth, xc[..., 1] / depth
        if self.has_distortion:
            k1, k2, p1, p2, k3 = np.pad(self.distortion, (0, 5 - len(self.distortion)))
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
            x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
        uv1 = np.stack([x, y, np.ones_like(x)], axis=-1) @ self.K.T
        return uv1[..., :2]

    def plane_homography(self) -> np.ndarray:
        """H mapping sample-plane (x, y, 1) to pixel (col, row, 1): H = K [r1 r2 t] (Zhang 2000), and for an
        orthographic camera the affine K [r1 r2 t] with its third row (0, 0, 1).

        Exact for an undistorted camera.
        """
        M = np.column_stack([self.R[:, 0], self.R[:, 1], self.t])
        if self.orthographic:
            M[2] = (0.0, 0.0, 1.0)
        return self.K @ M

    def pixel_plane_points(self, supersample: int = 1) -> np.ndarray:
        """Sample-plane (x, y) seen through each pixel: (H*s, W*s, 2).

        With ``supersample`` s > 1, an s x s grid of sub-pixel positions per
        pixel (row-major), for box-filtered rendering. Undistorted cameras only.
        """
        s = supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        cols = (np.arange(self.width)[:, None] + offsets[None, :]).ravel()
        rows = (np.arange(self.height)[:, None] + offsets[None, :]).ravel()
        cc, rr = np.meshgrid(cols, rows)
        pix = np.stack([cc, rr, np.ones_like(cc)], axis=-1)
        xy1 = pix @ np.linalg.inv(self.plane_homography()).T
        return xy1[..., :2] / xy1[..., 2:3]

    @classmethod
    def look_at(cls, position, target, width: int, height: int, focal_px: float,
                up=(0.0, 0.0, 1.0)) -> "Camera":
        """A camera at ``position`` looking at ``target`` with world ``up`` above.

        The principal point is the image centre ((W-1)/2, (H-1)/2).
        """
        position, target, up = (np.asarray(v, dtype=float) for v in (position, target, up))
        z = target - position
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        K = np.array([[focal_px, 0.0, (width - 1) / 2], [0.0, focal_px, (height - 1) / 2], [0.0, 0.0, 1.0]])
        return cls(width=width, height=height, K=K, R=R, t=-R @ position)
