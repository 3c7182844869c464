"""The virtual rig's calibration targets: images of checkerboards, a flat mirror and a white reference,
rendered from the rig's TRUE geometry (the nominal description plus its ``calibration_error``, as
:func:`facetsynth.truth.virtual_rig.capture` renders frames) and exposed with the rig's sensor model
(:func:`facetsynth.models.render.expose`), in the folder layout of :mod:`facetsynth.calibration` (``targets.json``).

Rendering is ray casting through an ideal pinhole (the virtual camera has no lens distortion): each pixel
is the box-filtered mean of s x s sub-pixel rays (antialiasing). A checkerboard is a plane in the camera's
frame (white squares and margin 0.85, black 0.04, a dark room 0.02 behind it, under uniform light); the
mirror is the plane z = h with reflectance 0.9 and each camera ray is reflected (d' = d - 2 (d.n) n) and
tested against the lit LED, a downward-facing Lambertian disc of ``led_radius`` at the LED's true position
(radiance L / (pi r^2) for an LED of intensity L on its axis); the white reference is Lambertian of
``albedo`` on z = 0, eq. 8 with rho = albedo / pi. The truth (camera, LED homes, step, intensities) goes
to ``truth.json`` beside the images, for the tests; the calibration never reads it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..geometry.camera import Camera
from ..io.fileio import atomic_dir, write_exr, write_json
from ..models.render import expose
from ..truth.virtual_rig import VirtualRig
from .checkerboard import Board
from .photometric import shading

log = logging.getLogger(__name__)

WHITE, BLACK, ROOM = 0.85, 0.04, 0.02     # checkerboard reflectances and the dark room behind it
MIRROR_REFLECTANCE = 0.9
LENS_BLUR_PX = 0.8   # the lens's point spread (Gaussian sigma, pixels) on the checkerboards: a real board is never
                     # pixel-sharp, and cornerSubPix's bias on a box-filtered step edge is twice that on a blurred one


@dataclass(frozen=True)
class TrueRig:
    """The virtual rig as it is (what renders) and as described (the nominal calibration)."""

    camera: Camera
    home: np.ndarray          # (count, 3) true LED positions at steps = 0
    step: np.ndarray          # (3,) metres per motor step
    intensity: np.ndarray     # (count, 3) true intensities
    nominal_camera: Camera
    nominal_home: np.ndarray
    nominal_intensity: np.ndarray

    def light(self, led: int, steps: int) -> np.ndarray:
        return self.home[led] + steps * self.step


def true_rig(rig: VirtualRig, sample_width: float, seed: int) -> TrueRig:
    """The truth the virtual capture of a ``sample_width`` sample with ``seed`` renders with: its camera
    (``CalibrationError.camera``), LED positions (nominal + offset) and intensities (the capture's
    ``led_intensities(default_rng(seed))`` times the error factor)."""
    nominal = rig.camera(sample_width)
    count = rig.desc["leds"]["count"]
    nominal_home = np.array([rig.led_position(led, 0) for led in range(count)])
    step = rig.led_position(0, 1) - rig.led_position(0, 0)
    intensity = rig.led_intensities(np.random.default_rng(seed))
    error = rig.calibration_error()
    if error is None:
        return TrueRig(nominal, nominal_home, step, intensity, nominal, nominal_home, intensity)
    return TrueRig(error.camera(nominal), nominal_home + error.led_offset, step, intensity * error.intensity_factor,
                   nominal, nominal_home, intensity)


def pixel_directions(K: np.ndarray, width: int, height: int, supersample: int,
                     window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Camera-frame ray directions (h*s, w*s, 3) (z = 1) of an s x s sub-pixel grid of each pixel of the
    ``window`` (col0, row0, col1, row1; default the whole image)."""
    c0, r0, c1, r1 = window or (0, 0, width, height)
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    cols = (np.arange(c0, c1)[:, None] + offsets).ravel()
    rows = (np.arange(r0, r1)[:, None] + offsets).ravel()
    cc, rr = np.meshgrid(cols, rows)
    pix = np.stack([cc, rr, np.ones_like(cc)], axis=-1)
    return pix @ np.linalg.inv(K).T


def box(values: np.ndarray, s: int) -> np.ndarray:
    """Mean over s x s sub-pixel blocks: (h*s, w*s, ...) -> (h, w, ...)."""
    h, w = values.shape[0] // s, values.shape[1] // s
    return values.reshape(h, s, w, s, *values.shape[2:]).mean(axis=(1, 3))


