from facetsynth.stages import cluster
from facetsynth.stages.runner import run_script

run_script(snakemake, cluster)
