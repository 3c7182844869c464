# Calibration of a rig (paper 002 sec. 4; issue 16 item 4): camera K, distortion, R, t from checkerboards
# (Zhang 2000), LED positions from a flat mirror's highlights, LED intensities from a white reference,
# into one results/calibration/{rig}/calibration.json (schema rig_calibration.schema.json; loader
# facetsynth.calibration.rigfile.RigCalibration). {rig} names rig/descriptions/{rig}.yaml.
# A virtual rig renders its targets (rule calibration_targets); for a real rig, photograph them into
# results/calibration/{rig}/targets/ in the layout of facetsynth.calibration (its docstring).

from facetsynth.calibration.settings import CalibrateSettings, TargetSettings


include: "calibrate_common.smk"


rule calibration_targets:
    input:
        calibration_rig,
    output:
        directory("results/calibration/{rig}/targets"),
    log:
        "results/calibration/{rig}/logs/calibration_targets.log",
    benchmark:
        "results/calibration/{rig}/benchmarks/calibration_targets.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    params:
        **calibration_params(TargetSettings),
        rig="rig/descriptions/{rig}.yaml",
        seed=config["seed"],
        noise=config["virtual"]["noise"],
    script:
        "../scripts/calibrate_targets.py"


rule calibrate:
    input:
        targets="results/calibration/{rig}/targets",
    output:
        "results/calibration/{rig}/calibration.json",
    log:
        "results/calibration/{rig}/logs/calibrate.log",
    benchmark:
        "results/calibration/{rig}/benchmarks/calibrate.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    params:
        **calibration_params(CalibrateSettings),
    script:
        "../scripts/calibrate_fit.py"
