"""Portable export (issue 17 item 3): the GGX fit, the glTF BRDF's numerics, the file, its round trip, its loss."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from facetsynth.io.errors import InputError
from facetsynth.export.gltf import (GLTF_NAME, IMAGES, decode_textures, encode_textures, export_gltf, fit_material,
                                    orient_directions, read_gltf, srgb_decode, srgb_encode, validate_gltf)
from facetsynth.models.ggx import GltfMaterial, anisotropic_alphas, fit_ggx_ndf, ggx_tables, roughness_strength
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.fit.params import normalise, projected_area
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.models.svbrdf import SVBRDF

GRID = DirectionGrid(32, 128)   # the demo's direction grid (balanced preset)


def _ggx_svbrdf(rows=3, cols=4, seed=0):
    """An SVBRDF whose per-point NDFs are known GGX lobes: 3 representatives (grid-normalised tables, as the
    params stage writes them), one-hot or two-way mixtures of them, and a per-point eq. 13 turn."""
    rng = np.random.default_rng(seed)
    ax, ay, phi = np.array([0.3, 0.12, 0.5]), np.array([0.1, 0.12, 0.25]), np.array([0.3, 0.0, -1.0])
    nd, _ = normalise(ggx_tables(GRID, ax, ay, phi).reshape((3,) + GRID.shape), GRID)
    p = rows * cols
    rep = rng.integers(0, 3, p)
    rotation = rng.uniform(-np.pi, np.pi, p)
    rotation[:3] = [0.0, np.pi / 2, 2 * np.pi / GRID.n_phi]
    return SVBRDF(plane=PlaneGrid(0.02, 0.015, cols, rows), grid=GRID, kd=rng.uniform(0.02, 0.5, (p, 3)),
                  ks=rng.uniform(0.2, 0.9, (p, 3)), eta=np.full(p, 1.6), ndf=nd.astype(np.float32),
                  area=projected_area(nd, GRID).astype(np.float32), neighbours=rep[:, None],
                  weights=np.ones((p, 1)), rotation=rotation), (ax, ay, phi, rep, rotation)


def _direction_error(a, b):
    """|a - b| for directions (angles mod pi)."""
    return np.abs(np.angle(np.exp(2j * (np.asarray(a) - np.asarray(b)))) / 2)


# --- the fit ---------------------------------------------------------------------------------------------------

def test_fit_recovers_known_anisotropic_ggx_on_the_model_grid():
    """Grid-normalised GGX tables (how the params stage stores NDFs): alphas, azimuth and the grid's scale."""
    rng = np.random.default_rng(3)
    n = 48
    ax, ay = np.exp(rng.uniform(np.log(0.04), np.log(0.8), (2, n)))
    phi = rng.uniform(-np.pi, np.pi, n)
    raw = ggx_tables(GRID, ax, ay, phi).reshape((n,) + GRID.shape)
    tables, integral = normalise(raw, GRID)
    fit = fit_ggx_ndf(tables, GRID, fit_scale=True)
    big, small = np.maximum(ax, ay), np.minimum(ax, ay)
    np.testing.assert_allclose(fit["alpha_x"], big, rtol=1e-6)
    np.testing.assert_allclose(fit["alpha_y"], small, rtol=1e-6)
    np.testing.assert_allclose(fit["scale"], 1.0 / integral, rtol=1e-6)
    axis = np.where(ax >= ay, phi, phi + np.pi / 2)
    aniso = big / small > 1.1
    assert np.all(_direction_error(fit["phi"], axis)[aniso] < 1e-6)
    assert np.all(fit["rel_l2"] < 1e-6)


