# Calibration of a rig (paper 002 sec. 4; issue 16 item 4): camera K, distortion, R, t from checkerboards
# (Zhang 2000), LED positions from a flat mirror's highlights, LED intensities from a white reference,
# into one results/calibration/{rig}/calibration.json (schema rig_calibration.schema.json; loader
# facetsynth.calibration.rigfile.RigCalibration). {rig} names rig/descriptions/{rig}.yaml.
# A virtual rig renders its targets (rule calibration_targets); for a real rig, photograph them into
# results/calibration/{rig}/targets/ in the layout of facetsynth.calibration (its docstring).

from dataclasses import fields as _fields

from facetsynth.stages.calibrate import CalibrateSettings, TargetSettings
from facetsynth.virtual_rig import VirtualRig


def calibration_params(settings):
    """A settings dataclass's fields from config section 'calibration', its defaults for keys left out."""
    return {f.name: (config.get("calibration") or {}).get(f.name, f.default) for f in _fields(settings)}


def calibration_rig(wildcards):
    """The virtual rig description the targets are rendered from; none for a real rig (its targets are photos:
    the job then says where to put them)."""
    path = f"rig/descriptions/{wildcards.rig}.yaml"
    try:
        VirtualRig.load(path)
    except Exception:
        return []
    return [path]


rule calibration_targets:
    input:
        calibration_rig,
    output:
        directory("results/calibration/{rig}/targets"),
    params:
        rig="rig/descriptions/{rig}.yaml",
        seed=config["seed"],
        noise=config["virtual"]["noise"],
        **calibration_params(TargetSettings),
    log:
        "results/calibration/{rig}/logs/calibration_targets.log",
    benchmark:
        "results/calibration/{rig}/benchmarks/calibration_targets.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../scripts/calibrate_targets.py"


rule calibrate:
    input:
        targets="results/calibration/{rig}/targets",
    output:
        "results/calibration/{rig}/calibration.json",
    params:
        **calibration_params(CalibrateSettings),
    log:
        "results/calibration/{rig}/logs/calibrate.log",
    benchmark:
        "results/calibration/{rig}/benchmarks/calibrate.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../scripts/calibrate_fit.py"
