# hdr: merge each frame's exposure bracket into one scene-linear EXR (paper 002 sec. 4).


rule hdr:
    input:
        capture="results/{sample}/capture",
    output:
        frames=directory("results/{sample}/hdr/frames"),
        manifest="results/{sample}/hdr/manifest.json",
        metrics="results/{sample}/hdr/metrics.json",
    log:
        "results/{sample}/logs/hdr.log",
    benchmark:
        "results/{sample}/benchmarks/hdr.tsv"
    threads: 2  # frames in parallel (facetsynth.io.frames)
    resources:
        mem_mb=7000,  # make bench-scale: 6.5 GB peak at the paper's 800^2 (1176 x 784 camera)
    params:
        floor_sigmas=config["hdr"]["floor_sigmas"],
        saturation_margin=config["hdr"]["saturation_margin"],
    script:
        "../scripts/hdr.py"
