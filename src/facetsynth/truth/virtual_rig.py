"""The virtual rig: renders ground-truth captures of a scene (paper 002 sec. 4 geometry).

It is driven exactly like the real rig: the capture loop talks to the
controller through :class:`facetsynth.rig.driver.RigController` over a serial
line (a pseudo-terminal to :class:`facetsynth.rig.emulator.VirtualController`),
and the virtual camera places the light from the controller's state (carriage
position, lit LED), not from the loop's own bookkeeping. Each frame is
rendered with the pixel model of DESIGN.md sec. 4 (eq. 8 read forwards),
exposed through a bracket with sensor noise and saturation, and written as EXR
with a capture manifest; the ground truth (scene, true radiance) goes beside it.

Calibration error (the description's ``calibration_error``): the rig renders
with LED intensities, LED positions and a camera pose that differ from its
calibration by seeded random amounts, while the manifest records the nominal
(calibrated) values, as a real rig's calibration would; the true values go to
``truth/calibration.json``. Without it a capture is what it always was.
"""

from __future__ import annotations

import copy
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import yaml

from ..capture import manifest
from ..geometry.camera import Camera
from ..io.fileio import atomic_dir, read_yaml, write_exr, write_json
from ..io.frames import map_frames
from ..models.render import expose, radiance
from ..rig.driver import RigController
from ..rig.emulator import VirtualController, virtual_port
from .scene import Scene
from ..io.validation import validate

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

    def calibration_error(self) -> "CalibrationError | None":
        """The rig's true departures from its calibration (``calibration_error``), or None without any.

        Drawn from their own stream, ``numpy.random.default_rng(seed)`` (not the capture's), in this
        order: relative intensity errors N(0, led_intensity^2) per LED and RGB channel (factor
        1 + e, clipped to [0.5, 1.5]); position offsets N(0, led_position_m^2) per LED and axis
        (metres; each LED keeps its offset at every carriage position); a camera rotation about
        its centre by exactly camera_rotation_deg about a uniformly random axis.
        """
        e = self.desc.get("calibration_error")
        if not e or not any(e.get(k, 0.0) > 0 for k in ("led_intensity", "led_position_m", "camera_rotation_deg")):
            return None
        count = self.desc["leds"]["count"]
        rng = np.random.default_rng(e.get("seed", 0))
        factor = np.clip(1.0 + e.get("led_intensity", 0.0) * rng.standard_normal((count, 3)), 0.5, 1.5)
        offset = e.get("led_position_m", 0.0) * rng.standard_normal((count, 3))
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        return CalibrationError(intensity_factor=factor, led_offset=offset,
                                camera_rotation=_rotation(axis, np.radians(e.get("camera_rotation_deg", 0.0))))

    def nominal_calibration(self, sample_width: float, seed: int = 0) -> dict[str, Any]:
        """The calibration this description states (``calibration.json``, schema ``rig_calibration``): the
        camera for a sample ``sample_width`` wide, each LED at home and the carriage's step, the LED
        intensities drawn for captures with ``seed``. Without ``calibration_error`` it is the rig's truth."""
        camera = self.camera(sample_width)
        home = np.array([self.led_position(led, 0) for led in range(self.desc["leds"]["count"])])
        return {"version": 1, "units": "m", "rig": self.desc["name"],
                "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(),
                           "distortion": camera.distortion.tolist(), "R": camera.R.tolist(), "t": camera.t.tolist(),
                           "reprojection_px": 0.0},
                "leds": {"count": len(home), "home": home.tolist(),
                         "step": (self.led_position(0, 1) - self.led_position(0, 0)).tolist(),
                         "intensity": self.led_intensities(np.random.default_rng(seed)).tolist()},
                "residuals": {"source": "nominal: the virtual rig's description"}}

    def camera(self, sample_width: float) -> Camera:
        """The rig's camera looking at the sample centre from distance d, height h."""
        c = self.desc["camera"]
        horizontal = np.sqrt(c["distance"] ** 2 - c["height"] ** 2)
        azimuth = np.radians(c["azimuth_deg"])
        position = [horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), c["height"]]
        focal = c["sample_fill"] * c["width"] * c["distance"] / sample_width
        return Camera.look_at(position, [0.0, 0.0, 0.0], c["width"], c["height_px"], focal)


