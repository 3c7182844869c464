from facetsynth.stages import synthesize
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, synthesize.run, geometry=snakemake.input.geometry, ndf=snakemake.input.ndf,
          grid_path=snakemake.input.grid,
          representatives=snakemake.input.representatives,
          rep_ndf=snakemake.input.rep_ndf, rep_confidence=snakemake.input.rep_confidence,
          rotation=snakemake.input.rotation, neighbours=snakemake.input.neighbours,
          weights=snakemake.input.weights, ndf_out=snakemake.output.ndf,
          confidence_out=snakemake.output.confidence, cosine_out=snakemake.output.fresnel_cosine,
          grid_out=snakemake.output.grid,
          metrics_out=snakemake.output.metrics, search=p.search, compare=p.compare,
          n_regions=p.n_regions, buckets=p.buckets, candidates=p.candidates, overlap=tuple(p.overlap),
          max_iterations=p.max_iterations, target_coverage=p.target_coverage,
          max_relative_error=p.max_relative_error, stalled_fraction=p.stalled_fraction,
          max_exemplars=p.max_exemplars, ann_neighbors=p.ann_neighbors, ann_epsilon=p.ann_epsilon,
          fill_overlap=p.fill_overlap, extend_rings=p.extend_rings,
          isotropic_threshold=p.isotropic_threshold, kd=snakemake.input.kd,
          material_tolerance=p.material_tolerance, seed=p.seed,
          rotations=list(zip(snakemake.input.rotation_geometry, snakemake.input.rotation_ndf)))
