"""Ground-truth scenes for the virtual rig: microfacet SVBRDFs (paper 002 eq. 6) and truth outside it.

A scene (``resources/scenes/*.yaml``, schema ``schemas/scene.schema.json``) is a
list of regions painted in order over the sample plane. Each region has kd,
ks (RGB), eta (eq. 3), an analytic anisotropic NDF (alpha_u, alpha_v) and the
azimuth of its local frame, constant or rotating about a centre. Markers are
black discs at known positions, used to measure registration error.

Regions outside eq. 6's family (docs/decisions.md, "Truth outside eq. 6"), each a region option:

* ``measured: {file, scale}``: a measured RGL BRDF (``.bsdf``, Dupuy and Jakob 2018) evaluated by
  :class:`facetsynth.stencil.readers.RGLBRDF` in the region's local frame, times ``scale``; no kd, ks,
  eta, alpha (``frame`` optional). A relative ``file`` is relative to the folder of the scene file
  (``../brdfs/rgl/x.bsdf`` from ``resources/scenes/``); a virtual capture copies the file into its
  ``truth/brdfs/`` and its ``truth/scene.yaml`` names the copy, so the truth travels with the capture.
* ``shadowing: height_correlated``: Smith's height-correlated G2 (Heitz 2014) instead of eq. 5's S(i)S(o).
* ``fresnel: {conductor: copper | gold | {n: [r, g, b], k: [r, g, b]}}`` instead of ``eta``: the
  exact conductor Fresnel term with a complex index per channel (:data:`microfacet.CONDUCTORS`).
* ``coat: {eta, alpha, weight}``: a clear GGX coat over the base (:func:`microfacet.rho_extended`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ..models import microfacet
from ..io.errors import InputError
from ..io.fileio import read_yaml
from ..io.validation import validate


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
        """A scene from its YAML dict; ``path`` (the scene file) names it in errors and anchors the
        relative ``measured.file`` paths (the current directory without a path)."""
        _check_exclusive(d, path)
        validate(d, "scene.schema.json", path, "scene")
        markers = d.get("markers", {"radius": 1.0, "positions": []})
        rotation = float(d.get("rotation_deg", 0.0))
        positions = np.asarray(markers["positions"], float).reshape(-1, 2)
        regions = tuple(_resolve_measured(r, i, path) for i, r in enumerate(d["regions"]))
        return cls(name=d["name"], size=(float(d["size"][0]), float(d["size"][1])), ndf=d.get("ndf", "ggx"),
                   regions=regions, marker_radius=float(markers["radius"]),
                   marker_positions=_turn(positions, rotation), rotation_deg=rotation)

    def parameters(self, xy: np.ndarray) -> "MaterialMaps":
        """The true SVBRDF parameters at plane points ``xy`` (..., 2) (the rig's frame: a turned sample
        shows there its point turned back, with its frames turned by the rotation).

        Regions outside eq. 6 fill the extra maps (None when no region of the scene needs them):
        a measured region gets kd = :func:`measured_kd` (scale included), ks = 0, eta = 1,
        alpha = (1, 1) (placeholders: its BRDF is the file); a conductor region gets
        eta = :func:`microfacet.conductor_equivalent_eta` (placeholder). ``analytic`` is True on
        plain eq. 6 regions and on markers (eq. 6 with kd = ks = 0), False on the others."""
        shape = xy.shape[:-1]
        turn = np.radians(self.rotation_deg)
        xy_sample = _turn(xy, -self.rotation_deg)
        region = np.full(shape, -1, dtype=np.int16)
        kd, ks = np.zeros(shape + (3,)), np.zeros(shape + (3,))
        eta, alpha_u, alpha_v, phi = (np.ones(shape), np.ones(shape), np.ones(shape), np.zeros(shape))
        analytic = np.ones(shape, dtype=bool)
        kinds = [_region_kind(r) for r in self.regions]
        used = {k for kind in kinds for k in kind}
        correlated = np.zeros(shape, dtype=bool) if "correlated" in used else None
        conductor = np.zeros(shape + (3,), dtype=np.complex128) if "conductor" in used else None
        coat = np.zeros(shape + (3,)) if "coat" in used else None
        measured = np.full(shape, -1, dtype=np.int16) if "measured" in used else None
        measured_scale = np.zeros(shape) if "measured" in used else None
        files = tuple(dict.fromkeys(r["measured"]["file"] for r in self.regions if "measured" in r))
        for index, r in enumerate(self.regions):
            inside = _inside(r["where"], xy_sample)
            region[inside] = index
            phi[inside] = _frame_azimuth(r.get("frame", {"angle_deg": 0.0}), xy_sample)[inside] + turn
            analytic[inside] = not kinds[index]
            if measured is not None:
                measured[inside], measured_scale[inside] = -1, 0.0
            if correlated is not None:
                correlated[inside] = "correlated" in kinds[index]
            if conductor is not None:
                conductor[inside] = 0.0
            if coat is not None:
                coat[inside] = 0.0
            if "measured" in r:
                m = r["measured"]
                scale = float(m.get("scale", 1.0))
                measured[inside], measured_scale[inside] = files.index(m["file"]), scale
                kd[inside], ks[inside] = scale * measured_kd(m["file"]), 0.0
                eta[inside], alpha_u[inside], alpha_v[inside] = 1.0, 1.0, 1.0
                continue
            kd[inside], ks[inside] = r["kd"], r["ks"]
            alpha_u[inside], alpha_v[inside] = r["alpha"]
            if "fresnel" in r:
                n, k = conductor_index(r["fresnel"]["conductor"])
                conductor[inside] = n + 1j * k
                eta[inside] = microfacet.conductor_equivalent_eta(n, k)
            else:
                eta[inside] = r["eta"]
            if coat is not None and "coat" in r:          # (a coat of weight 0 everywhere: no coat map)
                c = r["coat"]
                coat[inside] = (c["eta"], c["alpha"], c.get("weight", 1.0))
        on_marker = self.marker_mask(xy)
        kd[on_marker], ks[on_marker] = 0.0, 0.0
        region[on_marker] = -1
        analytic[on_marker] = True
        if measured is not None:
            measured[on_marker], measured_scale[on_marker] = -1, 0.0
        if coat is not None:
            coat[on_marker] = 0.0
        return MaterialMaps(kd=kd, ks=ks, eta=eta, alpha_u=alpha_u, alpha_v=alpha_v, phi_frame=phi,
                            region=region, ndf_kind=self.ndf, analytic=analytic, correlated=correlated,
                            conductor=conductor, coat=coat, measured=measured, measured_scale=measured_scale,
                            measured_brdfs=tuple(rgl_brdf(f) for f in files))

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
    """Per-point parameters of eq. 6 with an analytic NDF, and the truth outside eq. 6: arrays over points.

    The optional maps (None when the scene has no such region) describe the departures from eq. 6
    evaluated by :meth:`rho` (:func:`microfacet.rho_extended`, and the measured files):
    ``correlated`` (height-correlated Smith G2), ``conductor`` (complex n + i k per channel, zero rows
    where eq. 3's eta applies), ``coat`` (rows eta_c, alpha_c, weight; weight 0: no coat),
    ``measured`` (index into ``measured_brdfs``, -1: analytic) with ``measured_scale``.
    ``analytic`` is True only where the true BRDF is exactly eq. 6 with the NDF of ``ndf_kind``
    (plain microfacet regions, markers): accuracy metrics against kd, ks, eta or the NDF use those
    points only.
    """

    kd: np.ndarray         # (..., 3)
    ks: np.ndarray         # (..., 3)
    eta: np.ndarray        # (...)
    alpha_u: np.ndarray    # (...)
    alpha_v: np.ndarray    # (...)
    phi_frame: np.ndarray  # (...) radians, azimuth of the local u axis
    region: np.ndarray     # (...) region index, -1 on markers / off-sample
    ndf_kind: str = "ggx"
    analytic: np.ndarray | None = None        # (...) bool; None given: all True
    correlated: np.ndarray | None = None      # (...) bool
    conductor: np.ndarray | None = None       # (..., 3) complex
    coat: np.ndarray | None = None            # (..., 3)
    measured: np.ndarray | None = None        # (...) int
    measured_scale: np.ndarray | None = None  # (...)
    measured_brdfs: tuple = ()                # RGLBRDF of each measured index

    def __post_init__(self):
        if self.analytic is None:
            object.__setattr__(self, "analytic", np.ones(np.shape(self.region), dtype=bool))

    def rho(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """The true BRDF at every point for directions broadcast against the maps (..., 3): eq. 6
        (:func:`microfacet.rho`, bit for bit as before on plain scenes), its variants
        (:func:`microfacet.rho_extended`) and measured BRDFs (``scale * RGLBRDF.eval(wi, wo)`` of the
        directions turned into the region's local frame: ``wi`` the light, in the file's incident slot
        as it was measured; the files are reciprocal only to their accuracy, docs/decisions.md)."""
        if self.correlated is None and self.conductor is None and self.coat is None and self.measured is None:
            return microfacet.rho(wi, wo, self.kd, self.ks, self.eta, self.alpha_u, self.alpha_v,
                                  self.phi_frame, kind=self.ndf_kind)
        wi, wo = np.asarray(wi, np.float64), np.asarray(wo, np.float64)
        shape = np.broadcast_shapes(wi.shape[:-1], wo.shape[:-1], np.shape(self.region))
        if self.measured is None or np.any(self.measured < 0):
            out = microfacet.rho_extended(wi, wo, self.kd, self.ks, self.eta, self.alpha_u, self.alpha_v,
                                          self.phi_frame, kind=self.ndf_kind, correlated=self.correlated,
                                          conductor=self.conductor, coat=self.coat)
            out = np.array(np.broadcast_to(out, shape + (3,)))
        else:
            out = np.zeros(shape + (3,))
        if self.measured is not None:
            measured = np.broadcast_to(self.measured, shape)
            for j, brdf in enumerate(self.measured_brdfs):
                sel = measured == j
                if not sel.any():
                    continue
                phi = np.broadcast_to(self.phi_frame, shape)[sel]
                li = microfacet.to_local(np.broadcast_to(wi, shape + (3,))[sel], phi)
                lo = microfacet.to_local(np.broadcast_to(wo, shape + (3,))[sel], phi)
                scale = np.broadcast_to(self.measured_scale, shape)[sel]
                out[sel] = scale[:, None] * brdf.eval(li, lo)
        return out

    def ndf(self, h: np.ndarray) -> np.ndarray:
        """The true normalised NDF D(h) at every point (paper 002 eq. 6's D): the analytic lobe where
        one is defined (the base lobe of coated, conductor and height-correlated regions), 0 on
        measured regions."""
        d = microfacet.ndf(h, self.alpha_u, self.alpha_v, self.phi_frame, kind=self.ndf_kind)
        if self.measured is None:
            return d
        return np.where(self.measured >= 0, 0.0, d)

    def take(self, index) -> "MaterialMaps":
        """The maps at a subset of points (any numpy index), every map included."""
        values = {}
        for f in fields(self):
            v = getattr(self, f.name)
            values[f.name] = v if v is None or isinstance(v, (str, tuple)) else v[index]
        return MaterialMaps(**values)


def conductor_index(spec: str | dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) per RGB channel of a scene's ``fresnel.conductor``: a name of
    :data:`microfacet.CONDUCTORS` or ``{n: [r, g, b], k: [r, g, b]}``."""
    if isinstance(spec, str):
        n, k = microfacet.CONDUCTORS[spec]
    else:
        n, k = spec["n"], spec["k"]
    return np.asarray(n, float), np.asarray(k, float)


@lru_cache(maxsize=32)
def rgl_brdf(path: str):
    """The RGL measured BRDF of a file, loaded once per process (read-only, shared by threads)."""
    from ..stencil.readers import RGLBRDF
    return RGLBRDF(path)


@lru_cache(maxsize=32)
def measured_kd(path: str) -> np.ndarray:
    """A diffuse albedo estimate of a measured BRDF, in the spirit of eq. 9: pi times the minimum of
    each channel over light and view directions up to 60 deg from the normal (theta_i, theta_o in
    0, 10, ..., 60 deg, relative azimuth 0, 30, ..., 330 deg). Truth for display; kd metrics skip
    non-analytic points."""
    t = np.radians(np.arange(0.0, 61.0, 10.0))
    p = np.radians(np.arange(0.0, 360.0, 30.0))
    ti, to, dp = np.meshgrid(t, t, p, indexing="ij")
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], -1)
    wo = np.stack([np.sin(to) * np.cos(dp), np.sin(to) * np.sin(dp), np.cos(to)], -1)
    value = rgl_brdf(path).eval(wi, wo).reshape(-1, 3)
    return np.pi * value.min(axis=0)


