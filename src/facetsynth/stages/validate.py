"""Stage ``validate``: held-out views, predicted and scored (paper 002 sec. 6, Figs. 9-10).

For a virtual sample the virtual rig renders held-out captures from views
that were not used for fitting (``heldout_capture``); the fitted SVBRDF and
the Ward baseline predict them with :func:`facetsynth.predict.predict` (the
code path of ``facetsynth predict``); predictions are scored against the true
radiance of the held-out frames over the sample's pixels
(:func:`facetsynth.metrics.image_scores`, normalisation stated there and in
the metrics file), and side-by-side images are written.
"""

from __future__ import annotations

import copy
import csv
import logging
from pathlib import Path
from typing import Any

import numpy as np

from .. import manifest as manifest_io
from ..fileio import atomic_path, read_rgb, write_json
from ..metrics import image_scores
from ..predict import FrameRenderer, load_model, predict
from ..virtual_rig import VirtualRig, capture as virtual_capture

log = logging.getLogger(__name__)

NORMALISATION = ("over the sample's pixels (every sub-pixel on the sample), linear radiance, all frames of a view "
                 "pooled: rmse in radiance units; psnr_db = 20 log10(peak / rmse) with peak = the largest true "
                 "radiance of the view; ssim of channel-mean images divided by that peak (Gaussian window 1.5, "
                 "data range 1), averaged over sample pixels and frames; truth = the virtual rig's true radiance")


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


def heldout_capture(scene: str | Path, rig: str | Path, out_dir: str | Path, theta_deg: float, phi_deg: float,
                    led_every: int = 4, position_every: int = 4, seed: int = 0) -> None:
    """Render a held-out capture (noise-free; its truth radiance is what predictions are scored against)."""
    held = heldout_rig(VirtualRig.load(rig), theta_deg, phi_deg, led_every, position_every)
    log.info("held-out view theta %.1f deg, phi %+.1f deg (relative), %d lights", theta_deg, phi_deg,
             len(held.scan()))
    virtual_capture(scene, held, out_dir, seed=seed, noise=False)


def _benchmark_seconds(path: str | Path) -> float | None:
    path = Path(path)
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    return float(rows[0]["s"]) if rows else None


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


def run(svbrdf: str | Path, ward: str | Path | None, heldout: dict[str, str | Path], out_dir: str | Path,
        metrics_out: str | Path, images_out: str | Path, fit_benchmarks: list[str | Path],
        ward_benchmark: str | Path | None, images_per_view: int = 2) -> None:
    """Predict every held-out view with both models, score them, write metrics.json and the images."""
    out_dir, images_out = Path(out_dir), Path(images_out)
    images_out.mkdir(parents=True, exist_ok=True)
    per_view: dict[str, Any] = {}
    for view, folder in heldout.items():
        m = manifest_io.load(Path(folder) / "manifest.json", check_files=False)
        truth = np.stack([read_rgb(f["truth"]["radiance"]) for f in m["frames"]]).astype(float)
        mask = FrameRenderer(load_model(svbrdf), manifest_io.camera(m)).sample_mask
        predictions = {}
        for name, model in (("ours", svbrdf), ("ward", ward)):
            if model is None:
                continue
            target = out_dir / view / name
            predicted = predict(model, Path(folder) / "manifest.json", target, progress=False)
            predictions[name] = np.stack([read_rgb(target / f["exposures"][0]["file"])
                                          for f in predicted["frames"]]).astype(float)
        ours = image_scores(truth, predictions["ours"], mask)
        record = {"frames": len(m["frames"]), "sample_pixels": int(mask.sum()),
                  "camera_centre": manifest_io.camera(m).centre.tolist(),
                  "heldout_psnr_db": ours["psnr_db"], "heldout_rmse": ours["rmse"],
                  "heldout_rmse_normalised": ours["rmse_normalised"], "heldout_ssim": ours["ssim"],
                  "peak_radiance": ours["peak"]}
        if "ward" in predictions:
            base = image_scores(truth, predictions["ward"], mask)
            record.update({"baseline_ward_psnr_db": base["psnr_db"], "baseline_ward_rmse": base["rmse"],
                           "baseline_ward_ssim": base["ssim"]})
        per_view[view] = record
        log.info("%s: ours %.2f dB (SSIM %.4f)%s", view, ours["psnr_db"], ours["ssim"],
                 f", Ward {record['baseline_ward_psnr_db']:.2f} dB" if "ward" in predictions else "")
        brightest = np.argsort(truth.sum(axis=(1, 2, 3)))[::-1][:images_per_view]
        for q in brightest:
            peak = float(truth[q][mask].max()) if mask.any() else 1.0
            ward_img = predictions["ward"][q] if "ward" in predictions else None
            _to_png(images_out / f"{view}_frame{q:04d}.png",
                    side_by_side(truth[q], predictions["ours"][q], ward_img, peak))

    def mean(key):
        values = [v[key] for v in per_view.values() if key in v]
        return float(np.mean(values)) if values else None

    fit_times = {Path(b).stem: _benchmark_seconds(b) for b in fit_benchmarks}
    metrics = {"normalisation": NORMALISATION, "views": per_view,
               "heldout_psnr_db": mean("heldout_psnr_db"), "heldout_rmse": mean("heldout_rmse"),
               "heldout_ssim": mean("heldout_ssim"), "baseline_ward_psnr_db": mean("baseline_ward_psnr_db"),
               "baseline_ward_ssim": mean("baseline_ward_ssim"),
               "fit_seconds": {"ours": (sum(v for v in fit_times.values() if v is not None)
                                        if any(v is not None for v in fit_times.values()) else None),
                               "ours_stages": fit_times,
                               "baseline_ward": None if ward_benchmark is None else _benchmark_seconds(ward_benchmark)},
               "images": "validate/images/VIEW_frameNNNN.png: truth | ours | Ward | 4 x |ours - truth|, "
                         "scaled by the frame's peak, gamma 2.2"}
    write_json(metrics_out, metrics)
