from facetsynth.stages import validate
from facetsynth.stages.runner import run_script

run_script(snakemake, validate)
