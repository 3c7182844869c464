# rectify: map every HDR frame onto the regular sample-plane grid (paper 002 sec. 4).


rule rectify:
    input:
        frames="results/{sample}/hdr/frames",
        manifest="results/{sample}/hdr/manifest.json",
    output:
        frames=directory("results/{sample}/rectify/frames"),
        geometry="results/{sample}/rectify/geometry.json",
        metrics="results/{sample}/rectify/metrics.json",
    log:
        "results/{sample}/logs/rectify.log",
    benchmark:
        "results/{sample}/benchmarks/rectify.tsv"
    threads: 2  # frames in parallel (facetsynth.io.frames)
    resources:
        mem_mb=2000,
    params:
        resolution=config["rectify"]["resolution"],
        filter=config["rectify"]["filter"],
    script:
        "../scripts/rectify.py"
