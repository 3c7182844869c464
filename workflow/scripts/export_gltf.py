from facetsynth.stages import export
from facetsynth.stages.runner import run_stage

i, o, p = snakemake.input, snakemake.output, snakemake.params
heldout = dict(zip(p.views, i.heldout)) if "heldout" in i.keys() else None
run_stage(snakemake, export.run, svbrdf=i.svbrdf, gltf_out=o.gltf, metrics_out=o.metrics, heldout=heldout,
          validate_metrics=i.get("validate_metrics"), rig=i.get("rig"), settings=export.Settings())
