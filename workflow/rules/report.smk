# The report's figures (`snakemake --report report.html`): per sample and stage, drawn from the stages'
# outputs by facetsynth.app.figures; captions in workflow/report/. The committed speed / accuracy and scale
# plots (docs/bench, `make bench`) join as copies under results/report/bench when the working copy has them
# (not results/bench: make bench writes its own plots there).

REPORT_PARAMS = {
    "mosaic_frames": 12,
    "heldout_frames": 2,
    "ndf_points": ((0.5, 0.5), (0.25, 0.5), (0.5, 0.25), (0.3, 0.7)),
}
BENCH_FIGURES = [name for name in ("tradeoff", "scale") if Path(f"docs/bench/{name}.png").is_file()]


rule report_capture:
    input:
        manifest="results/{sample}/hdr/manifest.json",
    output:
        report(
            "results/{sample}/report/capture.png",
            caption="../report/capture.rst",
            category="{sample}",
            subcategory="1 capture",
            labels={"figure": "HDR frames"},
        ),
    log:
        "results/{sample}/logs/report_capture.log",
    benchmark:
        "results/{sample}/benchmarks/report_capture.tsv"
    threads: 1
    resources:
        mem_mb=300,  # demo, 168^2 points: 133 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_capture.py"


rule report_relief:
    input:
        geometry="results/{sample}/separate/geometry.json",
        metrics="results/{sample}/separate/metrics.json",
    output:
        report(
            "results/{sample}/report/relief.png",
            caption="../report/relief.rst",
            category="{sample}",
            subcategory="2 SVBRDF maps",
            labels={"figure": "shading normals, light intensities"},
        ),
    log:
        "results/{sample}/logs/report_relief.log",
    benchmark:
        "results/{sample}/benchmarks/report_relief.tsv"
    threads: 1
    resources:
        mem_mb=400,  # as report_maps: the grid's maps
    script:
        "../scripts/report_relief.py"


rule report_maps:
    input:
        svbrdf="results/{sample}/svbrdf",
        geometry="results/{sample}/separate/geometry.json",
    output:
        kd=report(
            "results/{sample}/report/kd.png",
            caption="../report/kd.rst",
            category="{sample}",
            subcategory="2 SVBRDF maps",
            labels={"figure": "kd"},
        ),
        ks=report(
            "results/{sample}/report/ks.png",
            caption="../report/ks.rst",
            category="{sample}",
            subcategory="2 SVBRDF maps",
            labels={"figure": "ks"},
        ),
        eta=report(
            "results/{sample}/report/eta.png",
            caption="../report/eta.rst",
            category="{sample}",
            subcategory="2 SVBRDF maps",
            labels={"figure": "eta"},
        ),
    log:
        "results/{sample}/logs/report_maps.log",
    benchmark:
        "results/{sample}/benchmarks/report_maps.tsv"
    threads: 1
    resources:
        mem_mb=400,  # demo, 168^2 points: 181 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_maps.py"


rule report_ndf:
    input:
        svbrdf="results/{sample}/svbrdf",
        partial="results/{sample}/partial_ndf/ndf",
        grid="results/{sample}/resample/grid.json",
        geometry="results/{sample}/separate/geometry.json",
    output:
        report(
            "results/{sample}/report/ndf.png",
            caption="../report/ndf.rst",
            category="{sample}",
            subcategory="3 NDFs",
            labels={"figure": "NDFs at a few points"},
        ),
    log:
        "results/{sample}/logs/report_ndf.log",
    benchmark:
        "results/{sample}/benchmarks/report_ndf.tsv"
    threads: 1
    resources:
        mem_mb=400,  # demo, 168^2 points: 187 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_ndf.py"


rule report_clusters:
    input:
        labels="results/{sample}/cluster/labels.npy",
        representatives="results/{sample}/cluster/representatives.npy",
        geometry="results/{sample}/separate/geometry.json",
    output:
        report(
            "results/{sample}/report/clusters.png",
            caption="../report/clusters.rst",
            category="{sample}",
            subcategory="4 clusters",
            labels={"figure": "cluster map"},
        ),
    log:
        "results/{sample}/logs/report_clusters.log",
    benchmark:
        "results/{sample}/benchmarks/report_clusters.tsv"
    threads: 1
    resources:
        mem_mb=200,  # demo, 168^2 points: 99 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_clusters.py"


rule report_heldout:
    input:
        heldout="results/{sample}/validate/heldout/{view}",
        predictions="results/{sample}/validate/predictions",
        svbrdf="results/{sample}/svbrdf",
        metrics="results/{sample}/validate/metrics.json",
    output:
        report(
            "results/{sample}/report/heldout_{view}.png",
            caption="../report/heldout.rst",
            category="{sample}",
            subcategory="5 held-out views",
            labels={"figure": "held-out view", "view": "{view}"},
        ),
    log:
        "results/{sample}/logs/report_heldout_{view}.log",
    benchmark:
        "results/{sample}/benchmarks/report_heldout_{view}.tsv"
    threads: 1
    resources:
        mem_mb=500,  # demo, 168^2 points: 218 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_heldout.py"


rule report_stencil:
    input:
        svbrdf="results/{sample}/svbrdf",
        models="results/{sample}/stencil_fit/models",
    output:
        report(
            directory("results/{sample}/report/stencil"),
            patterns=["cluster_{cluster}.png"],
            caption="../report/stencil.rst",
            category="{sample}",
            subcategory="6 stencil fits",
            labels={"figure": "stencil fit", "cluster": "{cluster}"},
        ),
    log:
        "results/{sample}/logs/report_stencil.log",
    benchmark:
        "results/{sample}/benchmarks/report_stencil.tsv"
    threads: 1
    resources:
        mem_mb=600,  # demo, 168^2 points: 260 MB peak
    params:
        **REPORT_PARAMS,
    script:
        "../scripts/report_stencil.py"


rule report_bench:
    input:
        "docs/bench/{plot}.png",
    output:
        report(
            "results/report/bench/{plot}.png",
            caption="../report/bench.rst",
            category="benchmarks",
            labels={"figure": "{plot}"},
        ),
    log:
        "results/report/bench/logs/report_{plot}.log",
    benchmark:
        "results/report/bench/benchmarks/report_{plot}.tsv"
    wildcard_constraints:
        plot="tradeoff|scale",
    threads: 1
    resources:
        mem_mb=100,  # cp
    shell:
        "cp {input} {output} 2> {log}"
