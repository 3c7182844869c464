"""Stage ``validate``: held-out views, predicted and scored (paper 002 sec. 6, Figs. 9-10).

For a virtual sample the virtual rig renders held-out captures from views
that were not used for fitting (``heldout_capture``); the fitted SVBRDF and
the Ward baseline predict them with :func:`facetsynth.app.predict.predict` (the
code path of ``facetsynth predict``); predictions are scored against the true
radiance of the held-out frames over the sample's pixels
(:func:`facetsynth.evaluation.metrics.image_scores`, normalisation stated there and in
the metrics file), and side-by-side images are written.
"""

from __future__ import annotations

import copy
import csv
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..capture import manifest
from ..io.fileio import atomic_path, read_rgb, read_yaml, write_json
from ..evaluation.metrics import finite_or_none, frame_psnr, image_scores, relative_l2
from ..app.predict import FrameRenderer, load_model, predict
from ..models.render import radiance
from ..truth.scene import Scene
from ..truth.virtual_rig import VirtualRig
from .common import RuleFiles, StageSettings

log = logging.getLogger(__name__)

NORMALISATION = ("over the sample's pixels (every sub-pixel on the sample), linear radiance, all frames of a view "
                 "pooled: rmse in radiance units; psnr_db = 20 log10(peak / rmse) with peak = the largest true "
                 "radiance of the view; ssim of channel-mean images divided by that peak (Gaussian window 1.5, "
                 "data range 1), averaged over sample pixels and frames; truth = the virtual rig's true radiance. "
                 "heldout_rel_l2 = sqrt(sum (pred - truth)^2 / sum truth^2) over every frame, sample pixel and RGB "
                 "channel of the view (no peak: every pixel counts by its radiance); heldout_specular_rel_l2 = the "
                 "same of (pred - diffuse_truth) against (truth - diffuse_truth), diffuse_truth = the truth's kd/pi "
                 "(n.i) L / r^2 of the same frames, over the sample pixels whose truth is analytic eq. 6 "
                 "(MaterialMaps.analytic; specular_pixels counts them), rendered with the rig as it truly was (its "
                 "calibration error, if any); heldout_rel_l2_regions (views only): heldout_rel_l2 per truth "
                 "region, over the pixels whose every sub-pixel lies in it; heldout_frame_psnr_median_db / "
                 "_worst_db: each frame's own PSNR over the sample pixels, peak = that frame's largest true radiance there, capped at 100 dB, frames "
                 "without light on the sample skipped; the median and the minimum over the view's frames. Top-level "
                 "figures are plain means of the per-view figures (the worst too: per view in views)")

# per-frame PSNR above this counts as exact (rmse 0 gives no finite PSNR)
MAX_FRAME_PSNR_DB = 100.0


class Inputs(RuleFiles):
    """Rule ``validate``'s inputs: the fitted SVBRDF folder, the held-out captures (one folder per view of
    ``Settings.views``, in that order), the Ward baseline's folder (None: ours alone), params' metrics (a
    dependency: the fit is done), the held-out truth's rig description (its ``supersample`` renders the truth's
    diffuse term as the truth was rendered; None: 1)."""
    svbrdf: Path
    heldout: list[Path]
    ward: Path | None = None
    params_metrics: Path | None = None
    rig: Path | None = None


class Outputs(RuleFiles):
    """Rule ``validate``'s outputs: the scores, the side-by-side images' folder and the predictions' folder."""
    metrics: Path
    images: Path
    predictions: Path


class Settings(StageSettings):
    """The stage's knobs: the rule's params (``images_per_view`` is config ``validate``'s; ``views`` its views'
    names; the benchmarks are files, read when the job runs)."""
    views: tuple = ("paper", "theta30")   # the held-out views' names, in the order of ``Inputs.heldout``
    fit_benchmarks: tuple = ()            # the fitting stages' Snakemake benchmark files (missing ones: no time)
    ward_benchmark: str | None = None     # the Ward baseline's benchmark file
    images_per_view: int = 2              # side-by-side images of each view's brightest frames


