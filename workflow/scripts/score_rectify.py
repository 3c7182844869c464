from facetsynth.stages import score_rectify
from facetsynth.stages.runner import run_script

run_script(snakemake, score_rectify)
