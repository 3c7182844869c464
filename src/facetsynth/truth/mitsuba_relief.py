"""A ground-truth capture for shading normals: a normal-mapped relief under an RTI light dome, rendered by Mitsuba 3.

The geometry of a reflectance-transformation-imaging (RTI) dome: a distant camera looking straight down (an
``orthographic`` sensor) and ``N`` distant lights (``directional`` emitters) on rings of elevation over the
sample. The sample is the plane z = 0 of ``width`` x ``height`` metres, centred at the origin, whose shading
normals come from a normal map (Mitsuba's ``normalmap`` BSDF): a smooth relief of bumps, dimples and ridges
of a height field h(x, y), normals n = normalize(-dh/dx, -dh/dy, 1), tilts up to ``max_tilt`` (33 deg), and
one quadrant (x < 0, y < 0: the bottom left of the image) exactly flat, n = +z. The capture is written as a
foreign capture (as :mod:`facetsynth.truth.mitsuba_capture` does): HDR EXR frames (R, G, B; one exposure of time 1.0,
never clipped, ``"saturation": null``), ``manifest.json``, and the truth: ``truth/normals.exr`` (channels X,
Y, Z: the unit normal of each camera pixel) and ``truth/kd.exr`` (R, G, B: the diffuse albedo kd).

Conventions, checked in ``tests/truth/test_mitsuba_relief.py``:

* camera (manifest): ``"projection": "orthographic"``, OpenCV axes (``X_cam = R X + t``, x right, y down, z
  forward), (col, row, 1) = K (X_cam_x, X_cam_y, 1). Top down: R = diag(1, -1, -1), t = (0, 0, 1), K =
  [[s, 0, (W-1)/2], [0, s, (H-1)/2], [0, 0, 1]], s = W / width pixels per metre, so col = s x + (W-1)/2,
  row = -s y + (H-1)/2: pixel (0, 0) is the centre of the top-left pixel, image right = world +x, image up =
  world +y, and the W x H image covers the sample exactly (height = H / s).
* camera (Mitsuba): an ``orthographic`` sensor, whose ``to_world`` maps its camera space (x left, y up, z
  forward; the film spans x in [-1, 1], y in [-H/W, H/W]) to the world: columns -(W / 2 s) r1,
  -(W / 2 s) r2, r3 and the film centre's world point (r1, r2, r3 the rows of R), for any R and principal
  point (square pixels only; tested top down). Measured: a small emissive disc lands where K puts it, within
  0.05 px (sampling noise; bound 0.5 px), for a non-square image and an off-centre principal point too.
* normal map: one texel per camera pixel (``filter_type`` nearest, so every pixel sees one normal: the truth
  of that pixel), tangent-space normals encoded (n + 1) / 2 in a float32 EXR read with ``raw``, stored bottom
  row first (:func:`write_texture`: Mitsuba's ``bitmap`` puts the file's row 0 at v = 0, the rectangle's
  v = 0 is y = -height / 2; a map in camera order would come out upside down). The plane is a Mitsuba
  ``rectangle`` (normal +z) whose dp/du is +x, so the tangent frame is (x, y, z) and the map's normals are
  world normals (measured: a map tilted towards +x or +y is brightest under a light from that side, each
  pixel (kd / pi)(n.l) E to 3e-7).
  ``use_shadowing_function`` is off: Mitsuba's default multiplies by the bump-terminator shadowing term of
  Estevez et al. 2019 (about 1 % darker at a 30 deg tilt), which is not the pixel model.
* lights: directional, ``direction`` in the manifest is the unit vector towards the light (z > 0), Mitsuba's
  ``direction`` its opposite; ``intensity`` = Mitsuba's ``irradiance`` (W/m^2 at normal incidence), RGB,
  white (1, 1, 1) unless per-light factors are given. The dome (:func:`dome_directions`) is deterministic.
* pixel model: I = rho(l, v) (n.l) E with v = +z (the orthographic camera), n the mapped normal, no
  interreflection (integrator ``direct``), ``box`` pixel filter, ``hdrfilm`` float32 RGB. rho is
  :func:`facetsynth.models.microfacet.rho` (eq. 6, isotropic GGX, dielectric Fresnel, uncorrelated Smith
  shadowing) with kd, ks, eta, alpha of the material: Mitsuba's ``blendbsdf`` of a ``diffuse`` and a
  k = 0 ``roughconductor`` (as in tests/truth/test_mitsuba_capture.py). Lights below the tangent plane of a
  pixel's normal (n.l <= 0) leave it black (attached shadow); there are no cast shadows (normal mapping).

Mitsuba is imported inside the functions: the pipeline never needs it.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..capture import manifest
from ..io.fileio import atomic_dir, write_exr
from .mitsuba_capture import mitsuba

log = logging.getLogger(__name__)

DEFAULT_MATERIAL: dict[str, Any] = {"kd": [0.55, 0.45, 0.35], "ks": 0.3, "eta": 1.5, "alpha": 0.25}
"""The relief's material: eq. 6 (:func:`facetsynth.models.microfacet.rho`), isotropic GGX of roughness alpha."""

