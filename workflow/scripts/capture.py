from facetsynth.stages import capture
from facetsynth.stages.runner import run_script

run_script(snakemake, capture)