@dataclass(frozen=True)
class CalibrationError:
    """How the virtual rig truly differs from its calibration (the manifest keeps the calibration)."""

    intensity_factor: np.ndarray   # (count, 3): true intensity = calibrated intensity * factor
    led_offset: np.ndarray         # (count, 3) metres: true LED position = nominal + offset
    camera_rotation: np.ndarray    # (3, 3) Q: true R = Q R_nominal (a rotation about the camera centre)

    def camera(self, nominal: Camera) -> Camera:
        """The true camera: the nominal one turned by Q about its own centre (same K, same centre)."""
        R = self.camera_rotation @ nominal.R
        return Camera(nominal.width, nominal.height, nominal.K, R, -R @ nominal.centre, nominal.distortion)

    def record(self, settings: dict[str, Any], nominal: Camera) -> dict[str, Any]:
        """The truth file ``truth/calibration.json``: settings and the true values."""
        true = self.camera(nominal)
        angle = np.degrees(np.arccos(np.clip((np.trace(self.camera_rotation) - 1.0) / 2.0, -1.0, 1.0)))
        return {"settings": settings, "led_intensity_factor": self.intensity_factor.tolist(),
                "led_offset_m": self.led_offset.tolist(), "camera_rotation_deg": float(angle),
                "camera": {"R": true.R.tolist(), "t": true.t.tolist(), "Q": self.camera_rotation.tolist()}}


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by ``angle`` (radians) about the unit ``axis``."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _portable_truth(scene_dict: dict[str, Any], scene: Scene) -> tuple[dict[str, Any], dict[str, str]]:
    """The truth copy of the scene and the measured files to copy beside it: each region's
    ``measured.file`` becomes ``brdfs/NAME`` (relative to ``truth/scene.yaml``), so the capture's
    truth does not depend on where the scene file was. Scenes without measured regions are unchanged."""
    if not any("measured" in r for r in scene.regions):
        return scene_dict, {}
    truth = copy.deepcopy(scene_dict)
    copies: dict[str, str] = {}
    for r, resolved in zip(truth["regions"], scene.regions):
        if "measured" in r:
            source = resolved["measured"]["file"]
            if source not in copies:
                name = Path(source).name
                if name in copies.values():
                    name = f"{len(copies)}_{name}"
                copies[source] = name
            r["measured"]["file"] = f"brdfs/{copies[source]}"
    return truth, copies


