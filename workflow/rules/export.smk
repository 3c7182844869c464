# Portable export (issue 17 item 3): a per-point anisotropic GGX fit of the SVBRDF written as a glTF 2.0
# material (KHR_materials_anisotropy, _specular, _ior textures on a quad) -> results/{sample}/export/gltf/,
# and what it costs: for a sample with held-out truth, the held-out relative L2 of the portable material
# beside the full SVBRDF's (validate/metrics.json) -> results/{sample}/export/metrics.json.
# Input function export_inputs: common.smk.


rule export_gltf:
    input:
        unpack(export_inputs),
    output:
        gltf=directory("results/{sample}/export/gltf"),
        metrics="results/{sample}/export/metrics.json",
    log:
        "results/{sample}/logs/export_gltf.log",
    benchmark:
        "results/{sample}/benchmarks/export_gltf.tsv"
    threads: 1
    resources:
        mem_mb=1000,  # measured: 0.40-0.65 GB peak (demo native 168 x 168; wallpaper, satin 64 x 64); 8-12 s of CPU
    params:
        views=list(HELDOUT_VIEWS),
    script:
        "../scripts/export_gltf.py"