def test_fit_material_follows_the_turn_and_maps_to_gltf_parameters():
    model, (ax, ay, phi, rep, rotation) = _ggx_svbrdf()
    material, record = fit_material(model)
    np.testing.assert_allclose(record["alpha_x"], ax[rep], rtol=1e-5)
    np.testing.assert_allclose(record["alpha_y"], ay[rep], rtol=1e-5)
    aniso = ax[rep] / ay[rep] > 1.1
    expected = phi[rep] - rotation                 # D(x, h) = D_rep(R(rotation) h): the frame turns back
    assert np.all(_direction_error(material.anisotropy_angle, expected)[aniso] < 1e-5)
    at, ab = anisotropic_alphas(material.roughness, material.anisotropy_strength)
    np.testing.assert_allclose(at, ax[rep], rtol=1e-5)
    np.testing.assert_allclose(ab, ay[rep], rtol=1e-5)
    assert record["summary"]["mixtures_fitted"] == 3 and material.ior == pytest.approx(1.6)
    # the exported lobe reproduces the one the model renders: the per-point table (rotated on the grid)
    index = np.arange(model.n_points)
    tables = model.point_ndf(index).reshape(model.n_points, -1)
    gltf = ggx_tables(GRID, at, ab, material.anisotropy_angle) * record["scale"][:, None]
    w = GRID.solid_angles.ravel()
    rel = np.sqrt((w * (gltf - tables) ** 2).sum(-1) / (w * tables ** 2).sum(-1))
    assert rel[:3].max() < 1e-5          # turns by whole cells: the grid rotation is exact
    assert rel.max() < 0.05, rel          # other turns: the grid's interpolated rotation (eq. 13) differs


def test_roughness_strength_inverts_the_extension_mapping():
    rng = np.random.default_rng(0)
    r, s = rng.uniform(0.05, 1, 200), rng.uniform(0, 1, 200)
    at, ab = anisotropic_alphas(r, s)
    r2, s2 = roughness_strength(at, ab)
    np.testing.assert_allclose(r2, r, atol=1e-12)
    np.testing.assert_allclose(s2[r < 0.999], s[r < 0.999], atol=1e-9)


# --- the glTF BRDF ------------------------------------------------------------------------------------------

def _material(n, seed=0, **fixed):
    rng = np.random.default_rng(seed)
    plane = PlaneGrid(0.01, 0.01, n, 1)
    values = dict(base_color=rng.uniform(0, 1, (n, 3)), roughness=rng.uniform(0.3, 1, n),
                  anisotropy_strength=rng.uniform(0, 1, n), anisotropy_angle=rng.uniform(-np.pi, np.pi, n),
                  specular=rng.uniform(0, 1, n), specular_color=rng.uniform(0, 2, (n, 3)), ior=1.5,
                  metallic=rng.uniform(0, 1, n))
    values.update(fixed)
    return GltfMaterial(plane=plane, **values)


def _hemisphere(theta, phi):
    return np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)), -1)


def test_gltf_brdf_is_finite_reciprocal_and_zero_below_the_horizon():
    rng = np.random.default_rng(1)
    n = 4000
    mat = _material(n, roughness=rng.uniform(0.0, 1, n))      # roughness 0 included: alpha floored
    theta = np.concatenate([rng.uniform(0, np.pi / 2, (2, n - 400)), np.full((2, 400), np.pi / 2 - 1e-9)], 1)
    theta[:, :50] = np.pi / 2                                   # exactly at the horizon
    wi, wo = _hemisphere(theta[0], rng.uniform(0, 2 * np.pi, n)), _hemisphere(theta[1], rng.uniform(0, 2 * np.pi, n))
    index = np.arange(n)
    a, b = mat.eval_index(index, wi, wo), mat.eval_index(index, wo, wi)
    assert np.all(np.isfinite(a)) and np.all(a >= 0)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)
    below = wi * [1, 1, -1]
    assert np.all(mat.eval_index(index, below, wo) == 0) and np.all(mat.eval_index(index, wo, below) == 0)


def test_gltf_brdf_matches_appendix_b_when_isotropic():
    """No anisotropy, specular 1, white specular colour, ior 1.5: the core spec's sample implementation."""
    rng = np.random.default_rng(2)
    n = 500
    mat = _material(n, anisotropy_strength=np.zeros(n), specular=np.ones(n), specular_color=np.ones((n, 3)))
    wi = _hemisphere(rng.uniform(0, 1.5, n), rng.uniform(0, 6.3, n))
    wo = _hemisphere(rng.uniform(0, 1.5, n), rng.uniform(0, 6.3, n))
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    a2 = (mat.roughness ** 2) ** 2
    nh, nl, nv, vh = h[:, 2], wi[:, 2], wo[:, 2], np.sum(wo * h, -1)
    d = a2 / (np.pi * (nh ** 2 * (a2 - 1) + 1) ** 2)
    vis = 1 / (2 * (nv * np.sqrt(a2 + (1 - a2) * nl ** 2) + nl * np.sqrt(a2 + (1 - a2) * nv ** 2)))
    fw = ((1 - np.abs(vh)) ** 5)[:, None]
    spec = (d * vis)[:, None]
    base = mat.base_color
    dielectric_fresnel = 0.04 + (1 - 0.04) * fw
    dielectric = (1 - dielectric_fresnel) * base / np.pi + dielectric_fresnel * spec
    metal = (base + (1 - base) * fw) * spec
    m = mat.metallic[:, None]
    np.testing.assert_allclose(mat.eval_index(np.arange(n), wi, wo), (1 - m) * dielectric + m * metal, rtol=1e-10)


