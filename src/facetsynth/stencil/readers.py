"""Readers (and writers for round trips) of measured BRDF files.

Every reader returns the BRDF evaluated on the UTIA grid
(:mod:`facetsynth.stencil.grid`): float64 ``(3, 6, 48, 6, 48)``, linear RGB,
1/sr, without the cosine factor.  Bad files raise
:class:`facetsynth.io.errors.InputError` naming the file and the problem:
also bad *values*, named by field with counts (NaN or Inf anywhere; negative
values beyond measurement noise, :data:`NOISE_FRACTION`; no positive value,
which would fit a zero model "perfectly"; a reflectance above :data:`MAX_BRDF`).

Formats
-------
* UTIA ``.bin``: raw little-endian float64, ``(3, 6, 48, 6, 48)`` C order.
* UTIA ``.exr``: the 288x288 unwrapping of paper 000, Fig. 1 (channel "RGB").
* RGL ``.bsdf``: Mitsuba 3 ``tensor_file`` (Dupuy & Jakob 2018).  The RGB
  values live in the warped sample space of the visible-normal distribution;
  :func:`rgl_eval` inverts that warp (continuous marginal 2D warp, bilinear
  in the sample square, linear in the incident-angle parameters), as
  Mitsuba's ``measured`` plugin does.  Mitsuba is not needed here.
* MERL ``.binary``: int32 dims (90, 90, 180), then float64 R, G, B blocks,
  scaled by (1/1500, 1.15/1500, 1.66/1500); half/difference angles
  (Rusinkiewicz) with nearest-bin lookup as in the MERL reference code.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from facetsynth.io.errors import InputError
from facetsynth.io.fileio import read_exr, write_exr

from . import grid

__all__ = [
    "read_utia_bin", "write_utia_bin", "read_utia_exr", "write_utia_exr",
    "read_tensor_file", "write_tensor_file", "RGLBRDF", "rgl_eval", "read_rgl",
    "read_merl_table", "write_merl_table", "merl_eval", "read_merl", "read_brdf",
]

_UTIA_BYTES = int(np.prod(grid.SHAPE)) * 8


NOISE_FRACTION = 0.25
"""Negative BRDF values down to -NOISE_FRACTION x the largest value are measurement noise.

