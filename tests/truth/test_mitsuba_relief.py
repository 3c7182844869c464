"""The ground-truth capture for shading normals (facetsynth.truth.mitsuba_relief): a normal-mapped relief under an RTI
dome of directional lights, seen by a top-down orthographic camera, rendered by Mitsuba 3.

(a) geometry: the orthographic sensor images a point where the manifest camera (K) puts it; (b) the normal map's
tangent frame is the plane's (x, y, z), so its normals are world normals; (c) radiometry: every pixel, flat or
tilted, equals rho (n.l) E (eq. 6 in the pixel's normal frame); (d) the capture: manifest, frames, truth, CLI.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install mitsuba, or the test extra): "
                                      "the independent-renderer tests need it")

from facetsynth.capture import manifest
from facetsynth.models import microfacet  # noqa: E402
from facetsynth.truth import mitsuba_relief  # noqa: E402
from facetsynth.io.fileio import read_exr, read_rgb  # noqa: E402

SIZE, LIGHTS, SPP = (48, 48), 24, 4
KD = np.array([0.6, 0.5, 0.4])


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("relief") / "capture"
    return out, mitsuba_relief.render_relief(out, SIZE, LIGHTS, SPP, sample_width=0.05, seed=0)


def _local(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Directions v (..., 3) in the frame of unit normals n (..., 3) (s = x made orthogonal to n, t = n x s)."""
    s = np.array([1.0, 0.0, 0.0]) - n * n[..., :1]
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    t = np.cross(n, s)
    v = np.broadcast_to(v, n.shape)
    return np.stack([(v * s).sum(-1), (v * t).sum(-1), (v * n).sum(-1)], axis=-1)


def _model(normals: np.ndarray, towards: np.ndarray, irradiance, material: dict) -> np.ndarray:
    """(H, W, 3) eq. 6 radiance rho (n.l) E seen from +z (the orthographic camera), per pixel normal."""
    wi, wo = _local(towards, normals), _local(np.array([0.0, 0.0, 1.0]), normals)
    kd = np.asarray(material["kd"], float)
    rho = microfacet.rho(wi, wo, kd, np.full(3, material["ks"]), material["eta"], material["alpha"],
                         material["alpha"])
    return rho * np.maximum(wi[..., 2:], 0.0) * np.asarray(irradiance, float)


# --- (a) geometry --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape,shift", [((48, 48), (0.0, 0.0)), ((40, 30), (-3.2, 2.4))],
                         ids=["square-centred", "wide-off-centre-principal-point"])
def test_orthographic_sensor_images_points_where_K_puts_them(shape, shift):
    """A small emissive disc at (x, y) lands at (col, row) = (s x + cx, -s y + cy) of the manifest camera: the
    sensor's to_world reproduces K, R, t (measured: within 0.05 px at 64 spp, 0.015 px at 1024: sampling noise;
    bound 0.5 px), non-square images and an off-centre principal point included."""
    import mitsuba as mi
    camera = mitsuba_relief.orthographic_camera(shape[0], shape[1], 0.05)
    camera["K"][0][2] += shift[0]
    camera["K"][1][2] += shift[1]
    s = camera["K"][0][0]
    for x, y in ((0.011, -0.004), (-0.015, 0.008)):
        scene = {"type": "scene", "integrator": {"type": "direct"},
                 "sensor": mitsuba_relief.sensor_dict(camera, spp=256),
                 "dot": {"type": "disk", "to_world": mi.ScalarTransform4f().translate([x, y, 0.0])
                         @ mi.ScalarTransform4f().scale([1.5 / s, 1.5 / s, 1.0]),
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}}
        image = np.array(mi.render(mi.load_dict(scene)))[..., 0]
        assert image.shape == (shape[1], shape[0])
        rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
        found = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
        expected = manifest._camera(camera).project(np.array([x, y, 0.0]))
        assert np.allclose(expected, [s * x + camera["K"][0][2], -s * y + camera["K"][1][2]])
        assert np.hypot(*(found - expected)) < 0.5
        assert np.hypot(*(found - expected)) < 0.1      # the mapping is exact, not just within half a pixel


