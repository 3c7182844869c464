"""The fitted SVBRDF (DESIGN.md sec. 4): the folder a user takes away, and its loader.

The model is paper 002's eq. 6 per point x of the rectified sample-plane grid,

    rho(x, i, o) = kd(x)/pi + ks(x) D(x, h) S(x, i) S(x, o) F(|i.h|, eta(x)) / (4 (i.n)(o.n))
                 = kd(x)/pi + ks(x) D(x, h) F(|i.h|, eta(x)) / (4 A(x, i) A(x, o)),

(S(k) = (k.n)/A(k), eq. 5; the second form has no 0/0 at grazing), with the
per-point NDF an eq. 18 mixture of representative NDFs,

    D(x, h) = max(0, sum_k w(x, k) D_rep[j(x, k)](h)),  A(x, k) = sum_k w(x, k) A_rep[j(x, k)](k)

(eq. 5 is linear in D, so the mixture's A is the mixture of the A's). The
weights here are those of the normalised NDFs: w = w18 ks_rep / ks(x), which
sum to one like eq. 18's.

Folder layout (``model.json`` describes it):

    kd.exr, ks.exr        R, G, B maps on the plane grid (rows, cols)
    eta.exr               channels ``eta`` and ``eta_fitted`` (1 where grazing data constrained eta); when
                          the params stage wrote them, ``eta_lo`` and ``eta_hi``: the 95 % profile-likelihood
                          interval of eta of the point's material (eqs. 19-20; model.json ``eta``
                          ``intervals`` per material). Folders without them load with None.
    ndf.npy               (R, n_theta, n_phi) float32 normalised representative NDFs on ``grid``
    projected_area.npy    (R, Ts, Fs) float32 eq. 5's A(k) of each representative on ``shadowing_grid``
    representatives.npy   (R,) int64 point index of each representative
    neighbours.npy        (P, K) int32 indices into the representatives
    weights.npy           (P, K) float32 mixture weights (padding has weight 0)
    rotation.npy          (optional) (P,) float32 eq. 13's per-point turn of the NDF about the normal, radians
    normal.exr            (optional) channels ``X``, ``Y``, ``Z``: the per-point unit shading normal n(x)
                          (mesostructure, :mod:`facetsynth.fit.normals`) in the plane's frame (x, y along the
                          plane grid's axes, z up), n_z > 0; read when model.json's ``files`` lists it
                          (``"normal": "normal.exr"``). Folders without it load with ``normal = None``: flat,
                          n = +z everywhere.
    model.json            version, units, plane grid, direction grids, eta range and default, provenance

Points are sample-plane positions in metres (z = 0); a point maps to the
rectified cell containing it (PlaneGrid, the one place that maps (row, col)
to (x, y)); points off the sample get rho = 0.

Frames. Eq. 6 above is written in the point's SHADING FRAME (local: n = +z). With per-point shading
normals (``normal``), the frame of point x is the rotation R(x) = :meth:`SVBRDF.frames` with
R(x) n(x) = +z (:func:`facetsynth.fit.normals.shading_frames`, the smallest rotation; the identity where
``normal`` is None or n = +z), and

* :meth:`SVBRDF.eval_index`, :meth:`~SVBRDF.specular_terms`, :meth:`~SVBRDF.ndf_at`, :meth:`~SVBRDF.area_at`
  and :meth:`~SVBRDF.mixture` take directions IN THE POINT'S SHADING FRAME (local: i_local = R(x) i_world,
  :func:`facetsynth.fit.normals.to_local`); their horizon is the shading one (local z <= 0 gives 0);
* :meth:`SVBRDF.eval` ``(points, wi, wo)`` takes WORLD directions (the plane's frame) and converts them with
  the frames first: rho(x, R(x) i, R(x) o), and 0 also where i or o is at or below the sample plane
  (world z <= 0: nothing reaches the sample from below it, whatever the normal).

rho never includes the foreshortening: a pixel is rho (n(x) . i) L / |P - x|^2, n(x) . i being the local
z of i (the plane's z for a flat model). With ``normal`` None nothing is rotated: every method gives, bit
for bit, what it gave before shading normals existed.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numba
import numpy as np

from ..io.errors import InputError
from ..io.fileio import read_exr, read_json, read_npy, write_exr, write_json, write_npy
from ..geometry.grid import DirectionGrid, bilinear_stencil, polar_coordinates, turn
from .microfacet import fresnel, half_vector
from ..fit.normals import shading_frames, to_local
from ..fit.partial_ndf import SHADOWING_GRID
from ..geometry.plane import PlaneGrid

FORMAT_VERSION = 1
CHUNK = 1 << 16   # directions evaluated per block: bounds eval's memory
NORMAL_FILE = "normal.exr"
NORMAL_UNIT_TOL = 1e-3   # |n| - 1 accepted on load (then renormalised)
MAX_GRID_CELLS = 1 << 20   # a plane or direction grid's side on load: far beyond any fit (paper scale: 4096)


@numba.njit(cache=True, nogil=True, inline="always")
def _mixture_one(table, neighbours, weights, x, t, p, n_theta, n_phi):
    """:func:`mixture_at` of one point ``x`` at one direction's cell coordinates (t, p)."""
    t0, t1, p0, p1, ft, fp = bilinear_stencil(t, p, n_theta, n_phi)
    cells = (t0 * n_phi + p0, t0 * n_phi + p1, t1 * n_phi + p0, t1 * n_phi + p1)
    bw = ((1 - ft) * (1 - fp), (1 - ft) * fp, ft * (1 - fp), ft * fp)
    acc = 0.0
    for k in range(neighbours.shape[1]):
        w = weights[x, k]
        if w != 0:
            row = table[neighbours[x, k]]
            value = row[cells[0]] * bw[0]
            value += row[cells[1]] * bw[1]
            value += row[cells[2]] * bw[2]
            value += row[cells[3]] * bw[3]
            acc += w * value
    return acc


