# The functions of calibrate.smk's rules, apart from common.smk: calibrate.smk runs without the samples'
# workflow too (a Snakefile with a config of seed and virtual.noise that includes calibrate.smk alone:
# tests/calibration/test_calibration.py), and snakemake --lint wants no functions beside rules.

from dataclasses import fields as _fields


def calibration_params(settings):
    """A settings dataclass's fields from config section 'calibration', its defaults for keys left out."""
    return {f.name: (config.get("calibration") or {}).get(f.name, f.default) for f in _fields(settings)}


def calibration_rig(wildcards):
    """The virtual rig description the targets are rendered from; none for a real rig (its targets are photos:
    the job then says where to put them)."""
    from facetsynth.truth.virtual_rig import VirtualRig  # here, not at parse: it imports the renderer

    path = f"rig/descriptions/{wildcards.rig}.yaml"
    try:
        VirtualRig.load(path)
    except Exception:
        return []
    return [path]