Real measurements hold small negative values where the signal is near 0
(background subtraction): in the RGL files up to 8.6 % of the channel's
largest value (cg_sunflower, blue) and 6.9 % of the file's largest. A value
more negative than 25 % of the largest, or a file with no positive value,
is not noise but broken data (a sign error, a wrong scale, a wrong field).
"""


MAX_BRDF = 1e6
"""The largest BRDF value (1/sr) a file may hold. The largest in the measured files here: 1166 (RGL
cg_sunflower, on the UTIA grid; the others 0.8 to 197); a mirror-like peak 0.05 deg wide reaches
1 / (pi (0.05 deg)^2) = 4e5. Beyond 1e6 a value is a wrong scale or a wrong field, not a reflectance:
a UTIA file of 1e300 "fitted perfectly" (Delta E 0, 100 dB) in float arithmetic that had overflowed."""


def _check_scale(path, field, arr):
    """``arr``, or InputError naming ``field`` and counting its values above :data:`MAX_BRDF`."""
    big = int(np.count_nonzero(arr > MAX_BRDF))
    if big:
        raise InputError(path, f"field {field!r}: {big} value(s) of {arr.size} above {MAX_BRDF:g} 1/sr (the largest "
                               f"{float(arr.max()):.3g}): not a reflectance (a wrong scale or a wrong field?)")
    return arr


def _check_finite(path, field, arr):
    """``arr``, or InputError naming ``field`` and counting its NaN or Inf values."""
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        raise InputError(path, f"field {field!r}: {bad} NaN or Inf value(s) of {arr.size}")
    return arr


def _check_values(path, field, arr, noise=False):
    """``arr`` if finite and non-negative, else InputError naming ``field`` with counts.

    With ``noise`` (measured radiometric data), negative values are accepted
    while they stay within :data:`NOISE_FRACTION` of the largest value.
    """
    _check_finite(path, field, arr)
    if noise:                       # reflectance: a scale no measurement has
        _check_scale(path, field, arr)
    neg = int(np.count_nonzero(arr < 0))
    if not neg:
        return arr
    low, top = float(arr.min()), float(arr.max())
    if noise and top > 0 and -low <= NOISE_FRACTION * top:
        return arr
    if not noise:
        why = "expected none"
    elif top <= 0:
        why = "and no positive value: not a reflectance"
    else:
        why = f"more than measurement noise: below -{NOISE_FRACTION:.0%} of the largest value {top:.3g}"
    raise InputError(path, f"field {field!r}: {neg} negative value(s) of {arr.size}, down to {low:.3g} ({why})")


def _read_bytes(path):
    try:
        return path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror}") from None


# --------------------------------------------------------------------- UTIA
def read_utia_bin(path):
    """UTIA ``.bin``: float64 ``(3, 6, 48, 6, 48)`` [channel, theta_i, phi_i, theta_v, phi_v]."""
    p = Path(path)
    raw = _read_bytes(p)
    if len(raw) != _UTIA_BYTES:
        what = "truncated" if len(raw) < _UTIA_BYTES else "too long"
        raise InputError(p, f"wrong size for a UTIA .bin ({what}): {len(raw)} bytes, expected {_UTIA_BYTES}")
    arr = np.frombuffer(raw, dtype="<f8").reshape(grid.SHAPE).astype(float)
    return _check_values(p, "rgb", arr, noise=True)


def write_utia_bin(path, brdf):
    brdf = np.asarray(brdf, dtype="<f8")
    if brdf.shape != grid.SHAPE:
        raise ValueError(f"expected shape {grid.SHAPE}, got {brdf.shape}")
    Path(path).write_bytes(np.ascontiguousarray(brdf).tobytes())


def read_utia_exr(path):
    """The 288x288 unwrapped BRDF image (paper 000, Fig. 1) -> ``(3, 6, 48, 6, 48)``."""
    p = Path(path)
    channels, _ = read_exr(p)   # a missing or damaged file: InputError naming it
    img = channels.get("RGB")
    if img is None:
        raise InputError(p, f"no RGB channels (has {sorted(channels)})")
    if img.shape != (288, 288, 3):
        raise InputError(p, f"wrong image size {img.shape[1]}x{img.shape[0]}, expected 288x288")
    return _check_values(p, "RGB", grid.wrap(np.asarray(img, float)), noise=True)


def write_utia_exr(path, brdf):
    write_exr(path, {"RGB": grid.unwrap(brdf).astype(np.float32)})


# ------------------------------------------------------ Mitsuba tensor_file
_MAGIC = b"tensor_file\0"
_DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8",
           9: "<f2", 10: "<f4", 11: "<f8"}
_DTYPE_CODES = {np.dtype(v).str.lstrip("|<"): k for k, v in _DTYPES.items()}


def read_tensor_file(path):
    """Parse a Mitsuba ``tensor_file`` -> ``{name: ndarray}`` (copies, native order)."""
    p = Path(path)
    raw = _read_bytes(p)
    if raw[:12] != _MAGIC:
        raise InputError(p, "wrong magic: not a Mitsuba tensor_file")
    try:
        major, minor, n_fields = struct.unpack_from("<BBI", raw, 12)
        if (major, minor) != (1, 0):
            raise InputError(p, f"unsupported tensor_file version {major}.{minor}")
        pos, fields = 18, {}
        for _ in range(n_fields):
            (nlen,) = struct.unpack_from("<H", raw, pos)
            name = raw[pos + 2:pos + 2 + nlen].decode("utf-8")
            pos += 2 + nlen
            ndim, code, offset = struct.unpack_from("<HBQ", raw, pos)
            pos += 11
            shape = struct.unpack_from(f"<{ndim}Q", raw, pos)
            pos += 8 * ndim
            if code not in _DTYPES:
                raise InputError(p, f"field {name!r}: unknown dtype code {code}")
            dt = np.dtype(_DTYPES[code])
            nbytes = math.prod(shape) * dt.itemsize     # exact: a damaged shape's product must not wrap
            if offset + nbytes > len(raw):
                raise InputError(p, f"truncated: field {name!r} needs bytes {offset}..{offset + nbytes}, "
                                    f"file has {len(raw)}")
            fields[name] = np.frombuffer(raw, dtype=dt, count=nbytes // dt.itemsize,
                                         offset=offset).reshape(shape).astype(dt.newbyteorder("="))
    except InputError:
        raise
    except struct.error:
        raise InputError(p, "truncated tensor_file header") from None
    except UnicodeDecodeError:
        raise InputError(p, "damaged tensor_file header: a field name is not UTF-8") from None
    except (ValueError, OverflowError) as exc:   # a shape, offset or size no array can have
        raise InputError(p, f"damaged tensor_file header: {exc}") from None
    return fields


def write_tensor_file(path, fields):
    """Write ``{name: ndarray}`` as a Mitsuba ``tensor_file`` (for round-trip tests)."""
    arrays = {k: np.ascontiguousarray(v) for k, v in fields.items()}
    header = bytearray(_MAGIC + struct.pack("<BBI", 1, 0, len(arrays)))
    hsize = len(header) + sum(2 + len(k.encode()) + 11 + 8 * v.ndim for k, v in arrays.items())
    offset, blobs = hsize, []
    for k, v in arrays.items():
        code = _DTYPE_CODES[v.dtype.str.lstrip("|<>=")]
        offset = (offset + 7) // 8 * 8
        header += struct.pack("<H", len(k.encode())) + k.encode()
        header += struct.pack("<HBQ", v.ndim, code, offset) + struct.pack(f"<{v.ndim}Q", *v.shape)
        blobs.append((offset, v.astype(v.dtype.newbyteorder("<")).tobytes()))
        offset += len(blobs[-1][1])
    out = bytearray(offset)
    out[:len(header)] = header
    for off, b in blobs:
        out[off:off + len(b)] = b
    Path(path).write_bytes(bytes(out))


# ---------------------------------------------------------------- RGL eval
def _interval(values, x):
    """Index i with values[i] <= x < values[i+1] (clamped) and weight of i+1 (clamped to [0,1])."""
    values = np.asarray(values, float)
    if values.size == 1:
        return np.zeros(np.shape(x), int), np.zeros(np.shape(x))
    i = np.clip(np.searchsorted(values, x, side="right") - 1, 0, values.size - 2)
    w = np.clip((x - values[i]) / (values[i + 1] - values[i]), 0.0, 1.0)
    return i, w


class _Slices:
    """Linear interpolation of per-slice 2D tables over the leading parameter axes."""

    def __init__(self, params, pvals):
        # params: list of arrays (one per parameter axis), pvals: query values broadcast
        self.terms = [(np.zeros(np.shape(pvals[0]), int), np.ones(np.shape(pvals[0])))]
        self.shape = tuple(len(v) for v in params)
        for ax, (vals, x) in enumerate(zip(params, pvals)):
            i, w = _interval(vals, x)
            new = []
            for idx, wt in self.terms:
                stride = int(np.prod(self.shape[ax + 1:], dtype=int))
                if len(vals) == 1:
                    new.append((idx, wt))
                else:
                    new.append((idx + i * stride, wt * (1 - w)))
                    new.append((idx + (i + 1) * stride, wt * w))
            self.terms = new

    def gather(self, table, iy, ix):
        """table: (n_slices, ny, nx); returns interpolated table[., iy, ix]."""
        return sum(wt * table[idx, iy, ix] for idx, wt in self.terms)


def _bilinear(table2d_slices, sl, u):
    """Bilinear lookup in the unit square of per-slice tables (n_slices, ny, nx); u = (..., 2) as (x, y)."""
    ny, nx = table2d_slices.shape[1:]
    px = np.clip(u[..., 0], 0, 1) * (nx - 1)
    py = np.clip(u[..., 1], 0, 1) * (ny - 1)
    ix = np.minimum(px.astype(int), nx - 2)
    iy = np.minimum(py.astype(int), ny - 2)
    fx, fy = px - ix, py - iy
    v00 = sl.gather(table2d_slices, iy, ix)
    v10 = sl.gather(table2d_slices, iy, ix + 1)
    v01 = sl.gather(table2d_slices, iy + 1, ix)
    v11 = sl.gather(table2d_slices, iy + 1, ix + 1)
    return (1 - fy) * ((1 - fx) * v00 + fx * v10) + fy * ((1 - fx) * v01 + fx * v11)


def _check_axis(path, field, values, lo, hi):
    """A parameter axis: finite, strictly increasing, within [lo, hi] (float32 slack)."""
    _check_finite(path, field, values)
    if values.size == 0 or np.any(np.diff(values) <= 0) or values[0] < lo - 1e-5 or values[-1] > hi + 1e-5:
        raise InputError(path, f"field {field!r}: expected increasing angles within [{lo:.4g}, {hi:.4g}], "
                               f"found {np.array2string(values, precision=4, threshold=8, max_line_width=10**6)}")


def _check_rgl_values(path, f, vndf, rgb):
    """The values of an RGL file's fields: what :meth:`RGLBRDF.eval` needs to give finite, meaningful fr.

    Angles finite and increasing; ``ndf``, ``sigma`` and ``vndf`` finite and
    non-negative, ``sigma`` positive (eval divides by it), every ``vndf``
    slice with some mass (its warp is normalised by it) and every table at
    least 2 x 2; ``rgb`` finite with negative values only as measurement noise
    (:data:`NOISE_FRACTION`) and some positive value.
    """
    _check_axis(path, "theta_i", f["theta_i"].astype(float), 0.0, np.pi / 2)
    _check_axis(path, "phi_i", f["phi_i"].astype(float), -np.pi, 2 * np.pi)
    if f["jacobian"].size == 0:
        raise InputError(path, "field 'jacobian': empty")
    for name, table in (("ndf", f["ndf"]), ("sigma", f["sigma"]), ("vndf", vndf), ("rgb", rgb)):
        if min(table.shape[-2:]) < 2:
            raise InputError(path, f"field {name!r}: tables of at least 2x2 needed, found shape {table.shape}")
    for name, table in (("ndf", f["ndf"]), ("sigma", f["sigma"]), ("vndf", vndf)):
        _check_values(path, name, np.asarray(table, float))
    zero = int(np.count_nonzero(f["sigma"] == 0))
    if zero:
        raise InputError(path, f"field 'sigma': {zero} zero value(s); the projected area must be positive")
    empty = np.flatnonzero(vndf.reshape(vndf.shape[0] * vndf.shape[1], -1).sum(axis=1) <= 0)
    if empty.size:
        raise InputError(path, f"field 'vndf': {empty.size} slice(s) hold no mass (first: slice {empty[0]})")
    _check_values(path, "rgb", rgb, noise=True)
    if not np.any(rgb > 0):
        raise InputError(path, "field 'rgb': no positive value (no reflectance to fit)")


class RGLBRDF:
    """An RGL (Dupuy & Jakob 2018) measured BRDF loaded from a tensor file."""

    REQUIRED = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "rgb", "jacobian")

    def __init__(self, path):
        self.path = Path(path)
        f = read_tensor_file(path)
        missing = [k for k in self.REQUIRED if k not in f]
        if missing:
            raise InputError(path, f"not an RGL RGB BRDF: missing fields {missing}")
        with np.errstate(invalid="ignore"):   # a signalling NaN raises the flag when cast: the checks name it
            self.theta_i = f["theta_i"].astype(float)
            self.phi_i = f["phi_i"].astype(float)
            nphi, nth = self.phi_i.size, self.theta_i.size
            vndf, rgb = f["vndf"].astype(float), f["rgb"].astype(float)
            if vndf.ndim != 4 or vndf.shape[:2] != (nphi, nth) or rgb.shape[:3] != (nphi, nth, 3) \
                    or rgb.ndim != 5 or f["ndf"].ndim != 2 or f["sigma"].ndim != 2:
                raise InputError(path, f"inconsistent field shapes: vndf {vndf.shape}, rgb {rgb.shape}")
            _check_rgl_values(path, f, vndf, rgb)
        self.description = bytes(f.get("description", np.zeros(0, np.uint8))).decode("utf-8", "replace")
        self.isotropic = nphi <= 2
        self.jacobian = bool(f["jacobian"][0])
        self.reduction = 0 if self.isotropic else int(round(2 * np.pi / (self.phi_i[-1] - self.phi_i[0])))
        self.ndf = f["ndf"].astype(float)[None]
        self.sigma = f["sigma"].astype(float)[None]
        self.rgb = rgb.reshape(nphi * nth * 3, *rgb.shape[3:])
        # Continuous marginal 2D warp of the VNDF: trapezoidal conditional / marginal CDFs.
        v = vndf.reshape(nphi * nth, *vndf.shape[2:])
        cond = np.concatenate([np.zeros(v.shape[:2] + (1,)), np.cumsum(0.5 * (v[..., 1:] + v[..., :-1]), -1)], -1)
        rows = cond[..., -1]
        marg = np.concatenate([np.zeros((v.shape[0], 1)), np.cumsum(0.5 * (rows[:, 1:] + rows[:, :-1]), -1)], -1)
        norm = 1.0 / marg[:, -1]
        self.vndf = v * norm[:, None, None]
        self.cond = cond * norm[:, None, None]
        self.marg = marg * norm[:, None]

    def _invert_vndf(self, u, sl):
        ny, nx = self.vndf.shape[1:]
        s = np.clip(u, 0, 1) * [nx - 1, ny - 1]
        px = np.minimum(s[..., 0].astype(int), nx - 2)
        py = np.minimum(s[..., 1].astype(int), ny - 2)
        sx, sy = s[..., 0] - px, s[..., 1] - py
        g = sl.gather
        v00, v10 = g(self.vndf, py, px), g(self.vndf, py, px + 1)
        v01, v11 = g(self.vndf, py + 1, px), g(self.vndf, py + 1, px + 1)
        c0 = (1 - sy) * v00 + sy * v01
        c1 = (1 - sy) * v10 + sy * v11
        x = sx * (c0 + 0.5 * sx * (c1 - c0))
        x = x + (1 - sy) * g(self.cond, py, px) + sy * g(self.cond, py + 1, px)
        r0, r1 = g(self.cond, py, np.full_like(px, nx - 1)), g(self.cond, py + 1, np.full_like(px, nx - 1))
        x = x / np.where((1 - sy) * r0 + sy * r1 > 0, (1 - sy) * r0 + sy * r1, 1.0)
        y = sy * (r0 + 0.5 * sy * (r1 - r0))
        marg_i = sum(wt * self.marg[idx, py] for idx, wt in sl.terms)
        return np.stack([x, y + marg_i], -1)

    def eval(self, wi, wo):
        """fr(wi, wo), ``(..., 3)``, 1/sr, without the cosine; zero below either horizon.

        The stored RGB tables hold fr * cos(theta_o) (Mitsuba's eval returns
        exactly that); the cosine is divided out here.
        """
        wi = np.array(wi, float)
        wo = np.array(wo, float)
        wi, wo = np.broadcast_arrays(wi, wo)
        wi, wo = wi.copy(), wo.copy()
        active = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        if self.reduction >= 2:
            sy = wi[..., 1].copy()
            sx = wi[..., 0].copy() if self.reduction == 4 else sy
            fx, fy = np.where(sx >= 0, -1.0, 1.0), np.where(sy >= 0, -1.0, 1.0)
            for v in (wi, wo):
                v[..., 0] *= fx
                v[..., 1] *= fy
        m = wi + wo
        m /= np.maximum(np.linalg.norm(m, axis=-1, keepdims=True), 1e-300)

        def elev(d):
            dist = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (d[..., 2] - 1) ** 2)
            return 2 * np.arcsin(np.clip(0.5 * dist, -1, 1))

        theta_i, phi_i = elev(wi), np.arctan2(wi[..., 1], wi[..., 0])
        theta_m, phi_m = elev(m), np.arctan2(m[..., 1], m[..., 0])
        t2u = lambda t: np.sqrt(np.maximum(t, 0) * (2 / np.pi))  # noqa: E731
        p2u = lambda p: (p + np.pi) / (2 * np.pi)  # noqa: E731
        u_wi = np.stack([t2u(theta_i), p2u(phi_i)], -1)
        um_y = p2u(phi_m - phi_i if self.isotropic else phi_m)
        u_m = np.stack([t2u(theta_m), um_y - np.floor(um_y)], -1)
        sl2 = _Slices([self.phi_i, self.theta_i], [phi_i, theta_i])
        sample = self._invert_vndf(u_m, sl2)
        out = np.empty(theta_i.shape + (3,))
        for c in range(3):  # three channels, not a loop over samples
            sl3 = _Slices([self.phi_i, self.theta_i, np.arange(3.0)], [phi_i, theta_i, np.full_like(phi_i, c)])
            out[..., c] = _bilinear(self.rgb, sl3, sample)
        if self.jacobian:
            one = _Slices([np.zeros(1)], [phi_i])
            out *= (_bilinear(self.ndf, one, u_m) / (4 * _bilinear(self.sigma, one, u_wi)))[..., None]
        # The tables store fr * cos(theta_o) (what Mitsuba's eval returns); divide it out.
        out = out / np.maximum(wo[..., 2], 1e-6)[..., None]
        out = np.where(active[..., None], np.maximum(out, 0.0), 0.0)
        return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


def rgl_eval(path_or_brdf, wi, wo):
    b = path_or_brdf if isinstance(path_or_brdf, RGLBRDF) else RGLBRDF(path_or_brdf)
    return b.eval(wi, wo)


def read_rgl(path):
    """RGL ``.bsdf`` -> BRDF on the UTIA grid ``(3, 6, 48, 6, 48)``."""
    wi, wo = grid.utia_directions()
    return np.moveaxis(RGLBRDF(path).eval(wi, wo), -1, 0)


# --------------------------------------------------------------------- MERL
_MERL_DIMS = (90, 90, 180)
_MERL_SCALE = np.array([1.0 / 1500, 1.15 / 1500, 1.66 / 1500])


def read_merl_table(path):
    """MERL ``.binary`` -> scaled table ``(3, 90, 90, 180)`` [channel, theta_h, theta_d, phi_d]."""
    p = Path(path)
    raw = _read_bytes(p)
    if len(raw) < 12:
        raise InputError(p, "truncated: shorter than the 12-byte MERL header")
    dims = struct.unpack_from("<3i", raw, 0)
    if dims != _MERL_DIMS:
        raise InputError(p, f"wrong MERL dimensions {dims}, expected {_MERL_DIMS}")
    n = 3 * int(np.prod(dims))
    if len(raw) != 12 + 8 * n:
        raise InputError(p, f"wrong size for a MERL .binary: {len(raw)} bytes, expected {12 + 8 * n}")
    t = np.frombuffer(raw, "<f8", count=n, offset=12).reshape(3, *dims) * _MERL_SCALE[:, None, None, None]
    # negative entries are MERL's own "not measured" marker (merl_eval reads them as 0); NaN or Inf are not
    _check_finite(p, "rgb", t)
    _check_scale(p, "rgb", t)
    if not np.any(t > 0):
        raise InputError(p, f"field 'rgb': no positive value; all {t.size} entries are 0 or negative "
                            "(MERL's 'not measured' marker)")
    return t


def write_merl_table(path, table):
    table = np.asarray(table, float)
    if table.shape != (3,) + _MERL_DIMS:
        raise ValueError(f"expected shape (3, 90, 90, 180), got {table.shape}")
    raw = (table / _MERL_SCALE[:, None, None, None]).astype("<f8").tobytes()
    Path(path).write_bytes(struct.pack("<3i", *_MERL_DIMS) + raw)


def _rotate(v, axis, angle):
    """Rotate vectors v (..., 3) about 'z' or 'y' by angle (...)."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    if axis == "z":
        return np.stack([c * x - s * y, s * x + c * y, z], -1)
    return np.stack([c * x + s * z, y, -s * x + c * z], -1)


