from facetsynth.stages import baseline
from facetsynth.stages.runner import run_script

run_script(snakemake, baseline)