@numba.njit(cache=True, nogil=True)
def mixture_at(table, neighbours, weights, index, t, p, n_theta, n_phi):
    """Eq. 18's mixture sum_k w(x, k) table[j(x, k)] at continuous cell coordinates (t, p) (N,)
    (:meth:`DirectionGrid.coordinates`) for points ``index`` (N,): each table read as
    :class:`facetsynth.geometry.grid.Bilinear` reads it (:func:`facetsynth.geometry.grid.bilinear_stencil`), with its arithmetic
    in its order, so the result is bitwise numpy's (tests/models/test_svbrdf.py). ``table`` (R, cells), ``neighbours``
    and ``weights`` (P, K); a zero weight reads nothing."""
    out = np.zeros(index.size)
    for s in range(index.size):
        out[s] = _mixture_one(table, neighbours, weights, index[s], t[s], p[s], n_theta, n_phi)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _fresnel_one(c, eta):
    """:func:`facetsynth.models.microfacet.fresnel` (eq. 3) of one cosine, in compiled kernels, with its
    arithmetic in its order."""
    c = min(max(abs(c), 0.0), 1.0)
    d = (eta - 1.0) * (eta + 1.0)
    g2 = d + c * c
    if g2 < 0.0:
        return 1.0
    s = np.sqrt(g2) + c
    if not s > 0.0:
        return 0.0
    gm = d / s
    r = gm / s
    t = (c * s - 1.0) / (c * gm + 1.0)
    return min(0.5 * r * r * (1.0 + t * t), 1.0)


@numba.njit(cache=True, nogil=True)
def sample_terms(at, wi, wo, cos_turn, sin_turn, eta, neighbours, weights, ndf, n_theta, n_phi, area, a_theta,
                 a_phi):
    """Eq. 6's factors of S samples in one compiled pass (:meth:`SVBRDF.sample_terms`): sample s of point
    ``at[s]`` lit from ``wi[s]``, seen from ``wo[s]`` (local directions), the point's turn (eq. 13) given by
    its ``cos_turn``, ``sin_turn`` (P,; empty: no turn). Returns the half vector's continuous cell
    coordinates (t, p) in the point's turned frame, D(h) (the eq. 18 mixture, clipped at 0), F(c) (c the mean
    of |i.h| and |o.h|, eq. 3) and A(i) (eq. 5, floored at 1e-6), each (S,): the numpy methods' arithmetic
    in their order, but for the arc cosines and tangents (libm's here, numpy's own there: equal to rounding)."""
    n = at.size
    t_out, p_out, d_out, f_out, a_out = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    tiny = np.finfo(np.float64).tiny
    for s in range(n):
        x = at[s]
        ix, iy, iz = wi[s, 0], wi[s, 1], wi[s, 2]
        sx, sy, sz = ix + wo[s, 0], iy + wo[s, 1], iz + wo[s, 2]
        ss = sx * sx + sy * sy + sz * sz
        if ss > tiny:
            inv = 1.0 / np.sqrt(ss)
            hx, hy, hz = sx * inv, sy * inv, sz * inv
        else:
            hx, hy, hz = 0.0, 0.0, 1.0
        c = 0.5 * (abs(ix * hx + iy * hy + iz * hz) + abs(wo[s, 0] * hx + wo[s, 1] * hy + wo[s, 2] * hz))
        f_out[s] = _fresnel_one(c, eta[x])
        if cos_turn.size:
            ct, st = cos_turn[x], sin_turn[x]
            hx, hy, ix, iy = ct * hx - st * hy, st * hx + ct * hy, ct * ix - st * iy, st * ix + ct * iy
        t, p = polar_coordinates(hx, hy, hz, n_theta, n_phi)
        t_out[s], p_out[s] = t, p
        d_out[s] = max(_mixture_one(ndf, neighbours, weights, x, t, p, n_theta, n_phi), 0.0)
        t, p = polar_coordinates(ix, iy, iz, a_theta, a_phi)
        a_out[s] = max(_mixture_one(area, neighbours, weights, x, t, p, a_theta, a_phi), 1e-6)
    return t_out, p_out, d_out, f_out, a_out