def _albedo(view, base=1.0, col=3.0, **params):
    """Directional albedo integral rho(i, o) (n.i) dw_i at the view elevation ``view`` (Gauss-Legendre in theta,
    480 azimuths; 400 x 1440 changes it by < 1e-4)."""
    x, w = np.polynomial.legendre.leggauss(150)
    theta, wt = (x + 1) * np.pi / 4, w * np.pi / 4
    p = np.linspace(0, 2 * np.pi, 481)[:-1]
    wi = _hemisphere(theta[:, None], p[None]).reshape(-1, 3)
    dw = ((wt * np.sin(theta))[:, None] * np.full(p.size, 2 * np.pi / p.size)[None]).ravel()
    mat = _material(1, base_color=np.full((1, 3), base), specular=np.ones(1), specular_color=np.full((1, 3), col),
                    anisotropy_angle=np.array([0.4]), **{k: np.array([v]) for k, v in params.items()})
    wo = np.broadcast_to(_hemisphere(np.array(view), np.array(1.0)), wi.shape)
    rho = mat.eval_index(np.zeros(len(wi), np.intp), wi, wo)
    return float(np.sum(rho[:, 0] * wi[:, 2] * dw))


@pytest.mark.parametrize("roughness, strength", [(1.0, 0.0), (0.6, 0.8), (0.45, 0.5), (0.35, 0.0)])
def test_gltf_brdf_conserves_energy(roughness, strength):
    """The specular BRDF (a white metal: F = 1) reflects at most what comes in at every view; the dielectric
    (white base, f0 0.12) up to 46 deg views. At grazing views Appendix B's fresnel_mix does not conserve energy
    (the diffuse is weighted by 1 - F(|v.h|) per light direction; the spec calls its sample implementation
    non-physical there): 1.15 at 80 deg for roughness 0.35. Measured, pinned so that it is not mistaken for ours."""
    for view in (0.0, 0.8, 1.2, 1.4, 1.5):
        metal = _albedo(view, roughness=roughness, anisotropy_strength=strength, metallic=1.0)
        assert 0.3 < metal <= 1.0, (view, metal)
    for view in (0.0, 0.8):
        assert _albedo(view, roughness=roughness, anisotropy_strength=strength, metallic=0.0) <= 1.0
    if roughness == 0.35:
        assert 1.1 < _albedo(1.4, roughness=roughness, anisotropy_strength=strength, metallic=0.0) < 1.2


# --- the file -----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    model, _ = _ggx_svbrdf(rows=6, cols=8, seed=4)
    folder = tmp_path_factory.mktemp("model") / "svbrdf"
    model.save(folder)
    out = tmp_path_factory.mktemp("export") / "gltf"
    summary = export_gltf(folder, out)
    return folder, out, summary


def test_export_writes_a_valid_gltf_that_pygltflib_loads(exported):
    import pygltflib
    folder, out, summary = exported
    assert sorted(Path(f).name for f in summary["files"]) == sorted(list(IMAGES.values()) + ["sample.bin", GLTF_NAME])
    validate_gltf(out / GLTF_NAME)
    doc = pygltflib.GLTF2().load(str(out / GLTF_NAME))
    material = doc.materials[0]
    assert set(material.extensions) == {"KHR_materials_anisotropy", "KHR_materials_specular", "KHR_materials_ior"}
    assert doc.meshes[0].primitives[0].attributes.TANGENT is not None
    blob = (out / "sample.bin").read_bytes()
    positions = np.frombuffer(blob[:4 * 48], np.float32).reshape(4, 12)[:, :3]
    np.testing.assert_allclose(np.ptp(positions, 0), [0.02, 0.0, 0.015], rtol=1e-6)   # x, z, -y of the plane
    # the folder is export's: again without force; a foreign one needs force; never the model's folder
    export_gltf(folder, out)
    with pytest.raises(InputError, match="output folder"):
        export_gltf(folder, folder / "gltf")


