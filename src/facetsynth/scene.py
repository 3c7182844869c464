"""Ground-truth scenes for the virtual rig: microfacet SVBRDFs (paper 002 eq. 6).

A scene (``resources/scenes/*.yaml``, schema ``schemas/scene.schema.json``) is a
list of regions painted in order over the sample plane. Each region has kd,
ks (RGB), eta (eq. 3), an analytic anisotropic NDF (alpha_u, alpha_v) and the
azimuth of its local frame, constant or rotating about a centre. Markers are
black discs at known positions, used to measure registration error.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import microfacet
from .fileio import read_yaml
from .validation import validate


@dataclass(frozen=True)
class Scene:
    """A validated ground-truth scene."""

    name: str
    size: tuple[float, float]
    ndf: str
    regions: tuple[dict[str, Any], ...]
    marker_radius: float
    marker_positions: np.ndarray  # (M, 2), on the rig's plane (turned with the sample)
    rotation_deg: float = 0.0     # the sample turned about its normal (a turntable), counter-clockwise

    @classmethod
    def load(cls, path: str | Path) -> "Scene":
        return cls.from_dict(read_yaml(path), path)

    @classmethod
    def from_dict(cls, d: Any, path: str | Path | None = None) -> "Scene":
        validate(d, "scene.schema.json", path, "scene")
        markers = d.get("markers", {"radius": 1.0, "positions": []})
        rotation = float(d.get("rotation_deg", 0.0))
        positions = np.asarray(markers["positions"], float).reshape(-1, 2)
        return cls(name=d["name"], size=(float(d["size"][0]), float(d["size"][1])), ndf=d.get("ndf", "ggx"),
                   regions=tuple(d["regions"]), marker_radius=float(markers["radius"]),
                   marker_positions=_turn(positions, rotation), rotation_deg=rotation)

    def parameters(self, xy: np.ndarray) -> "MaterialMaps":
        """The true SVBRDF parameters at plane points ``xy`` (..., 2) (the rig's frame: a turned sample
        shows there its point turned back, with its frames turned by the rotation)."""
        shape = xy.shape[:-1]
        turn = np.radians(self.rotation_deg)
        xy_sample = _turn(xy, -self.rotation_deg)
        region = np.full(shape, -1, dtype=np.int16)
        kd, ks = np.zeros(shape + (3,)), np.zeros(shape + (3,))
        eta, alpha_u, alpha_v, phi = (np.ones(shape), np.ones(shape), np.ones(shape), np.zeros(shape))
        for index, r in enumerate(self.regions):
            inside = _inside(r["where"], xy_sample)
            region[inside] = index
            kd[inside], ks[inside] = r["kd"], r["ks"]
            eta[inside] = r["eta"]
            alpha_u[inside], alpha_v[inside] = r["alpha"]
            phi[inside] = _frame_azimuth(r["frame"], xy_sample)[inside] + turn
        on_marker = self.marker_mask(xy)
        kd[on_marker], ks[on_marker] = 0.0, 0.0
        region[on_marker] = -1
        return MaterialMaps(kd=kd, ks=ks, eta=eta, alpha_u=alpha_u, alpha_v=alpha_v, phi_frame=phi,
                            region=region, ndf_kind=self.ndf)

    def marker_mask(self, xy: np.ndarray) -> np.ndarray:
        """True where a point lies on a registration marker."""
        mask = np.zeros(xy.shape[:-1], dtype=bool)
        for centre in self.marker_positions:
            mask |= np.sum((xy - centre) ** 2, axis=-1) <= self.marker_radius**2
        return mask

    def on_sample(self, xy: np.ndarray) -> np.ndarray:
        """True where a point lies on the sample (inside its width x height, turned with it)."""
        xy = _turn(xy, -self.rotation_deg)
        return (np.abs(xy[..., 0]) <= self.size[0] / 2) & (np.abs(xy[..., 1]) <= self.size[1] / 2)


@dataclass(frozen=True)
class MaterialMaps:
    """Per-point parameters of eq. 6 with an analytic NDF: arrays over points."""

    kd: np.ndarray         # (..., 3)
    ks: np.ndarray         # (..., 3)
    eta: np.ndarray        # (...)
    alpha_u: np.ndarray    # (...)
    alpha_v: np.ndarray    # (...)
    phi_frame: np.ndarray  # (...) radians, azimuth of the local u axis
    region: np.ndarray     # (...) region index, -1 on markers / off-sample
    ndf_kind: str = "ggx"

    def rho(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """Eq. 6 at every point for directions broadcast against the maps (..., 3)."""
        return microfacet.rho(wi, wo, self.kd, self.ks, self.eta, self.alpha_u, self.alpha_v,
                              self.phi_frame, kind=self.ndf_kind)

    def ndf(self, h: np.ndarray) -> np.ndarray:
        """The true normalised NDF D(h) at every point (paper 002 eq. 6's D)."""
        return microfacet.ndf(h, self.alpha_u, self.alpha_v, self.phi_frame, kind=self.ndf_kind)

    def take(self, index) -> "MaterialMaps":
        """The maps at a subset of points (any numpy index)."""
        return MaterialMaps(self.kd[index], self.ks[index], self.eta[index], self.alpha_u[index],
                            self.alpha_v[index], self.phi_frame[index], self.region[index], self.ndf_kind)


def _turn(xy: np.ndarray, degrees: float) -> np.ndarray:
    """Points (..., 2) turned counter-clockwise by ``degrees`` about the origin."""
    if degrees == 0.0:
        return xy
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def _inside(where: dict[str, Any], xy: np.ndarray) -> np.ndarray:
    x, y = xy[..., 0], xy[..., 1]
    if "all" in where:
        return np.ones(x.shape, dtype=bool)
    if "rect" in where:
        (x0, x1), (y0, y1) = where["rect"]["x"], where["rect"]["y"]
        return (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    if "disc" in where:
        c, r = where["disc"]["centre"], where["disc"]["radius"]
        return (x - c[0]) ** 2 + (y - c[1]) ** 2 <= r * r
    if "fan" in where:
        f = where["fan"]
        angle = np.degrees(np.arctan2(y - f["centre"][1], x - f["centre"][0]))
        return np.floor(angle / f["period_deg"]).astype(int) % 2 == f.get("parity", 0)
    c = where["checker"]
    return (np.floor(x / c["size"]) + np.floor(y / c["size"])).astype(int) % 2 == c.get("parity", 0)


def _frame_azimuth(frame: dict[str, Any], xy: np.ndarray) -> np.ndarray:
    if "angle_deg" in frame:
        return np.full(xy.shape[:-1], np.radians(frame["angle_deg"]))
    cx, cy = frame["polar"]
    return np.arctan2(xy[..., 1] - cy, xy[..., 0] - cx) + np.radians(frame.get("offset_deg", 0.0))
