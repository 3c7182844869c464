"""The fitted facetsynth SVBRDF as a Mitsuba 3 BSDF plugin (Python, ``scalar_rgb``).

Written by ``facetsynth export mitsuba`` into the exported folder as
``facetsynth_bsdf.py``; it needs numpy and Mitsuba 3 only. It evaluates the
fitted model itself, the same arithmetic as ``facetsynth.models.svbrdf.SVBRDF.eval_index``:

    rho(x, i, o) = kd(x)/pi + ks(x) D(x, h) F(c, eta(x)) / (4 A(x, i) A(x, o)),   c = |i.h|

    D(x, h) = max(0, sum_k w(x, k) D_k(R(phi_x) h))        eq. 18 mixture of the representative NDFs
    A(x, k) = max(1e-6, sum_k w(x, k) A_k(R(phi_x) k))     eq. 5's projected area, of the same mixture

with D_k and A_k tabulated on polar (theta, phi) grids and looked up bilinearly
(periodic in phi, theta clamped to the rings), R(phi_x) the point's optional
turn about the normal, F eq. 3's dielectric Fresnel, and rho = 0 when the light
or the view is at or below the horizon. The point x is the rectified cell
holding the shading point: the sample is the quad [-W/2, W/2] x [-H/2, H/2] of
z = 0 whose uv is Mitsuba's ``rectangle`` parametrisation, u = x/W + 1/2,
v = y/H + 1/2, and whose shading frame is the sample plane's (s = +x, t = +y,
n = +z); cell (row, col) = (floor((1 - v) rows), floor(u cols)).

Shading normals (``normal`` in model.npz, when the model has them): the directions Mitsuba gives (in the
quad's frame, the sample plane's) are turned into the point's shading frame, i_local = R(x) i with R(x) the
smallest rotation taking the point's normal n(x) to +z (facetsynth.fit.normals.shading_frames, the same
formula here), rho is evaluated there, the cosine is n(x) . i (the local z), and rho = 0 also where the
light or the view is at or below the sample plane. So :meth:`TabulatedSVBRDF.eval` equals
``facetsynth.models.svbrdf.SVBRDF.eval`` (world directions) and Mitsuba's pixel is rho (n(x) . i) L / r^2,
facetsynth's. The plugin turns the frame itself rather than being wrapped in Mitsuba's ``normalmap`` BSDF:
``normalmap`` builds its frame from dp/du by Gram-Schmidt (a different twist about n than R(x) when n
leans along both x and y: up to about tilt^2 / 4 radians, 4.1 deg at a 30 deg tilt, by which an
anisotropic lobe would turn), filters the normal texture bilinearly across
cells where the model has one normal per cell, and masks only the light's side of the geometric horizon.

Importance sampling (path tracing): with probability p_spec = mean(ks) /
(mean(ks) + mean(kd)) a half vector is drawn: a representative k with
probability proportional to max(w(x, k), 0), then a grid cell of that
representative's table from the piecewise-constant distribution
D_k(h) cos(theta_h) Omega_cell (cells where D_k is 0 get half their 3 x 3
neighbourhood's maximum, so every direction where the bilinear lookup is
positive can be drawn), uniformly in solid angle inside the cell, turned back
by -phi_x, and the view direction reflected about it; otherwise a cosine lobe.
pdf(o) = (1 - p_spec) cos(theta_o)/pi + p_spec sum_k q_k p_k(R h) / (4 |o.h|). With shading normals
all this happens in the point's frame (a rotation keeps solid angles: the pdf is the same number), and a
direction drawn below the sample plane is no sample.

Usage (see ``render.py`` beside this file)::

    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    import facetsynth_bsdf
    facetsynth_bsdf.register()                 # plugin type "facetsynth_svbrdf", property "filename"
    scene = mi.load_file("scene.xml")

Only the scalar variants run Python BSDFs one call at a time; this plugin
supports ``scalar_rgb``. Without Mitsuba, :class:`TabulatedSVBRDF` evaluates,
samples and gives the pdf with plain Python floats.
"""

