"""Render the exported facetsynth sample with Mitsuba 3 (``scalar_rgb``): one view, one point light, an EXR.

Written by ``facetsynth export mitsuba`` into the exported folder as ``render.py``, beside ``scene.xml``,
``model.npz`` and the plugin ``facetsynth_bsdf.py``; it needs numpy and Mitsuba 3 only::

    python render.py --theta 30 --phi 0 --distance 0.3 --light 0 0 0.3 --intensity 0.1 0.1 0.1 --out view.exr
    python render.py --manifest capture/manifest.json --frame 12 --out frame12.exr

The sample is the quad [-W/2, W/2] x [-H/2, H/2] of z = 0 (metres), normal +z. A view (``--theta``,
``--phi``: degrees from the normal and from +x towards +y; ``--distance``: metres) is a camera at that
direction looking at the sample's centre; ``--manifest`` takes the camera of a facetsynth capture manifest
(OpenCV x right, y down, z forward: a Mitsuba perspective sensor whose to_world has columns (-r1, -r2, r3, C),
horizontal field of view 2 atan(W / (2 fx)), the principal point as film offsets) and, with ``--frame``, that
frame's point light. A point light's intensity is radiant intensity (per steradian), so a pixel's value is
rho (n.i) L / |P - x|^2: facetsynth's pixel model. The integrator is ``direct`` with light sampling only (one
bounce, as the captures); ``--bsdf-samples N`` adds BSDF samples (the plugin's importance sampling).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
VARIANT = "scalar_rgb"


def look_at(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4 x 4 camera-to-world matrix of Mitsuba's look_at: columns (left, up, forward, origin)."""
    origin, target, up = (np.asarray(v, float) for v in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-9:                      # looking along up: any other up will do
        left = np.cross([0.0, 1.0, 0.0], forward)
    left /= np.linalg.norm(left)
    new_up = np.cross(forward, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, forward, origin
    return m


def view_camera(theta: float, phi: float, distance: float, fov: float = 25.0, width: int = 480,
                height: int = 320) -> dict:
    """Sensor parameters of a camera at (theta, phi) degrees and ``distance`` metres looking at the centre."""
    t, p = math.radians(theta), math.radians(phi)
    origin = distance * np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
    return {"to_world": look_at(origin), "fov": float(fov), "ppx": 0.0, "ppy": 0.0,
            "width": int(width), "height": int(height)}


def manifest_camera(camera: dict) -> dict:
    """Sensor parameters of a capture manifest's OpenCV camera (``K``, ``R``, ``t``, ``width``, ``height``)."""
    K, R, t = (np.asarray(camera[k], float) for k in ("K", "R", "t"))
    if any(abs(float(d)) > 0 for d in camera.get("distortion") or []):
        raise ValueError("a Mitsuba perspective sensor has no lens distortion; use an undistorted camera")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx - fy) > 1e-9 * fx or abs(K[0, 1]) > 1e-12:
        raise ValueError(f"Mitsuba's perspective sensor has square pixels and no skew: fx {fx}, fy {fy}")
    W, H = int(camera["width"]), int(camera["height"])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = -R[0], -R[1], R[2]
    m[:3, 3] = -R.T @ t.reshape(3)
    return {"to_world": m, "fov": float(np.degrees(2.0 * np.arctan(W / (2.0 * fx)))),
            # OpenCV pixel centre (cx, cy) is film coordinate (cx + 0.5, cy + 0.5); offsets along x left, y up
            "ppx": float(-(cx + 0.5 - W / 2) / W), "ppy": float(-(cy + 0.5 - H / 2) / H), "width": W, "height": H}


def scene_parameters(sensor: dict, light_position, light_intensity, spp: int = 16, seed: int = 0,
                     bsdf_samples: int = 0) -> dict:
    """The ``$`` parameters of scene.xml."""
    def triple(v):
        return ", ".join(repr(float(x)) for x in v)
    return {"to_world": " ".join(repr(float(x)) for x in np.asarray(sensor["to_world"], float).ravel()),
            "fov": repr(float(sensor["fov"])), "ppx": repr(float(sensor["ppx"])), "ppy": repr(float(sensor["ppy"])),
            "width": str(int(sensor["width"])), "height": str(int(sensor["height"])), "spp": str(int(spp)),
            "seed": str(int(seed)), "bsdf_samples": str(int(bsdf_samples)),
            "light_position": triple(light_position), "light_intensity": triple(light_intensity)}


def mitsuba():
    """Mitsuba in ``scalar_rgb`` with the facetsynth plugin registered."""
    import mitsuba as mi
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    if str(HERE) not in sys.path:
        sys.path.insert(0, str(HERE))
    import facetsynth_bsdf
    facetsynth_bsdf.register()
    return mi


def load_scene(sensor: dict, light_position, light_intensity, spp: int = 16, seed: int = 0,
               bsdf_samples: int = 0, scene_file: str | Path = HERE / "scene.xml"):
    """The Mitsuba scene of ``scene_file`` with this camera and light."""
    mi = mitsuba()
    params = scene_parameters(sensor, light_position, light_intensity, spp, seed, bsdf_samples)
    return mi.load_file(str(scene_file), parallel=False, **params)


def render(scene, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 radiance."""
    mi = mitsuba()
    return np.array(mi.render(scene, seed=int(seed)), dtype=np.float32)[..., :3]


def write_exr(path: str | Path, image: np.ndarray) -> None:
    mi = mitsuba()
    mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32), mi.Bitmap.PixelFormat.RGB).write(str(path))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="render.py", description=__doc__.split("\n")[0])
    parser.add_argument("--theta", type=float, default=30.0, help="view angle from the normal, degrees (30)")
    parser.add_argument("--phi", type=float, default=0.0, help="view azimuth from +x towards +y, degrees (0)")
    parser.add_argument("--distance", type=float, default=0.3, help="camera distance from the centre, m (0.3)")
    parser.add_argument("--fov", type=float, default=25.0, help="horizontal field of view, degrees (25)")
    parser.add_argument("--size", type=int, nargs=2, default=(480, 320), metavar=("W", "H"), help="pixels")
    parser.add_argument("--manifest", help="a capture manifest.json: use its camera (and --frame's light)")
    parser.add_argument("--frame", type=int, help="with --manifest: the frame whose point light to use")
    parser.add_argument("--light", type=float, nargs=3, default=(0.0, 0.0, 0.3), metavar=("X", "Y", "Z"),
                        help="point light position, m (0 0 0.3)")
    parser.add_argument("--intensity", type=float, nargs=3, default=(0.1, 0.1, 0.1), metavar=("R", "G", "B"),
                        help="point light radiant intensity, W/sr (0.1 each)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (16)")
    parser.add_argument("--bsdf-samples", type=int, default=0, help="BSDF samples per pixel sample (0)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="render.exr", help="output EXR (render.exr)")
    args = parser.parse_args(argv)
    light, intensity = args.light, args.intensity
    if args.manifest:
        manifest = json.loads(Path(args.manifest).read_text())
        sensor = manifest_camera(manifest["camera"])
        if args.frame is not None:
            frame = manifest["frames"][args.frame]["light"]
            light, intensity = frame["position"], frame["intensity"]
    else:
        sensor = view_camera(args.theta, args.phi, args.distance, args.fov, *args.size)
    start = time.perf_counter()
    scene = load_scene(sensor, light, intensity, args.spp, args.seed, args.bsdf_samples)
    image = render(scene, args.seed)
    write_exr(args.out, image)
    print(f"{args.out}: {image.shape[1]} x {image.shape[0]}, {args.spp} spp, "
          f"{time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
