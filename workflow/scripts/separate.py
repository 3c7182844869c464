from facetsynth.stages import separate
from facetsynth.stages.runner import run_script

run_script(snakemake, separate)