# --- (b) the normal map's tangent frame ------------------------------------------------------------------------

@pytest.mark.parametrize("axis", [0, 1], ids=["tilted-towards-+x", "tilted-towards-+y"])
def test_normal_map_normals_are_world_normals(tmp_path, axis):
    """A constant normal tilted 30 deg towards +x (or +y) makes the light from that side brighter than the one
    opposite, each pixel matching (kd / pi)(n.l) E to 1 % (measured 1e-7: the render is noiseless), with an
    RGB irradiance: the map's tangent frame is the plane's x, y, z."""
    camera = mitsuba_relief.orthographic_camera(16, 12, 0.05)
    n = np.zeros(3)
    n[axis], n[2] = np.sin(np.radians(30)), np.cos(np.radians(30))
    normal_map = mitsuba_relief.write_normal_map(tmp_path / "n.exr", np.broadcast_to(n, (12, 16, 3)))
    material = {"kd": KD.tolist(), "ks": 0.0, "eta": 1.5, "alpha": 0.25}
    assert mitsuba_relief.material_bsdf(material)["type"] == "diffuse"
    renderer = mitsuba_relief.Renderer(mitsuba_relief.scene_dict(camera, normal_map,
                                                                 mitsuba_relief.material_bsdf(material), spp=4))
    irradiance = np.array([2.0, 1.0, 0.5])
    seen = {}
    for sign in (1, -1):
        towards = np.zeros(3)
        towards[axis], towards[2] = sign * np.cos(np.radians(45)), np.sin(np.radians(45))
        image = renderer.render(towards, irradiance)
        expected = KD / np.pi * max(n @ towards, 0.0) * irradiance
        assert np.abs(image / expected - 1).max() < 0.01
        seen[sign] = image.mean()
    assert seen[1] > 2.5 * seen[-1]           # cos 15 deg / cos 75 deg = 3.7


def test_texture_rows_are_camera_rows(tmp_path):
    """A normal map tilted towards +x on its top rows only (camera order) tilts the image's top rows: the texture
    is stored bottom row first (a file in camera order would come out upside down, the relief mirrored in y)."""
    W, H = 8, 12
    camera = mitsuba_relief.orthographic_camera(W, H, 0.05)
    normals = np.zeros((H, W, 3)) + [0.0, 0.0, 1.0]
    normals[:3] = [np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))]
    material = {"kd": KD.tolist(), "ks": 0.0, "eta": 1.5, "alpha": 0.25}
    renderer = mitsuba_relief.Renderer(mitsuba_relief.scene_dict(
        camera, mitsuba_relief.write_normal_map(tmp_path / "n.exr", normals), mitsuba_relief.material_bsdf(material),
        spp=1))
    towards = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    image = renderer.render(towards, [1.0, 1.0, 1.0])
    expected = KD / np.pi * np.maximum(normals @ towards, 0)[..., None]
    assert np.abs(image / expected - 1).max() < 1e-3


def test_use_shadowing_function_is_off(tmp_path):
    """Mitsuba's default bump-terminator term (Estevez 2019) would darken tilted normals (by ~1 % at 30 deg):
    the scene switches it off, so the pixel model is plain (n.l)."""
    camera = mitsuba_relief.orthographic_camera(8, 8, 0.05)
    scene = mitsuba_relief.scene_dict(
        camera, mitsuba_relief.write_normal_map(tmp_path / "n.exr", np.zeros((8, 8, 3)) + [0.5, 0, 0.866]),
        mitsuba_relief.material_bsdf({"kd": KD.tolist(), "ks": 0.0, "eta": 1.5, "alpha": 0.25}), spp=1)
    assert scene["sample"]["bsdf"]["use_shadowing_function"] is False


# --- (c) radiometry --------------------------------------------------------------------------------------------