MAX_TILT = 33.0          # degrees: the steepest normal of the relief
ELEVATIONS = (15.0, 75.0)  # degrees: the lowest and the highest ring of the dome
TOP_DOWN_R = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]


# --- the camera ------------------------------------------------------------------------------------------------

def orthographic_camera(width_px: int, height_px: int, sample_width: float) -> dict[str, Any]:
    """The manifest camera looking straight down at a sample ``sample_width`` metres wide that fills the
    ``width_px`` x ``height_px`` image (s = width_px / sample_width pixels per metre)."""
    s = width_px / float(sample_width)
    return {"projection": "orthographic", "width": int(width_px), "height": int(height_px),
            "K": [[s, 0.0, (width_px - 1) / 2.0], [0.0, s, (height_px - 1) / 2.0], [0.0, 0.0, 1.0]],
            "R": [row[:] for row in TOP_DOWN_R], "t": [0.0, 0.0, 1.0]}


def pixel_points(camera: dict[str, Any]) -> np.ndarray:
    """(H, W, 2) world (x, y) on the plane z = 0 of every pixel centre of a top-down orthographic camera."""
    K = np.asarray(camera["K"], float)
    rows, cols = np.mgrid[0:camera["height"], 0:camera["width"]].astype(float)
    return np.stack([(cols - K[0, 2]) / K[0, 0], -(rows - K[1, 2]) / K[1, 1]], axis=-1)


def sensor_dict(camera: dict[str, Any], spp: int = 16, seed: int = 0) -> dict[str, Any]:
    """A Mitsuba ``orthographic`` sensor imaging the world as the orthographic manifest ``camera`` does."""
    mi = mitsuba()
    K, R, t = (np.asarray(camera[k], float) for k in ("K", "R", "t"))
    s, W, H = K[0, 0], camera["width"], camera["height"]
    if abs(K[1, 1] - s) > 1e-9 * s or abs(K[0, 1]) > 1e-12:
        raise ValueError(f"an orthographic sensor here has square pixels and no skew: K {K.tolist()}")
    centre = -R.T @ t
    # Mitsuba camera space: x left, y up; the film's x spans [-1, 1] (W pixels), y [-H/W, H/W] (H pixels)
    film_centre = R[0] * ((W - 1) / 2 - K[0, 2]) / s + R[1] * ((H - 1) / 2 - K[1, 2]) / s + centre
    to_world = np.eye(4)
    to_world[:3, 0], to_world[:3, 1], to_world[:3, 2] = -W / (2 * s) * R[0], -W / (2 * s) * R[1], R[2]
    to_world[:3, 3] = film_centre
    return {
        "type": "orthographic",
        "near_clip": 1e-3,
        "far_clip": 1e3,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        "film": {"type": "hdrfilm", "width": int(W), "height": int(H), "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
    }


# --- the relief ------------------------------------------------------------------------------------------------

def relief_features(width: float, height: float, seed: int = 0, count: int = 10) -> list[dict[str, Any]]:
    """``count`` elliptical features (bumps, dimples, ridges) of h, drawn from ``seed``: centre (x, y), semi-axes
    a >= b (metres), azimuth of a (radians), relative amplitude. Each lies off the flat quadrant x < 0, y < 0."""
    rng = np.random.default_rng(seed)
    size = min(width, height)
    features: list[dict[str, Any]] = []
    while len(features) < count:
        x, y = rng.uniform(-width / 2, width / 2), rng.uniform(-height / 2, height / 2)
        room = _distance_to_flat(x, y)
        ridge = len(features) % 3 == 2
        a = min(room, rng.uniform(0.3, 0.5) * size if ridge else rng.uniform(0.12, 0.25) * size)
        if a < 0.08 * size:
            continue
        b = max(a * (rng.uniform(0.15, 0.3) if ridge else rng.uniform(0.6, 1.0)), 0.05 * size)
        features.append({"centre": [float(x), float(y)], "a": float(a), "b": float(b),
                         "azimuth": float(rng.uniform(0, np.pi)),
                         "amplitude": float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0))})
    return features


