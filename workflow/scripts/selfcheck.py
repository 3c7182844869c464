from facetsynth.stages import selfcheck
from facetsynth.stages.runner import run_stage

i, o = snakemake.input, snakemake.output
run_stage(snakemake, selfcheck.run, svbrdf=i.svbrdf, manifest=i.manifest, geometry=i.geometry,
          metrics_out=o.metrics, images_out=o.images, settings=selfcheck.Settings.from_params(snakemake.params))
