from facetsynth.stages import hdr
from facetsynth.stages.runner import run_script

run_script(snakemake, hdr)