_CHECKED_NORMALS: weakref.WeakValueDictionary = weakref.WeakValueDictionary()   # id -> a unit, read-only field


def normal_problem(normal: np.ndarray, tol: float = NORMAL_UNIT_TOL) -> str | None:
    """Why ``normal`` (P, 3) is not a field of unit shading normals facing up (None when it is): finite,
    | |n| - 1 | <= ``tol``, n_z > 0. The message names the first bad point (flat index)."""
    n = np.asarray(normal, float)
    checks = (("not finite", ~np.isfinite(n).all(axis=-1)),
              (f"not a unit vector (| |n| - 1 | > {tol:g})",
               ~(np.abs(np.linalg.norm(np.nan_to_num(n), axis=-1) - 1.0) <= tol)),
              ("not facing up (n_z <= 0)", ~(np.nan_to_num(n[..., 2]) > 0.0)))
    for what, bad in checks:
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            return (f"{int(bad.sum())} shading normal(s) {what}; first at point {first}: "
                    f"{np.array2string(n[first], precision=4, separator=', ')}")
    return None


def _count(value: Any, positive_int: bool) -> bool:
    """Whether ``value`` is a JSON integer >= 1 (``positive_int``) or a finite number > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if positive_int:
        return isinstance(value, int) and 1 <= value <= MAX_GRID_CELLS
    try:
        number = float(value)           # a JSON integer of any size: beyond a float's range it is not a size
    except OverflowError:
        return False
    return bool(np.isfinite(number)) and number > 0.0


def model_grids(file: Path, meta: dict) -> tuple[PlaneGrid, DirectionGrid, DirectionGrid]:
    """The plane grid and the two direction grids that model.json (``file``, read as ``meta``) describes;
    InputError naming the key for a missing one or a value that is not a positive finite size (a NaN plane
    width would place every point off the sample: a black picture)."""
    fields = (("plane_grid", (("width", False), ("height", False), ("cols", True), ("rows", True))),
              ("grid", (("n_theta", True), ("n_phi", True))),
              ("shadowing_grid", (("n_theta", True), ("n_phi", True))))
    for key, names in fields:
        record = meta.get(key)
        if not isinstance(record, dict):
            raise InputError(file, f"incomplete SVBRDF description: no {key!r} object")
        for name, integer in names:
            if not _count(record.get(name), integer):
                kind = f"an integer from 1 to {MAX_GRID_CELLS}" if integer else "a finite number > 0"
                raise InputError(file, f"{key}.{name} must be {kind}, found {record.get(name)!r:.40}")
    return (PlaneGrid.from_dict(meta["plane_grid"]), DirectionGrid.from_dict(meta["grid"]),
            DirectionGrid.from_dict(meta["shadowing_grid"]))


def refuse_bad_values(file: str | Path, what: str, values: np.ndarray, lowest: float | None = None) -> None:
    """InputError naming ``file`` and the count when ``values`` (any shape, P first) hold NaN or Inf, or values
    below ``lowest`` (None: any finite value); the first bad one's flat index says where."""
    values = np.asarray(values)
    if values.dtype.kind not in "biuf":
        raise InputError(file, f"{what} has data type {values.dtype}, expected numbers")
    checks = [("NaN or Inf", ~np.isfinite(values))]
    if lowest is not None:
        checks.append((f"below {lowest:g}", np.nan_to_num(values, nan=lowest) < lowest))
    for problem, bad in checks:
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise InputError(file, f"{int(bad.sum())} {what} value(s) {problem} (first at flat index {first}: "
                                   f"{float(values.ravel()[first]):.6g})")


