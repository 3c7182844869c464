from facetsynth.stages import synthesize
from facetsynth.stages.runner import run_script

run_script(snakemake, synthesize)
