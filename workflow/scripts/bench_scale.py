"""Growth of time, memory and disk with the points P and the frames F (issue 14), run by `make bench-scale`.

Points sweep: the paper-scale scene (resources/scenes/paper-scale.yaml, several materials with turning
frames) under the paper's 480 lights (rig/descriptions/paper-scale.yaml), its camera scaled so that the
sample spans at least P x P rectified points, fitted at P x P (rectify.resolution). Frames sweep: the same
scene at 128 x 128 points under 120, 480, 1360 and 2600 lights (the demo camera). Every run is its own
Snakemake working directory, results/bench/scale/P{P}_F{F}/ (links to the repository, its own rig and
sample sheet), up to results/scale/svbrdf, in one job per stage (scatter.tiles 1: the per-point stages run
their tiles on the job's 2 threads, with nothing to join). A
finished run is not repeated (Snakemake finds its outputs up to date), so an interrupted bench resumes.

Writes results/bench/scale.csv (facetsynth.app.bench.SCALE_COLUMNS: one row per run and stage, plus stage
"total", rectify through refine; stage "read_frames", the floor of reading the merged frames once, and stage
"write_disk", the disk's speed for writing 1 GiB, at which each stage's write_floor_s prices what it wrote) and
scale.png (wall seconds against P and F per stage, log-log, with each stage's fitted exponent).

    python workflow/scripts/bench_scale.py [--points 64 128 256 512 800] [--frames 120 480 1360 2600]
                                           [--cores 2] [--collect-only] [--prune] [-- extra snakemake args]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import yaml

from facetsynth.app import bench

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "resources/scenes/paper-scale.yaml"
RIGS = {120: "paper-120", 480: "paper-scale", 1360: "virtual-demo", 2600: "paper-2600"}
FRAMES_SWEEP_POINTS = 128
PAPER_SCALE_NATIVE = 839      # rectify.resolution auto of rig/descriptions/paper-scale.yaml (1200 x 800)


def rig_description(points: int, frames: int) -> dict:
    """The rig of a run: the light density of ``frames``; for the paper's 480, the paper-scale camera scaled
    (in steps of 24 pixels) so that the sample spans at least ``points`` rectified points, never beyond
    1200 x 800."""
    rig = yaml.safe_load((REPO / "rig/descriptions" / f"{RIGS[frames]}.yaml").read_text())
    if frames == 480:
        width = min(1200, 24 * math.ceil(1200 * points / PAPER_SCALE_NATIVE * 1.02 / 24))
        rig["camera"]["width"], rig["camera"]["height_px"] = width, width * 2 // 3
    return rig


def prepare(workdir: Path, points: int, frames: int) -> None:
    rig = workdir / "rig.yaml"
    bench.prepare_workdir(workdir, [{"sample": "scale", "source": "virtual", "path": SCENE, "rig": rig}], REPO)
    for name, text in (("rig.yaml", yaml.safe_dump(rig_description(points, frames), sort_keys=False)),
                       ("scale.yaml", yaml.safe_dump({"samples": "samples.tsv", "rectify": {"resolution": points},
                                                      "scatter": {"tiles": 1}}))):
        if not (workdir / name).is_file() or (workdir / name).read_text() != text:
            (workdir / name).write_text(text)


def runs(points: list[int], frames: list[int]) -> list[tuple[int, int]]:
    """(P, F) of every run: the points sweep at 480 frames, the frames sweep at 128 x 128 points."""
    wanted = [(p, 480) for p in points] + [(FRAMES_SWEEP_POINTS, f) for f in frames]
    return sorted(dict.fromkeys(wanted))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", nargs="+", type=int, default=[64, 128, 256, 512, 800])
    parser.add_argument("--frames", nargs="+", type=int, default=sorted(RIGS), choices=sorted(RIGS))
    parser.add_argument("--out", type=Path, default=REPO / "results/bench")
    parser.add_argument("--cores", default="2")
    parser.add_argument("--collect-only", action="store_true", help="only (re)write the csv and the plot")
    parser.add_argument("--prune", action="store_true",
                        help="after recording a run's figures, delete its frames and per-point tables (disk)")
    parser.add_argument("snakemake_args", nargs="*", help="after --: passed to every snakemake call")
    args = parser.parse_args(argv)

    done_runs = []
    for p, f in runs(args.points, args.frames):
        workdir = args.out / "scale" / f"P{p}_F{f}"
        if not args.collect_only:
            prepare(workdir, p, f)
            command = [sys.executable, "-m", "snakemake", "--cores", str(args.cores), "results/scale/svbrdf",
                       "--configfile", "config/config.yaml", "scale.yaml", *args.snakemake_args]
            print(f"bench-scale: P {p}^2, F {f}: {' '.join(command[2:])}  (in {workdir})", file=sys.stderr, flush=True)
            start = time.monotonic()
            finished = subprocess.run(command, cwd=workdir)
            if finished.returncode != 0:
                print(f"bench-scale: P {p}^2, F {f} failed (exit {finished.returncode}); logs in "
                      f"{workdir}/results/scale/logs", file=sys.stderr)
                return finished.returncode
            print(f"bench-scale: P {p}^2, F {f} done in {time.monotonic() - start:.0f} s", file=sys.stderr, flush=True)
            (workdir / "results/scale/benchmarks/scale_rows.json").unlink(missing_ok=True)
            recorded(workdir / "results/scale", p, f)          # right after the run: its floor from the page cache
            if args.prune:
                prune(workdir / "results/scale")
        if (workdir / "results/scale/benchmarks/scale_rows.json").is_file() or \
                (workdir / "results/scale/svbrdf").is_dir():
            done_runs.append((p, f, workdir / "results/scale"))

    rows = [row for p, f, root in done_runs for row in recorded(root, p, f)]
    csv_path = bench.write_csv(rows, args.out / "scale.csv", bench.SCALE_COLUMNS)
    exponents = bench.growth_exponents(rows)
    title = (f"facetsynth: growth with points and frames\n{datetime.date.today().isoformat()}, "
             f"{bench.machine_description()}, snakemake --cores {args.cores}, scatter.tiles 1")
    png_path = bench.plot_scale(rows, exponents, args.out / "scale.png", title)
    for stage, (in_points, in_frames) in exponents.items():
        print(f"bench-scale: {stage:12s} wall ~ P^{_fmt(in_points)} F^{_fmt(in_frames)}", file=sys.stderr)
    large = [r for r in rows if r["stage"] == "total" and r["frames"] == 480 and r["points"] >= 256 ** 2]
    print(f"bench-scale: total (rectify .. refine) wall ~ P^"
          f"{_fmt(bench.growth_exponent([r['points'] for r in large], [r['wall_s'] for r in large]))} from 256^2 "
          f"points up (issue 31: at most 1.05)", file=sys.stderr)
    print(f"bench-scale: wrote {csv_path} and {png_path}", file=sys.stderr)
    return 0


def recorded(root: Path, points: int, frames: int) -> list[dict]:
    """The run's rows (:func:`facetsynth.app.bench.scale_rows` and its floors, :func:`facetsynth.app.bench.read_floor`
    and :func:`facetsynth.app.bench.write_floor`, which prices each stage's writes), measured once and kept in
    ``benchmarks/scale_rows.json`` beside its results: a later --collect-only must not measure the floors under
    other load, and needs no intermediates of a pruned run."""
    saved = root / "benchmarks" / "scale_rows.json"
    if not saved.is_file():
        p = points * points
        rows = bench.scale_rows(root, p, frames) + [bench.read_floor(root, p, frames), bench.write_floor(root, p, frames)]
        saved.write_text(json.dumps(bench.with_write_floors(rows)))
    return json.loads(saved.read_text())


PRUNED = ("capture", "hdr", "rectify/frames", "separate", "resample", "partial_ndf")


def prune(root: Path) -> None:
    """--prune: a recorded run's frames and (P, F) / (P, T, F) tables removed (the paper's 800^2 alone writes
    about 50 GB); its metrics, logs, benchmarks and fitted SVBRDF stay. Running the bench again repeats it."""
    for name in PRUNED:
        for path in sorted((root / name).rglob("*"), reverse=True) if (root / name).is_dir() else []:
            if path.is_file() and path.name != "metrics.json":
                path.unlink()


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


if __name__ == "__main__":
    sys.exit(main())
