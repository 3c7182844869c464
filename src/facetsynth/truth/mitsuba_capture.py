"""A capture rendered by another renderer: Mitsuba 3 (``scalar_rgb``) through the capture manifest.

The project's own virtual rig renders with the project's own model
(:mod:`facetsynth.models.render`, :mod:`facetsynth.models.microfacet`); a fit checked only
on such data can share that model's mistakes. This module renders a flat
sample with Mitsuba 3 instead, on the geometry of a rig description
(``rig/descriptions/*.yaml``: the rig's camera, LED positions, LED
intensities and scan, through :class:`facetsynth.truth.virtual_rig.VirtualRig`),
and writes it as a *foreign* capture: HDR EXR frames (one exposure of time
1.0, never clipped, so the manifest states ``"saturation": null``) and a
``manifest.json`` valid against the published schema, with a ``provenance``
field naming the renderer, its version and the BSDF. Import it with a
sample-sheet row ``NAME  import  DIR``; render a held-out view with
``--view THETA PHI`` and check the fit with ``facetsynth predict``.

Conventions, checked in ``tests/truth/test_mitsuba_capture.py``:

* camera: the manifest's OpenCV camera (``X_cam = R X + t``, x right, y down,
  z forward) is a Mitsuba ``perspective`` sensor whose ``to_world`` has
  columns (-r1, -r2, r3, C) (Mitsuba's camera frame is x left, y up, z
  forward; rows r1, r2, r3 of R; C the camera centre), ``fov`` the horizontal
  field of view 2 atan(W / (2 fx)), the principal point offset relative to
  the film centre (OpenCV pixel (0, 0) is the centre of the top-left pixel,
  Mitsuba's film coordinate (0.5, 0.5)). Square pixels only (fx = fy).
* light: a Mitsuba ``point`` emitter's ``intensity`` is radiant intensity
  (per steradian), so its radiance is rho (n.i) L / |P - x|^2: the pixel
  model of DESIGN.md sec. 4 with L the LED's RGB intensity.
* integrator ``direct`` (one bounce: the pixel model has no
  interreflection), ``box`` reconstruction filter (each pixel is the average
  radiance over its footprint, as a sensor integrates), ``hdrfilm`` float32 RGB.
* sample: the plane z = 0 of the manifest's width x height, a triangle mesh
  whose texture coordinates set the tangent frame per cell (the BSDF's u axis
  at azimuth ``frame``: a fixed angle, or ``"turned"``, along circles about the
  centre like the demo's lathe-turned disc), and black registration discs
  (the demo's four markers) 10 micrometres above the plane: below Mitsuba's
  shadow-ray offset, so they cast no shadow.
* regions: instead of one BSDF, a list of rectangles each with its own BSDF
  (``{"name", "rect": [[x0, x1], [y0, y1]], "bsdf"}``), one mesh per region
  clipped to the sample; :func:`scene_regions` reads them from a virtual rig
  scene of ``rect`` regions with ``measured`` RGL files
  (``resources/scenes/rgl-quadrants.yaml``), each a Mitsuba ``measured``
  BSDF. Mitsuba's ``measured`` puts the camera (``si.wi``) in the file's
  incident slot, the virtual rig the light (docs/decisions.md, "Argument
  order"): the same file, rendered by both, differs by the file's
  non-reciprocity (measured: 0.7-22 % relative L1 per quadrant and frame,
  at most 0.5 % with the slots swapped).

Mitsuba is imported inside the functions: the pipeline never needs it.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..capture import manifest
from ..geometry.camera import Camera
from ..io.fileio import atomic_dir, write_exr
from .virtual_rig import VirtualRig

log = logging.getLogger(__name__)

VARIANT = "scalar_rgb"
DEMO_MARKERS = {"radius": 0.0025, "positions": [[-0.042, -0.042], [0.042, -0.042], [-0.042, 0.042], [0.042, 0.042]]}
MARKER_LIFT = 1e-5          # metres above the plane: below Mitsuba's ray offset (~9e-5 m here), so no shadow

# The default material (README, tests/truth/test_mitsuba_capture.py): anisotropic GGX (alpha_u 0.15, alpha_v 0.35)
# as Mitsuba's rough copper conductor: its complex-index Fresnel term (eq. 6 has a dielectric one), no diffuse.
EXAMPLE_BSDF = {"type": "roughconductor", "distribution": "ggx", "material": "Cu", "alpha_u": 0.15, "alpha_v": 0.35}


def mitsuba(variant: str = VARIANT):
    """The ``mitsuba`` module with ``variant`` set (ImportError with the remedy if it is not installed)."""
    try:
        import mitsuba as mi
    except ImportError as exc:   # pragma: no cover - exercised only without mitsuba
        raise ImportError("facetsynth.truth.mitsuba_capture needs Mitsuba 3: pip install mitsuba") from exc
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def sensor_dict(camera: Camera, spp: int = 16, seed: int = 0) -> dict[str, Any]:
    """A Mitsuba ``perspective`` sensor with the pose and intrinsics of ``camera`` (OpenCV convention)."""
    mi = mitsuba()
    if camera.has_distortion:
        raise ValueError("a Mitsuba perspective sensor has no lens distortion; use an undistorted camera")
    K = np.asarray(camera.K, float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx - fy) > 1e-9 * fx or abs(K[0, 1]) > 1e-12:
        raise ValueError(f"Mitsuba's perspective sensor has square pixels and no skew: fx {fx}, fy {fy}, "
                         f"skew {K[0, 1]}")
    W, H = camera.width, camera.height
    to_world = np.eye(4)
    to_world[:3, 0], to_world[:3, 1], to_world[:3, 2] = -camera.R[0], -camera.R[1], camera.R[2]
    to_world[:3, 3] = camera.centre
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": float(np.degrees(2.0 * np.arctan(W / (2.0 * fx)))),
        # OpenCV pixel centre (cx, cy) is Mitsuba film coordinate (cx + 0.5, cy + 0.5); Mitsuba's offsets are
        # film fractions along its camera axes x left, y up (measured: tests/truth/test_mitsuba_capture.py)
        "principal_point_offset_x": float(-(cx + 0.5 - W / 2) / W),
        "principal_point_offset_y": float(-(cy + 0.5 - H / 2) / H),
        "near_clip": 1e-3,
        "far_clip": 1e3,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
    }


TILES = 4          # frame "tiles": 4 x 4 tiles, tile k = 4 row + col turned by k x 11.25 deg (ggx-tiles' layout)


def frame_azimuth(xy: np.ndarray, frame: str | float, size: tuple[float, float] = (0.10, 0.10)) -> np.ndarray:
    """Azimuth (radians) of the BSDF's u axis at sample points (..., 2): a fixed angle in degrees,
    ``"turned"``: along circles about the centre (the polar angle + 90 deg, the demo's lathe-turned disc), or
    ``"tiles"``: TILES x TILES tiles of the ``size`` sample, tile k (row from -y, column from -x) turned by
    k x 180 / TILES^2 deg, as resources/scenes/ggx-tiles.yaml."""
    if frame == "turned":
        return np.arctan2(xy[..., 1], xy[..., 0]) + np.pi / 2
    if frame == "tiles":
        col = np.clip(np.floor((xy[..., 0] / size[0] + 0.5) * TILES), 0, TILES - 1)
        row = np.clip(np.floor((xy[..., 1] / size[1] + 0.5) * TILES), 0, TILES - 1)
        return (row * TILES + col) * np.pi / TILES**2
    return np.full(xy.shape[:-1], np.radians(float(frame)))


def write_plane_mesh(path: str | Path, width: float, height: float, frame: str | float = 0.0,
                     cells: int = 64, rect: Any = None) -> Path:
    """The sample plane (z = 0, centred, normal +z) as a PLY triangle mesh whose texture coordinates set
    the tangent frame: in each of ``cells`` x ``cells`` quads, (u, v) = (x, y) turned by minus the frame
    azimuth at the quad's centre, so Mitsuba's dp/du (the BSDF's u axis) points along that azimuth.
    ``rect`` ((x0, x1), (y0, y1)): only that part of the sample (clipped to it; the frame still that of the
    whole sample: "tiles" is exact on a rect of whole tiles)."""
    mi = mitsuba()
    n = {"turned": int(cells), "tiles": TILES}.get(frame, 1) if isinstance(frame, str) else 1
    (x0, x1), (y0, y1) = _clipped(rect, width, height)
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    corners = []
    for j in range(n):
        for i in range(n):
            a, b, c, d = (xs[i], ys[j]), (xs[i + 1], ys[j]), (xs[i + 1], ys[j + 1]), (xs[i], ys[j + 1])
            corners += [a, b, c, a, c, d]                     # counter-clockwise seen from +z: normal +z
    xy = np.asarray(corners, float)                           # (6 n^2, 2), three vertices per triangle
    centres = xy.reshape(-1, 6, 2).mean(axis=1).repeat(6, axis=0)
    phi = frame_azimuth(centres, frame, (width, height))
    uv = np.stack([np.cos(phi) * xy[:, 0] + np.sin(phi) * xy[:, 1],
                   -np.sin(phi) * xy[:, 0] + np.cos(phi) * xy[:, 1]], axis=-1)
    mesh = mi.Mesh("sample", len(xy), len(xy) // 3, has_vertex_normals=False, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    positions = np.concatenate([xy, np.zeros((len(xy), 1))], axis=-1)
    params["vertex_positions"] = type(params["vertex_positions"])(positions.ravel().astype(np.float32))
    params["faces"] = type(params["faces"])(np.arange(len(xy), dtype=np.uint32))
    params["vertex_texcoords"] = type(params["vertex_texcoords"])(uv.ravel().astype(np.float32))
    params.update()
    path = Path(path)
    mesh.write_ply(str(path))
    return path


def scene_dict(camera: Camera, bsdf: dict[str, Any] | list[dict[str, Any]], plane_ply: str | Path | list,
               markers: dict | None = DEMO_MARKERS, spp: int = 16, seed: int = 0,
               extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The Mitsuba scene: the sample mesh with ``bsdf`` (or, ``bsdf`` a list of regions, one mesh of
    ``plane_ply``'s list per region, shape ``sample-NAME``, each with its region's BSDF), black marker discs,
    one point light (placed per frame by :meth:`Renderer.render`), the camera, the ``direct`` integrator;
    ``extra`` adds or replaces entries (more shapes, another integrator)."""
    mi = mitsuba()
    scene = {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},   # a point light: only
        "sensor": sensor_dict(camera, spp, seed),                                    # light sampling finds it
        "light": {"type": "point", "position": [0.0, 0.0, 1.0], "intensity": {"type": "rgb", "value": [1.0] * 3}},
    }
    if isinstance(bsdf, dict):
        scene["sample"] = {"type": "ply", "filename": str(plane_ply), "face_normals": True, "bsdf": _resolved(bsdf)}
    else:
        for region, ply in zip(bsdf, plane_ply, strict=True):
            scene[f"sample-{region['name']}"] = {"type": "ply", "filename": str(ply), "face_normals": True,
                                                 "bsdf": _resolved(region["bsdf"])}
    for m, (x, y) in enumerate((markers or {"positions": []})["positions"]):
        r = float(markers["radius"])
        scene[f"marker{m}"] = {"type": "disk",
                               "to_world": mi.ScalarTransform4f().translate([float(x), float(y), MARKER_LIFT])
                               @ mi.ScalarTransform4f().scale([r, r, 1.0]),
                               "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}}}
    scene.update(extra or {})
    return scene


def sample_pixels(camera: Camera, size: tuple[float, float], markers: dict | None = DEMO_MARKERS,
                  subpixels: int = 4) -> np.ndarray:
    """(H, W) True where a pixel's whole footprint (``subpixels`` x ``subpixels`` points) lies on the
    sample and off the markers: the pixels on which a box-filtered render and a prediction through the
    pixel centre should agree."""
    xy = camera.pixel_plane_points(subpixels)
    ok = (np.abs(xy[..., 0]) < size[0] / 2) & (np.abs(xy[..., 1]) < size[1] / 2)
    for centre in (markers or {"positions": []})["positions"]:
        ok &= np.hypot(xy[..., 0] - centre[0], xy[..., 1] - centre[1]) > markers["radius"]
    s = subpixels
    return ok.reshape(camera.height, s, camera.width, s).all(axis=(1, 3))


def measured_bsdf(file: str | Path, scale: float = 1.0) -> dict[str, Any]:
    """Mitsuba's ``measured`` BSDF of an RGL ``.bsdf`` file times ``scale`` (the virtual rig's
    ``measured: {file, scale}``): ``scale`` below 1 as a ``blendbsdf`` with a black diffuse BSDF (Mitsuba has
    no scaling BSDF), above 1 refused (a blend cannot amplify)."""
    measured = {"type": "measured", "filename": str(Path(file).resolve())}
    scale = float(scale)
    if scale == 1.0:
        return measured
    if not 0.0 <= scale < 1.0:
        raise ValueError(f"measured scale {scale}: Mitsuba renders scales in [0, 1] only (a blend with black)")
    return {"type": "blendbsdf", "weight": scale, "bsdf_1": measured,
            "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}}}


def scene_regions(path: str | Path) -> dict[str, Any]:
    """A virtual rig scene (``resources/scenes/*.yaml``) as Mitsuba regions: ``{"size", "regions",
    "markers"}`` for :func:`render_capture` (``bsdf=regions``). Each region must be a ``rect`` with a
    ``measured`` file and a constant frame (``angle_deg``, or none); rects must not overlap on the sample
    (the virtual rig paints regions in order, one mesh per region cannot) and the scene must not be turned."""
    from .scene import Scene
    scene = Scene.load(path)
    if scene.rotation_deg:
        raise ValueError(f"{path}: a turned scene (rotation_deg {scene.rotation_deg}) is not supported")
    regions = []
    for i, r in enumerate(scene.regions):
        frame = r.get("frame", {"angle_deg": 0.0})
        if "rect" not in r["where"] or "measured" not in r or set(frame) != {"angle_deg"}:
            raise ValueError(f"{path}: region {i} ({r.get('name', i)}) is not a rect with a measured file and a "
                             "constant frame; only those render as Mitsuba regions")
        rect = _clipped((r["where"]["rect"]["x"], r["where"]["rect"]["y"]), *scene.size)
        for other in regions:
            (a0, a1), (b0, b1) = other["rect"]
            if min(a1, rect[0][1]) > max(a0, rect[0][0]) and min(b1, rect[1][1]) > max(b0, rect[1][0]):
                raise ValueError(f"{path}: regions {other['name']} and {r.get('name', i)} overlap")
        regions.append({"name": str(r.get("name", f"region{i}")), "rect": [list(rect[0]), list(rect[1])],
                        "frame": float(frame["angle_deg"]),
                        "bsdf": measured_bsdf(r["measured"]["file"], r["measured"].get("scale", 1.0))})
    markers = {"radius": scene.marker_radius, "positions": scene.marker_positions.tolist()}
    return {"size": scene.size, "regions": regions, "markers": markers if markers["positions"] else None}


def _clipped(rect, width: float, height: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """``rect`` ((x0, x1), (y0, y1)) clipped to the centred ``width`` x ``height`` sample (None: all of it);
    ValueError if nothing is left."""
    (x0, x1), (y0, y1) = rect if rect is not None else ((-width / 2, width / 2), (-height / 2, height / 2))
    x0, x1 = max(float(x0), -width / 2), min(float(x1), width / 2)
    y0, y1 = max(float(y0), -height / 2), min(float(y1), height / 2)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"rect {rect} does not overlap the {width} x {height} sample")
    return (x0, x1), (y0, y1)


def _resolved(bsdf: dict[str, Any]) -> dict[str, Any]:
    """The BSDF dict with every ``filename`` made absolute (relative names are relative to the cwd)."""
    out = {}
    for k, v in bsdf.items():
        if isinstance(v, dict):
            out[k] = _resolved(v)
        elif k == "filename":
            out[k] = str(Path(v).resolve())
        else:
            out[k] = v
    return out


class Renderer:
    """A loaded Mitsuba scene whose point light is moved and set per frame."""

    def __init__(self, scene: dict[str, Any]):
        mi = mitsuba()
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self.position_key, self.intensity_key = "light.position", "light.intensity.value"

    def render(self, light_position, light_intensity, seed: int = 0) -> np.ndarray:
        """(H, W, 3) float32 radiance of the frame lit by the point light."""
        mi = mitsuba()
        self.params[self.position_key] = mi.ScalarPoint3f([float(v) for v in light_position])
        self.params[self.intensity_key] = mi.ScalarColor3f([float(v) for v in light_intensity])
        self.params.update()
        return np.array(mi.render(self.scene, seed=int(seed)), dtype=np.float32)[..., :3]


def capture_rig(rig: VirtualRig, view: tuple[float, float] | None = None, led_every: int = 1,
                position_every: int = 1) -> VirtualRig:
    """The rig, or (with ``view`` = (theta, phi) degrees, phi relative to the rig camera's azimuth) the
    held-out rig of :func:`facetsynth.stages.validate.heldout_rig`: the camera moved, a subset of the lights."""
    if view is None and led_every == 1 and position_every == 1:
        return rig
    from ..stages.validate import heldout_rig
    if view is None:   # the rig's own view (theta from its camera height), a subset of the lights
        c = rig.desc["camera"]
        view = (float(np.degrees(np.arccos(c["height"] / c["distance"]))), 0.0)
    return heldout_rig(rig, view[0], view[1], led_every, position_every)


def render_capture(rig: VirtualRig | str | Path, bsdf: dict[str, Any] | list[dict[str, Any]], out_dir: str | Path,
                   size: tuple[float, float] = (0.10, 0.10), frame: str | float = "turned",
                   markers: dict | None = DEMO_MARKERS, spp: int = 16, seed: int = 0,
                   view: tuple[float, float] | None = None, led_every: int = 1,
                   position_every: int = 1) -> dict[str, Any]:
    """Render a foreign capture of a ``size`` (width, height in metres) sample with ``bsdf`` (a Mitsuba
    BSDF dict, or a list of regions ``{"name", "rect", "bsdf"[, "frame"]}``: :func:`scene_regions`) into
    ``out_dir``: ``frames/NNNN.exr`` (R, G, B float32 radiance, one exposure of time 1.0) and
    ``manifest.json`` (published schema; ``"saturation": null``: never clipped). The lights are the rig's scan
    (LED intensities drawn from ``seed`` as the virtual rig draws them); with ``view`` or the ``*_every``
    subsets, those of the held-out rig (:func:`capture_rig`). Returns the manifest, whose
    ``provenance`` records the renderer, the BSDF and the rate (frames/s; ``scalar_rgb`` renders a frame on
    one core)."""
    mi = mitsuba()
    base = rig if isinstance(rig, VirtualRig) else VirtualRig.load(rig)
    used = capture_rig(base, view, led_every, position_every)
    camera = used.camera(size[0])
    intensities = base.led_intensities(np.random.default_rng(seed))   # the virtual rig's draw for this seed
    plan = used.scan()
    out_dir = Path(out_dir)
    with tempfile.TemporaryDirectory() as tmp, atomic_dir(out_dir) as staging:
        if isinstance(bsdf, dict):
            ply = write_plane_mesh(Path(tmp) / "sample.ply", size[0], size[1], frame)
        else:
            ply = [write_plane_mesh(Path(tmp) / f"sample-{k}.ply", size[0], size[1], r.get("frame", frame),
                                    rect=r["rect"]) for k, r in enumerate(bsdf)]
        renderer = Renderer(scene_dict(camera, bsdf, ply, markers, spp, seed))
        (staging / "frames").mkdir()
        frames = []
        start = time.perf_counter()
        for q, (steps, led) in enumerate(plan):
            light, intensity = used.led_position(led, steps), intensities[led]
            image = renderer.render(light, intensity, seed=seed * 100003 + q)
            name = f"frames/{q:04d}.exr"
            write_exr(staging / name, {"RGB": image}, {"exposure_time": 1.0, "renderer": f"Mitsuba {mi.__version__}"})
            frames.append({"light": {"position": light.tolist(), "intensity": intensity.tolist()},
                           "exposures": [{"file": name, "time": 1.0}], "led": int(led), "carriage_steps": int(steps)})
        seconds = time.perf_counter() - start
        capture = {
            "version": 1, "units": "m",
            "sample": {"width": float(size[0]), "height": float(size[1])},
            "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(),
                       "R": camera.R.tolist(), "t": camera.t.tolist(), "distortion": [0.0] * 5},
            "saturation": None,   # HDR radiance, never clipped
            "frames": frames,
            "provenance": {
                "renderer": f"Mitsuba {mi.__version__} ({mi.variant()})",
                "integrator": "direct (one bounce), box pixel filter, float32 hdrfilm",
                "spp": int(spp), "seed": int(seed), "bsdf": bsdf, "frame": frame, "markers": markers,
                "rig": used.desc["name"], "view": None if view is None else list(view),
                "led_every": int(led_every), "position_every": int(position_every),
                "frames_per_second": len(plan) / seconds if seconds > 0 else None,
                "note": "HDR radiance, never clipped (saturation null); pixel model I = rho (n.i) L / |P - x|^2",
            },
        }
        manifest.save(staging / "manifest.json", capture)
    log.info("Mitsuba capture %s: %d frames, %.2f frames/s", out_dir, len(plan), len(plan) / max(seconds, 1e-9))
    return capture


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m facetsynth.truth.mitsuba_capture",
        description="Render a capture with Mitsuba 3 (scalar_rgb) on a rig description's geometry and write it "
                    "as an importable capture folder (manifest.json + HDR EXR frames).")
    parser.add_argument("--rig", required=True, help="rig description (rig/descriptions/*.yaml)")
    parser.add_argument("--bsdf-json", help="Mitsuba BSDF dict: a JSON file or an inline JSON object "
                                            "(default: anisotropic GGX copper, alpha_u 0.15, alpha_v 0.35)")
    parser.add_argument("--scene", help="a virtual rig scene of rect regions with measured RGL files "
                                        "(resources/scenes/rgl-quadrants.yaml): its regions (one Mitsuba "
                                        "'measured' BSDF each), size and markers; replaces --bsdf-json and --size")
    parser.add_argument("--out", required=True, help="capture folder to write")
    parser.add_argument("--size", nargs=2, type=float, default=(0.10, 0.10), metavar=("W", "H"),
                        help="sample width and height in metres (default 0.10 0.10)")
    parser.add_argument("--frame", default="turned",
                        help="azimuth of the BSDF's u axis: degrees, 'turned' (along circles about the centre) or 'tiles' (4 x 4 tiles at 16 turns, as ggx-tiles)")
    parser.add_argument("--view", nargs=2, type=float, metavar=("THETA", "PHI"),
                        help="held-out view: camera theta from vertical, phi relative to the rig camera's azimuth "
                             "(degrees); the paper's is 50.9 -15.3")
    parser.add_argument("--every", nargs=2, type=int, default=(1, 1), metavar=("LED", "POSITION"),
                        help="every LED-th LED at every POSITION-th carriage position (held out: 4 4)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    parser.add_argument("--seed", type=int, default=0, help="LED intensity variation and sampler seed")
    parser.add_argument("--no-markers", action="store_true", help="leave out the four black registration discs")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.bsdf_json is None:
        bsdf = copy.deepcopy(EXAMPLE_BSDF)
    elif Path(args.bsdf_json).is_file():
        bsdf = json.loads(Path(args.bsdf_json).read_text())
    else:
        bsdf = json.loads(args.bsdf_json)
    frame: str | float = args.frame if args.frame in ("turned", "tiles") else float(args.frame)
    size, markers = tuple(args.size), DEMO_MARKERS
    if args.scene:
        regions = scene_regions(args.scene)
        bsdf, size, markers = regions["regions"], regions["size"], regions["markers"]
    made = render_capture(args.rig, bsdf, args.out, size, frame, None if args.no_markers else markers,
                          args.spp, args.seed, tuple(args.view) if args.view else None, args.every[0], args.every[1])
    print(f"{args.out}: {len(made['frames'])} HDR frames and manifest.json "
          f"({made['provenance']['renderer']}, {made['provenance']['frames_per_second']:.2f} frames/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
