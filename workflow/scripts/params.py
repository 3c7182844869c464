from facetsynth.stages import params
from facetsynth.stages.runner import run_script

run_script(snakemake, params)
