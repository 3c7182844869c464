from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

i = snakemake.input
run_stage(snakemake, figures.write_clusters, labels=i.labels, representatives=i.representatives,
          geometry=i.geometry, out=snakemake.output[0], sample=snakemake.wildcards.sample)
