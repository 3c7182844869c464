from facetsynth.stages import stencil_fit
from facetsynth.stages.runner import run_script

run_script(snakemake, stencil_fit)