@pytest.mark.parametrize("breakage", ["no asset", "strength 2", "ior 0.5", "texture index", "byte length 0",
                                      "missing image"])
def test_a_broken_gltf_does_not_validate(exported, tmp_path, breakage):
    _, out, _ = exported
    doc = json.loads((out / GLTF_NAME).read_text())
    broken = copy.deepcopy(doc)
    ext = broken["materials"][0]["extensions"]
    if breakage == "no asset":
        del broken["asset"]
    elif breakage == "strength 2":
        ext["KHR_materials_anisotropy"]["anisotropyStrength"] = 2.0
    elif breakage == "ior 0.5":
        ext["KHR_materials_ior"]["ior"] = 0.5
    elif breakage == "texture index":
        ext["KHR_materials_anisotropy"]["anisotropyTexture"]["index"] = 9
    elif breakage == "byte length 0":
        broken["buffers"][0]["byteLength"] = 0
    for f in out.iterdir():
        if f.name != GLTF_NAME and not (breakage == "missing image" and f.name == IMAGES["anisotropy"]):
            (tmp_path / f.name).write_bytes(f.read_bytes())
    (tmp_path / GLTF_NAME).write_text(json.dumps(broken))
    with pytest.raises(InputError, match=GLTF_NAME):
        validate_gltf(tmp_path / GLTF_NAME)


def test_textures_round_trip_within_8_bit_quantisation(exported):
    folder, out, summary = exported
    model = SVBRDF.load(folder)
    fitted, _ = fit_material(model)
    read = read_gltf(out / GLTF_NAME)
    half = 0.5 / 255
    srgb_half = half * 2.4 / 1.055 * 1.0 ** 1.4 * 1.0001      # the largest slope of the sRGB decode, at 1
    assert np.max(np.abs(read.roughness - fitted.roughness)) <= half + 1e-9
    assert np.max(np.abs(read.anisotropy_strength - fitted.anisotropy_strength)) <= half + 1e-9
    assert np.max(np.abs(read.specular - fitted.specular)) <= half + 1e-9
    assert np.max(np.abs(read.base_color - fitted.base_color)) <= srgb_half
    factor = max(1.0, fitted.specular_color.max())
    assert np.max(np.abs(read.specular_color - fitted.specular_color)) <= srgb_half * factor
    aniso = fitted.anisotropy_strength > 0.02
    assert np.max(_direction_error(read.anisotropy_angle, fitted.anisotropy_angle)[aniso]) <= 1.0 / 127
    assert read.ior == pytest.approx(fitted.ior) and np.all(read.metallic == 0)
    assert summary["round_trip"]["roughness"] <= half + 1e-9
    # encode / decode alone, and the sRGB pair
    images, factors = encode_textures(fitted)
    again = decode_textures(images, factors, fitted.plane)
    np.testing.assert_array_equal(again.roughness, read.roughness)
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)


def test_anisotropy_directions_are_oriented_for_linear_filtering():
    """Lines turning about a point (the demo's turned disc) with random signs: the texture's vectors agree with
    their neighbours (a linearly filtered RG never averages to nothing) away from the centre; the lines kept."""
    rng = np.random.default_rng(5)
    y, x = np.mgrid[40:-40:-1, -40:40] + 0.5
    lines = np.arctan2(y, x) + np.pi / 2 + np.pi * rng.integers(0, 2, x.shape)
    strength = np.where(np.hypot(x, y) < 8, 0.01, 0.6)                  # an isotropic spot in the middle
    lines[strength < 0.05] = rng.uniform(-np.pi, np.pi, int((strength < 0.05).sum()))
    a = orient_directions(lines, strength)
    assert np.all(_direction_error(a, lines) < 1e-9)
    away = np.hypot(x, y) > 10
    for d in (np.cos(np.diff(a, axis=0)), np.cos(np.diff(a, axis=1))):
        ok = away[: d.shape[0], : d.shape[1]]
        assert np.all(d[ok] > 0.5)


