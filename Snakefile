# facetsynth: single-view SVBRDF capture (Wang et al. 2008) as a Snakemake workflow.
# Run from the repository root:  snakemake --cores 2
# Stages and their contracts: docs/pipeline.md and ../shared/DESIGN.md.

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/capture.smk"
include: "workflow/rules/hdr.smk"
include: "workflow/rules/rectify.smk"
include: "workflow/rules/reflectance.smk"


rule all:
    input:
        expand("results/{sample}/partial_ndf/metrics.json", sample=SAMPLES),
    default_target: True