def heldout_rig(rig: VirtualRig, theta_deg: float, phi_deg: float, led_every: int, position_every: int) -> VirtualRig:
    """The sample's rig with the camera moved to (theta, phi) and a subset of its lights.

    theta is the camera's angle from vertical; phi its azimuth relative to the
    fitting camera's azimuth (the paper's held-out view, theta 50.9 deg,
    phi -15.3 deg, is given relative to its capture view). The camera keeps
    its distance and framing.
    """
    desc = copy.deepcopy(rig.desc)
    cam = desc["camera"]
    cam["height"] = float(cam["distance"] * np.cos(np.radians(theta_deg)))
    cam["azimuth_deg"] = float(cam["azimuth_deg"] + phi_deg)
    desc["leds"]["use_every"] = int(desc["leds"].get("use_every", 1) * led_every)
    desc["carriage"]["step"] = float(desc["carriage"]["step"] * position_every)
    desc["name"] = f"{desc['name']}-heldout-theta{theta_deg:g}-phi{phi_deg:+g}"
    return VirtualRig(desc)


def _benchmark_seconds(path: str | Path) -> float | None:
    path = Path(path)
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    return float(rows[0]["s"]) if rows else None


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.4g}"


def _to_png(path: Path, image: np.ndarray) -> None:
    import OpenImageIO as oiio
    data = (np.clip(image, 0.0, 1.0) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
    with atomic_path(path, suffix=".png") as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise RuntimeError(oiio.geterror())
        out.open(str(tmp), oiio.ImageSpec(data.shape[1], data.shape[0], 3, oiio.UINT8))
        out.write_image(data)
        out.close()


def side_by_side(truth: np.ndarray, ours: np.ndarray, ward: np.ndarray | None, peak: float) -> np.ndarray:
    """[truth | prediction | Ward | 4 x |prediction - truth|], scaled by the frame's peak (display gamma 2.2)."""
    gap = np.ones((truth.shape[0], 2, 3))
    panels = [truth, ours] + ([ward] if ward is not None else []) + [4.0 * np.abs(ours - truth)]
    parts = []
    for p in panels:
        parts += [p / max(peak, 1e-30), gap]
    return np.concatenate(parts[:-1], axis=1)


def diffuse_truth(scene: Scene, camera, lights: np.ndarray, intensities: np.ndarray,
                  supersample: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truth's diffuse radiance kd/pi (n.i) L / |P - x|^2 (eq. 8 forwards, eq. 6's first term) per frame.

    Rendered as the virtual rig renders the truth (each sub-pixel sees its plane
    point, box filter over ``supersample`` x ``supersample`` sub-pixels), for the
    lights (F, 3) and intensities (F, 3). Returns (diffuse (F, H, W, 3) float32,
    analytic (H, W) bool: pixels whose every sub-pixel is on the sample and whose
    truth is exactly eq. 6 there, i.e. where kd is the truth's diffuse term;
    ``MaterialMaps.analytic`` when the scene has it, else every sample point;
    region (H, W) int: the scene region every sub-pixel of the pixel lies in, -1
    where they differ, on markers and off the sample).
    """
    s = int(supersample)
    xy = camera.pixel_plane_points(s)
    on = scene.on_sample(xy)
    maps = scene.parameters(xy[on])
    points = np.concatenate([xy[on], np.zeros((int(on.sum()), 1))], axis=-1)
    analytic_points = getattr(maps, "analytic", None)
    known = on.copy()
    if analytic_points is not None:
        known[on] = np.asarray(analytic_points, bool).reshape(-1)
    h, w = camera.height, camera.width
    analytic = known.reshape(h, s, w, s).all(axis=(1, 3))
    sub = np.full(on.shape, -1, np.int32)
    sub[on] = np.asarray(maps.region).reshape(-1)
    sub = sub.reshape(h, s, w, s).transpose(0, 2, 1, 3).reshape(h, w, -1)
    region = np.where((sub == sub[..., :1]).all(axis=-1), sub[..., 0], -1)
    kd_over_pi = np.asarray(maps.kd, float) / np.pi
    out = np.zeros((len(lights), h, w, 3), np.float32)
    image = np.zeros(on.shape + (3,))
    for q, (light, intensity) in enumerate(zip(lights, intensities)):
        image[on] = radiance(points, lambda wi, wo: kd_over_pi, light, intensity, camera.view_point)
        out[q] = image.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    return out, analytic, region


def region_scores(truth: np.ndarray, prediction: np.ndarray, mask: np.ndarray, region: np.ndarray,
                  names: list[str]) -> dict[str, float | None]:
    """Relative L2 of the radiance (:func:`facetsynth.evaluation.metrics.relative_l2`) per truth region: which
    material holds a view's error (a scene's mean hides a region its model cannot show)."""
    return {name: finite_or_none(relative_l2(prediction, truth, mask & (region == k)))
            for k, name in enumerate(names) if np.any(mask & (region == k))}


def true_rig(m: dict[str, Any]) -> tuple[Any, np.ndarray, np.ndarray]:
    """(camera, homogeneous lights (F, 4), intensities (F, 3)) the held-out truth was rendered with.

    The manifest's calibrated values, or, when the virtual rig had a
    calibration error (``truth/calibration.json``), the true ones: the camera
    turned by its rotation, each frame's LED moved by its offset and scaled by
    its intensity factor (:class:`facetsynth.truth.virtual_rig.CalibrationError`).
    """
    from ..geometry.camera import Camera
    from ..io.fileio import read_json
    camera = manifest.camera(m)
    lights, intensities = manifest.lights(m["frames"]), manifest.light_intensities(m["frames"])
    record = m.get("truth", {}).get("calibration")
    if record is None:
        return camera, lights, intensities
    cal = read_json(Path(m["_dir"]) / record)
    camera = Camera(camera.width, camera.height, camera.K, np.asarray(cal["camera"]["R"], float),
                    np.asarray(cal["camera"]["t"], float), camera.distortion)
    led = np.array([f["led"] for f in m["frames"]], int)
    lights[:, :3] += np.asarray(cal["led_offset_m"], float)[led]
    intensities = intensities * np.asarray(cal["led_intensity_factor"], float)[led]
    return camera, lights, intensities


def trusted_scores(truth: np.ndarray, prediction: np.ndarray, mask: np.ndarray,
                   diffuse: np.ndarray | None = None, specular_mask: np.ndarray | None = None) -> dict[str, Any]:
    """The scores that do not hide faults behind the view's peak (issue 13 item 4).

    ``heldout_rel_l2``: relative L2 of the radiance over ``mask``, every frame
    and channel (:func:`facetsynth.evaluation.metrics.relative_l2`);
    ``heldout_specular_rel_l2``: the same of the specular part, (prediction -
    diffuse) against (truth - diffuse), over ``specular_mask`` (None without a
    diffuse truth); ``heldout_frame_psnr_median_db`` / ``_worst_db``: median and
    minimum of each frame's own PSNR (:func:`facetsynth.evaluation.metrics.frame_psnr`).
    Values that are not finite become None (no NaN leaves the stage).
    """
    psnr = frame_psnr(truth, prediction, mask, MAX_FRAME_PSNR_DB)
    lit = psnr[np.isfinite(psnr)]
    out = {"heldout_rel_l2": finite_or_none(relative_l2(prediction, truth, mask)),
           "heldout_frame_psnr_median_db": finite_or_none(np.median(lit)) if lit.size else None,
           "heldout_frame_psnr_worst_db": finite_or_none(lit.min()) if lit.size else None,
           "heldout_specular_rel_l2": None}
    if diffuse is not None and specular_mask is not None:
        out["heldout_specular_rel_l2"] = finite_or_none(relative_l2(prediction, truth, specular_mask, diffuse))
    return out


def supersample(rig: str | Path | None) -> int:
    """The rig description's sub-pixel count per axis (the held-out truth was rendered with it); 1 without one."""
    if rig is None:
        return 1
    return int(read_yaml(rig).get("supersample", 1))