def test_stage_without_heldout_truth_writes_the_fit_record(exported, tmp_path):
    from facetsynth.stages import export
    folder, _, _ = exported
    export.run(export.Inputs(svbrdf=folder), export.Outputs(gltf=tmp_path / "gltf", metrics=tmp_path / "metrics.json"),
               export.Settings(iterations=8))
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["views"] == {} and m["fit"]["iterations"] == 8 and m["fit_seconds"] > 0
    assert "heldout_loss_rel_l2" not in m
    validate_gltf(tmp_path / "gltf" / GLTF_NAME)


# --- the workflow -------------------------------------------------------------------------------------------

def test_demo_export_metrics(demo_run):
    """The noise-free demo (native 168 x 168): the portable material on the held-out views beside the full SVBRDF.
    Measured 2026-12-05 (fresnel_cos_min 0.5, refine fitting the NDF tables): see the bounds' comments."""
    m = json.loads((demo_run / "results/demo/export/metrics.json").read_text())
    folder = demo_run / "results/demo/export/gltf"
    validate_gltf(folder / GLTF_NAME)
    assert m["fit"]["points"] == 168 * 168 and m["fit_seconds"] < 120
    assert set(m["views"]) == {"paper", "theta30"}
    for view in m["views"].values():
        assert np.isfinite(view["portable_rel_l2"]) and view["full_rel_l2"] is not None
    # measured: portable 0.0743 / 0.0777 (paper / theta30), full 0.0639 / 0.0560: mean 0.0760 against 0.0600.
    # Since refine fits the NDF tables to the samples (issue 29) the full SVBRDF gained 0.026 and the portable
    # one-lobe material, bounded by its family, 0.010: the loss grew from 0.005 to 0.015-0.016 (CI / here).
    assert m["heldout_portable_rel_l2"] <= 0.085
    assert abs(m["heldout_loss_rel_l2"]) <= 0.02
    assert all(abs(v["loss_rel_l2"]) <= 0.026 for v in m["views"].values())
    assert m["round_trip"]["roughness"] <= 0.5 / 255 + 1e-9


# --- shading normals ----------------------------------------------------------------------------------------

def _normals(p, seed=0, max_tilt=40.0):
    rng = np.random.default_rng(seed)
    t, a = np.radians(rng.uniform(0, max_tilt, p)), rng.uniform(0, 2 * np.pi, p)
    n = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], -1)
    n[0], n[1], n[2] = [0.0, 0.0, 1.0], [np.sin(0.5), 0.0, np.cos(0.5)], [0.0, np.sin(0.5), np.cos(0.5)]
    return n


@pytest.fixture(scope="module")
def exported_normals(tmp_path_factory):
    from dataclasses import replace
    model, _ = _ggx_svbrdf(rows=6, cols=8, seed=4)
    model = replace(model, normal=_normals(model.n_points))
    folder = tmp_path_factory.mktemp("model") / "svbrdf"
    model.save(folder)
    out = tmp_path_factory.mktemp("export") / "gltf"
    return SVBRDF.load(folder), out, export_gltf(folder, out)


def test_normal_texture_is_written_valid_and_read_back(exported_normals, exported):
    """normalTexture: validates, decodes to the model's normals within 1 deg at 8 bits (measured 0.323 deg at most,
    median 0.185, over 48 normals up to 40 deg; the largest is n = +z: 0.5 has no 8-bit code), and a flat model writes none."""
    from facetsynth.export.gltf import NORMAL_IMAGE, normal_angles
    model, out, summary = exported_normals
    assert NORMAL_IMAGE in {Path(f).name for f in summary["files"]}
    validate_gltf(out / GLTF_NAME)
    doc = json.loads((out / GLTF_NAME).read_text())
    info = doc["materials"][0]["normalTexture"]
    assert doc["images"][doc["textures"][info["index"]]["source"]]["uri"] == NORMAL_IMAGE
    assert info.get("scale", 1.0) == 1.0 and info.get("texCoord", 0) == 0
    read = read_gltf(out / GLTF_NAME)
    angle = normal_angles(model.normal, read.normal)
    print(f"normalTexture round trip: max {angle.max():.3f} deg, median {np.median(angle):.3f} deg")
    assert angle.max() < 1.0
    assert summary["round_trip"]["normal_angle_deg"] == pytest.approx(angle.max(), abs=1e-9)
    fitted, _ = fit_material(model)
    np.testing.assert_array_equal(fitted.normal, model.normal)
    np.testing.assert_allclose(read.frames(np.arange(model.n_points)) @ read.normal[..., None],
                               np.tile([[0.0], [0.0], [1.0]], (model.n_points, 1, 1)), atol=1e-12)
    # a broken normalTexture index does not validate
    broken = copy.deepcopy(doc)
    broken["materials"][0]["normalTexture"]["index"] = 17
    (out / "broken.gltf").write_text(json.dumps(broken))
    with pytest.raises(InputError, match="normalTexture"):
        validate_gltf(out / "broken.gltf")
    (out / "broken.gltf").unlink()
    # flat: no normal texture, normal None read back, angle 0
    _, flat_out, flat_summary = exported
    assert "normalTexture" not in json.loads((flat_out / GLTF_NAME).read_text())["materials"][0]
    assert read_gltf(flat_out / GLTF_NAME).normal is None and flat_summary["round_trip"]["normal_angle_deg"] == 0


