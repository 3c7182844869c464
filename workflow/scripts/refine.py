from facetsynth.stages import refine
from facetsynth.stages.runner import run_script

run_script(snakemake, refine)