def view_mean(per_view: dict[str, dict], key: str) -> float | None:
    """The mean of ``key`` over the views' records that have it (None where none has)."""
    values = [v[key] for v in per_view.values() if v.get(key) is not None]
    return float(np.mean(values)) if values else None


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Predict every held-out view with both models and score them (:func:`view_scores`), write metrics.json;
    the images as each view is scored."""
    Path(outputs.images).mkdir(parents=True, exist_ok=True)
    per_view: dict[str, Any] = {view: view_scores(inputs, outputs, settings, view, folder)
                                for view, folder in zip(settings.views, inputs.heldout)}

    def mean(key):
        return view_mean(per_view, key)

    trusted = {prefix + key: mean(prefix + key) for prefix in ("heldout_", "baseline_ward_")
               for key in ("rel_l2", "specular_rel_l2", "frame_psnr_median_db", "frame_psnr_worst_db")}

    fit_times = {Path(b).stem: _benchmark_seconds(b) for b in settings.fit_benchmarks}
    metrics = {"normalisation": NORMALISATION, "views": per_view,
               "heldout_psnr_db": mean("heldout_psnr_db"), "heldout_rmse": mean("heldout_rmse"),
               "heldout_ssim": mean("heldout_ssim"), "baseline_ward_psnr_db": mean("baseline_ward_psnr_db"),
               "baseline_ward_ssim": mean("baseline_ward_ssim"),
               **trusted,
               "specular_pixels": {v: r["specular_pixels"] for v, r in per_view.items()},
               "fit_seconds": {"ours": (sum(v for v in fit_times.values() if v is not None)
                                        if any(v is not None for v in fit_times.values()) else None),
                               "ours_stages": fit_times,
                               "baseline_ward": None if settings.ward_benchmark is None
                                                 else _benchmark_seconds(settings.ward_benchmark)},
               "images": "validate/images/VIEW_frameNNNN.png: truth | ours | Ward | 4 x |ours - truth|, "
                         "scaled by the frame's peak, gamma 2.2"}
    write_json(outputs.metrics, metrics)


def view_scores(inputs: Inputs, outputs: Outputs, settings: Settings, view: str, folder: str | Path) -> dict[str, Any]:
    """One held-out view (the capture in ``folder``): predicted by both models into ``outputs.predictions``,
    scored against its truth; its brightest frames' side-by-side images written. Returns the view's record."""
    svbrdf, ward, rig = inputs.svbrdf, inputs.ward, inputs.rig
    out_dir, images_out = Path(outputs.predictions), Path(outputs.images)
    m = manifest.load(Path(folder) / "manifest.json", check_files=False)
    truth = np.stack([read_rgb(f["truth"]["radiance"]) for f in m["frames"]]).astype(float)
    mask = FrameRenderer(load_model(svbrdf), manifest.camera(m)).sample_mask
    predictions = {}
    for name, model in (("ours", svbrdf), ("ward", ward)):
        if model is None:
            continue
        target = out_dir / view / name
        predicted = predict(model, Path(folder) / "manifest.json", target, progress=False)
        predictions[name] = np.stack([read_rgb(target / f["exposures"][0]["file"])
                                      for f in predicted["frames"]]).astype(float)
    diffuse, specular_mask, region, names = None, None, None, []
    if manifest.has_truth(m):
        scene = Scene.load(m["truth"]["scene"])
        diffuse, analytic, region = diffuse_truth(scene, *true_rig(m), supersample(rig))
        specular_mask = mask & analytic
        names = [r["name"] for r in scene.regions]
    ours = image_scores(truth, predictions["ours"], mask)
    record = {"frames": len(m["frames"]), "sample_pixels": int(mask.sum()),
              "camera_view_point": manifest.camera(m).view_point.tolist(),
              "heldout_psnr_db": ours["psnr_db"], "heldout_rmse": ours["rmse"],
              "heldout_rmse_normalised": ours["rmse_normalised"], "heldout_ssim": ours["ssim"],
              "peak_radiance": ours["peak"],
              "specular_pixels": None if specular_mask is None else int(specular_mask.sum())}
    record.update(trusted_scores(truth, predictions["ours"], mask, diffuse, specular_mask))
    if region is not None:
        record["heldout_rel_l2_regions"] = region_scores(truth, predictions["ours"], mask, region, names)
    if "ward" in predictions:
        base = image_scores(truth, predictions["ward"], mask)
        record.update({"baseline_ward_psnr_db": base["psnr_db"], "baseline_ward_rmse": base["rmse"],
                       "baseline_ward_ssim": base["ssim"]})
        record.update({"baseline_ward_" + k[len("heldout_"):]: v for k, v in
                       trusted_scores(truth, predictions["ward"], mask, diffuse, specular_mask).items()})
        if region is not None:
            record["baseline_ward_rel_l2_regions"] = region_scores(truth, predictions["ward"], mask, region,
                                                                   names)
    log.info("%s: ours %.2f dB (SSIM %.4f, rel L2 %s, specular rel L2 %s, frame PSNR median %s / worst %s dB)%s",
             view, ours["psnr_db"], ours["ssim"], _fmt(record["heldout_rel_l2"]),
             _fmt(record["heldout_specular_rel_l2"]), _fmt(record["heldout_frame_psnr_median_db"]),
             _fmt(record["heldout_frame_psnr_worst_db"]),
             f", Ward {record['baseline_ward_psnr_db']:.2f} dB (rel L2 {_fmt(record['baseline_ward_rel_l2'])}, "
             f"specular {_fmt(record['baseline_ward_specular_rel_l2'])})" if "ward" in predictions else "")
    brightest = np.argsort(truth.sum(axis=(1, 2, 3)))[::-1][:settings.images_per_view]
    for q in brightest:
        peak = float(truth[q][mask].max()) if mask.any() else 1.0
        ward_img = predictions["ward"][q] if "ward" in predictions else None
        _to_png(images_out / f"{view}_frame{q:04d}.png",
                side_by_side(truth[q], predictions["ours"][q], ward_img, peak))
    return record