def _distance_to_flat(x: float, y: float) -> float:
    """Distance from (x, y) to the flat quadrant x < 0, y < 0."""
    return float(np.hypot(max(x, 0.0), max(y, 0.0)))


def height_gradient(xy: np.ndarray, features: list[dict[str, Any]]) -> np.ndarray:
    """(..., 2) dh/dx, dh/dy of h = sum of A b (1 - q)^2 over q < 1, q = (d.e1 / a)^2 + (d.e2 / b)^2 (d the offset
    from a feature's centre, e1 its azimuth): smooth (C1), zero outside each ellipse (so on the flat quadrant)."""
    grad = np.zeros(xy.shape[:-1] + (2,))
    for f in features:
        c, s = np.cos(f["azimuth"]), np.sin(f["azimuth"])
        d = xy - np.asarray(f["centre"])
        p, r = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
        q = (p / f["a"]) ** 2 + (r / f["b"]) ** 2
        # dh/dq = -2 A b (1 - q); dq/dp = 2 p / a^2, dq/dr = 2 r / b^2
        k = np.where(q < 1.0, -2.0 * f["amplitude"] * f["b"] * (1.0 - q), 0.0)
        gp, gr = k * 2 * p / f["a"] ** 2, k * 2 * r / f["b"] ** 2
        grad[..., 0] += gp * c - gr * s
        grad[..., 1] += gp * s + gr * c
    return grad