def test_every_pixel_is_eq6_in_its_normal_frame(capture):
    """The flat quadrant (n = +z) equals (kd / pi + GGX specular)(n.l) E (facetsynth.models.microfacet.rho) under every
    light, and so does every tilted pixel in its own normal frame. The render is noiseless (one normal per pixel,
    a delta light, v = +z everywhere) and Mitsuba's isotropic GGX is eq. 6's: measured, relative error at most
    3e-4 (float32; 1e-7 typical) where n.l > 0, absolute 6e-8 everywhere; bounds 1e-3 and 1e-6 (the brief's:
    a few %). The specular term adds 1 % to 7 % of the diffuse on the flat quadrant, more under higher lights."""
    out, rendered = capture
    truth = read_exr(out / rendered["truth"]["normals"])[0]
    normals = np.stack([truth[c] for c in "XYZ"], axis=-1).astype(float)
    material = rendered["provenance"]["material"]
    flat = mitsuba_relief.flat_quadrant(rendered["camera"])
    gain = []
    for frame in rendered["frames"]:
        towards, irradiance = np.array(frame["light"]["direction"]), frame["light"]["intensity"]
        image = read_rgb(out / frame["exposures"][0]["file"])
        model = _model(normals, towards, irradiance, material)
        lit = (normals @ towards) > 0
        assert np.abs(image / np.where(lit[..., None], model, 1) - 1)[lit].max() < 1e-3
        assert np.abs(image - model).max() < 1e-6
        assert (image[~lit] == 0).all()                          # attached shadow: black
        flat_diffuse = np.asarray(material["kd"]) / np.pi * towards[2] * np.asarray(irradiance)
        gain.append((image[flat] / flat_diffuse - 1).mean())
        assert np.abs(image[flat] - model[flat]).max() < 1e-6 and flat.any()
    elevation = np.array([f["light"]["direction"][2] for f in rendered["frames"]])
    assert min(gain) > 0.005 and max(gain) > 0.05                # the specular term is there ...
    assert gain[int(np.argmax(elevation))] == pytest.approx(max(gain))   # ... strongest near the view


# --- (d) the capture -----------------------------------------------------------------------------------------------

def test_capture_manifest_truth_and_frames(capture):
    out, rendered = capture
    loaded = manifest.load(out)                      # schema and meaning, every frame file present
    cam = loaded["camera"]
    W, H = SIZE
    s = W / 0.05
    assert cam["projection"] == "orthographic" and (cam["width"], cam["height"]) == SIZE
    assert np.allclose(cam["K"], [[s, 0, (W - 1) / 2], [0, s, (H - 1) / 2], [0, 0, 1]])
    assert cam["R"] == [[1, 0, 0], [0, -1, 0], [0, 0, -1]] and cam["t"] == [0, 0, 1]
    assert loaded["saturation"] is None and loaded["version"] == 1 and loaded["units"] == "m"
    assert np.allclose([loaded["sample"]["width"], loaded["sample"]["height"]], [0.05, 0.05])
    assert loaded["truth"] == {"normals": "truth/normals.exr", "kd": "truth/kd.exr"}
    assert {"renderer", "bsdf", "spp", "material"} <= set(loaded["provenance"])
    assert loaded["provenance"]["renderer"].startswith("Mitsuba 3")
    assert len(loaded["frames"]) == LIGHTS
    directions = np.array([f["light"]["direction"] for f in loaded["frames"]])
    assert np.allclose(np.linalg.norm(directions, axis=1), 1)
    elevations = np.degrees(np.arcsin(directions[:, 2]))
    assert elevations.min() == pytest.approx(15) and elevations.max() == pytest.approx(75)
    assert len(np.unique(np.round(directions, 6), axis=0)) == LIGHTS
    for f in loaded["frames"]:
        assert f["light"]["intensity"] == [1.0, 1.0, 1.0]
        assert f["exposures"] == [{"file": str(out.resolve() / f"frames/{loaded['frames'].index(f):04d}.exr"),
                                   "time": 1.0}]
        image = read_rgb(f["exposures"][0]["file"])
        assert image.shape == (H, W, 3) and np.isfinite(image).all() and image.max() > 0
    truth = read_exr(out / "truth/normals.exr")[0]
    n = np.stack([truth[c] for c in "XYZ"], axis=-1)
    assert n.shape == (H, W, 3) and np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-6)
    flat = mitsuba_relief.flat_quadrant(cam)
    assert flat.mean() == 0.25 and (n[flat] == [0, 0, 1]).all()           # the flat quadrant: exactly +z
    tilt = np.degrees(np.arccos(n[..., 2]))
    assert 30 <= tilt.max() <= 35 and (tilt[~flat] > 1).mean() > 0.3       # a relief, up to ~33 deg
    kd = read_rgb(out / "truth/kd.exr")
    assert np.allclose(kd, mitsuba_relief.DEFAULT_MATERIAL["kd"])


