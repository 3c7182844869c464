"""Stages ``calibration_targets`` and ``calibrate``: the rig's camera, LED positions and intensities
(paper 002 sec. 4; facetsynth.calibration) from target images, written to ``calibration.json``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..calibration import checkerboard, mirror, photometric
from ..calibration.layout import load_layout, read_image
from ..calibration.rigfile import RigCalibration
from ..calibration.settings import CalibrateSettings, TargetSettings
from ..calibration.targets import write_targets
from ..geometry.camera import Camera
from ..io.errors import InputError
from ..truth.virtual_rig import VirtualRig

log = logging.getLogger(__name__)


def run_targets(rig: str | Path, out_dir: str | Path, seed: int, noise: bool, settings: TargetSettings) -> None:
    """Render the virtual rig ``rig``'s calibration targets into ``out_dir``."""
    log.info("calibration targets of %s (seed %d, noise %s): %s", rig, seed, noise, settings)
    try:
        VirtualRig.load(rig)
    except InputError as exc:
        raise InputError(rig, f"not a virtual rig description ({exc.problem}): a real rig's calibration targets "
                              f"are photographs; put them into {out_dir} in the layout of facetsynth.calibration"
                         ) from None
    write_targets(rig, out_dir, settings.sample_width, seed, noise, intrinsic_views=settings.intrinsic_views,
                  mirror_heights=tuple(settings.mirror_heights), mirror_every=settings.mirror_every,
                  led_radius=settings.led_radius, albedo=settings.albedo)


def run_calibrate(targets: str | Path, out_file: str | Path, settings: CalibrateSettings) -> RigCalibration:
    """Calibrate from a targets folder and write ``out_file`` (calibration.json)."""
    if settings.lens not in checkerboard.LENS_MODELS:
        raise InputError(None, f"calibration: lens must be one of {', '.join(checkerboard.LENS_MODELS)}, "
                               f"not {settings.lens!r}")
    calibration = calibrate(targets, settings)
    calibration.save(out_file)
    log.info("wrote %s", out_file)
    return calibration


