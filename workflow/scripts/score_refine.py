from facetsynth.stages import score_refine
from facetsynth.stages.runner import run_script

run_script(snakemake, score_refine)
