"""Readers: round trips through written files, bad files, RGL against Mitsuba 3."""

import struct
import warnings

import numpy as np
import pytest

from facetsynth.io.errors import InputError
from facetsynth.stencil import grid, readers

from conftest import RGL_DIR


def _random_brdf(seed=0):
    return np.random.default_rng(seed).uniform(0, 2, grid.SHAPE)


def test_unwrap_layout_and_inverse():
    b = _random_brdf()
    img = grid.unwrap(b)
    assert img.shape == (288, 288, 3)
    # row 48*ti + pi, column 48*tv + pv
    assert img[48 * 2 + 5, 48 * 4 + 7, 1] == b[1, 2, 5, 4, 7]
    assert np.array_equal(grid.wrap(img), b)


def test_utia_bin_round_trip_and_errors(tmp_path):
    b = _random_brdf(1)
    p = tmp_path / "x.bin"
    readers.write_utia_bin(p, b)
    assert np.array_equal(readers.read_utia_bin(p), b)
    p.write_bytes(p.read_bytes()[:-8])
    with pytest.raises(InputError, match="truncated"):
        readers.read_utia_bin(p)


def test_utia_exr_round_trip_and_errors(tmp_path):
    b = _random_brdf(2).astype(np.float32).astype(float)
    p = tmp_path / "x.exr"
    readers.write_utia_exr(p, b)
    np.testing.assert_array_equal(readers.read_utia_exr(p), b)
    from facetsynth.io.fileio import write_exr
    write_exr(tmp_path / "bad.exr", {"RGB": np.zeros((10, 288, 3), np.float32)})
    with pytest.raises(InputError, match="288x288"):
        readers.read_utia_exr(tmp_path / "bad.exr")


def test_merl_round_trip_and_lookup(tmp_path):
    rng = np.random.default_rng(3)
    t = rng.uniform(0.01, 1, (3, 90, 90, 180))
    p = tmp_path / "x.binary"
    readers.write_merl_table(p, t)
    t2 = readers.read_merl_table(p)
    np.testing.assert_allclose(t2, t, rtol=1e-12)
    # mirror pair at theta = 31.5 deg: theta_h = 0, theta_d = 31.5 deg, phi_d = 0 -> bin (0, 31, 0)
    wi = grid.sph_to_dir(np.deg2rad(31.5), 0.0)
    wo = grid.sph_to_dir(np.deg2rad(31.5), np.pi)
    # (phi_h and so phi_d are ill-defined at theta_h = 0: any phi_d bin of that row)
    v = readers.merl_eval(t2, wi, wo)
    assert np.isclose(t[:, 0, 31, :].T, v).all(axis=1).any()
    # theta_h = 20 deg (bin sqrt(20/90)*90 = 42), theta_d = 0: wi = wo
    w = grid.sph_to_dir(np.deg2rad(20), 1.0)
    np.testing.assert_allclose(readers.merl_eval(t2, w, w), t[:, 42, 0, 0])
    b = readers.read_merl(p)
    assert b.shape == grid.SHAPE and np.all(np.isfinite(b))
    p.write_bytes(struct.pack("<3i", 90, 90, 90) + b"\0" * 64)
    with pytest.raises(InputError, match="dimensions"):
        readers.read_merl_table(p)


def test_tensor_file_round_trip_and_errors(tmp_path):
    f = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([7], np.uint8),
         "c": np.linspace(0, 1, 5)}
    p = tmp_path / "t.bsdf"
    readers.write_tensor_file(p, f)
    g = readers.read_tensor_file(p)
    for k in f:
        assert g[k].dtype == f[k].dtype and np.array_equal(g[k], f[k])
    raw = p.read_bytes()
    p.write_bytes(raw[:-4])
    with pytest.raises(InputError, match="truncated"):
        readers.read_tensor_file(p)
    p.write_bytes(b"not_a_tensor" + raw[12:])
    with pytest.raises(InputError, match="magic"):
        readers.read_tensor_file(p)


