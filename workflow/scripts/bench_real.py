"""facetsynth against the per-pixel fits RTI users rely on, on real light-dome photos: `make bench-real`
(a command-line script, not a rule's script).

Runs the main Snakefile in its own working directory, results/bench-real/run/ (links to Snakefile,
workflow, config, resources, rig; its own samples.tsv with the captures' absolute paths), up to
results/{capture}/selfcheck/metrics.json of every capture of --samples, one capture after the other (so
the stage times of one are not shared with another's jobs), with selfcheck={heldout_every: 8,
relit_every: 1}: every 8th light (from the 4th) held out of the fit, every fitting light relit. Then
prints and writes results/bench-real/table.md and table.csv (facetsynth.app.bench.REAL_COLUMNS): per capture,
relative L2 on the fitting / held-out lights of facetsynth, Lambert, PTM, HSH2, HSH3 and HSH3 fitted to the
8-bit codes as RTI tools fit it (the selfcheck's baselines, same frames and pixels), facetsynth's fit time (wall seconds of the benchmark files of
facetsynth.app.bench.FIT_STAGES: capture and hdr, i.e. reading and linearising the JPEGs, included; the csv
also has rectify..refine alone) and peak memory, and whether facetsynth <= each HSH3 on both subsets. A
finished run is not repeated (Snakemake finds its outputs up to date), so an interrupted bench resumes.

The photos are read where they are (../shared/data/rti/..., no licence): nothing derived from them is
written outside results/, which git ignores.

    python workflow/scripts/bench_real.py [--samples config/samples-rti.tsv] [--out results/bench-real]
                                          [--cores 2] [--captures rti-leaf ...] [--dry-run] [--collect-only]
                                          [-- extra snakemake args]
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

from facetsynth.app import bench

REPO = Path(__file__).resolve().parents[2]
SELFCHECK = "selfcheck={heldout_every: 8, relit_every: 1}"


def sample_rows(sheet: Path, captures: list[str] | None) -> list[dict]:
    """The sheet's rows (paths relative to the repository made absolute); exits naming the missing folder
    when a capture's .lp file is not there."""
    if not sheet.is_file():
        sys.exit(f"bench-real: sample sheet {sheet} not found")
    rows = bench.sheet_rows(sheet, captures, "bench-real: capture(s)")
    for row in rows:
        path = Path(row["path"])
        path = path if path.is_absolute() else (REPO / path)
        if not path.exists():
            missing = path
            while not missing.parent.exists():
                missing = missing.parent
            sys.exit(f"bench-real: {missing.resolve()} does not exist: capture {row['sample']} is read from "
                     f"{row['path']} (relative to {REPO}); the real light-dome photos are not part of the "
                     "repository (no licence) and must be there on this machine")
        row["path"] = str(path.resolve())
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=Path, default=REPO / "config/samples-rti.tsv")
    parser.add_argument("--captures", nargs="+", default=None, help="default: every row of --samples")
    parser.add_argument("--out", type=Path, default=REPO / "results/bench-real")
    parser.add_argument("--cores", default="2")
    parser.add_argument("--dry-run", action="store_true", help="snakemake -n for every capture; nothing collected")
    parser.add_argument("--collect-only", action="store_true", help="only (re)write the table")
    parser.add_argument("snakemake_args", nargs="*", help="after --: passed to every snakemake call")
    args = parser.parse_args(argv)

    rows = sample_rows(args.samples, args.captures)
    captures = [r["sample"] for r in rows]
    workdir = args.out / "run"
    if not args.collect_only:
        bench.prepare_workdir(workdir, rows, REPO)
    for capture in [] if args.collect_only else captures:
        command = [sys.executable, "-m", "snakemake", "--cores", str(args.cores),
                   "--config", "samples=samples.tsv", SELFCHECK, *args.snakemake_args,
                   "--", f"results/{capture}/selfcheck/metrics.json"]
        if args.dry_run:
            command.insert(-2, "-n")
        failed = bench.run_workflow(command, workdir, f"bench-real: {capture}", f"results/{capture}/logs")
        if failed:
            return failed
    if args.dry_run:
        return 0

    table = [bench.real_row(workdir / "results", capture) for capture in captures]
    csv_path = bench.write_csv(table, args.out / "table.csv", columns=bench.REAL_COLUMNS)
    text = (f"facetsynth against per-pixel RTI fits on real light-dome photos ({args.samples.name}), "
            f"{datetime.date.today().isoformat()}, {bench.machine_description()}, snakemake --cores {args.cores}, "
            f"{SELFCHECK}. Relative L2 = selfcheck's rel_l2 on the fitting lights (every one relit) / the held-out "
            "lights (every 8th from the 4th, kept out of every fit); fit s = wall seconds of capture..refine "
            "(reading and linearising the JPEGs included), peak MB = largest max_rss of those stages.\n\n"
            + bench.real_table(table))
    md_path = args.out / "table.md"
    md_path.write_text(text)
    print(text)
    print(f"bench-real: wrote {md_path} and {csv_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