def relief_normals(camera: dict[str, Any], seed: int = 0, max_tilt: float = MAX_TILT) -> np.ndarray:
    """(H, W, 3) unit normals at the pixel centres of the top-down ``camera``: normalize(-dh/dx, -dh/dy, 1) of the
    relief of ``seed``, scaled so that the steepest is ``max_tilt`` degrees; exactly +z where h is flat."""
    xy = pixel_points(camera)
    W, H = camera["width"], camera["height"]
    s = camera["K"][0][0]
    grad = height_gradient(xy, relief_features(W / s, H / s, seed))
    steepest = float(np.hypot(grad[..., 0], grad[..., 1]).max())
    if steepest > 0:
        grad *= np.tan(np.radians(max_tilt)) / steepest
    n = np.concatenate([-grad, np.ones(grad.shape[:-1] + (1,))], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def flat_quadrant(camera: dict[str, Any]) -> np.ndarray:
    """(H, W) True on the pixels of the flat quadrant x < 0, y < 0 (normal exactly +z)."""
    xy = pixel_points(camera)
    return (xy[..., 0] < 0) & (xy[..., 1] < 0)


# --- the lights --------------------------------------------------------------------------------------------------

def dome_directions(count: int = 48, elevations: tuple[float, float] = ELEVATIONS) -> np.ndarray:
    """(count, 3) unit directions towards ``count`` lights on rings of elevation evenly spaced from
    ``elevations[0]`` to ``elevations[1]`` degrees (round(sqrt(count / 3)) rings), the lights shared among the
    rings in proportion to cos(elevation) (the ring's circumference), evenly spaced in azimuth on each ring,
    each ring turned by the golden angle from the one below. Deterministic."""
    if count < 1:
        raise ValueError(f"a dome needs at least one light, not {count}")
    rings = max(1, min(count, int(round(np.sqrt(count / 3.0)))))
    elev = np.radians(np.linspace(elevations[0], elevations[1], rings) if rings > 1 else [np.mean(elevations)])
    share = np.cos(elev) / np.cos(elev).sum() * count
    per_ring = np.maximum(1, np.floor(share).astype(int))
    while per_ring.sum() < count:                     # largest remainder
        per_ring[np.argmax(share - per_ring)] += 1
    while per_ring.sum() > count:
        per_ring[np.argmax(per_ring - share)] -= 1
    golden = np.pi * (3.0 - np.sqrt(5.0))
    out = []
    for k, (e, m) in enumerate(zip(elev, per_ring)):
        phi = k * golden + 2 * np.pi * np.arange(m) / m
        out.append(np.stack([np.cos(e) * np.cos(phi), np.cos(e) * np.sin(phi), np.full(m, np.sin(e))], axis=-1))
    return np.concatenate(out)


# --- the material and the scene -------------------------------------------------------------------------------------

def material_bsdf(material: dict[str, Any], kd_file: str | Path | None = None) -> dict[str, Any]:
    """eq. 6 as Mitsuba BSDFs: ``blendbsdf`` (1 - w) ``diffuse`` (kd / (1 - w)) + w ``roughconductor`` (GGX alpha,
    eta, k = 0, ks / w), w between ks and 1 - max kd (each part's reflectance <= 1). ``kd_file``: an EXR of kd
    (R, G, B; a texel per pixel) instead of the constant ``material['kd']``, whose largest value it must hold."""
    ks, w = float(material["ks"]), blend_weight(material)
    if kd_file is None:
        reflectance = {"type": "rgb", "value": (np.asarray(material["kd"], float) / (1 - w)).tolist()}
    else:
        reflectance = {"type": "bitmap", "filename": str(Path(kd_file).resolve()), "raw": True,
                       "filter_type": "nearest", "wrap_mode": "clamp"}
    diffuse = {"type": "diffuse", "reflectance": reflectance}
    if w == 0.0:
        return diffuse
    return {"type": "blendbsdf", "weight": w, "bsdf_0": diffuse,
            "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha": float(material["alpha"]),
                       "eta": float(material["eta"]), "k": 0.0,
                       "specular_reflectance": {"type": "rgb", "value": [ks / w] * 3}}}


def blend_weight(material: dict[str, Any]) -> float:
    """The ``blendbsdf`` weight w of :func:`material_bsdf`, halfway between ks and 1 - max kd (a kd texture
    must hold kd / (1 - w)); ValueError if max kd + ks > 1."""
    kd_max, ks = float(np.max(material["kd"])), float(material["ks"])
    if not (kd_max >= 0 and ks >= 0 and kd_max + ks <= 1):
        raise ValueError(f"kd and ks must be >= 0 with max kd + ks <= 1 (energy): max kd {kd_max}, ks {ks}")
    return ks + (1.0 - kd_max - ks) / 2 if ks > 0 else 0.0


def write_texture(path: str | Path, image: np.ndarray) -> Path:
    """An (H, W, 3) image in camera order (row 0 at the top, world +y) as a float32 EXR (R, G, B) texture of the
    sample rectangle, each texel on its pixel: stored bottom row first, as the rectangle's v = 0 is at
    y = -height / 2 and Mitsuba's ``bitmap`` puts the file's row 0 at v = 0 (measured:
    tests/truth/test_mitsuba_relief.py)."""
    write_exr(path, {"RGB": np.ascontiguousarray(np.asarray(image, float)[::-1]).astype(np.float32)})
    return Path(path)


def write_normal_map(path: str | Path, normals: np.ndarray) -> Path:
    """Unit normals (H, W, 3), camera order, as Mitsuba's tangent-space normal map: (n + 1) / 2, float32 EXR."""
    return write_texture(path, (np.asarray(normals, float) + 1.0) / 2.0)


