
from facetsynth.stages import validate
from facetsynth.stages.runner import run_stage

i, o, p = snakemake.input, snakemake.output, snakemake.params
run_stage(snakemake, validate.run, svbrdf=i.svbrdf, ward=i.ward, heldout=dict(zip(p.views, i.heldout)),
          out_dir=o.predictions, metrics_out=o.metrics, images_out=o.images, fit_benchmarks=p.fit_benchmarks,
          ward_benchmark=p.ward_benchmark, images_per_view=p.images_per_view, rig=i.rig)
