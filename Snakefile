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


rule all:
    default_target: True
    input:
        [path for sample in MODEL_SAMPLES for path in final_outputs(sample)],
