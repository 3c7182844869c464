# facetsynth: single-view SVBRDF capture (Wang et al. 2008) as a Snakemake workflow.
# Run from the repository root:  snakemake --cores 2
# Stages and their contracts: README.md, docs/decisions.md and ../shared/DESIGN.md.

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/capture.smk"
include: "workflow/rules/hdr.smk"
include: "workflow/rules/rectify.smk"
include: "workflow/rules/reflectance.smk"
include: "workflow/rules/synthesis.smk"
include: "workflow/rules/params.smk"
include: "workflow/rules/validate.smk"
include: "workflow/rules/stencil.smk"
include: "workflow/rules/export.smk"
include: "workflow/rules/report.smk"


def final_outputs(sample):
    """What a user takes away: the fitted SVBRDF with its stencil models and self-check, and for a sample whose
    held-out views the virtual rig can render (a virtual one, or the rig with the virtual camera)
    the held-out validation."""
    outputs = [f"results/{sample}/svbrdf", f"results/{sample}/stencil_fit/metrics.json",
               f"results/{sample}/selfcheck/metrics.json"]   # every sample: the fit against its own frames
    if rendered_truth(sample) is not None:
        outputs.append(f"results/{sample}/validate/metrics.json")
    outputs.append(f"results/{sample}/export/metrics.json")   # the portable glTF material and its loss
    outputs += report_figures(sample)   # the figures of `snakemake --report` (workflow/rules/report.smk)
    return outputs


rule all:
    input:
        [path for sample in MODEL_SAMPLES for path in final_outputs(sample)],
    default_target: True
