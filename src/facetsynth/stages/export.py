"""Stage ``export_gltf``: the portable glTF 2.0 material and what it costs in accuracy (issue 17 item 3).

Writes the glTF folder (:func:`facetsynth.export.gltf.export_gltf`) and, for a sample with held-out truth
(``validate/heldout/{view}``), renders every held-out frame with the portable material as read back from
the written files (8-bit textures, what a renderer gets) through :class:`facetsynth.app.predict.FrameRenderer`,
and scores it with the validate stage's own scoring (:func:`facetsynth.stages.validate.trusted_scores`,
same sample mask, same diffuse truth), beside the full SVBRDF's scores from ``validate/metrics.json``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..capture import manifest
from ..export.gltf import GLTF_NAME, export_gltf, read_gltf
from ..io.fileio import read_json, read_rgb, write_json
from ..app.predict import FrameRenderer
from ..truth.scene import Scene
from .common import RuleFiles, StageSettings
from .validate import diffuse_truth, supersample, true_rig, trusted_scores, view_mean

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``export_gltf``'s inputs: the SVBRDF folder; for a sample with held-out truth (else None) the
    held-out captures (one folder per view of ``Settings.views``), validate's metrics and the truth's rig."""
    svbrdf: Path
    heldout: list[Path] | None = None
    validate_metrics: Path | None = None
    rig: Path | None = None


class Outputs(RuleFiles):
    """Rule ``export_gltf``'s outputs: the glTF folder and the export's figures."""
    gltf: Path
    metrics: Path


class Settings(StageSettings):
    """The export's knobs: measured defaults, not in the workflow's config (nothing there to trade yet); and the
    rule's ``views``, the names of the held-out views in the order of ``Inputs.heldout``."""
    MEASURED = ("weight_quantum", "iterations", "fresnel_cos_min")
    views: tuple = ()              # rule param: the held-out views' names (config validate.views)
    weight_quantum: float = 0.01   # eq. 18 weights rounded to this before fitting each distinct mixture once
                                   # (demo: 639 mixtures for 28224 points; alphas within 0.5 % of the exact fit)
    iterations: int = 12           # Levenberg-Marquardt steps of the GGX fit (exact GGX tables: converged by 12)
    fresnel_cos_min: float = 0.5   # the Schlick f0 is fitted to eq. 3's Fresnel over |v.h| in [this, 1]
                                   # (1: matched at normal incidence only; facetsynth.export.gltf.schlick_f0)


def score_view(model, folder: str | Path, supersample: int = 1) -> dict[str, Any]:
    """The held-out scores of ``model`` on the capture in ``folder`` (validate's normalisation)."""
    m = manifest.load(Path(folder) / "manifest.json", check_files=False)
    truth = np.stack([read_rgb(f["truth"]["radiance"]) for f in m["frames"]]).astype(float)
    renderer = FrameRenderer(model, manifest.camera(m))
    mask = renderer.sample_mask
    prediction = np.stack([renderer.radiance(manifest.light_point(f["light"]), f["light"]["intensity"])
                           for f in m["frames"]]).astype(float)
    diffuse, specular_mask = None, None
    if manifest.has_truth(m):
        diffuse, analytic, _ = diffuse_truth(Scene.load(m["truth"]["scene"]), *true_rig(m), supersample)
        specular_mask = mask & analytic
    return trusted_scores(truth, prediction, mask, diffuse, specular_mask)


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Export, then score the portable material on the held-out views (if any) against the full SVBRDF's;
    write export/metrics.json."""
    start = time.perf_counter()
    summary = export_gltf(inputs.svbrdf, outputs.gltf, weight_quantum=settings.weight_quantum,
                          iterations=settings.iterations, fresnel_cos_min=settings.fresnel_cos_min)
    export_seconds = time.perf_counter() - start
    metrics: dict[str, Any] = {
        "gltf": str(Path(outputs.gltf) / GLTF_NAME), "files": [Path(f).name for f in summary["files"]],
        "fit_seconds": summary["fit"]["fit_seconds"], "export_seconds": export_seconds,
        "fit": summary["fit"], "round_trip": summary["round_trip"],
        "normalisation": "heldout_rel_l2 and heldout_specular_rel_l2 as validate/metrics.json (same frames, sample "
                         "mask and diffuse truth); portable = the material read back from the written glTF "
                         "(8-bit textures), rendered by facetsynth.models.ggx; full = validate/metrics.json's; "
                         "loss = portable - full", "views": {}}
    if inputs.heldout:
        metrics.update(heldout_scores(inputs, Path(outputs.gltf) / GLTF_NAME, settings.views))
    write_json(outputs.metrics, metrics)


def heldout_scores(inputs: Inputs, gltf: Path, views) -> dict[str, Any]:
    """The portable material read back from ``gltf`` on every held-out view (``inputs.heldout``, named by
    ``views``) beside the full SVBRDF's (``inputs.validate_metrics``): per view and their means."""
    full = read_json(inputs.validate_metrics)["views"] if inputs.validate_metrics else {}
    sub_pixels = supersample(inputs.rig)
    portable = read_gltf(gltf)
    out: dict[str, Any] = {"views": {}}
    for view, folder in zip(views, inputs.heldout):
        scores = score_view(portable, folder, sub_pixels)
        record = {"portable_" + k[len("heldout_"):]: v for k, v in scores.items()}
        for key in ("rel_l2", "specular_rel_l2"):
            ours = full.get(view, {}).get("heldout_" + key)
            record["full_" + key] = ours
            mine = record["portable_" + key]
            record["loss_" + key] = None if ours is None or mine is None else mine - ours
        out["views"][view] = record
        log.info("%s: held-out rel L2 portable %.4f, full %s", view, record["portable_rel_l2"],
                 record["full_rel_l2"])
    for key in ("portable_rel_l2", "full_rel_l2", "loss_rel_l2", "portable_specular_rel_l2",
                "full_specular_rel_l2", "loss_specular_rel_l2"):
        out["heldout_" + key] = view_mean(out["views"], key)
    return out