from __future__ import annotations

import bisect
import math
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
PLUGIN_NAME = "facetsynth_svbrdf"
VARIANTS = ("scalar_rgb",)


def fresnel(c: float, eta: float) -> float:
    """Unpolarised dielectric Fresnel reflectance (eq. 3), as facetsynth.models.microfacet.fresnel, for one c = |i.h|."""
    c = min(max(abs(c), 0.0), 1.0)
    d = (eta - 1.0) * (eta + 1.0)
    g2 = d + c * c
    if g2 < 0.0:
        return 1.0
    g = math.sqrt(g2)
    s = g + c
    if not s > 0.0:
        return 0.0
    gm = d / s
    r = gm / s
    t = (c * s - 1.0) / (c * gm + 1.0)
    f = 0.5 * r * r * (1.0 + t * t)
    return min(f, 1.0) if f == f else float("nan")


class _Grid:
    """A polar direction grid (facetsynth.geometry.grid.DirectionGrid): cell (t, p) spans theta in [t, t+1) pi/(2 n_theta),
    phi in [p, p+1) 2 pi / n_phi from +x towards +y."""

    def __init__(self, n_theta: int, n_phi: int):
        self.nt, self.nf = int(n_theta), int(n_phi)
        self.dt = 0.5 * np.pi / self.nt
        self.df = 2.0 * np.pi / self.nf
        self.two_pi = 2.0 * np.pi

    def coordinates(self, x: float, y: float, z: float) -> tuple[float, float]:
        """Continuous cell coordinates (cell centres integer); below the horizon maps to the horizon."""
        theta = math.acos(min(max(z, 0.0), 1.0))
        phi = math.atan2(y, x) % self.two_pi
        return theta / self.dt - 0.5, phi / self.df - 0.5

    def bilinear(self, x: float, y: float, z: float):
        """Flat cells (4,) and bilinear weights (4,) of one direction (theta clamped, phi periodic)."""
        t, p = self.coordinates(x, y, z)
        nt, nf = self.nt, self.nf
        t = min(max(t, 0.0), nt - 1.0)
        if nt > 1:
            t0 = min(math.floor(t), nt - 2)
            ft = t - t0
        else:
            t0, ft = 0, 0.0
        t1 = min(t0 + 1, nt - 1)
        p0 = math.floor(p)
        fp = p - p0
        p0 %= nf
        p1 = (p0 + 1) % nf
        return ((t0 * nf + p0, t0 * nf + p1, t1 * nf + p0, t1 * nf + p1),
                ((1 - ft) * (1 - fp), (1 - ft) * fp, ft * (1 - fp), ft * fp))

    def cell(self, x: float, y: float, z: float) -> int:
        """The flat cell holding a direction (theta clamped to the grid)."""
        theta = math.acos(min(max(z, 0.0), 1.0))
        phi = math.atan2(y, x) % self.two_pi
        t = min(int(theta / self.dt), self.nt - 1)
        p = min(int(phi / self.df), self.nf - 1)
        return t * self.nf + p

    def solid_angles(self) -> np.ndarray:
        edges = np.arange(self.nt + 1) * self.dt
        ring = np.cos(edges[:-1]) - np.cos(edges[1:])
        return np.repeat((ring * self.df)[:, None], self.nf, axis=1)


def _unit(x: float, y: float, z: float) -> tuple[float, float, float]:
    n = math.sqrt(x * x + y * y + z * z)
    return (x / n, y / n, z / n) if n > 0 else (0.0, 0.0, 0.0)


def _half(wi, wo) -> tuple[float, float, float]:
    """h = (i + o) / |i + o|, the normal where i + o vanishes (facetsynth.models.microfacet.half_vector)."""
    sx, sy, sz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
    ss = sx * sx + sy * sy + sz * sz
    if not ss > 2.2250738585072014e-308:
        return (0.0, 0.0, 1.0)
    inv = 1.0 / math.sqrt(ss)
    return (sx * inv, sy * inv, sz * inv)


