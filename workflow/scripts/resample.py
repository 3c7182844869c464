from facetsynth.stages import resample
from facetsynth.stages.common import scatter_item
from facetsynth.stages.runner import run_stage

settings = resample.Settings.from_params(snakemake.params)
i, o = snakemake.input, snakemake.output
if "record" in o.keys():        # one scatter part ({scatteritem} = "k-of-n")
    part, parts = scatter_item(snakemake.wildcards.scatteritem)
    run_stage(snakemake, resample.run_part, geometry=i.geometry, specular=i.specular, valid=i.valid, part=part,
              parts=parts, slice_out=o.slice, record_out=o.record, settings=settings,
              threads=snakemake.threads)
elif "records" in i.keys():     # the parts joined
    run_stage(snakemake, resample.gather, geometry=i.geometry, specular=i.specular, valid=i.valid,
              slice_parts=list(i.slice), records=list(i.records), slice_out=o.slice,
              colour_out=o.colour, grid_out=o.grid, metrics_out=o.metrics, settings=settings)
else:
    run_stage(snakemake, resample.run, geometry=i.geometry, specular=i.specular, valid=i.valid, slice_out=o.slice,
              colour_out=o.colour, grid_out=o.grid, metrics_out=o.metrics, settings=settings,
              threads=snakemake.threads)
