from facetsynth.stages import baseline
from facetsynth.stages.common import scatter_item
from facetsynth.stages.runner import run_stage

i, o = snakemake.input, snakemake.output
if "record" in o.keys():        # one scatter part ({scatteritem} = "k-of-n")
    part, parts = scatter_item(snakemake.wildcards.scatteritem)
    run_stage(snakemake, baseline.run_part, geometry=i.geometry, specular=i.specular, valid=i.valid, part=part,
              parts=parts, record_out=o.record, max_nfev=snakemake.params.max_nfev)
elif "records" in i.keys():     # the parts joined
    run_stage(snakemake, baseline.gather, geometry=i.geometry, kd_path=i.kd, colour=i.colour, specular=i.specular,
              records=list(i.records), model_out=o.model, metrics_out=o.metrics)
else:
    run_stage(snakemake, baseline.run, geometry=i.geometry, kd_path=i.kd, specular=i.specular, valid=i.valid,
              colour=i.colour, model_out=o.model, metrics_out=o.metrics, max_nfev=snakemake.params.max_nfev)