@pytest.mark.parametrize("shape", [(2**63 + 1, 2), (2**32, 2**32)])
def test_tensor_file_shape_beyond_int64_is_truncation_not_a_wrapped_size(tmp_path, shape):
    """A damaged header's shape whose element count passes 2^63 (or wraps to 0 in int64) is measured exactly:
    the field needs more bytes than the file has, said as such, and numpy warns of nothing."""
    p = tmp_path / "t.bsdf"
    readers.write_tensor_file(p, {"a": np.zeros((2, 3), np.float32)})
    raw = bytearray(p.read_bytes())
    struct.pack_into("<2Q", raw, 32, *shape)     # field "a": its shape after magic, version, count, name, dtype, offset
    p.write_bytes(bytes(raw))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="truncated: field 'a' needs bytes"):
            readers.read_tensor_file(p)


def test_rgl_signalling_nan_is_named_without_a_numpy_warning(tmp_path):
    """A signalling NaN in an RGL table (bits a damaged file holds: the fuzz test found them) raises the invalid
    flag when cast to float64: the reader names the field and its NaN count, and numpy warns of nothing."""
    fields = readers.read_tensor_file(min(RGL_DIR.glob("*.bsdf"), key=lambda q: q.stat().st_size))
    vndf = np.array(fields["vndf"], np.float32)
    vndf.reshape(-1).view(np.uint32)[5] = 0x7F800001               # exponent all ones, quiet bit clear: sNaN
    fields["vndf"] = vndf
    p = tmp_path / "snan.bsdf"
    readers.write_tensor_file(p, fields)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="field 'vndf': 1 NaN or Inf value"):
            readers.read_rgl(p)


def test_rgl_matches_mitsuba_measured():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(0)
    n = 60
    for name in ("paper_white_rgb", "satin_rosaline_rgb", "cg_sunflower_rgb"):
        path = f"{RGL_DIR}/{name}.bsdf"
        ours = readers.RGLBRDF(path)
        bsdf = mi.load_dict({"type": "measured", "filename": path})
        wi = grid.sph_to_dir(np.arccos(rng.uniform(0.1, 1, n)), rng.uniform(0, 2 * np.pi, n))
        wo = grid.sph_to_dir(np.arccos(rng.uniform(0.1, 1, n)), rng.uniform(0, 2 * np.pi, n))
        fr = ours.eval(wi, wo)
        ref = np.zeros((n, 3))
        for k in range(n):  # Mitsuba's scalar API: one direction pair per call
            si = mi.SurfaceInteraction3f()
            si.wi = mi.Vector3f(*wi[k])
            si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
            ref[k] = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[k]))) / wo[k, 2]
        # Mitsuba returns fr * cos(theta_o) and lets negative interpolants through; we clamp at 0
        ref = np.maximum(ref, 0.0)
        np.testing.assert_allclose(fr, ref, rtol=2e-4, atol=1e-6 * ref.max())


def test_rgl_paper_white_level_and_reciprocity():
    b = readers.read_rgl(f"{RGL_DIR}/paper_white_rgb.bsdf")
    assert b.shape == grid.SHAPE and np.all(np.isfinite(b)) and b.min() >= 0
    # README: near-diffuse, fr about 0.25-0.35 /sr
    assert 0.22 < np.median(b) < 0.36
    # reciprocity on the grid, away from grazing (measured data: a few %)
    sw = b.transpose(0, 3, 4, 1, 2)
    sel = (slice(None), slice(1, 4), slice(None), slice(1, 4), slice(None))
    assert np.median(np.abs(b[sel] - sw[sel]) / b[sel]) < 0.03


def test_read_brdf_rejects_unknown(tmp_path):
    with pytest.raises(InputError, match="unknown BRDF file type"):
        readers.read_brdf(tmp_path / "x.txt")
    with pytest.raises(InputError, match="does not exist"):
        readers.read_brdf(tmp_path / "missing.bin")
