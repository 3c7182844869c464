"""Stage ``selfcheck``: the fitted SVBRDF against its own capture, for every sample (issue 29).

No ground truth is needed: the fitting camera's HDR frames are the
measurement. The model relights (a) every ``relit_every``-th of the frames it
was fitted on and (b) the held-out lights (every ``heldout_every``-th frame,
which ``separate`` kept out of the fit): :mod:`facetsynth.evaluation.selfcheck` defines
both subsets and the scores. Pixels clipped in a frame (hdr's ``saturated``)
are left out of that frame's scores. Writes ``selfcheck/metrics.json`` and,
per subset, a measured | predicted | 4 x difference picture of its worst frame.

A light dome's capture (directional lights, an orthographic camera: one light
direction per frame for every pixel) is also fitted per pixel by the models its
users rely on today (:mod:`facetsynth.rti.fits`: Lambertian photometric stereo,
PTM, HSH of orders 2 and 3) on the same fitting frames, and scored on the same
subsets and pixels: ``baselines`` in the metrics; the pictures then read
measured | facetsynth | HSH order 3 | 4 x facetsynth's difference. These fit
the linear frames. RTIBuilder and relight fit HSH to the 8-bit codes as they
are; where the capture declares its codes' transfer (one 8-bit exposure per
frame, ``inputs.capture``), ``hsh3_codes`` is that fit, its predicted codes
decoded by the same transfer and scored on the same linear frames.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..capture import manifest, transfer
from ..io.fileio import read_codes, read_frame, read_json, write_json
from ..evaluation.metrics import finite_or_none
from ..app.predict import FrameRenderer, load_model
from ..capture.rectify import sample_pixels
from ..rti import fits
from ..evaluation.selfcheck import FrameScores, heldout_lights, relit_frames
from .common import RuleFiles, StageSettings
from .validate import _to_png, side_by_side

log = logging.getLogger(__name__)

# A self-check a fit fails: relative L2 on the held-out lights above this (the specular part is reported
# beside it). On the virtual scenes of docs/accuracy.md the self-check and the truth-based held-out views
# agree within this order (docs/accuracy.md "Self-check").
POOR_FIT_REL_L2 = 0.15
PICTURE_HEIGHT = 320   # the worst frames' pictures are at least this tall (the report's figures)

DEFINITION = ("relative L2 = sqrt(sum (pred - meas)^2 / sum meas^2) over the pixels that see the sample alone "
              "(all four corners on it, facetsynth.capture.rectify.sample_pixels; pixels clipped in a frame left out of "
              "that frame), every frame and RGB channel of "
              "the subset, meas = the hdr stage's frames of the fitting camera; specular_rel_l2 = the same error "
              "against sum (meas - diffuse)^2, diffuse = the model's own kd/pi (n.i) L / r^2; frame PSNR = 20 "
              "log10(peak / rmse) per frame, peak = the frame's largest measured radiance on the sample, capped "
              "at 100 dB. relit: every relit_every-th frame of those the fit used; heldout: every "
              "heldout_every-th frame from heldout_every // 2, kept out of every stage after hdr "
              "(facetsynth.evaluation.selfcheck)")


class Inputs(RuleFiles):
    """Rule ``selfcheck``'s inputs: the fitted SVBRDF folder, hdr's manifest and its frames folder (the files the
    manifest lists: a dependency, read through the manifest; None outside the workflow), separate's geometry
    (the lights' intensities as the fit saw them; None: the manifest's)."""
    svbrdf: Path
    manifest: Path
    frames: Path | None = None
    geometry: Path | None = None
    capture: Path | None = None      # the capture folder: its 8-bit exposures and their transfer (hsh3_codes)


class Outputs(RuleFiles):
    """Rule ``selfcheck``'s outputs: the scores and the folder of the worst frames' pictures."""
    metrics: Path
    images: Path


class Settings(StageSettings):
    """The stage's knobs: config ``selfcheck`` (workflow/schemas/config.schema.yaml)."""
    heldout_every: int = 10    # every 10th light is held out of the fit (0: none) ...
    relit_every: int = 8       # ... and every 8th of the others relit


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> dict:
    """Relight both subsets from the model in ``inputs.svbrdf``, score them against the frames of the hdr
    ``inputs.manifest``, write the metrics and pictures; returns the metrics. The lights' intensities are
    those the fit saw, from ``inputs.geometry`` (``separate/geometry.json``: estimated for a capture that
    stated none) when given, else the manifest's."""
    m = manifest.load(inputs.manifest)
    nominal = copy.deepcopy(m)      # the per-pixel baselines fit the photos as their users do: nominal lights
    if inputs.geometry is not None:
        for frame, seen in zip(m["frames"], read_json(inputs.geometry)["frames"]):
            frame["light"]["intensity"] = seen["light"]["intensity"]
    camera = manifest.camera(m)
    renderer = FrameRenderer(load_model(inputs.svbrdf), camera)
    # pixels across the sample's edge mix it with the background: no measurement of it (rectify leaves them out)
    sample = renderer.sample_mask & sample_pixels(camera, m["sample"]["width"], m["sample"]["height"])
    held = heldout_lights(len(m["frames"]), settings.heldout_every)
    subsets = {"relit": relit_frames(held, settings.relit_every), "heldout": np.flatnonzero(held)}
    images_out = Path(outputs.images)
    images_out.mkdir(parents=True, exist_ok=True)
    metrics: dict = {"definition": DEFINITION, "frames": len(m["frames"]), "sample_pixels": int(sample.sum()),
                     "heldout_every": settings.heldout_every, "relit_every": settings.relit_every}
    codes = None if inputs.capture is None else declared_codes(Path(inputs.capture) / "manifest.json")
    baselines = per_pixel_baselines(nominal, held, subsets, sample, codes)
    if baselines is not None:
        metrics["baselines"] = {kind: {name: finite_or_none(s.rel_l2) for name, s in scored.items()}
                                for kind, (scored, _) in baselines.items()}
    for name, frames in subsets.items():
        metrics[name] = subset_scores(m, renderer, sample, name, frames, baselines, images_out)
    for kind, scores in metrics.get("baselines", {}).items():
        log.info("per-pixel %s: relit %s, held-out %s", kind, scores["relit"], scores["heldout"])
    poor = (metrics["heldout"]["rel_l2"] or 0.0) > POOR_FIT_REL_L2
    metrics["poor_fit"] = bool(poor)
    if poor:
        log.warning("POOR FIT: the held-out lights miss by %.3f relative L2 (more than %.2f): the model does not "
                    "predict this capture's own lights", metrics["heldout"]["rel_l2"], POOR_FIT_REL_L2)
    write_json(outputs.metrics, metrics)
    return metrics