def test_relief_is_deterministic_and_the_map_orientation_is_the_image():
    """The relief depends on the seed only; row 0 of the normal map is the image's top row (world +y)."""
    camera = mitsuba_relief.orthographic_camera(32, 32, 0.05)
    a, b, c = (mitsuba_relief.relief_normals(camera, 0), mitsuba_relief.relief_normals(camera, 0),
               mitsuba_relief.relief_normals(camera, 1))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    xy = mitsuba_relief.pixel_points(camera)
    assert xy[0, 0, 1] > 0 > xy[-1, 0, 1] and xy[0, 0, 0] < 0 < xy[0, -1, 0]
    assert (a[mitsuba_relief.flat_quadrant(camera)] == [0, 0, 1]).all()


def test_dome_directions():
    for count in (1, 5, 24, 48, 100):
        d = mitsuba_relief.dome_directions(count)
        assert d.shape == (count, 3) and np.allclose(np.linalg.norm(d, axis=1), 1) and (d[:, 2] > 0).all()
    d = mitsuba_relief.dome_directions(48)
    elevation = np.degrees(np.arcsin(d[:, 2]))
    assert len(np.unique(elevation.round(6))) == 4 and elevation.min() == pytest.approx(15)
    assert np.array_equal(d, mitsuba_relief.dome_directions(48))
    with pytest.raises(ValueError):
        mitsuba_relief.dome_directions(0)


def test_per_light_rgb_factors_and_kd_map(tmp_path):
    """Per-light irradiance factors and a spatially varying kd scale the flat quadrant's diffuse radiance."""
    W = H = 16
    kd = np.zeros((H, W, 3)) + [0.5, 0.3, 0.2]
    kd[:, : W // 4] *= 0.5                                  # a darker band on the left (in the flat quadrant)
    rgb = np.array([[1.0, 0.5, 2.0], [0.25, 1.0, 1.0]])
    material = {"kd": [0.5, 0.3, 0.2], "ks": 0.0, "eta": 1.5, "alpha": 0.25}
    made = mitsuba_relief.render_relief(tmp_path / "c", (W, H), 2, 2, material=material, kd=kd, light_rgb=rgb)
    assert np.allclose(read_rgb(tmp_path / "c/truth/kd.exr"), kd)
    flat = mitsuba_relief.flat_quadrant(made["camera"])
    for q, frame in enumerate(made["frames"]):
        assert frame["light"]["intensity"] == rgb[q].tolist()
        image = read_rgb(tmp_path / "c" / frame["exposures"][0]["file"])
        expected = kd / np.pi * frame["light"]["direction"][2] * rgb[q]
        assert np.allclose(image[flat], expected[flat], rtol=1e-3)


def test_cli(tmp_path):
    assert mitsuba_relief.main([str(tmp_path / "cli"), "--size", "12", "--lights", "3", "--spp", "1", "--width", "0.02",
                                "--seed", "2"]) == 0
    loaded = manifest.load(tmp_path / "cli")
    assert len(loaded["frames"]) == 3 and loaded["camera"]["K"][0][0] == pytest.approx(12 / 0.02)
    assert loaded["provenance"]["seed"] == 2