def _region_kind(r: dict[str, Any]) -> tuple[str, ...]:
    """The departures from eq. 6 of a region: () for a plain microfacet region."""
    kind = []
    if "measured" in r:
        kind.append("measured")
    if r.get("shadowing", "separable") == "height_correlated":
        kind.append("correlated")
    if "fresnel" in r:
        kind.append("conductor")
    if "coat" in r and r["coat"].get("weight", 1.0) > 0:
        kind.append("coat")
    return tuple(kind)


_MEASURED_EXCLUDES = ("kd", "ks", "eta", "alpha", "fresnel", "shadowing", "coat")


def _check_exclusive(d: Any, path: str | Path | None) -> None:
    """Clear errors for keys that exclude each other (the schema says the same, less readably)."""
    regions = d.get("regions") if isinstance(d, dict) else None
    for i, r in enumerate(regions if isinstance(regions, list) else []):
        if not isinstance(r, dict):
            continue
        if "measured" in r:
            for key in _MEASURED_EXCLUDES:
                if key in r:
                    raise InputError(path, f"invalid scene at 'regions/{i}/{key}': a measured region takes its "
                                           f"whole BRDF from its file (no {', '.join(_MEASURED_EXCLUDES)})")
        elif "fresnel" in r and "eta" in r:
            raise InputError(path, f"invalid scene at 'regions/{i}/eta': a region with a conductor 'fresnel' "
                                   "has no dielectric eta")


def _resolve_measured(r: dict[str, Any], index: int, path: str | Path | None) -> dict[str, Any]:
    """The region with its measured file made absolute (relative: to the scene file's folder), checked
    to exist and to load."""
    if "measured" not in r:
        return r
    file = Path(r["measured"]["file"]).expanduser()
    if not file.is_absolute():
        file = (Path(path).parent if path is not None else Path.cwd()) / file
    file = file.resolve()
    if not file.is_file():
        raise InputError(path, f"invalid scene at 'regions/{index}/measured/file': no such file {file} "
                               "(a relative path is relative to the scene file's folder)")
    rgl_brdf(str(file))       # a bad file: InputError naming it
    return {**r, "measured": {**r["measured"], "file": str(file)}}


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
