from facetsynth.stages import heldout_capture
from facetsynth.stages.runner import run_script

run_script(snakemake, heldout_capture)
