"""The virtual rig: renders ground-truth captures of a scene (paper 002 sec. 4 geometry).

It is driven exactly like the real rig: the capture loop talks to the
controller through :class:`facetsynth.rig.driver.RigController` over a serial
line (a pseudo-terminal to :class:`facetsynth.rig.emulator.VirtualController`),
and the virtual camera places the light from the controller's state (carriage
position, lit LED), not from the loop's own bookkeeping. Each frame is
rendered with the pixel model of DESIGN.md sec. 4 (eq. 8 read forwards),
exposed through a bracket with sensor noise and saturation, and written as EXR
with a capture manifest; the ground truth (scene, true radiance) goes beside it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import manifest as manifest_io
from .camera import Camera
from .fileio import atomic_dir, read_yaml, write_exr
from .frames import map_frames
from .render import expose, radiance
from .rig.driver import RigController
from .rig.emulator import VirtualController, virtual_port
from .scene import Scene
from .validation import validate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VirtualRig:
    """A validated virtual rig description (``rig/descriptions/*.yaml``)."""

    desc: dict[str, Any]

    @classmethod
    def load(cls, path: str | Path) -> "VirtualRig":
        desc = read_yaml(path)
        validate(desc, "virtual_rig.schema.json", path, "virtual rig description")
        return cls(desc)

    @property
    def steps_per_metre(self) -> float:
        return self.desc["carriage"]["steps_per_mm"] * 1000.0

    @property
    def max_steps(self) -> int:
        c = self.desc["carriage"]
        return int(round(abs(c["start_y"] - c["end_y"]) * self.steps_per_metre))

    def scan(self) -> list[tuple[int, int]]:
        """(carriage steps, LED index) of every frame: positions from p0 to p1, LEDs along x."""
        c, leds = self.desc["carriage"], self.desc["leds"]
        n_positions = int(np.floor(abs(c["start_y"] - c["end_y"]) / c["step"] + 1e-9)) + 1
        steps = [int(round(k * c["step"] * self.steps_per_metre)) for k in range(n_positions)]
        used = range(0, leds["count"], leds.get("use_every", 1))
        return [(s, led) for s in steps for led in used]

    def led_position(self, led: int, steps: int) -> np.ndarray:
        """World position of LED ``led`` with the carriage at ``steps`` from home (p0)."""
        c, leds = self.desc["carriage"], self.desc["leds"]
        direction = np.sign(c["end_y"] - c["start_y"]) or 1.0
        x = (led - (leds["count"] - 1) / 2) * leds["pitch"]
        y = c["start_y"] + direction * steps / self.steps_per_metre
        return np.array([x, y, leds["height"]])

    def led_intensities(self, rng: np.random.Generator) -> np.ndarray:
        """(count, 3) calibrated RGB intensity of each LED: nominal times (1 + variation N(0,1))."""
        leds = self.desc["leds"]
        spread = leds.get("variation", 0.0) * rng.standard_normal((leds["count"], 3))
        return np.asarray(leds["intensity"]) * np.clip(1.0 + spread, 0.5, 1.5)

    def camera(self, sample_width: float) -> Camera:
        """The rig's camera looking at the sample centre from distance d, height h."""
        c = self.desc["camera"]
        horizontal = np.sqrt(c["distance"] ** 2 - c["height"] ** 2)
        azimuth = np.radians(c["azimuth_deg"])
        position = [horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), c["height"]]
        focal = c["sample_fill"] * c["width"] * c["distance"] / sample_width
        return Camera.look_at(position, [0.0, 0.0, 0.0], c["width"], c["height_px"], focal)


def capture(scene_path: str | Path, rig: VirtualRig, out_dir: str | Path, seed: int = 0,
            noise: bool = True, rotation_deg: float = 0.0, threads: int = 1) -> Path:
    """Render a virtual capture of the scene into ``out_dir`` (a capture folder).

    Writes ``frames/NNNN_eK.exr`` (one per exposure, half floats as a camera
    would deliver), ``truth/radiance_NNNN.exr`` (the true radiance I, half
    floats: relative precision 5e-4, ample for the accuracy records),
    ``truth/scene.yaml`` and ``manifest.json``. The folder is staged and moved
    into place only when complete. ``rotation_deg``: the sample turned on the
    rig by this angle (added to the scene's own ``rotation_deg``; the truth
    scene records the total). Frames are rendered and written on ``threads``
    threads while the scan goes on; each frame's sensor noise has its own
    random stream (seed, frame), so a capture is the same on any number of threads.
    """
    scene_dict = read_yaml(scene_path)
    scene_dict["rotation_deg"] = float(scene_dict.get("rotation_deg", 0.0)) + float(rotation_deg)
    scene = Scene.from_dict(scene_dict, scene_path)
    rng = np.random.default_rng(seed)
    camera = rig.camera(scene.size[0])
    intensities = rig.led_intensities(rng)
    exposure, sensor_noise = rig.desc["exposure"], rig.desc["noise"]
    read_sigma, shot_gain = (sensor_noise["read_sigma"], sensor_noise["shot_gain"]) if noise else (0.0, 0.0)
    supersample = rig.desc.get("supersample", 1)

    # What each (sub-)pixel sees on the plane; pixels off the sample see black velvet.
    xy = camera.pixel_plane_points(supersample)
    on_sample = scene.on_sample(xy)
    points = np.concatenate([xy[on_sample], np.zeros((on_sample.sum(), 1))], axis=-1)
    maps = scene.parameters(xy[on_sample])

    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as staging:
        (staging / "frames").mkdir()
        (staging / "truth").mkdir()
        (staging / "truth" / "scene.yaml").write_text(yaml.safe_dump(scene_dict, sort_keys=False))
        controller = VirtualController(n_leds=rig.desc["leds"]["count"], max_steps=rig.max_steps,
                                       steps_per_mm=rig.desc["carriage"]["steps_per_mm"])

        def expose_frame(job: tuple[int, np.ndarray, int, int]) -> dict:
            """Render frame q lit from ``light``, expose its bracket, write its files; its manifest entry."""
            q, light, led, steps = job
            rng_frame = np.random.default_rng([seed, q])   # one stream per frame: the same noise on any thread
            true_radiance = _render_frame(points, maps, on_sample, camera, light, intensities[led], supersample)
            exposures = []
            for e, t in enumerate(exposure["times"]):
                value = expose(true_radiance, t, exposure["saturation"], read_sigma, shot_gain, rng_frame)
                name = f"frames/{q:04d}_e{e}.exr"
                write_exr(staging / name, {"RGB": value}, {"exposure_time": float(t)}, precision="float16")
                exposures.append({"file": name, "time": float(t)})
            truth_name = f"truth/radiance_{q:04d}.exr"
            write_exr(staging / truth_name, {"RGB": true_radiance}, precision="float16")
            return {"light": {"position": light.tolist(), "intensity": intensities[led].tolist()},
                    "exposures": exposures, "truth": {"radiance": truth_name}, "led": led, "carriage_steps": steps}

        with virtual_port(controller) as port, RigController.open(port) as driver:
            info = driver.identify()
            log.info("virtual rig: %s on %s", info, port)
            driver.home()

            plan = rig.scan()

            def scan():
                """Drive the rig through the scan; the virtual camera sees the hardware, not the loop."""
                for q, (steps, led) in enumerate(plan):
                    if driver.position() != steps:
                        driver.move_to(steps)
                    driver.led_on(led)
                    state = controller.state()
                    yield q, rig.led_position(state.lit_led, state.position), int(state.lit_led), int(state.position)

            frames = map_frames(expose_frame, scan(), threads, "capture", total=len(plan))
            driver.leds_off()
        manifest_io.save(staging / "manifest.json", {
            "version": 1, "units": "m",
            "sample": {"width": scene.size[0], "height": scene.size[1]},
            "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(),
                       "R": camera.R.tolist(), "t": camera.t.tolist(), "distortion": [0.0] * 5},
            "saturation": exposure["saturation"],
            "noise": {"read_sigma": read_sigma, "shot_gain": shot_gain},
            "frames": frames,
            "truth": {"scene": "truth/scene.yaml"},
            "rig": {"name": rig.desc["name"], "firmware": info.firmware, "seed": seed, "noise": noise},
        })
    return out_dir


def _render_frame(points, maps, on_sample, camera, light, intensity, supersample) -> np.ndarray:
    """True radiance image (H, W, 3) of one frame, box-filtered over sub-pixels."""
    s = supersample
    image = np.zeros(on_sample.shape + (3,))
    image[on_sample] = radiance(points, maps.rho, light, intensity, camera.centre)
    return image.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3)).astype(np.float32)
