from facetsynth.stages import selfcheck
from facetsynth.stages.runner import run_script

run_script(snakemake, selfcheck)