def refuse_bad_indices(file: str | Path, what: str, index: np.ndarray, count: int, table: str) -> None:
    """InputError naming ``file`` and the count when ``index`` holds a non-integer or an index outside
    0 .. ``count`` - 1 (a ``table`` of ``count`` entries): such an index reads past the table, or, negative,
    silently reads another entry."""
    index = np.asarray(index)
    if index.dtype.kind not in "iu":
        raise InputError(file, f"{what} indices have data type {index.dtype}, expected integers")
    bad = (index < 0) | (index >= count)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InputError(file, f"{int(bad.sum())} {what} index(es) outside the {count} {table} (0 to {count - 1}); "
                               f"first {int(index.ravel()[first])} at flat index {first}")


@dataclass
class SVBRDF:
    """A fitted SVBRDF in memory; :meth:`load` reads the folder, :meth:`eval` evaluates rho in 1/sr."""

    plane: PlaneGrid
    grid: DirectionGrid
    kd: np.ndarray                 # (P, 3)
    ks: np.ndarray                 # (P, 3)
    eta: np.ndarray                # (P,)
    ndf: np.ndarray                # (R, T, F) normalised
    area: np.ndarray               # (R, Ts, Fs)
    neighbours: np.ndarray         # (P, K) int
    weights: np.ndarray            # (P, K)
    representatives: np.ndarray | None = None
    eta_fitted: np.ndarray | None = None     # (P,) bool
    shadowing_grid: DirectionGrid = SHADOWING_GRID
    info: dict[str, Any] = field(default_factory=dict)
    eta_lo: np.ndarray | None = None         # (P,) 95 % interval of eta (the point's material), if known
    eta_hi: np.ndarray | None = None
    rotation: np.ndarray | None = None       # (P,) radians: D(x, h) = sum_k w_k D_k(R(phi_x) h) (eq. 13's turn)
    normal: np.ndarray | None = None         # (P, 3) unit shading normals n(x) in the plane's frame; None: flat

    def __post_init__(self):
        p = self.plane.rows * self.plane.cols
        for name, shape in (("kd", (p, 3)), ("ks", (p, 3)), ("eta", (p,)), ("eta_lo", (p,)), ("eta_hi", (p,)),
                            ("rotation", (p,))):
            if getattr(self, name) is not None and getattr(self, name).shape != shape:
                raise ValueError(f"SVBRDF {name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.normal is not None and _CHECKED_NORMALS.get(id(self.normal)) is not self.normal:
            self.normal = np.asarray(self.normal, float)
            if self.normal.shape != (p, 3):
                raise ValueError(f"SVBRDF normal has shape {self.normal.shape}, expected {(p, 3)}")
            problem = normal_problem(self.normal)
            if problem:
                raise ValueError(f"SVBRDF normal: {problem}")
            self.normal = self.normal / np.linalg.norm(self.normal, axis=-1, keepdims=True)
            self.normal.setflags(write=False)      # checked once: a model made from this one by replace() keeps it
            _CHECKED_NORMALS[id(self.normal)] = self.normal
        if self.neighbours.shape != self.weights.shape or self.neighbours.shape[0] != p:
            raise ValueError(f"SVBRDF neighbours {self.neighbours.shape} / weights {self.weights.shape}: "
                             f"expected (P={p}, K) each")
        if self.ndf.shape[1:] != self.grid.shape or self.area.shape[1:] != self.shadowing_grid.shape:
            raise ValueError("SVBRDF NDF / projected-area tables do not match their grids")
        self._ndf_flat = np.ascontiguousarray(self.ndf.reshape(self.ndf.shape[0], -1), dtype=np.float64)
        self._area_flat = np.ascontiguousarray(self.area.reshape(self.area.shape[0], -1), dtype=np.float64)

    # --- the folder ----------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> "SVBRDF":
        """Read a fitted SVBRDF folder (InputError names the file on a bad one)."""
        path = Path(path)
        meta = read_json(path / "model.json")
        if not isinstance(meta, dict):
            raise InputError(path / "model.json", f"expected a JSON object, found {type(meta).__name__}")
        if meta.get("version") != FORMAT_VERSION:
            raise InputError(path / "model.json", f"unsupported SVBRDF format version {meta.get('version')!r:.40}")
        plane, grid, sgrid = model_grids(path / "model.json", meta)
        p = plane.rows * plane.cols

        def image(name, channel):
            channels, _ = read_exr(path / name)
            if channel not in channels:
                raise InputError(path / name, f"no {channel} channel (found: {', '.join(sorted(channels))})")
            a = channels[channel]
            if a.shape[:2] != (plane.rows, plane.cols):
                raise InputError(path / name, f"map is {a.shape[1]}x{a.shape[0]}, the plane grid "
                                              f"{plane.cols}x{plane.rows}")
            return a.reshape((p,) + a.shape[2:]).astype(np.float64)

        def tensor(name, integer=False):
            a = read_npy(path / name)
            if a.dtype.kind not in ("iu" if integer else "biuf"):
                raise InputError(path / name, f"data type {a.dtype}, expected {'integers' if integer else 'numbers'}")
            return a

        eta_channels, _ = read_exr(path / "eta.exr")
        fitted = eta_channels.get("eta_fitted")
        interval = {k: image("eta.exr", k) if k in eta_channels else None for k in ("eta_lo", "eta_hi")}
        normal = None
        files = meta.get("files") if isinstance(meta.get("files"), dict) else {}
        if "normal" in files:                       # model.json lists it: a stale file beside it is not read
            name = str(files["normal"])
            normal = np.stack([image(name, c) for c in "XYZ"], -1)
            problem = normal_problem(normal)
            if problem:
                raise InputError(path / name, problem)
        try:
            model = cls(plane=plane, grid=grid, kd=image("kd.exr", "RGB"), ks=image("ks.exr", "RGB"),
                       eta=image("eta.exr", "eta"), ndf=tensor("ndf.npy"), area=tensor("projected_area.npy"),
                       neighbours=tensor("neighbours.npy", True).astype(np.intp), weights=tensor("weights.npy"),
                       representatives=tensor("representatives.npy", True),
                       eta_fitted=None if fitted is None else fitted.reshape(-1) > 0.5,
                       shadowing_grid=sgrid, info=meta, eta_lo=interval["eta_lo"], eta_hi=interval["eta_hi"],
                       rotation=(tensor("rotation.npy").astype(np.float64) if (path / "rotation.npy").is_file()
                                 else None), normal=normal)
        except ValueError as exc:
            raise InputError(path, f"inconsistent SVBRDF folder ({exc})") from None
        return model.check_values(path)

    def check_values(self, path: str | Path) -> "SVBRDF":
        """This model, if every parameter is finite and in range (issue 32 item 8), else InputError naming the
        file in folder ``path`` and the count of bad values: a NaN kd, a negative ks, a neighbour index outside
        the representatives' table would otherwise render black, NaN or plausible but wrong pictures. (eta's
        interval, eta_lo and eta_hi, is a record of the fit, not a parameter of rho: not checked.)"""
        path = Path(path)
        maps = (("kd.exr", "kd", self.kd, 0.0), ("ks.exr", "ks", self.ks, 0.0), ("eta.exr", "eta", self.eta, None),
                ("ndf.npy", "ndf", self.ndf, None), ("projected_area.npy", "projected area", self.area, None),
                ("weights.npy", "weights", self.weights, None), ("rotation.npy", "rotation", self.rotation, None))
        for name, what, values, lowest in maps:
            if values is not None:
                refuse_bad_values(path / name, what, values, lowest)
        if (self.eta <= 0.0).any():
            raise InputError(path / "eta.exr", f"{int((self.eta <= 0.0).sum())} eta value(s) <= 0 (first at point "
                                               f"{int(np.flatnonzero(self.eta <= 0.0)[0])}); eta is a refraction index")
        refuse_bad_indices(path / "neighbours.npy", "neighbour", self.neighbours, self.ndf.shape[0], "representatives")
        if self.representatives is not None:
            refuse_bad_indices(path / "representatives.npy", "representative", self.representatives, self.n_points,
                               "points")
        return self

    def save(self, path: str | Path, provenance: dict[str, Any] | None = None) -> None:
        """Write the folder (every file atomically; model.json last)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        rc = (self.plane.rows, self.plane.cols)
        header = {"units": "kd, ks: dimensionless albedo; rho = kd/pi + ks D S S F / (4 (i.n)(o.n)) in 1/sr",
                  "source": "facetsynth params (paper 002 sec. 5.4)"}
        write_exr(path / "kd.exr", {"RGB": self.kd.reshape(rc + (3,))}, dict(header, quantity="kd"))
        write_exr(path / "ks.exr", {"RGB": self.ks.reshape(rc + (3,))}, dict(header, quantity="ks"))
        fitted = np.ones(rc) if self.eta_fitted is None else self.eta_fitted.reshape(rc).astype(float)
        eta_maps = {"eta": self.eta.reshape(rc), "eta_fitted": fitted}
        if self.eta_lo is not None and self.eta_hi is not None:
            eta_maps.update(eta_lo=self.eta_lo.reshape(rc), eta_hi=self.eta_hi.reshape(rc))
        write_exr(path / "eta.exr", eta_maps, dict(header, quantity="eta (relative refraction index, eq. 3)"))
        write_npy(path / "ndf.npy", self.ndf.astype(np.float32))
        write_npy(path / "projected_area.npy", self.area.astype(np.float32))
        reps = self.representatives if self.representatives is not None else np.arange(self.ndf.shape[0])
        write_npy(path / "representatives.npy", np.asarray(reps, np.int64))
        write_npy(path / "neighbours.npy", self.neighbours.astype(np.int32))
        write_npy(path / "weights.npy", self.weights.astype(np.float32))
        if self.rotation is not None:
            write_npy(path / "rotation.npy", self.rotation.astype(np.float32))
        if self.normal is not None:
            write_exr(path / NORMAL_FILE, {c: self.normal[:, k].reshape(rc) for k, c in enumerate("XYZ")},
                      dict(header, quantity="unit shading normal (x, y, z) in the sample plane's frame, z up"))
        meta = {"version": FORMAT_VERSION, "units": "m", "model": "paper 002 eq. 6 with eq. 18 NDF mixtures",
                "plane_grid": self.plane.to_dict(), "grid": self.grid.to_dict(),
                "shadowing_grid": self.shadowing_grid.to_dict(),
                "files": {"kd": "kd.exr", "ks": "ks.exr", "eta": "eta.exr", "ndf": "ndf.npy",
                          "projected_area": "projected_area.npy", "representatives": "representatives.npy",
                          "neighbours": "neighbours.npy", "weights": "weights.npy",
                          **({"rotation": "rotation.npy"} if self.rotation is not None else {}),
                          **({"normal": NORMAL_FILE} if self.normal is not None else {})},
                "loader": "facetsynth.SVBRDF.load(path).eval(points, wi, wo)"}
        meta.update({k: v for k, v in self.info.items() if k not in meta})
        if provenance:
            meta["provenance"] = provenance
        write_json(path / "model.json", meta)

    # --- evaluation ----------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return self.plane.rows * self.plane.cols

    def point_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell index (...) of sample-plane points (..., 2 or 3) and whether each lies on the sample."""
        points = np.asarray(points, float)
        cr = self.plane.to_pixel(points[..., 0], points[..., 1])
        col, row = np.floor(cr[..., 0] + 0.5), np.floor(cr[..., 1] + 0.5)
        inside = (col >= 0) & (col < self.plane.cols) & (row >= 0) & (row < self.plane.rows)
        if points.shape[-1] == 3:
            inside &= np.abs(points[..., 2]) < 1e-6
        col = np.clip(col, 0, self.plane.cols - 1).astype(np.intp)
        row = np.clip(row, 0, self.plane.rows - 1).astype(np.intp)
        return row * self.plane.cols + col, inside

    def frames(self, index: np.ndarray) -> np.ndarray:
        """The shading frames (..., 3, 3) of points ``index`` (...): rotations R with R n(x) = +z
        (:func:`facetsynth.fit.normals.shading_frames`); the identity where ``normal`` is None. Local directions
        are R d (:func:`facetsynth.fit.normals.to_local`), world ones R^T d_local."""
        index = np.asarray(index, np.intp)
        if self.normal is None:
            return np.broadcast_to(np.eye(3), index.shape + (3, 3)).copy()
        return shading_frames(self.normal[index])

    def mixture(self, table: np.ndarray, grid: DirectionGrid, index: np.ndarray, d: np.ndarray) -> np.ndarray:
        """sum_k w(x, k) table[j(x, k)](R(phi_x) d) for points ``index`` (N,) and directions d (N, 3); ``table``
        is (R, cells of ``grid``), one flattened table per representative; phi_x the point's ``rotation``
        (a material whose frame turns across the sample: a representative and a per-point turn, eq. 13)."""
        index = np.asarray(index, np.intp)
        if self.rotation is not None:
            d = turn(d, self.rotation[index])
        t, p = grid.coordinates(d)
        return mixture_at(np.ascontiguousarray(table), self.neighbours, self.weights, index.ravel(),
                          t.ravel(), p.ravel(), grid.n_theta, grid.n_phi).reshape(index.shape)

    def ndf_at(self, index: np.ndarray, h: np.ndarray) -> np.ndarray:
        """The per-point normalised NDF D(x, h) (eq. 18 mixture, clipped at 0) at points (N,), half vectors (N, 3)."""
        return np.maximum(self.mixture(self._ndf_flat, self.grid, index, h), 0.0)

    def point_ndf(self, index: np.ndarray) -> np.ndarray:
        """The per-point normalised NDFs (N, T, F) on the model's grid at points ``index`` (N,).

        Eq. 18's mixture of the representative tables, clipped at 0: what
        :meth:`ndf_at` gives at the cell centres (no interpolation).
        """
        index = np.asarray(index, np.intp).ravel()
        out = np.zeros((index.size, self._ndf_flat.shape[1]))
        for k in range(self.neighbours.shape[1]):
            w = self.weights[index, k]
            use = w != 0
            if use.any():
                out[use] += w[use, None] * self._ndf_flat[self.neighbours[index[use], k]]
        out = np.maximum(out, 0.0).reshape((index.size,) + self.grid.shape)
        if self.rotation is not None:
            out = np.stack([self.grid.rotate(table, phi) for table, phi in zip(out, self.rotation[index])])
        return out

    def area_at(self, index: np.ndarray, k: np.ndarray) -> np.ndarray:
        """A(x, k) of eq. 5 (the mixture's projected area, floored at 1e-6) at points (N,), directions (N, 3)."""
        return np.maximum(self.mixture(self._area_flat, self.shadowing_grid, index, k), 1e-6)

    def sample_terms(self, at: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, ...]:
        """Eq. 6's factors of samples in one compiled pass (:func:`sample_terms`): at points ``at`` (S,), for
        directions ``wi``, ``wo`` (S, 3) in each point's shading frame, the continuous cell coordinates (t, p)
        of h in the point's turned frame (:meth:`DirectionGrid.coordinates`), D(x, h) (:meth:`ndf_at`), F(c)
        (c the mean of |i.h| and |o.h|) and A(x, i) (:meth:`area_at`), each (S,)."""
        cos, sin = self._turn
        return sample_terms(np.asarray(at, np.intp), np.ascontiguousarray(wi, float), np.ascontiguousarray(wo, float),
                            cos, sin, self.eta, self.neighbours, self.weights, self._ndf_flat, *self.grid.shape,
                            self._area_flat, *self.shadowing_grid.shape)

    @cached_property
    def _turn(self) -> tuple[np.ndarray, np.ndarray]:
        """cos and sin of each point's eq. 13 turn (P,), float64; empty without a turn field."""
        if self.rotation is None:
            return np.empty(0), np.empty(0)
        phi = np.asarray(self.rotation, float)
        return np.cos(phi), np.sin(phi)

    def specular_terms(self, index: np.ndarray, wi: np.ndarray, wo: np.ndarray,
                       area_o: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(D / (4 A(i) A(o)), c = |i.h|) for flat point indices (N,) and directions (N, 3).

        The specular factor of eq. 6 without ks and F; 0 where i or o is at or
        below the horizon. ``area_o``: A(x, o) when already known (a fixed camera).
        """
        h = half_vector(wi, wo)
        c = 0.5 * (np.abs(np.sum(wi * h, -1)) + np.abs(np.sum(wo * h, -1)))
        d = self.ndf_at(index, h)
        a_i = self.area_at(index, wi)
        a_o = self.area_at(index, wo) if area_o is None else area_o
        spec = d / (4.0 * (a_i * a_o))
        valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
        return np.where(valid, spec, 0.0), c

    def eval_index(self, index: np.ndarray, wi: np.ndarray, wo: np.ndarray,
                   area_o: np.ndarray | None = None) -> np.ndarray:
        """rho (N, 3) in 1/sr at flat point indices (N,) for unit directions (N, 3) in each point's shading
        frame (local: R(x) d, :meth:`frames`; the plane's frame when ``normal`` is None); 0 below the local
        horizon. ``area_o``: A(x, o) of the local o when already known."""
        spec, c = self.specular_terms(index, wi, wo, area_o)
        f = fresnel(c, self.eta[index])
        rho = self.kd[index] / np.pi + self.ks[index] * (spec * f)[:, None]
        valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
        rho = np.where(valid[:, None], rho, 0.0)
        return np.clip(np.nan_to_num(rho, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)

    def eval(self, points: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """rho(x, i, o) of eq. 6 in 1/sr, shape broadcast(points[..., 0], wi[..., 0], wo[..., 0]) + (3,).

        ``points`` (..., 2 or 3) sample-plane positions in metres; ``wi``,
        ``wo`` (..., 3) unit directions (normalised here anyway). Vectorised and
        broadcast over any leading dimensions, evaluated in blocks. Reciprocal
        (h and c = |i.h| are symmetric in i, o; A(i) A(o) commutes),
        non-negative, never NaN/Inf: 0 below the horizon (i.n <= 0 or
        o.n <= 0) and off the sample; finite at grazing (A(k) > 0 there).

        Directions are WORLD ones (the plane's frame, z up). With shading normals they are turned into
        each point's frame first (:meth:`frames`), and rho is 0 also where i or o is at or below the
        sample plane (z <= 0); with ``normal`` None, the plane's frame is every point's.
        """
        points, wi, wo = (np.asarray(a, float) for a in (points, wi, wo))
        index, inside = self.point_index(points)
        shape = np.broadcast_shapes(index.shape, wi.shape[:-1], wo.shape[:-1])
        index = np.broadcast_to(index, shape).ravel()
        inside = np.broadcast_to(inside, shape).ravel()
        wi = np.broadcast_to(wi, shape + (3,)).reshape(-1, 3)
        wo = np.broadcast_to(wo, shape + (3,)).reshape(-1, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            wi = np.nan_to_num(wi / np.linalg.norm(wi, axis=-1, keepdims=True))
            wo = np.nan_to_num(wo / np.linalg.norm(wo, axis=-1, keepdims=True))
        out = np.zeros((index.size, 3))
        for s in range(0, index.size, CHUNK):
            sl = slice(s, s + CHUNK)
            if self.normal is None:
                out[sl] = self.eval_index(index[sl], wi[sl], wo[sl])
                continue
            frames = self.frames(index[sl])
            out[sl] = self.eval_index(index[sl], to_local(frames, wi[sl]), to_local(frames, wo[sl]))
            out[sl][(wi[sl, 2] <= 0.0) | (wo[sl, 2] <= 0.0)] = 0.0
        out[~inside] = 0.0
        return out.reshape(shape + (3,))


def tabulate_truth(maps, grid: DirectionGrid, plane: PlaneGrid, shadowing_grid: DirectionGrid = SHADOWING_GRID) -> SVBRDF:
    """An SVBRDF with the true NDFs tabulated on ``grid``: one representative per distinct NDF.

    ``maps`` are the true MaterialMaps at the plane grid's points (P,). Points
    whose NDF parameters (alpha_u, alpha_v, frame azimuth) are equal share one
    representative with weight 1. The reference for the loader's tabulation
    error and for predict's consistency (the fitted model's limit with perfect
    NDF synthesis); not a fit. The tabulated NDF is renormalised on the grid,
    and A(k) computed from it by eq. 5.
    """
    from ..fit.params import normalise, projected_area
    p = plane.rows * plane.cols
    key = np.stack([maps.alpha_u, maps.alpha_v, np.mod(maps.phi_frame, 2 * np.pi)], -1).reshape(p, 3)
    unique, first, owner = np.unique(np.round(key, 12), axis=0, return_index=True, return_inverse=True)
    reps = maps.take(first)
    table = reps.take((slice(None), None)).ndf(grid.directions.reshape(1, -1, 3)).reshape((len(first),) + grid.shape)
    nd, _ = normalise(table, grid)
    area = projected_area(nd, grid, shadowing_grid)
    return SVBRDF(plane=plane, grid=grid, kd=np.asarray(maps.kd, float).reshape(p, 3),
                  ks=np.asarray(maps.ks, float).reshape(p, 3), eta=np.asarray(maps.eta, float).reshape(p),
                  ndf=nd.astype(np.float32), area=area.astype(np.float32),
                  neighbours=owner.reshape(p, 1).astype(np.intp), weights=np.ones((p, 1)),
                  representatives=first, eta_fitted=np.ones(p, bool), shadowing_grid=shadowing_grid)
