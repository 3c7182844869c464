from facetsynth.stages import rectify
from facetsynth.stages.runner import run_script

run_script(snakemake, rectify)