class TabulatedSVBRDF:
    """The exported model (``model.npz``): evaluation, sampling and pdf at one point and one pair of directions.

    Directions are unit 3-vectors in the sample-plane frame (x, y in the plane, z the plane's normal).
    ``eval`` takes (light, view) as facetsynth's ``SVBRDF.eval(points, wi, wo)`` (world directions; without
    shading normals the same as ``eval_index(index, wi, wo)``); the model is reciprocal. With shading normals
    (``frames`` not None) every query is turned into the point's shading frame first (module docstring).
    """

    def __init__(self, data):
        """``data``: a mapping of the arrays :func:`facetsynth.export.mitsuba.model_arrays` writes."""
        version = int(np.asarray(data["version"]))
        if version != FORMAT_VERSION:
            raise ValueError(f"unsupported facetsynth Mitsuba model version {version} (this plugin reads "
                             f"{FORMAT_VERSION})")
        self.width, self.height = (float(v) for v in np.asarray(data["size"], np.float64))
        self.rows, self.cols = (int(v) for v in np.asarray(data["plane_shape"]))
        self.grid = _Grid(*(int(v) for v in np.asarray(data["grid"])))
        self.sgrid = _Grid(*(int(v) for v in np.asarray(data["shadowing_grid"])))
        p = self.rows * self.cols
        kd = np.asarray(data["kd"], np.float64).reshape(p, 3)
        ks = np.asarray(data["ks"], np.float64).reshape(p, 3)
        self.kd = [tuple(v) for v in kd.tolist()]
        self.ks = [tuple(v) for v in ks.tolist()]
        self.eta = np.asarray(data["eta"], np.float64).reshape(p).tolist()
        ndf = np.asarray(data["ndf"]).astype(np.float64)
        area = np.asarray(data["projected_area"]).astype(np.float64)
        if ndf.shape[1:] != (self.grid.nt, self.grid.nf) or area.shape[1:] != (self.sgrid.nt, self.sgrid.nf):
            raise ValueError(f"NDF tables {ndf.shape} / projected-area tables {area.shape} do not match their grids")
        self.n_rep = ndf.shape[0]
        self.ndf = ndf.reshape(self.n_rep, -1).tolist()
        self.area = area.reshape(self.n_rep, -1).tolist()
        neighbours = np.asarray(data["neighbours"]).astype(np.int64)
        weights = np.asarray(data["weights"])
        if neighbours.shape != weights.shape or neighbours.shape[0] != p:
            raise ValueError(f"neighbours {neighbours.shape} / weights {weights.shape}: expected (P={p}, K) each")
        if neighbours.size and (neighbours.min() < 0 or neighbours.max() >= self.n_rep):
            raise ValueError(f"neighbours index representatives outside 0..{self.n_rep - 1}")
        # the non-zero terms of each point's mixture, in the order eval_index adds them
        w64 = weights.astype(np.float64)
        self.mix = [tuple(zip(n[w != 0].tolist(), w[w != 0].tolist())) for n, w in zip(neighbours, w64)]
        rotation = np.asarray(data["rotation"]) if "rotation" in data else np.zeros(0)
        if rotation.size:
            rotation = rotation.astype(np.float64).reshape(p)
            self.turn = list(zip(np.cos(rotation).tolist(), np.sin(rotation).tolist()))
        else:
            self.turn = None
        # shading frames: R (row by row) with R n = +z, facetsynth.fit.normals.shading_frames' formula
        normal = np.asarray(data["normal"]) if "normal" in data else np.zeros(0)
        if normal.size:
            n = normal.astype(np.float64).reshape(p, 3)
            if not np.isfinite(n).all() or not (n[:, 2] > 0).all():
                raise ValueError("shading normals must be finite and face up (n_z > 0)")
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
            x, y, z = n[:, 0], n[:, 1], n[:, 2]
            c = 1.0 / (1.0 + z)
            frames = np.stack([1 - x * x * c, -x * y * c, -x, -x * y * c, 1 - y * y * c, -y, x, y, z], -1)
            self.frames = [tuple(f) for f in frames.tolist()]
        else:
            self.frames = None
        # diffuse / specular choice and each point's representative choice
        kd_mean, ks_mean = np.clip(kd.mean(1), 0, None), np.clip(ks.mean(1), 0, None)
        positive = np.clip(w64, 0.0, None)
        has_spec = (positive.sum(1) > 0) & (ks_mean > 0)
        total = kd_mean + ks_mean
        p_spec = np.where(has_spec, np.divide(ks_mean, total, out=np.ones_like(total), where=total > 0), 0.0)
        self.p_spec = p_spec.tolist()
        choice = []
        for n, w in zip(neighbours, positive):
            use = w > 0
            if not use.any():
                choice.append(((), (), ()))
                continue
            q = w[use] / w[use].sum()
            choice.append((tuple(n[use].tolist()), tuple(np.cumsum(q).tolist()), tuple(q.tolist())))
        self.choice = choice
        # each representative's sampling table: D cos(theta) Omega per cell (zero cells dilated)
        t = np.asarray(ndf)
        pos = np.clip(t, 0.0, None)
        pad = np.concatenate([pos[:, :1], pos, pos[:, -1:]], axis=1)                   # theta clamped
        pad = np.concatenate([pad[:, :, -1:], pad, pad[:, :, :1]], axis=2)             # phi periodic
        nt, nf = self.grid.nt, self.grid.nf
        neighbourhood = np.max([pad[:, a:a + nt, b:b + nf] for a in range(3) for b in range(3)], axis=0)
        value = np.where(pos > 0, pos, 0.5 * neighbourhood)
        theta = (np.arange(nt) + 0.5) * self.grid.dt
        omega = self.grid.solid_angles()
        mass = value * np.cos(theta)[None, :, None] * omega[None]
        mass = mass.reshape(self.n_rep, -1)
        sums = mass.sum(1, keepdims=True)
        prob = np.divide(mass, sums, out=np.zeros_like(mass), where=sums > 0)
        self.cdf = [np.cumsum(pr).tolist() for pr in prob]
        self.density = (prob / omega.reshape(1, -1)).tolist()           # pdf of h in each cell (1/sr)
        self.cos_edges = np.cos(np.arange(nt + 1) * self.grid.dt).tolist()

    @classmethod
    def load(cls, path: str | Path) -> "TabulatedSVBRDF":
        """Read ``model.npz`` (no pickles)."""
        with np.load(Path(path), allow_pickle=False) as data:
            return cls({k: data[k] for k in data.files})

    # --- points ---------------------------------------------------------------------
    def point_uv(self, u: float, v: float) -> int:
        """Flat cell index (row * cols + col) of the quad's texture coordinate (u, v); -1 off the sample."""
        col = math.floor(u * self.cols)
        row = math.floor((1.0 - v) * self.rows)
        if 0 <= col < self.cols and 0 <= row < self.rows:
            return row * self.cols + col
        return -1

    def point_xy(self, x: float, y: float) -> int:
        """Flat cell index of a sample-plane point (metres); -1 off the sample."""
        return self.point_uv(x / self.width + 0.5, y / self.height + 0.5)

    # --- shading frames -------------------------------------------------------------
    def local(self, index: int, d):
        """Direction d (sample-plane frame) in point ``index``'s shading frame, R d (d itself when flat)."""
        if self.frames is None:
            return d
        r = self.frames[index]
        return (r[0] * d[0] + r[1] * d[1] + r[2] * d[2], r[3] * d[0] + r[4] * d[1] + r[5] * d[2],
                r[6] * d[0] + r[7] * d[1] + r[8] * d[2])

    def world(self, index: int, d):
        """Direction d of point ``index``'s shading frame in the sample-plane frame, R^T d."""
        if self.frames is None:
            return d
        r = self.frames[index]
        return (r[0] * d[0] + r[3] * d[1] + r[6] * d[2], r[1] * d[0] + r[4] * d[1] + r[7] * d[2],
                r[2] * d[0] + r[5] * d[1] + r[8] * d[2])

    def cosine(self, index: int, d) -> float:
        """n(x) . d: the foreshortening of direction d (sample-plane frame) at point ``index``."""
        if self.frames is None or index < 0:
            return d[2]
        r = self.frames[index]
        return r[6] * d[0] + r[7] * d[1] + r[8] * d[2]

    # --- the model ------------------------------------------------------------------
    def _turned(self, index: int, d):
        if self.turn is None:
            return d
        c, s = self.turn[index]
        return (c * d[0] - s * d[1], s * d[0] + c * d[1], d[2])

    def _mixture(self, table, grid: _Grid, index: int, d) -> float:
        cells, bw = grid.bilinear(*d)
        out = 0.0
        for rep, w in self.mix[index]:
            row = table[rep]
            out += w * (row[cells[0]] * bw[0] + row[cells[1]] * bw[1] + row[cells[2]] * bw[2]
                        + row[cells[3]] * bw[3])
        return out

    def specular(self, index: int, wi, wo) -> tuple[float, float]:
        """(D / (4 A(i) A(o)), c = |i.h|): eq. 6's specular factor without ks and F (0 below the horizon)."""
        h = _half(wi, wo)
        c = 0.5 * (abs(wi[0] * h[0] + wi[1] * h[1] + wi[2] * h[2]) + abs(wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2]))
        if not (wi[2] > 0.0 and wo[2] > 0.0):
            return 0.0, c
        d = max(self._mixture(self.ndf, self.grid, index, self._turned(index, h)), 0.0)
        a_i = max(self._mixture(self.area, self.sgrid, index, self._turned(index, wi)), 1e-6)
        a_o = max(self._mixture(self.area, self.sgrid, index, self._turned(index, wo)), 1e-6)
        return d / (4.0 * (a_i * a_o)), c

    def eval(self, index: int, wi, wo, diffuse: bool = True, glossy: bool = True) -> tuple[float, float, float]:
        """rho (r, g, b) in 1/sr at point ``index`` for unit directions wi (light) and wo (view) in the
        sample-plane frame: 0 below the horizon (the sample plane's and the shading frame's) and off the
        sample, never NaN or Inf. ``diffuse`` / ``glossy`` keep one term only."""
        if index < 0 or not (wi[2] > 0.0 and wo[2] > 0.0):
            return (0.0, 0.0, 0.0)
        return self.eval_local(index, self.local(index, wi), self.local(index, wo), diffuse, glossy)

    def eval_local(self, index: int, wi, wo, diffuse: bool = True, glossy: bool = True) -> tuple[float, float, float]:
        """:meth:`eval` for directions already in the point's shading frame (facetsynth's ``eval_index``)."""
        if index < 0 or not (wi[2] > 0.0 and wo[2] > 0.0):
            return (0.0, 0.0, 0.0)
        kd, ks = self.kd[index], self.ks[index]
        g = 0.0
        if glossy:
            spec, c = self.specular(index, wi, wo)
            g = spec * fresnel(c, self.eta[index])
        out = []
        for ch in range(3):
            value = (kd[ch] / math.pi if diffuse else 0.0) + (ks[ch] * g if glossy else 0.0)
            out.append(value if math.isfinite(value) and value > 0.0 else 0.0)
        return tuple(out)

    def pdf(self, index: int, wi, wo, diffuse: bool = True, glossy: bool = True) -> float:
        """Solid-angle density (1/sr) with which :meth:`sample` draws wo given wi (0 below the horizon)."""
        if index < 0 or not (wi[2] > 0.0 and wo[2] > 0.0):
            return 0.0
        if self.frames is not None:
            wi, wo = self.local(index, wi), self.local(index, wo)
            if not (wi[2] > 0.0 and wo[2] > 0.0):
                return 0.0
        p_spec = self.p_spec[index]
        if not diffuse:
            p_spec = 1.0 if p_spec > 0 else 0.0
        if not glossy:
            p_spec = 0.0
        out = (1.0 - p_spec) * wo[2] / math.pi
        if p_spec > 0.0:
            h = _half(wi, wo)
            cell = self.grid.cell(*self._turned(index, h))
            reps, _, q = self.choice[index]
            ph = 0.0
            for rep, qk in zip(reps, q):
                ph += qk * self.density[rep][cell]
            oh = abs(wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2])
            if oh > 0.0:
                out += p_spec * ph / (4.0 * oh)
        return out

    def sample(self, index: int, wi, s1: float, u: float, v: float, diffuse: bool = True,
               glossy: bool = True):
        """Draw a direction given wi (the view) from uniform numbers s1, u, v in [0, 1).

        Returns (wo, pdf, lobe) with lobe "glossy" or "diffuse", or None when nothing is drawn (wi below the
        horizon, or the reflection about the drawn half vector falls below it).
        """
        if index < 0 or not wi[2] > 0.0:
            return None
        world_wi = wi
        wi = self.local(index, wi)
        if not wi[2] > 0.0:
            return None
        p_spec = self.p_spec[index]
        if not diffuse:
            p_spec = 1.0 if p_spec > 0 else 0.0
        if not glossy:
            p_spec = 0.0
        if s1 < p_spec:
            lobe = "glossy"
            s1 = min(s1 / p_spec, 1.0 - 1e-12)
            reps, cum, _ = self.choice[index]
            rep = reps[min(bisect.bisect_right(cum, s1), len(reps) - 1)]
            cdf = self.cdf[rep]
            cell = min(bisect.bisect_right(cdf, u * cdf[-1]), len(cdf) - 1)
            while cell > 0 and cdf[cell] == cdf[cell - 1]:     # never a cell of zero probability
                cell -= 1
            lo = cdf[cell - 1] if cell > 0 else 0.0
            width = cdf[cell] - lo
            u2 = min(max((u * cdf[-1] - lo) / width, 0.0), 1.0) if width > 0 else 0.5
            t, p = divmod(cell, self.grid.nf)
            c0, c1 = self.cos_edges[t], self.cos_edges[t + 1]
            ct = c0 - u2 * (c0 - c1)
            st = math.sqrt(max(0.0, 1.0 - ct * ct))
            phi = (p + v) * self.grid.df
            h = (st * math.cos(phi), st * math.sin(phi), ct)
            if self.turn is not None:                      # h = R(-phi_x) h'
                c, s = self.turn[index]
                h = (c * h[0] + s * h[1], -s * h[0] + c * h[1], h[2])
            ih = wi[0] * h[0] + wi[1] * h[1] + wi[2] * h[2]
            if ih <= 0.0:
                return None
            wo = _unit(2.0 * ih * h[0] - wi[0], 2.0 * ih * h[1] - wi[1], 2.0 * ih * h[2] - wi[2])
        else:
            lobe = "diffuse"
            r, phi = math.sqrt(u), 2.0 * math.pi * v
            wo = (r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - u)))
        if not wo[2] > 0.0:
            return None
        wo = self.world(index, wo)
        if not wo[2] > 0.0:                                # drawn below the sample plane: no sample
            return None
        pdf = self.pdf(index, world_wi, wo, diffuse, glossy)
        if not pdf > 0.0:
            return None
        return wo, pdf, lobe