def scene_dict(camera: dict[str, Any], normal_map: str | Path, bsdf: dict[str, Any], spp: int = 16,
               seed: int = 0, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The Mitsuba scene: the sample rectangle with ``bsdf`` under the normal map, one directional light (set
    per frame by :meth:`Renderer.render`), the orthographic sensor, the ``direct`` integrator; ``extra`` adds
    or replaces entries."""
    mi = mitsuba()
    s = camera["K"][0][0]
    width, height = camera["width"] / s, camera["height"] / s
    scene = {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},   # a delta light: only
        "sensor": sensor_dict(camera, spp, seed),                                    # light sampling finds it
        "sample": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([width / 2, height / 2, 1.0]),
                   "bsdf": {"type": "normalmap", "use_shadowing_function": False, "flip_invalid_normals": True,
                            "normalmap": {"type": "bitmap", "filename": str(Path(normal_map).resolve()),
                                          "raw": True, "filter_type": "nearest", "wrap_mode": "clamp"},
                            "bsdf": bsdf}},
        "light": {"type": "directional", "direction": [0.0, 0.0, -1.0],
                  "irradiance": {"type": "rgb", "value": [1.0] * 3}},
    }
    scene.update(extra or {})
    return scene


class Renderer:
    """A loaded Mitsuba scene whose directional light is turned and set per frame."""

    def __init__(self, scene: dict[str, Any]):
        mi = mitsuba()
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)

    def render(self, direction, irradiance, seed: int = 0) -> np.ndarray:
        """(H, W, 3) float32 radiance of the frame lit from unit ``direction`` (towards the light) with RGB
        ``irradiance`` at normal incidence."""
        mi = mitsuba()
        towards = np.asarray(direction, float)
        towards = towards / np.linalg.norm(towards)
        up = [0.0, 0.0, 1.0] if abs(towards[2]) < 0.9 else [1.0, 0.0, 0.0]
        # the emitter's direction of travel, -towards, is its to_world's local +z
        self.params["light.to_world"] = mi.ScalarTransform4f().look_at(
            origin=[0.0, 0.0, 0.0], target=(-towards).tolist(), up=up)
        self.params["light.irradiance.value"] = mi.ScalarColor3f([float(v) for v in irradiance])
        self.params.update()
        return np.array(mi.render(self.scene, seed=int(seed)), dtype=np.float32)[..., :3]


# --- the capture ---------------------------------------------------------------------------------------------------

def render_relief(out_dir: str | Path, size: tuple[int, int] = (128, 128), lights: int = 48, spp: int = 16,
                  sample_width: float = 0.05, seed: int = 0, material: dict[str, Any] | None = None,
                  kd: np.ndarray | None = None, light_rgb: np.ndarray | None = None,
                  max_tilt: float = MAX_TILT) -> dict[str, Any]:
    """Render the relief of ``seed`` (``size`` = (W, H) pixels, ``sample_width`` metres wide, the image filling
    the sample) under a dome of ``lights`` directional lights into ``out_dir``: ``frames/NNNN.exr``,
    ``truth/normals.exr`` (X, Y, Z), ``truth/kd.exr`` (R, G, B) and ``manifest.json``, atomically. ``material``:
    kd, ks, eta, alpha (default :data:`DEFAULT_MATERIAL`); ``kd``: an (H, W, 3) albedo map instead of the
    constant; ``light_rgb``: (lights, 3) irradiance factors (default white, 1). Returns the manifest."""
    mi = mitsuba()
    material = dict(DEFAULT_MATERIAL if material is None else material)
    W, H = int(size[0]), int(size[1])
    camera = orthographic_camera(W, H, sample_width)
    normals = relief_normals(camera, seed, max_tilt)
    kd_map = np.broadcast_to(np.asarray(material["kd"] if kd is None else kd, float), (H, W, 3))
    if kd is not None:
        material["kd"] = float(kd_map.max())       # the blend weight must leave room for the largest kd
    directions = dome_directions(lights)
    irradiance = np.ones((lights, 3)) if light_rgb is None else np.broadcast_to(np.asarray(light_rgb, float),
                                                                                 (lights, 3))
    out_dir = Path(out_dir)
    with tempfile.TemporaryDirectory() as tmp, atomic_dir(out_dir) as staging:
        normal_map = write_normal_map(Path(tmp) / "normalmap.exr", normals)
        kd_file = None
        if kd is not None:
            kd_file = Path(tmp) / "kd.exr"
            write_texture(kd_file, kd_map / (1 - blend_weight(material)))
        bsdf = material_bsdf(material, kd_file)
        renderer = Renderer(scene_dict(camera, normal_map, bsdf, spp, seed))
        (staging / "frames").mkdir()
        (staging / "truth").mkdir()
        write_exr(staging / "truth/normals.exr", {c: normals[..., i].astype(np.float32) for i, c in enumerate("XYZ")})
        write_exr(staging / "truth/kd.exr", {"RGB": kd_map.astype(np.float32)})
        frames = []
        start = time.perf_counter()
        for q, (direction, rgb) in enumerate(zip(directions, irradiance)):
            image = renderer.render(direction, rgb, seed=seed * 100003 + q)
            name = f"frames/{q:04d}.exr"
            write_exr(staging / name, {"RGB": image}, {"exposure_time": 1.0, "renderer": f"Mitsuba {mi.__version__}"})
            frames.append({"light": {"direction": direction.tolist(), "intensity": rgb.tolist()},
                           "exposures": [{"file": name, "time": 1.0}]})
        seconds = time.perf_counter() - start
        capture = {
            "version": 1, "units": "m",
            "sample": {"width": W / camera["K"][0][0], "height": H / camera["K"][0][0]},
            "camera": camera,
            "saturation": None,   # HDR radiance, never clipped
            "frames": frames,
            "truth": {"normals": "truth/normals.exr", "kd": "truth/kd.exr"},
            "provenance": {
                "renderer": f"Mitsuba {mi.__version__} ({mi.variant()})",
                "integrator": "direct (one bounce), box pixel filter, float32 hdrfilm, orthographic sensor",
                "spp": int(spp), "seed": int(seed), "material": material if kd is None else
                {**material, "kd": "truth/kd.exr"},
                "bsdf": _portable(bsdf), "normal_map": "normalmap (use_shadowing_function false), a texel a pixel, "
                                                         "nearest filter",
                "relief": {"seed": int(seed), "max_tilt_deg": float(max_tilt), "flat": "x < 0 and y < 0",
                           "features": relief_features(W / camera["K"][0][0], H / camera["K"][0][0], seed)},
                "lights": int(lights), "seconds": seconds,
                "frames_per_second": lights / seconds if seconds > 0 else None,
                "note": "HDR radiance, never clipped (saturation null); pixel model I = rho (n.l) E, "
                        "rho = kd/pi + GGX eq. 6 (facetsynth.models.microfacet.rho), v = +z",
            },
        }
        manifest.save(staging / "manifest.json", capture)   # validates: schema and meaning
    log.info("Mitsuba relief %s: %d frames, %.2f s (%.2f frames/s)", out_dir, lights, seconds,
             lights / max(seconds, 1e-9))
    return capture


def _portable(bsdf: dict[str, Any]) -> dict[str, Any]:
    """The BSDF dict with temporary file names replaced by what they held."""
    out = {}
    for k, v in bsdf.items():
        if isinstance(v, dict):
            out[k] = _portable(v)
        elif k == "filename":
            out[k] = "kd / (1 - weight) of truth/kd.exr"
        else:
            out[k] = v
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m facetsynth.truth.mitsuba_relief",
        description="Render a normal-mapped relief under an RTI dome of directional lights, seen by a top-down "
                    "orthographic camera, with Mitsuba 3 (scalar_rgb): a capture folder (manifest.json, HDR EXR "
                    "frames) with its true normals (truth/normals.exr) and albedo (truth/kd.exr).")
    parser.add_argument("out_dir", help="capture folder to write")
    parser.add_argument("--size", type=int, default=128, help="image width and height in pixels (default 128)")
    parser.add_argument("--lights", type=int, default=48, help="directional lights of the dome (default 48)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    parser.add_argument("--width", type=float, default=0.05, help="sample width (and height) in metres (default 0.05)")
    parser.add_argument("--seed", type=int, default=0, help="relief layout and sampler seed (default 0)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    made = render_relief(args.out_dir, (args.size, args.size), args.lights, args.spp, args.width, args.seed)
    p = made["provenance"]
    print(f"{args.out_dir}: {len(made['frames'])} HDR frames, truth/normals.exr, truth/kd.exr and manifest.json "
          f"({p['renderer']}, {p['seconds']:.1f} s, {p['frames_per_second']:.2f} frames/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
