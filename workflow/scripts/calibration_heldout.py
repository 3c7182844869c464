"""What fitting from calibrated geometry costs in held-out accuracy (issue 16 item 4), measured.

A virtual capture of a scene with a rig that has ``calibration_error`` records the rig's nominal geometry in
its manifest while its frames were rendered with the true one (facetsynth.truth.virtual_rig). This script fits the
same frames three times and compares the held-out relative L2 (validate/metrics.json):

  nominal     the capture as made (its manifest's nominal camera, LED positions and intensities);
  calibrated  its manifest with the camera and every frame's light position and intensity from
              calibration.json (frames carry ``led`` and ``carriage_steps``), imported (source: import);
  true        the same with the truth (the capture's truth/calibration.json);
  nominal-import  the manifest unchanged, imported: the control (what importing alone changes).

Imported samples have no held-out views of their own (validate renders them for virtual samples only), so
the virtual sample's held-out captures score all three (the same truth). Usage, from a working directory
holding the workflow (Snakefile, workflow/, config/, resources/, rig/):

  python workflow/scripts/calibration_heldout.py --sample cal --scene resources/scenes/demo.yaml \
      --rig rig/descriptions/virtual-demo-calibration-error.yaml \
      --calibration results/calibration/virtual-demo-calibration-error/calibration.json

It runs snakemake (--cores 2) for the virtual sample's validate/metrics.json and the imports' fits, then the
validate stage on the imports; writes calibration_heldout.json and prints the numbers. A few minutes per
fit on 2 cores. Two scorings: ``as_recorded`` is validate's own (each held-out view predicted with the
geometry its manifest records, the nominal one, and scored against the radiance its true geometry
rendered: it charges every fit with the held-out views' own calibration error, and rewards a fit that
absorbed the same LEDs' errors into its BRDF); ``true_geometry`` predicts each held-out view with the
geometry its truth was rendered with, so that only the fitted BRDF is scored.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from facetsynth.capture import manifest
from facetsynth.calibration.rigfile import RigCalibration
from facetsynth.io.fileio import read_json, write_json
from facetsynth.stages import validate


def rewritten(original: dict, camera: dict, light) -> dict:
    """A copy of the manifest ``original`` with ``camera`` (K, R, t, distortion) and each frame's light from
    ``light(frame) -> (position, intensity)``."""
    out = json.loads(json.dumps(original))
    out["camera"].update(camera)
    for frame in out["frames"]:
        position, intensity = light(frame)
        frame["light"] = {"position": np.asarray(position, float).tolist(),
                          "intensity": np.asarray(intensity, float).tolist()}
    return out


def variants(capture: Path, calibration: Path) -> dict[str, dict]:
    """The calibrated and true manifests of a virtual capture with calibration error."""
    nominal = manifest.load(capture / "manifest.json")
    truth = read_json(capture / "truth" / "calibration.json")
    cal = RigCalibration.load(calibration)
    c = cal.camera()
    calibrated = rewritten(nominal, {"K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(),
                                     "distortion": np.asarray(c.distortion, float).tolist()},
                           lambda f: (cal.light_position(f["led"], f["carriage_steps"]), cal.intensity(f["led"])))
    offset, factor = np.asarray(truth["led_offset_m"]), np.asarray(truth["led_intensity_factor"])
    true = rewritten(nominal, {"R": truth["camera"]["R"], "t": truth["camera"]["t"]},
                     lambda f: (np.asarray(f["light"]["position"]) + offset[f["led"]],
                                np.asarray(f["light"]["intensity"]) * factor[f["led"]]))
    return {"calibrated": calibrated, "true": true, "nominal-import": json.loads(json.dumps(nominal))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sample", default="cal")
    parser.add_argument("--scene", default="resources/scenes/demo.yaml")
    parser.add_argument("--rig", default="rig/descriptions/virtual-demo-calibration-error.yaml")
    parser.add_argument("--calibration", required=True)
    parser.add_argument("--cores", default="2")
    parser.add_argument("--out", default="calibration_heldout.json")
    parser.add_argument("--tag", default="",
                        help="suffix of the calibrated import's sample name, to compare calibrations (--tag=-v2)")
    parser.add_argument("--score-only", action="store_true", help="the fits exist: only score them")
    args = parser.parse_args()
    sample = args.sample
    sheet = Path(f"samples-{sample}-heldout.tsv")
    rows = [f"{sample}\tvirtual\t{args.scene}\t{args.rig}"]
    snake = [sys.executable, "-m", "snakemake", "--cores", args.cores]
    config = ["--config", f"samples={sheet}"]     # after the targets: --config takes every word that follows
    if not args.score_only:
        sheet.write_text("sample\tsource\tpath\trig\n" + "\n".join(rows) + "\n")
        subprocess.run(snake + [f"results/{sample}/validate/metrics.json"] + config, check=True)

    names = {}
    for name, variant in variants(Path("results") / sample / "capture", Path(args.calibration)).items():
        names[name] = f"{sample}-{name}" + (args.tag if name == "calibrated" else "")
        folder = Path("imports") / names[name]
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / "manifest.json"
        clean = json.loads(json.dumps({k: v for k, v in variant.items() if not k.startswith("_")}))
        if not path.is_file() or read_json(path) != clean:    # unchanged: no re-fit
            manifest.save(path, variant)
        rows.append(f"{names[name]}\timport\t{folder}\t")
    if not args.score_only:
        sheet.write_text("sample\tsource\tpath\trig\n" + "\n".join(rows) + "\n")
        targets = [f"results/{s}/{p}" for s in names.values()
                   for p in ("svbrdf", "params/metrics.json", "baseline/ward")]
        subprocess.run(snake + targets + config, check=True)

    heldout_root = Path("results") / sample / "validate" / "heldout"
    heldout = {p.name: p for p in sorted(heldout_root.iterdir())}
    true_heldout = {view: true_geometry_view(folder, Path("results") / sample / "validate" / "heldout-true" / view)
                    for view, folder in heldout.items()}
    record = {"calibration": str(args.calibration)}
    for label, s in [("nominal", sample)] + list(names.items()):
        for scoring, views, sub in (("as_recorded", heldout, "validate"), ("true_geometry", true_heldout,
                                                                           "validate-true-geometry")):
            out = Path("results") / s / sub
            if scoring == "as_recorded" and s == sample:
                pass                                   # the virtual sample's own validate/metrics.json
            elif not (out / "metrics.json").is_file() or not args.score_only or scoring == "true_geometry":
                validate.run(validate.Inputs(svbrdf=Path(f"results/{s}/svbrdf"), heldout=list(views.values()),
                                             ward=Path(f"results/{s}/baseline/ward"), rig=args.rig),
                             validate.Outputs(metrics=out / "metrics.json", images=out / "images",
                                              predictions=out / "predictions"),
                             validate.Settings(views=tuple(views), fit_benchmarks=tuple(
                                 f"results/{s}/benchmarks/{st}.tsv"
                                 for st in ("partial_ndf", "cluster", "synthesize", "params", "refine")),
                                 ward_benchmark=f"results/{s}/benchmarks/baseline_ward.tsv"))
            m = read_json(out / "metrics.json")
            record.setdefault(label, {})[scoring] = {k: m.get(k) for k in ("heldout_rel_l2", "heldout_specular_rel_l2",
                                                                           "baseline_ward_rel_l2")}
    write_json(args.out, record)
    for label, r in record.items():
        if isinstance(r, dict):
            for scoring, v in r.items():
                print(f"{label:>14} {scoring:>13}: held-out rel. L2 {v['heldout_rel_l2']:.4f}, "
                      f"specular {v['heldout_specular_rel_l2']:.4f}, Ward {v['baseline_ward_rel_l2']:.4f}")


def true_geometry_view(folder: Path, out: Path) -> Path:
    """A held-out view's manifest with the geometry its truth was rendered with (the true camera, each frame's
    true light and intensity) in place of the nominal one, its truth/calibration dropped (the manifest is the
    truth now): predictions from it score the fitted BRDF alone, not the held-out view's own calibration."""
    m = manifest.load(folder / "manifest.json", check_files=False)
    truth = read_json(folder / "truth" / "calibration.json")
    offset, factor = np.asarray(truth["led_offset_m"]), np.asarray(truth["led_intensity_factor"])
    new = rewritten({k: v for k, v in m.items() if not k.startswith("_")},
                    {"R": truth["camera"]["R"], "t": truth["camera"]["t"]},
                    lambda f: (np.asarray(f["light"]["position"]) + offset[f["led"]],
                               np.asarray(f["light"]["intensity"]) * factor[f["led"]]))
    new["truth"].pop("calibration", None)
    out.mkdir(parents=True, exist_ok=True)
    manifest.save(out / "manifest.json", new)
    return out

if __name__ == "__main__":
    main()