def calibrate(targets: str | Path, settings: CalibrateSettings = CalibrateSettings()) -> RigCalibration:
    """The calibrated rig from a targets folder: intrinsics, pose, LED positions, LED intensities."""
    folder = Path(targets)
    layout = load_layout(folder)
    size = (int(layout["camera"]["width"]), int(layout["camera"]["height"]))
    sat = layout.get("saturation")
    board = checkerboard.Board(tuple(layout["board"]["inner_corners"]), float(layout["board"]["square"]))

    # 1. Intrinsics (Zhang 2000) from the hand-held views and the board on the sample plane (one more view, the
    #    most tilted and the largest), then the pose of the latter.
    views = []
    for view in layout["intrinsics"]:
        image = read_image(folder, view["file"], size)
        views.append(checkerboard.find_corners(checkerboard.to_gray8(image, sat), board, folder / view["file"],
                                               settings.corner_window, checkerboard.to_grey(image)))
    pose = layout["pose"]
    pose_board = board
    if "board" in pose:                  # the board on the sample plane may be another, larger one
        pose_board = checkerboard.Board(tuple(pose["board"]["inner_corners"]), float(pose["board"]["square"]))
    image = read_image(folder, pose["file"], size)
    corners = checkerboard.find_corners(checkerboard.to_gray8(image, sat), pose_board, folder / pose["file"],
                                        settings.corner_window, checkerboard.to_grey(image))
    intr = checkerboard.calibrate_intrinsics(views + [corners], [board] * len(views) + [pose_board], size,
                                             settings.lens, settings.fix_principal_point)
    log.info("intrinsics from %d views: f = %.1f px, RMS %.3f px", len(views) + 1, intr.K[0, 0], intr.rms_px)
    world = checkerboard.board_to_world(pose_board, pose["origin"], pose["x_axis"], pose["y_axis"])
    prior = layout.get("prior", {})
    prior_centre = None if prior.get("camera_centre") is None else np.asarray(prior["camera_centre"], float)

    # 2. LED positions from the mirror highlights.
    read_sigma = float(layout.get("noise", {}).get("read_sigma", 0.0)) or 0.002 * (sat or 1.0)
    floor = settings.highlight_floor_sigmas * read_sigma
    count = int(layout["leds"]["count"])
    found, skipped = [], []
    for frame in layout["mirror"]["frames"]:
        if not 0 <= frame["led"] < count:
            raise InputError(folder / "targets.json", f"mirror frame {frame['file']}: LED {frame['led']} is not one "
                                                      f"of the rig's {count}")
        highlight = mirror.find_highlight(read_image(folder, frame["file"], size), floor)
        if highlight is None:
            skipped.append(frame["file"])
        else:
            found.append((frame, highlight))
    if not found:
        raise InputError(folder / "targets.json", f"no LED highlight found in any of the "
                                                  f"{len(layout['mirror']['frames'])} mirror frames")
    pixels = np.array([h.centre for _, h in found])
    heights = np.array([float(f["height"]) for f, _ in found])
    frame_leds = np.array([f["led"] for f, _ in found])
    frame_steps = np.array([f["steps"] for f, _ in found])

    def geometry(K: np.ndarray):
        """The pose on the sample-plane board and the LED fit with intrinsics K."""
        R, t, rms = checkerboard.solve_pose(corners, world, K, intr.distortion, pose_board, prior_centre)
        cam = Camera(size[0], size[1], K, R, t, intr.distortion)
        origins, directions = mirror.reflected_rays(cam, pixels, heights)
        return cam, rms, mirror.fit_leds(count, frame_leds, frame_steps, origins, directions,
                                         prior_home=prior.get("led_home"))

    K = intr.K.copy()
    camera, pose_rms, fit = geometry(K)
    step_length = layout.get("carriage", {}).get("step_length")
    scale = {"focal_zhang_px": float(intr.K[0, 0]), "step_length_fitted_mm": 1e3 * float(np.linalg.norm(fit.step))}
    if settings.scale_from_carriage and step_length:
        # A lens of a few degrees leaves the focal length and the distance nearly interchangeable (Zhang's
        # tilted views fix f to a few tenths of a per cent only), and a focal error scales the camera's distance
        # and every triangulated length alike. The carriage's travel per step is a machine constant (lead screw
        # and microstepping): the focal length is scaled until the fitted step has that length.
        for _ in range(8):
            ratio = float(step_length) / float(np.linalg.norm(fit.step))
            if abs(ratio - 1.0) < 1e-6:
                break
            K[0, 0] *= ratio
            K[1, 1] *= ratio
            camera, pose_rms, fit = geometry(K)
        scale.update({"step_length_known_mm": 1e3 * float(step_length), "focal_scaled_px": float(K[0, 0]),
                      "focal_change_percent": 100.0 * (K[0, 0] / intr.K[0, 0] - 1.0)})
        log.info("focal length %.1f -> %.1f px (%+.3f %%) so that the fitted carriage step is the known %.6f mm",
                 intr.K[0, 0], K[0, 0], scale["focal_change_percent"], 1e3 * step_length)
    R, t = camera.R, camera.t
    log.info("pose: camera centre %s m, RMS %.3f px", np.round(camera.centre, 4), pose_rms)
    log.info("LEDs: %d fitted from %d highlights (%d frames without one), %d extrapolated; ray distance RMS "
             "%.3f mm", int(fit.seen.sum()), len(found), len(skipped), len(fit.extrapolated),
             1e3 * np.sqrt(np.mean(fit.ray_distance**2)))

    # 3. LED intensities from the white reference (median over pixels, then over an LED's frames).
    white = layout["white"]
    albedo = float(white["albedo"])
    points = photometric.plane_points(camera)
    per_led: dict[int, list[np.ndarray]] = {}
    used = []
    for frame in white["frames"]:
        image = read_image(folder, frame["file"], size)
        light = fit.home[frame["led"]] + frame["steps"] * fit.step
        value, n = photometric.led_intensity(image, float(frame["time"]), points, light, albedo, 10 * read_sigma, sat)
        if n == 0:
            raise InputError(folder / frame["file"], "white reference frame: no pixel between the noise floor and "
                                                     "saturation")
        per_led.setdefault(int(frame["led"]), []).append(value)
        used.append(n)
    missing = [led for led in range(count) if led not in per_led]
    if missing:
        raise InputError(folder / "targets.json", f"white reference: no frame of LED(s) {missing[:10]}")
    intensity = np.array([np.median(per_led[led], axis=0) for led in range(count)])

    data = {
        "version": 1, "units": "m", "rig": str(layout.get("rig", "unnamed")),
        "camera": {"width": size[0], "height": size[1], "K": K.tolist(),
                   "distortion": np.pad(intr.distortion, (0, 5 - len(intr.distortion))).tolist(),
                   "R": R.tolist(), "t": t.tolist(), "reprojection_px": intr.rms_px},
        "leds": {"count": count, "home": fit.home.tolist(), "step": fit.step.tolist(),
                 "intensity": intensity.tolist()},
        "residuals": {
            "intrinsics_rms_px": intr.rms_px, "intrinsics_views_px": intr.per_view_px,
            "pose_rms_px": pose_rms,
            "mirror_frames": len(layout["mirror"]["frames"]), "mirror_highlights": len(found),
            "mirror_without_highlight": len(skipped),
            "led_ray_distance_rms_mm": 1e3 * float(np.sqrt(np.mean(fit.ray_distance**2))),
            "led_ray_distance_max_mm": 1e3 * float(fit.ray_distance.max()),
            "leds_fitted": int(fit.seen.sum()), "leds_extrapolated": fit.extrapolated,
            "scale": scale,
            "white_pixels_median": int(np.median(used)),
            "settings": {k: getattr(settings, k) for k in settings.__dataclass_fields__},
        },
    }
    return RigCalibration(data)