class VirtualCamera:
    """The virtual rig's camera: renders a scene as the rig truly is (paper 002 sec. 4 geometry).

    It is also a camera backend of a capture on the real rig (:mod:`facetsynth.rig.session`, rig
    description ``camera: {backend: virtual, scene, rig, seed, noise}``): there ``hardware()`` returns the
    controller's state, carriage steps and lit LED, asked through the driver (``POS?``, ``LED?``), so the
    camera sees what the hardware does, never the capture loop's intentions. Each frame's sensor noise has
    the stream (seed, LED, steps): a frame taken again after a fault or a resume is the same frame.

    The rig renders with its true geometry: with ``calibration_error`` the LED intensities, positions and
    camera pose differ from :attr:`camera` and :attr:`intensities`, the calibrated (nominal) values.
    """

    def __init__(self, scene_path: str | Path, rig: VirtualRig, seed: int = 0, noise: bool = True,
                 rotation_deg: float = 0.0, hardware: Callable[[], tuple[int, int | None]] | None = None):
        self.scene_dict = read_yaml(scene_path)
        self.scene_dict["rotation_deg"] = float(self.scene_dict.get("rotation_deg", 0.0)) + float(rotation_deg)
        self.scene = Scene.from_dict(self.scene_dict, scene_path)
        self.scene_path, self.rig, self.seed, self.hardware = Path(scene_path), rig, seed, hardware
        self.camera = rig.camera(self.scene.size[0])                            # the calibration
        self.intensities = rig.led_intensities(np.random.default_rng(seed))     # calibrated, per LED
        self.error = rig.calibration_error()
        self.seen_by = self.camera if self.error is None else self.error.camera(self.camera)   # the true pose
        noise_model = rig.desc["noise"]
        self.read_sigma, self.shot_gain = ((noise_model["read_sigma"], noise_model["shot_gain"]) if noise
                                           else (0.0, 0.0))
        self.noise = noise
        self.supersample = rig.desc.get("supersample", 1)
        # What each (sub-)pixel sees on the plane; pixels off the sample see black velvet.
        xy = self.seen_by.pixel_plane_points(self.supersample)
        self.on_sample = self.scene.on_sample(xy)
        self.points = np.concatenate([xy[self.on_sample], np.zeros((self.on_sample.sum(), 1))], axis=-1)
        self.maps = self.scene.parameters(xy[self.on_sample])

    def render(self, led: int | None, steps: int) -> np.ndarray:
        """True radiance image (H, W, 3) with LED ``led`` lit (None: all dark) and the carriage at ``steps``."""
        if led is None:
            return np.zeros((self.camera.height, self.camera.width, 3), np.float32)
        light, intensity = self.rig.led_position(led, steps), self.intensities[led]
        if self.error is not None:                                              # the rig as it is
            light, intensity = light + self.error.led_offset[led], intensity * self.error.intensity_factor[led]
        return _render_frame(self.points, self.maps, self.on_sample, self.seen_by, light, intensity,
                             self.supersample)

    def exposures(self, radiance_image: np.ndarray, times: Sequence[float], rng: np.random.Generator,
                  folder: Path, stem: str) -> list[dict]:
        """Expose ``radiance_image`` through the bracket ``times``; write ``folder/{stem}_e{k}.exr``, half floats
        as a camera delivers them; their manifest entries (file names relative to ``folder``)."""
        saturation = self.rig.desc["exposure"]["saturation"]
        written = []
        for k, t in enumerate(times):
            value = expose(radiance_image, t, saturation, self.read_sigma, self.shot_gain, rng)
            name = f"{stem}_e{k}.exr"
            write_exr(folder / name, {"RGB": value}, {"exposure_time": float(t)}, precision="float16")
            written.append({"file": name, "time": float(t)})
        return written

    # -- the camera backend (facetsynth.rig.cameras.CameraBackend) ---------------------------------

    def describe(self) -> str:
        return (f"virtual camera {self.camera.width}x{self.camera.height} of rig {self.rig.desc['name']}, "
                f"scene {self.scene_path}")

    def capture(self, times: Sequence[float], folder: Path, stem: str) -> list[dict]:
        """One exposure per time of what the hardware shows now."""
        steps, led = self.hardware()
        rng = np.random.default_rng([self.seed, -1 if led is None else led, steps])
        return self.exposures(self.render(led, steps), times, rng, Path(folder), stem)

    def truth(self, folder: Path) -> dict[str, str]:
        """Write the truth of a capture into ``folder/truth/`` (the scene, its measured BRDF files, and with
        ``calibration_error`` the rig's true calibration); the manifest's ``truth`` entry."""
        truth_dir = Path(folder) / "truth"
        truth_dir.mkdir(exist_ok=True)
        truth_scene, brdf_files = _portable_truth(self.scene_dict, self.scene)
        (truth_dir / "scene.yaml").write_text(yaml.safe_dump(truth_scene, sort_keys=False))
        if brdf_files:
            (truth_dir / "brdfs").mkdir(exist_ok=True)
            for source, name in brdf_files.items():
                shutil.copyfile(source, truth_dir / "brdfs" / name)
        if self.error is None:
            return {"scene": "truth/scene.yaml"}
        write_json(truth_dir / "calibration.json", self.error.record(self.rig.desc["calibration_error"], self.camera))
        return {"scene": "truth/scene.yaml", "calibration": "truth/calibration.json"}

    def close(self) -> None:
        pass