def test_normal_texture_convention_through_the_quad(exported_normals):
    """A renderer's view of the file: the quad's TEXCOORD_0 at a plane point selects the texel of that point's cell,
    and the tangent-space normal of that texel, put in the frame (TANGENT, cross(NORMAL, TANGENT) w, NORMAL) and
    taken from glTF's (X, Y, Z) = (x, z, -y) back to the plane's frame, is the model's normal there."""
    from PIL import Image
    model, out, _ = exported_normals
    doc = json.loads((out / GLTF_NAME).read_text())
    blob = (out / "sample.bin").read_bytes()
    attrs = doc["meshes"][0]["primitives"][0]["attributes"]

    def accessor(k, width):
        a = doc["accessors"][attrs[k]]
        view = doc["bufferViews"][a["bufferView"]]
        raw = np.frombuffer(blob, np.float32, count=a["count"] * view["byteStride"] // 4,
                            offset=view.get("byteOffset", 0)).reshape(a["count"], -1)
        return raw[:, a["byteOffset"] // 4: a["byteOffset"] // 4 + width].astype(float)

    pos, nrm, tan, uv = accessor("POSITION", 3), accessor("NORMAL", 3), accessor("TANGENT", 4), accessor("TEXCOORD_0", 2)
    # the quad is a rectangle: uv is affine in the position (exact on the 4 corners)
    design = np.concatenate([pos[:, [0, 2]], np.ones((4, 1))], 1)
    affine, *_ = np.linalg.lstsq(design, uv, rcond=None)
    np.testing.assert_allclose(design @ affine, uv, atol=1e-7)
    plane = model.plane
    centres = plane.points3d().reshape(-1, 3)
    gltf_xz = np.stack([centres[:, 0], -centres[:, 1]], -1)           # glTF (X, Z) = (x, -y)
    tex_uv = np.concatenate([gltf_xz, np.ones((len(centres), 1))], 1) @ affine
    image = np.asarray(Image.open(out / "normal.png").convert("RGB"), float) / 255.0
    rows, cols = image.shape[:2]
    col, row = np.floor(tex_uv[:, 0] * cols).astype(int), np.floor(tex_uv[:, 1] * rows).astype(int)
    index, inside = model.point_index(centres)
    assert inside.all()
    np.testing.assert_array_equal(row * cols + col, index)            # the texel of the point's own cell
    ts = image[row, col] * 2.0 - 1.0
    ts /= np.linalg.norm(ts, axis=1, keepdims=True)
    n, t = nrm[0], tan[0, :3]
    b = np.cross(n, t) * tan[0, 3]
    world = ts[:, :1] * t + ts[:, 1:2] * b + ts[:, 2:] * n             # glTF coordinates
    plane_frame = np.stack([world[:, 0], -world[:, 2], world[:, 1]], -1)
    angle = np.degrees(np.arccos(np.clip(np.sum(plane_frame * model.normal[index], -1), -1, 1)))
    assert angle.max() < 1.0, angle.max()
    # the two normals tilted along +x and +y alone: R and G carry them, not swapped nor flipped
    assert image[0, 1, 0] > 0.7 and abs(image[0, 1, 1] - 0.5) < 0.01
    assert image[0, 2, 1] > 0.7 and abs(image[0, 2, 0] - 0.5) < 0.01