def render_board(K: np.ndarray, width: int, height: int, board: Board, R_b: np.ndarray, t_b: np.ndarray,
                 supersample: int = 12) -> np.ndarray:
    """Reflectance image (H, W) of ``board`` at camera-frame pose X_cam = R_b X_board + t_b: the squares around
    the inner corners and a one-square white margin; the room elsewhere."""
    d = pixel_directions(K, width, height, supersample)
    n = R_b[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t_b) / (d @ n)
    local = (s[..., None] * d - t_b) @ R_b          # board coordinates of the hit
    cols, rows = board.inner_corners
    u, v = local[..., 0] / board.square, local[..., 1] / board.square
    checker = (u >= -1) & (u < cols) & (v >= -1) & (v < rows)
    card = (u >= -2) & (u < cols + 1) & (v >= -2) & (v < rows + 1) & (s > 0)
    parity = (np.floor(u).astype(int) + np.floor(v).astype(int)) % 2 == 0
    value = np.where(card, WHITE, ROOM)
    value = np.where(checker & parity, BLACK, value)
    return cv2.GaussianBlur(box(value, supersample), (0, 0), LENS_BLUR_PX)


def board_corners_camera(board: Board, R_b: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """Camera-frame corners of the card (the board with its margin) (4, 3)."""
    cols, rows = board.inner_corners
    q = board.square
    card = np.array([[-2 * q, -2 * q, 0], [(cols + 1) * q, -2 * q, 0], [(cols + 1) * q, (rows + 1) * q, 0],
                     [-2 * q, (rows + 1) * q, 0]])
    return card @ R_b.T + t_b


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def board_poses(K: np.ndarray, width: int, height: int, board: Board, distance: float, n: int,
                rng: np.random.Generator, max_tilt_deg: float = 50.0, margin: float = 3.0) -> list:
    """``n`` camera-frame poses (R_b, t_b) of a hand-held board about ``distance`` in front of the camera, tilted
    by half to all of ``max_tilt_deg`` about axes at evenly spread azimuths (Zhang's views), the whole card in
    view (tilt and spin shrink until it is)."""
    cols, rows = board.inner_corners
    middle = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * board.square
    poses = []
    for k in range(n):
        azimuth = 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / n
        shrink = 1.0
        for _ in range(60):
            tilt = np.radians(rng.uniform(0.5, 1.0) * max_tilt_deg * shrink)
            spin = np.radians(rng.uniform(-15, 15) * shrink)
            R_b = _rotation([np.cos(azimuth), np.sin(azimuth), 0.0], tilt) @ _rotation([0, 0, 1], spin)
            centre = np.array([rng.uniform(-0.004, 0.004), rng.uniform(-0.003, 0.003),
                               distance * rng.uniform(1.0, 1.05)])
            t_b = centre - R_b @ middle
            corners = board_corners_camera(board, R_b, t_b)
            pix = corners @ K.T
            pix = pix[:, :2] / pix[:, 2:]
            if (pix[:, 0].min() > margin and pix[:, 0].max() < width - 1 - margin and pix[:, 1].min() > margin
                    and pix[:, 1].max() < height - 1 - margin):
                poses.append((R_b, t_b))
                break
            shrink *= 0.95
        else:
            raise ValueError(f"board of {cols} x {rows} corners, {board.square} m squares, does not fit a "
                             f"{width} x {height} camera's view at {distance} m")
    return poses


def render_mirror(camera: Camera, height: float, led: np.ndarray, radius: float, radiance: np.ndarray,
                  supersample: int = 5, half_window: int = 16) -> np.ndarray:
    """Radiance image (H, W, 3) of a flat mirror at z = ``height`` showing an LED disc (facing down, centre
    ``led``, ``radius``) of ``radiance`` (3,); only a window about the LED's mirror image is traced (the rest is
    black: a dark room)."""
    image = np.zeros((camera.height, camera.width, 3))
    mirrored = np.array([led[0], led[1], 2 * height - led[2]])
    col, row = camera.project(mirrored)
    c0, r0 = max(int(col) - half_window, 0), max(int(row) - half_window, 0)
    c1, r1 = min(int(col) + half_window + 1, camera.width), min(int(row) + half_window + 1, camera.height)
    if c0 >= c1 or r0 >= r1:
        return image
    d = pixel_directions(camera.K, camera.width, camera.height, supersample, (c0, r0, c1, r1)) @ camera.R
    centre = camera.centre
    s = (height - centre[2]) / d[..., 2]
    hit = centre + s[..., None] * d
    up = d * np.array([1.0, 1.0, -1.0])
    s2 = (led[2] - hit[..., 2]) / up[..., 2]
    at = hit + s2[..., None] * up
    inside = (np.hypot(at[..., 0] - led[0], at[..., 1] - led[1]) <= radius) & (s2 > 0)
    image[r0:r1, c0:c1] = box(inside.astype(float), supersample)[..., None] * MIRROR_REFLECTANCE * radiance
    return image


def render_white(camera: Camera, light: np.ndarray, intensity: np.ndarray, albedo: float) -> np.ndarray:
    """Radiance image (H, W, 3) of a Lambertian reference of ``albedo`` covering the view on z = 0 (eq. 8)."""
    xy = camera.pixel_plane_points(1)
    points = np.concatenate([xy, np.zeros(xy.shape[:2] + (1,))], axis=-1)
    return shading(points, light, albedo)[..., None] * np.asarray(intensity, float)


def _camera_dict(camera: Camera) -> dict:
    return {"width": camera.width, "height": camera.height, "K": camera.K.tolist(),
            "distortion": np.asarray(camera.distortion, float).tolist(), "R": camera.R.tolist(),
            "t": camera.t.tolist()}


def write_targets(rig_path: str | Path, out_dir: str | Path, sample_width: float, seed: int, noise: bool = True,
                  board: Board = Board((8, 5), 0.007), pose_board: Board = Board((9, 8), 0.009),
                  intrinsic_views: int = 12,
                  mirror_heights: tuple[float, ...] = (0.0, 0.025), mirror_every: int = 3, led_radius: float = 0.0015,
                  albedo: float = 0.95, white_steps: int | None = None) -> Path:
    """Render the virtual rig's calibration targets into ``out_dir`` (the layout of :mod:`facetsynth.calibration`).

    ``sample_width`` and ``seed``: those of the capture the calibration is for (the virtual camera's focal
    length follows the sample width, the LEDs' intensities the seed). Mirror frames: every
    ``mirror_every``-th carriage position of the rig's scan, every LED whose mirror image falls in view (a real
    rig's user may shoot them all: frames without a highlight are skipped). White reference: one frame per
    LED at carriage ``white_steps`` (default: the scan position nearest y = 0.07 m, where the light falls on
    the sample at about 60 deg and an LED height error changes cos/r^2 least).
    """
    rig = VirtualRig.load(rig_path)
    truth = true_rig(rig, sample_width, seed)
    cam = truth.camera
    sat = rig.desc["exposure"]["saturation"]
    sensor = rig.desc["noise"]
    read_sigma, shot_gain = (sensor["read_sigma"], sensor["shot_gain"]) if noise else (0.0, 0.0)
    count = len(truth.home)
    scan_steps = sorted({s for s, _ in rig.scan()})
    out_dir = Path(out_dir)

    def exposed(radiance: np.ndarray, time: float, key: list[int]) -> np.ndarray:
        rng = np.random.default_rng([seed, *key])
        return expose(radiance.astype(np.float32), time, sat, read_sigma, shot_gain, rng)

    with atomic_dir(out_dir) as staging:
        for sub in ("intrinsics", "pose", "mirror", "white"):
            (staging / sub).mkdir()
        layout = {"version": 1, "rig": rig.desc["name"], "units": "m",
                  "camera": {"width": cam.width, "height": cam.height},
                  "saturation": sat, "noise": {"read_sigma": read_sigma, "shot_gain": shot_gain},
                  "prior": {"camera_centre": truth.nominal_camera.centre.tolist(),
                            "led_home": truth.nominal_home.tolist()},
                  "board": {"inner_corners": list(board.inner_corners), "square": board.square},
                  "leds": {"count": count},
                  "carriage": {"step_length": float(np.linalg.norm(truth.step))}}

        # Checkerboards: uniform room light, white squares at 70 % of saturation.
        board_time = 0.01
        light_level = 0.7 * (sat or 1.0) / (board_time * WHITE)
        rng = np.random.default_rng([seed, 11])
        distance = float(np.linalg.norm(cam.centre))
        views = []
        for k, (R_b, t_b) in enumerate(board_poses(cam.K, cam.width, cam.height, board, distance,
                                                   intrinsic_views, rng)):
            value = render_board(cam.K, cam.width, cam.height, board, R_b, t_b) * light_level
            name = f"intrinsics/{k:02d}.exr"
            write_exr(staging / name, {"RGB": np.repeat(exposed(value, board_time, [1, k])[..., None], 3, -1)},
                      {"exposure_time": board_time}, precision="float16")
            views.append({"file": name, "time": board_time})
        layout["intrinsics"] = views

        cols, rows = pose_board.inner_corners
        origin = [-(cols - 1) / 2 * pose_board.square, -(rows - 1) / 2 * pose_board.square, 0.0]
        axes = np.eye(3)
        R_b, t_b = cam.R @ axes, cam.R @ np.asarray(origin) + cam.t
        value = render_board(cam.K, cam.width, cam.height, pose_board, R_b, t_b) * light_level
        write_exr(staging / "pose" / "board.exr",
                  {"RGB": np.repeat(exposed(value, board_time, [2, 0])[..., None], 3, -1)},
                  {"exposure_time": board_time}, precision="float16")
        layout["pose"] = {"file": "pose/board.exr", "time": board_time, "origin": origin,
                          "board": {"inner_corners": list(pose_board.inner_corners), "square": pose_board.square},
                          "x_axis": [1.0, 0.0, 0.0], "y_axis": [0.0, 1.0, 0.0]}

        # Mirror: the LED disc's radiance L / (pi r^2); the brightest peak at half of saturation.
        led_radiance = truth.intensity / (np.pi * led_radius**2)
        mirror_time = 0.5 * (sat or 1.0) / (MIRROR_REFLECTANCE * led_radiance.max())
        frames = []
        for h_index, h in enumerate(mirror_heights):
            for steps in scan_steps[::mirror_every]:
                for led in range(count):
                    position = truth.light(led, steps)
                    col, row = cam.project(np.array([position[0], position[1], 2 * h - position[2]]))
                    if not (4 <= col <= cam.width - 5 and 4 <= row <= cam.height - 5):
                        continue
                    radiance = render_mirror(cam, h, position, led_radius, led_radiance[led])
                    name = f"mirror/h{h_index}_s{steps:05d}_l{led:03d}.exr"
                    write_exr(staging / name, {"RGB": exposed(radiance, mirror_time, [3, h_index, steps, led])},
                              {"exposure_time": mirror_time}, precision="float16")
                    frames.append({"file": name, "height": h, "led": led, "steps": steps, "time": mirror_time})
        layout["mirror"] = {"heights": list(mirror_heights), "frames": frames}
        log.info("mirror: %d frames at %d heights", len(frames), len(mirror_heights))

        # White reference: one frame per LED, the brightest pixel at 60 % of saturation.
        if white_steps is None:
            y = np.array([truth.light(0, s)[1] for s in scan_steps])
            white_steps = scan_steps[int(np.argmin(np.abs(y - 0.07)))]
        images = [render_white(cam, truth.light(led, white_steps), truth.intensity[led], albedo)
                  for led in range(count)]
        white_time = 0.6 * (sat or 1.0) / max(float(im.max()) for im in images)
        white = []
        for led, radiance in enumerate(images):
            name = f"white/s{white_steps:05d}_l{led:03d}.exr"
            write_exr(staging / name, {"RGB": exposed(radiance, white_time, [4, led])},
                      {"exposure_time": white_time}, precision="float16")
            white.append({"file": name, "led": led, "steps": white_steps, "time": white_time})
        layout["white"] = {"albedo": albedo, "frames": white}
        write_json(staging / "targets.json", layout)
        write_json(staging / "truth.json", {
            "camera": _camera_dict(cam), "nominal_camera": _camera_dict(truth.nominal_camera),
            "leds": {"home": truth.home.tolist(), "step": truth.step.tolist(), "intensity": truth.intensity.tolist()},
            "nominal_leds": {"home": truth.nominal_home.tolist(), "step": truth.step.tolist(),
                             "intensity": truth.nominal_intensity.tolist()},
            "sample_width": sample_width, "seed": seed})
    return out_dir