def capture(scene_path: str | Path, rig: VirtualRig, out_dir: str | Path, seed: int = 0,
            noise: bool = True, rotation_deg: float = 0.0, threads: int = 1) -> Path:
    """Render a virtual capture of the scene into ``out_dir`` (a capture folder).

    Writes ``frames/NNNN_eK.exr`` (one per exposure, half floats as a camera
    would deliver), ``truth/radiance_NNNN.exr`` (the true radiance I, half
    floats: relative precision 5e-4, ample for the accuracy records),
    ``truth/scene.yaml`` (its measured BRDF files copied to ``truth/brdfs/``),
    ``truth/calibration.json`` (with the rig's ``calibration_error``: the true
    LED intensities, positions and camera pose; the manifest keeps the nominal
    ones) and ``manifest.json``. The folder is staged and moved
    into place only when complete. ``rotation_deg``: the sample turned on the
    rig by this angle (added to the scene's own ``rotation_deg``; the truth
    scene records the total). Frames are rendered and written on ``threads``
    threads while the scan goes on; each frame's sensor noise has its own
    random stream (seed, frame), so a capture is the same on any number of threads.
    """
    cam = VirtualCamera(scene_path, rig, seed=seed, noise=noise, rotation_deg=rotation_deg)
    camera, exposure = cam.camera, rig.desc["exposure"]
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as staging:
        (staging / "frames").mkdir()
        truth = cam.truth(staging)
        controller = VirtualController(n_leds=rig.desc["leds"]["count"], max_steps=rig.max_steps,
                                       steps_per_mm=rig.desc["carriage"]["steps_per_mm"])

        def expose_frame(job: tuple[int, int, int]) -> dict:
            """Render frame q lit by LED ``led`` at ``steps``, expose its bracket, write its files; its manifest entry."""
            q, led, steps = job
            true_radiance = cam.render(led, steps)
            rng_frame = np.random.default_rng([seed, q])   # one stream per frame: the same noise on any thread
            exposures = cam.exposures(true_radiance, exposure["times"], rng_frame, staging / "frames", f"{q:04d}")
            truth_name = f"truth/radiance_{q:04d}.exr"
            write_exr(staging / truth_name, {"RGB": true_radiance}, precision="float16")
            return {"light": {"position": rig.led_position(led, steps).tolist(), "intensity": cam.intensities[led].tolist()},
                    "exposures": [{**e, "file": f"frames/{e['file']}"} for e in exposures],
                    "truth": {"radiance": truth_name}, "led": led, "carriage_steps": steps}

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
                    yield q, int(state.lit_led), int(state.position)

            frames = map_frames(expose_frame, scan(), threads, "capture", total=len(plan))
            driver.leds_off()
        manifest.save(staging / "manifest.json", {
            "version": 1, "units": "m",
            "sample": {"width": cam.scene.size[0], "height": cam.scene.size[1]},
            "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(),
                       "R": camera.R.tolist(), "t": camera.t.tolist(), "distortion": [0.0] * 5},
            "saturation": exposure["saturation"],
            "noise": {"read_sigma": cam.read_sigma, "shot_gain": cam.shot_gain},
            "frames": frames,
            "truth": truth,
            "rig": {"name": rig.desc["name"], "firmware": info.firmware, "seed": seed, "noise": noise},
        })
    return out_dir


def _render_frame(points, maps, on_sample, camera, light, intensity, supersample) -> np.ndarray:
    """True radiance image (H, W, 3) of one frame, box-filtered over sub-pixels."""
    s = supersample
    image = np.zeros(on_sample.shape + (3,))
    image[on_sample] = radiance(points, maps.rho, light, intensity, camera.view_point)
    return image.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3)).astype(np.float32)