_CACHE: dict[str, TabulatedSVBRDF] = {}


def load_model(path: str | Path) -> TabulatedSVBRDF:
    """:meth:`TabulatedSVBRDF.load`, cached by resolved path and modification time."""
    path = Path(path).resolve()
    key = f"{path}:{path.stat().st_mtime_ns}"
    if key not in _CACHE:
        _CACHE[key] = TabulatedSVBRDF.load(path)
    return _CACHE[key]


def register(name: str = PLUGIN_NAME):
    """Register the BSDF with Mitsuba as plugin ``name`` (set the variant ``scalar_rgb`` first); returns the
    class. Its properties: ``filename`` (the model .npz, relative names found by Mitsuba's file resolver, which
    holds the scene file's folder while a scene loads)."""
    import mitsuba as mi

    if mi.variant() not in VARIANTS:
        raise RuntimeError(f"the facetsynth BSDF runs in the Mitsuba variants {', '.join(VARIANTS)}; "
                           f"call mi.set_variant('scalar_rgb') first (current: {mi.variant()})")
    flags = mi.BSDFFlags
    diffuse_flags = flags.DiffuseReflection | flags.FrontSide | flags.SpatiallyVarying
    glossy_flags = flags.GlossyReflection | flags.FrontSide | flags.Anisotropic | flags.SpatiallyVarying

    def resolve(filename: str) -> Path:
        resolver = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
        return Path(str(resolver.resolve(filename)))

    class FacetsynthSVBRDF(mi.BSDF):
        """The fitted facetsynth SVBRDF (module docstring): eval, pdf, eval_pdf, sample."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.filename = str(props["filename"])
            path = resolve(self.filename)
            if not path.is_file():
                raise FileNotFoundError(f"facetsynth_svbrdf: model file {self.filename} not found ({path})")
            self.model = load_model(path)
            self.m_components = [diffuse_flags, glossy_flags]
            self.m_flags = diffuse_flags | glossy_flags

        # (u, v), local directions and the enabled lobes of one query
        def _query(self, ctx, si):
            index = self.model.point_uv(float(si.uv[0]), float(si.uv[1]))
            wi = (float(si.wi[0]), float(si.wi[1]), float(si.wi[2]))
            diffuse = bool(ctx.is_enabled(flags.DiffuseReflection, 0))
            glossy = bool(ctx.is_enabled(flags.GlossyReflection, 1))
            return index, wi, diffuse, glossy

        def _eval(self, index, wi, wo, diffuse, glossy):
            # facetsynth's rho(light = wo, view = wi) times the cosine at the light, n(x) . wo
            rho = self.model.eval(index, wo, wi, diffuse, glossy)
            c = max(self.model.cosine(index, wo), 0.0)
            return mi.Color3f(rho[0] * c, rho[1] * c, rho[2] * c)

        def eval(self, ctx, si, wo, active=True):
            if not active:
                return mi.Color3f(0.0)
            index, wi, diffuse, glossy = self._query(ctx, si)
            return self._eval(index, wi, (float(wo[0]), float(wo[1]), float(wo[2])), diffuse, glossy)

        def pdf(self, ctx, si, wo, active=True):
            if not active:
                return 0.0
            index, wi, diffuse, glossy = self._query(ctx, si)
            return self.model.pdf(index, wi, (float(wo[0]), float(wo[1]), float(wo[2])), diffuse, glossy)

        def eval_pdf(self, ctx, si, wo, active=True):
            if not active:
                return mi.Color3f(0.0), 0.0
            index, wi, diffuse, glossy = self._query(ctx, si)
            o = (float(wo[0]), float(wo[1]), float(wo[2]))
            return self._eval(index, wi, o, diffuse, glossy), self.model.pdf(index, wi, o, diffuse, glossy)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            index, wi, diffuse, glossy = self._query(ctx, si)
            drawn = (self.model.sample(index, wi, float(sample1), float(sample2[0]), float(sample2[1]),
                                       diffuse, glossy) if active else None)
            if drawn is None:
                bs.pdf = 0.0
                return bs, mi.Color3f(0.0)
            wo, pdf, lobe = drawn
            bs.wo = mi.Vector3f(*wo)
            bs.pdf = pdf
            bs.eta = 1.0
            bs.sampled_type = int(flags.GlossyReflection if lobe == "glossy" else flags.DiffuseReflection)
            bs.sampled_component = 1 if lobe == "glossy" else 0
            value = self._eval(index, wi, wo, diffuse, glossy)
            return bs, value / pdf

        def traverse(self, callback):
            return

        def parameters_changed(self, keys):
            return

        def to_string(self):
            m = self.model
            return (f"FacetsynthSVBRDF[filename={self.filename!r}, points={m.rows}x{m.cols}, "
                    f"representatives={m.n_rep}]")

    mi.register_bsdf(name, lambda props: FacetsynthSVBRDF(props))
    return FacetsynthSVBRDF