def merl_eval(table, wi, wo):
    """MERL lookup (nearest bin, as the reference code) -> fr ``(..., 3)``; invalid entries -> 0."""
    wi, wo = np.broadcast_arrays(np.asarray(wi, float), np.asarray(wo, float))
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-300)
    th = np.arccos(np.clip(h[..., 2], -1, 1))
    ph = np.arctan2(h[..., 1], h[..., 0])
    d = _rotate(_rotate(wi, "z", -ph), "y", -th)
    td = np.arccos(np.clip(d[..., 2], -1, 1))
    pd = np.arctan2(d[..., 1], d[..., 0])
    pd = np.where(pd < 0, pd + np.pi, pd)
    ith = np.clip(np.sqrt(np.clip(th / (np.pi / 2), 0, 1)) * 90, 0, 89).astype(int)
    itd = np.clip(td / (np.pi / 2) * 90, 0, 89).astype(int)
    ipd = np.clip(pd / np.pi * 180, 0, 179).astype(int)
    v = table[:, ith, itd, ipd]
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return np.moveaxis(np.where(ok & (v >= 0), v, 0.0), 0, -1)


def read_merl(path):
    """MERL ``.binary`` -> BRDF on the UTIA grid."""
    wi, wo = grid.utia_directions()
    return np.moveaxis(merl_eval(read_merl_table(path), wi, wo), -1, 0)


def read_brdf(path):
    """Dispatch on the suffix: ``.bin`` UTIA, ``.exr`` UTIA image, ``.bsdf`` RGL, ``.binary`` MERL."""
    p = Path(path)
    readers = {".bin": read_utia_bin, ".exr": read_utia_exr, ".bsdf": read_rgl, ".binary": read_merl}
    fn = readers.get(p.suffix.lower())
    if fn is None:
        raise InputError(p, f"unknown BRDF file type {p.suffix!r} (expected {sorted(readers)})")
    if not p.exists():
        raise InputError(p, "file does not exist")
    if p.is_dir():
        raise InputError(p, "is a folder, not a BRDF file")
    brdf = fn(p)
    if not np.any(brdf > 0):
        raise InputError(p, "no reflectance: the BRDF is 0 at every direction pair of the UTIA grid")
    return brdf