def subset_scores(m: dict, renderer: FrameRenderer, sample: np.ndarray, name: str, frames: np.ndarray, baselines,
                  images_out: Path) -> dict:
    """The subset ``name`` (frames ``frames`` of the manifest ``m``) relit by ``renderer`` and scored against
    hdr's frames over the unclipped pixels of ``sample`` (H, W); its worst frame's picture written to
    ``images_out`` (beside the per-pixel HSH order 3 where ``baselines``). Returns the subset's record."""
    scores, picture = FrameScores(), None
    for q in tqdm(frames, desc=f"selfcheck: {name}", unit="frame"):
        light = m["frames"][q]["light"]
        exposure = m["frames"][q]["exposures"][0]             # hdr's merged frame (time 1: radiance)
        measured, clipped = read_frame(exposure["file"])
        measured = measured / float(exposure["time"])
        predicted = renderer.radiance(manifest.light_point(light), light["intensity"])
        diffuse = renderer.radiance(manifest.light_point(light), light["intensity"], diffuse_only=True)
        scores.add(q, measured, predicted, diffuse, sample & ~clipped)
        if scores.worst_frame() == q:         # the worst frame so far: its images are kept
            picture = (measured, predicted, None if baselines is None else baselines["hsh3"][1](q))
    psnr = np.asarray(scores.psnr_db)
    lit = psnr[np.isfinite(psnr)]
    worst = scores.worst_frame()
    record = {"frames": len(frames), "rel_l2": finite_or_none(scores.rel_l2),
              "specular_rel_l2": finite_or_none(scores.specular_rel_l2),
              "frame_psnr_median_db": finite_or_none(np.median(lit)) if lit.size else None,
              "frame_psnr_worst_db": finite_or_none(lit.min()) if lit.size else None,
              "worst_frame": worst}
    if picture is not None:
        measured, predicted, hsh = picture
        peak = float(measured[sample].max()) if sample.any() else 1.0
        picture = side_by_side(measured, predicted, hsh, peak)
        zoom = max(1, -(-PICTURE_HEIGHT // picture.shape[0]))    # small cameras: pixels shown zoom x zoom
        _to_png(images_out / f"{name}_worst.png", picture.repeat(zoom, axis=0).repeat(zoom, axis=1))
    log.info("%s: %d frames, rel L2 %s, specular %s, frame PSNR median %s dB, worst %s dB (frame %s)", name,
             len(frames), record["rel_l2"], record["specular_rel_l2"], record["frame_psnr_median_db"],
             record["frame_psnr_worst_db"], worst)
    return record


def declared_codes(path: Path):
    """The capture manifest's 8-bit codes and how they decode, for ``hsh3_codes``: (codes (F, H, W, 3) uint8,
    frame q -> the linear frame of code values (H, W, 3), any reals); None unless it declares a ``transfer`` and
    every frame has one exposure (a light dome's one JPEG per light). The codes stay 8-bit: the fits convert
    them a block of pixels at a time (a float64 copy of the fresco's is 250 MB)."""
    m = manifest.load(path)
    if "transfer" not in m or any(len(f["exposures"]) != 1 for f in m["frames"]):
        return None
    times = np.array([float(f["exposures"][0]["time"]) for f in m["frames"]])
    codes = np.stack([read_codes(f["exposures"][0]["file"]) for f in m["frames"]])

    def linear(q: int, code: np.ndarray) -> np.ndarray:     # hdr's frame of these codes: decoded, over the time
        return transfer.linearise(code / float(transfer.LEVELS - 1), m["transfer"], m.get("black_level", 0.0)) / times[q]

    return codes, linear


def per_pixel_baselines(m: dict, held: np.ndarray, subsets: dict[str, np.ndarray], sample: np.ndarray,
                        codes=None):
    """Per kind of :data:`facetsynth.rti.fits.KINDS`: ({subset: FrameScores}, frame q -> predicted image), the
    per-pixel fit on the frames not ``held`` out, scored as the SVBRDF is; with ``codes``
    (:func:`declared_codes`) also ``hsh3_codes``: HSH 3 fitted to the codes, its predictions decoded. None
    unless every light is directional and the camera orthographic (elsewhere a frame has no one light
    direction)."""
    lights = manifest.lights(m["frames"])
    if np.any(lights[:, 3] != 0) or not manifest.camera(m).orthographic:
        return None
    frames = [read_frame(f["exposures"][0]["file"]) for f in m["frames"]]
    measured = np.stack([rgb / float(f["exposures"][0]["time"]) for (rgb, _), f in zip(frames, m["frames"])])
    measured /= manifest.light_intensities(m["frames"])[:, None, None, :]   # to unit irradiance
    directions, training = lights[:, :3], np.flatnonzero(~held)
    predictors = {}
    for kind in fits.KINDS:
        coefficients = fits.fit(kind, directions[training], measured[training])

        def predict(q: int, coefficients=coefficients, kind=kind) -> np.ndarray:
            intensity = np.asarray(m["frames"][q]["light"]["intensity"], float)
            return fits.relight(kind, coefficients, directions[q:q + 1])[0] * intensity

        predictors[kind] = predict
    if codes is not None and codes[0].shape != measured.shape:
        log.warning("hsh3_codes not fitted: the capture's 8-bit exposures are %s, hdr's frames %s",
                    codes[0].shape, measured.shape)
    elif codes is not None:
        values, linear = codes
        on_codes = fits.fit("hsh3", directions[training], values[training])
        predictors["hsh3_codes"] = lambda q: linear(q, fits.relight("hsh3", on_codes, directions[q:q + 1])[0])
    out = {}
    for kind, predict in predictors.items():
        scored = {}
        for name, subset in subsets.items():
            scored[name] = FrameScores()
            for q in subset:
                clipped = frames[q][1]
                truth = measured[q] * np.asarray(m["frames"][q]["light"]["intensity"], float)
                scored[name].add(q, truth, predict(q), np.zeros_like(truth), sample & ~clipped)
        out[kind] = (scored, predict)
    return out
