# Reflectance stages (paper 002 sec. 4 end, sec. 5.1): per-point BRDF samples and
# diffuse separation (eqs. 8-9), push-pull resampling onto the direction grid,
# partial NDF with the constrained shadowing iteration (eqs. 5, 10-12).


rule separate:
    input:
        frames="results/{sample}/rectify/frames",
        geometry="results/{sample}/rectify/geometry.json",
    output:
        geometry="results/{sample}/separate/geometry.json",  # rectify's, with the shading normals
        normals="results/{sample}/separate/normals.npy",
        kd="results/{sample}/separate/kd.exr",
        specular="results/{sample}/separate/specular.npy",
        valid="results/{sample}/separate/valid.npy",
        metrics="results/{sample}/separate/metrics.json",
    log:
        "results/{sample}/logs/separate.log",
    benchmark:
        "results/{sample}/benchmarks/separate.tsv"
    threads: 2  # frames read in parallel
    resources:
        mem_mb=6000,  # make bench-scale: 5.7 GB peak at 800^2 (the memory-mapped (P, F, 3) tables)
    params:
        **config["separate"],
        heldout_every=config["selfcheck"]["heldout_every"],  # those lights are kept out of every later stage
    script:
        "../scripts/separate.py"


RESAMPLE_INPUTS = {
    "geometry": "results/{sample}/separate/geometry.json",
    "specular": "results/{sample}/separate/specular.npy",
    "valid": "results/{sample}/separate/valid.npy",
}


rule resample:  # the whole capture; with scatter.tiles > 1 the join of resample_part's jobs (bitwise the same)
    input:
        **RESAMPLE_INPUTS,
        **scatter_parts(
            slice="results/{{sample}}/resample/parts/{scatteritem}/slice",
            records="results/{{sample}}/resample/parts/{scatteritem}/record.npz",
        ),
    output:
        # the per-point slices are read by partial_ndf alone: deleted once it has them (--notemp keeps them;
        # a forced partial_ndf runs resample again). At 800^2 x 480 they are 4.8 of the 15 GB rectify..refine write
        slice=temp(directory("results/{sample}/resample/slice")),
        colour="results/{sample}/resample/specular_colour.npy",
        grid="results/{sample}/resample/grid.json",
        metrics="results/{sample}/resample/metrics.json",
    log:
        "results/{sample}/logs/resample.log",
    benchmark:
        "results/{sample}/benchmarks/resample.tsv"
    threads: 1 if SCATTERED else 2  # tiles of points in parallel; the join copies
    resources:
        mem_mb=1000 if SCATTERED else 2000,
    params:
        **config["resample"],
        grazing_deg=config["partial_ndf"]["grazing_deg"],
    script:
        "../scripts/resample.py"


use rule resample as resample_part with:  # one part of the points (whole tiles); unused at scatter.tiles 1
    input:
        **RESAMPLE_INPUTS,
    output:
        slice=temp(directory("results/{sample}/resample/parts/{scatteritem}/slice")),
        record=temp("results/{sample}/resample/parts/{scatteritem}/record.npz"),
    log:
        "results/{sample}/logs/resample/{scatteritem}.log",
    benchmark:
        "results/{sample}/benchmarks/resample/{scatteritem}.tsv"
    threads: 1
    resources:
        mem_mb=2000,


PARTIAL_NDF_INPUTS = {
    "geometry": "results/{sample}/separate/geometry.json",
    "slice": "results/{sample}/resample/slice",
    "grid": "results/{sample}/resample/grid.json",
}


rule partial_ndf:  # the whole capture; with scatter.tiles > 1 the join of partial_ndf_part's jobs (bitwise the same)
    input:
        **PARTIAL_NDF_INPUTS,
        **scatter_parts(
            ndf="results/{{sample}}/partial_ndf/parts/{scatteritem}/ndf",
            records="results/{{sample}}/partial_ndf/parts/{scatteritem}/record.npz",
        ),
    output:
        ndf=directory("results/{sample}/partial_ndf/ndf"),
        metrics="results/{sample}/partial_ndf/metrics.json",
    log:
        "results/{sample}/logs/partial_ndf.log",
    benchmark:
        "results/{sample}/benchmarks/partial_ndf.tsv"
    threads: 1 if SCATTERED else 2  # tiles of points in parallel; the join copies
    resources:
        mem_mb=1000 if SCATTERED else 3000,
    params:
        **config["partial_ndf"],
    script:
        "../scripts/partial_ndf.py"


use rule partial_ndf as partial_ndf_part with:  # one part of the points (whole tiles); unused at scatter.tiles 1
    input:
        **PARTIAL_NDF_INPUTS,
    output:
        ndf=temp(directory("results/{sample}/partial_ndf/parts/{scatteritem}/ndf")),
        record=temp("results/{sample}/partial_ndf/parts/{scatteritem}/record.npz"),
    log:
        "results/{sample}/logs/partial_ndf/{scatteritem}.log",
    benchmark:
        "results/{sample}/benchmarks/partial_ndf/{scatteritem}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
