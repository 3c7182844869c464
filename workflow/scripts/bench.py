"""Speed against accuracy benchmark, run by `make bench` (a command-line script, not a rule's script).

For every preset it runs the main Snakefile in its own working directory, results/bench/runs/{preset}/
(links to Snakefile, workflow, config, resources, rig; its own samples.tsv), up to
results/{scene}/validate/metrics.json of every scene, then writes results/bench/tradeoff.csv (one row
per preset and scene: facetsynth.app.bench.COLUMNS) and results/bench/tradeoff.png (held-out PSNR against
the fit time, capture to refine, with the Pareto front). A finished run is not repeated (Snakemake
finds its outputs up to date), so an interrupted bench resumes.

    python workflow/scripts/bench.py [--presets fast balanced accurate] [--scenes demo wallpaper satin]
                                     [--cores 2] [--dry-run] [--collect-only] [--x wall_s|cpu_s|preset_s]
                                     [-- extra snakemake args]
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

from facetsynth.app import bench

REPO = Path(__file__).resolve().parents[2]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", nargs="+", default=["fast", "balanced", "accurate"])
    parser.add_argument("--scenes", nargs="+", default=None, help="default: every row of --sheet")
    parser.add_argument("--sheet", type=Path, default=REPO / "config/bench_samples.tsv")
    parser.add_argument("--out", type=Path, default=REPO / "results/bench")
    parser.add_argument("--cores", default="2")
    parser.add_argument("--dry-run", action="store_true", help="snakemake -n for every preset; nothing collected")
    parser.add_argument("--collect-only", action="store_true", help="only (re)write the csv and the plot")
    parser.add_argument("--x", choices=["wall_s", "cpu_s", "preset_s"], default="wall_s", help="time axis of the plot")
    parser.add_argument("snakemake_args", nargs="*", help="after --: passed to every snakemake call")
    args = parser.parse_args(argv)

    rows = bench.sheet_rows(args.sheet, args.scenes, "bench: scene(s)")
    scenes = [r["sample"] for r in rows]
    virtual = [r["sample"] for r in rows if r["source"] == "virtual"]
    if virtual != scenes:
        print(f"bench: no held-out views for non-virtual samples: {sorted(set(scenes) - set(virtual))}", file=sys.stderr)
    for preset in args.presets:
        workdir = args.out / "runs" / preset
        if args.collect_only:
            continue
        bench.prepare_workdir(workdir, rows, REPO)
        targets = [f"results/{s}/validate/metrics.json" if s in virtual else f"results/{s}/svbrdf" for s in scenes]
        command = [sys.executable, "-m", "snakemake", "--cores", str(args.cores), *targets,
                   "--config", f"preset={preset}", "samples=samples.tsv", *args.snakemake_args]
        if args.dry_run:
            command.append("-n")
        failed = bench.run_workflow(command, workdir, f"bench: preset {preset}", "results/*/logs")
        if failed:
            return failed
    if args.dry_run:
        return 0

    table = [bench.collect_row(args.out / "runs" / preset / "results", preset, scene)
             for preset in args.presets for scene in scenes]
    csv_path = bench.write_csv(table, args.out / "tradeoff.csv")
    what = {"wall_s": "fit time", "cpu_s": "fit CPU time", "preset_s": "rectify..params time"}[args.x]
    title = (f"facetsynth presets: held-out PSNR against {what}\n"
             f"{datetime.date.today().isoformat()}, {bench.machine_description()}, snakemake --cores {args.cores}")
    png_path = bench.plot(table, args.out / "tradeoff.png", title, presets=args.presets, x=args.x)
    for row in table:
        print("bench: {preset:9s} {scene:10s} wall {wall} s, peak {mem} MB, held-out {psnr} dB, ndf_rel_l2 {ndf}".format(
            preset=row["preset"], scene=row["scene"], wall=_fmt(row["wall_s"], ".0f"), mem=_fmt(row["peak_mem_mb"], ".0f"),
            psnr=_fmt(row["heldout_psnr_db"], ".2f"), ndf=_fmt(row["ndf_rel_l2_median"], ".3f")), file=sys.stderr)
    print(f"bench: wrote {csv_path} and {png_path}", file=sys.stderr)
    return 0


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


if __name__ == "__main__":
    sys.exit(main())
