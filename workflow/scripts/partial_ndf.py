from facetsynth.stages import partial_ndf
from facetsynth.stages.common import scatter_item
from facetsynth.stages.runner import run_stage

settings = partial_ndf.Settings.from_params(snakemake.params)
i, o = snakemake.input, snakemake.output
if "record" in o.keys():        # one scatter part ({scatteritem} = "k-of-n")
    part, parts = scatter_item(snakemake.wildcards.scatteritem)
    run_stage(snakemake, partial_ndf.run_part, geometry=i.geometry, slice_path=i.slice, grid_path=i.grid, part=part,
              parts=parts, ndf_out=o.ndf, record_out=o.record, settings=settings, threads=snakemake.threads)
elif "records" in i.keys():     # the parts joined
    run_stage(snakemake, partial_ndf.gather, geometry=i.geometry, grid_path=i.grid, ndf_parts=list(i.ndf),
              records=list(i.records), ndf_out=o.ndf, metrics_out=o.metrics, settings=settings)
else:
    run_stage(snakemake, partial_ndf.run, geometry=i.geometry, slice_path=i.slice, grid_path=i.grid, ndf_out=o.ndf,
              metrics_out=o.metrics, settings=settings, threads=snakemake.threads)
