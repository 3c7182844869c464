"""Speed against accuracy: collect the presets' measured time, memory and accuracy (``make bench``).

Pure functions over a results tree (``results/{scene}/benchmarks/{stage}.tsv``, the Snakemake
``benchmark:`` files, and the stages' ``metrics.json``), the Pareto front, and the plot.
``workflow/scripts/bench.py`` runs the presets and calls these.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

#: The fitting stages, capture to refine: ``wall_s`` is the sum of their benchmark seconds. Capture
#: and hdr do not depend on the preset; ``preset_s`` sums the stages that do (rectify to refine).
FIT_STAGES = ("capture", "hdr", "rectify", "separate", "resample", "partial_ndf", "cluster", "synthesize", "params",
              "refine")
PRESET_STAGES = FIT_STAGES[2:]

COLUMNS = (["preset", "scene", "wall_s", "preset_s", "cpu_s", "peak_mem_mb"] + [f"{s}_s" for s in FIT_STAGES]
           + ["heldout_psnr_db", "heldout_ssim", "baseline_ward_psnr_db", "ndf_rel_l2_median",
              "partial_ndf_rel_l2_median", "resolution", "n_theta", "n_phi", "representatives", "exemplars"])


def _number(text: str | None) -> float | None:
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def read_benchmark(path: str | Path) -> dict[str, float | None]:
    """Seconds, peak resident memory (MB), CPU seconds and MiB written of one Snakemake benchmark file
    ({'s', 'max_rss', 'cpu_time', 'io_out'}); the means over its rows (``benchmark: repeat(...)``) but for
    max_rss, the largest. ``io_out`` is what the job's processes wrote to the disk (Linux's write_bytes: files
    deleted later, ``temp()`` ones too, included), as Snakemake last sampled it: every 0.5 s in a job's first
    15 s, then every 30 s, so the writes of a long job's last seconds (up to 30) are missed: a lower bound."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    if not rows:
        raise ValueError(f"{path}: benchmark file has no rows")

    def values(column):
        return [v for v in (_number(r.get(column)) for r in rows) if v is not None]

    def mean(column):
        found = values(column)
        return sum(found) / len(found) if found else None

    return {"s": mean("s"), "max_rss": max(values("max_rss"), default=None), "cpu_time": mean("cpu_time"),
            "io_out": mean("io_out")}


def _json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def collect_row(results: str | Path, preset: str, scene: str) -> dict:
    """One row of tradeoff.csv from ``results/{scene}/`` of one preset's run: per-stage seconds,
    ``wall_s`` (sum over FIT_STAGES; None when one is missing), ``preset_s`` (rectify to refine),
    ``cpu_s`` (sum of their cpu_time: less sensitive to other load on the machine than wall time),
    ``peak_mem_mb`` (max of max_rss over FIT_STAGES), and the accuracy records."""
    root = Path(results) / scene
    row: dict = {"preset": preset, "scene": scene}
    seconds, peaks, cpu = [], [], []
    for stage in FIT_STAGES:
        path = root / "benchmarks" / f"{stage}.tsv"
        bench = read_benchmark(path) if path.is_file() else {"s": None, "max_rss": None, "cpu_time": None}
        row[f"{stage}_s"] = bench["s"]
        seconds.append(bench["s"])
        cpu.append(bench["cpu_time"])
        if bench["max_rss"] is not None:
            peaks.append(bench["max_rss"])
    row["wall_s"] = None if None in seconds else sum(seconds)
    preset_seconds = seconds[len(FIT_STAGES) - len(PRESET_STAGES):]
    row["preset_s"] = None if None in preset_seconds else sum(preset_seconds)
    row["cpu_s"] = None if None in cpu else sum(cpu)
    row["peak_mem_mb"] = max(peaks) if peaks else None
    validate = _json(root / "validate/metrics.json")
    for key in ("heldout_psnr_db", "heldout_ssim", "baseline_ward_psnr_db"):
        row[key] = validate.get(key)
    synthesize = _json(root / "synthesize/metrics.json")
    row["ndf_rel_l2_median"] = synthesize.get("ndf_rel_l2_median")
    row["representatives"] = synthesize.get("representatives")
    row["exemplars"] = synthesize.get("exemplars")
    row["partial_ndf_rel_l2_median"] = _json(root / "partial_ndf/metrics.json").get("ndf_rel_l2_median")
    geometry = _json(root / "rectify/geometry.json")
    row["resolution"] = (geometry.get("grid") or {}).get("cols")
    grid = _json(root / "resample/grid.json")
    row["n_theta"], row["n_phi"] = grid.get("n_theta"), grid.get("n_phi")
    return {column: row.get(column) for column in COLUMNS}


def write_csv(rows: Iterable[dict], path: str | Path, columns: Sequence[str] = COLUMNS) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _cell(row.get(k)) for k in columns})
    return path


# --- growth with points and frames (make bench-scale, issue 14) ------------------------------------

SCALE_COLUMNS = ["points", "frames", "stage", "wall_s", "cpu_s", "max_rss_mb", "bytes_written", "io_out_mib",
                 "write_floor_s"]
#: What a user with HDR frames pays: rectify through refine (the row with stage "total").
TOTAL_STAGES = PRESET_STAGES


def stage_cost(root: str | Path, stage: str) -> dict | None:
    """Wall and CPU seconds, peak RSS (MB) and MiB written of one stage of a run (``results/{sample}``), from
    its benchmark file and those of its scatter parts (``benchmarks/{stage}/*.tsv``, run side by side): wall =
    the slowest part + the join, CPU and MiB written = the sums, RSS = the largest. None if the stage has no
    benchmark."""
    root = Path(root)
    main = root / "benchmarks" / f"{stage}.tsv"
    if not main.is_file():
        return None
    joined = read_benchmark(main)
    parts = [read_benchmark(p) for p in sorted((root / "benchmarks" / stage).glob("*.tsv"))]
    wall = [p["s"] for p in parts if p["s"] is not None]
    cpu = [p["cpu_time"] for p in parts + [joined] if p["cpu_time"] is not None]
    rss = [p["max_rss"] for p in parts + [joined] if p["max_rss"] is not None]
    written = [p["io_out"] for p in parts + [joined] if p["io_out"] is not None]
    return {"wall_s": (joined["s"] or 0.0) + max(wall, default=0.0), "cpu_s": sum(cpu) if cpu else None,
            "max_rss_mb": max(rss) if rss else None, "io_out_mib": sum(written) if written else None}


def folder_bytes(*paths: str | Path) -> int:
    """Bytes of the files under ``paths`` (files or folders; missing ones count 0)."""
    total = 0
    for path in map(Path, paths):
        files = [path] if path.is_file() else (p for p in path.rglob("*") if p.is_file())
        total += sum(f.stat().st_size for f in files)
    return total


def scale_rows(root: str | Path, points: int, frames: int) -> list[dict]:
    """scale.csv's rows of one run (``results/{sample}``): one per stage (FIT_STAGES), ``bytes_written``
    the size of the stage's output folder once the run is over (refine: with ``svbrdf/``): what it leaves on
    the disk; ``io_out_mib`` what its jobs wrote (:func:`stage_cost`: with what was deleted, resample's
    ``temp()`` slices); and ``total`` over TOTAL_STAGES (wall and CPU summed, RSS the largest, bytes summed)."""
    root = Path(root)
    rows = []
    for stage in FIT_STAGES:
        cost = stage_cost(root, stage)
        if cost is None:
            continue
        outputs = [root / stage] + ([root / "svbrdf"] if stage == "refine" else [])
        rows.append({"points": points, "frames": frames, "stage": stage, **cost,
                     "bytes_written": folder_bytes(*outputs)})
    fit = [r for r in rows if r["stage"] in TOTAL_STAGES]
    if len(fit) == len(TOTAL_STAGES):
        rows.append({"points": points, "frames": frames, "stage": "total",
                     "wall_s": sum(r["wall_s"] for r in fit), "cpu_s": sum(r["cpu_s"] or 0.0 for r in fit),
                     "max_rss_mb": max((r["max_rss_mb"] or 0.0) for r in fit),
                     "bytes_written": sum(r["bytes_written"] for r in fit),
                     "io_out_mib": sum(r["io_out_mib"] or 0.0 for r in fit)})
    return rows


def read_floor(root: str | Path, points: int, frames: int, threads: int = 2) -> dict:
    """The floor of a run (stage ``read_frames``): reading its merged frames (``hdr/frames``, what rectify
    reads) once with the pipeline's reader on ``threads`` threads, as rectify does; ``bytes_written`` here
    is the bytes read. Measured after the run, so from the page cache when the frames still fit in it."""
    from ..io.fileio import read_frame
    from ..io.frames import map_frames
    files = sorted((Path(root) / "hdr" / "frames").glob("*.exr"))
    start, cpu = time.perf_counter(), time.process_time()
    map_frames(lambda f: read_frame(f)[0].shape, files, threads, "read_frames")
    return {"points": points, "frames": frames, "stage": "read_frames", "wall_s": time.perf_counter() - start,
            "cpu_s": time.process_time() - cpu, "max_rss_mb": None, "bytes_written": folder_bytes(*files)}


def write_floor(root: str | Path, points: int, frames: int, size: int = 1 << 30) -> dict:
    """The disk's floor for writing (stage ``write_disk``): ``size`` bytes written to a file in ``root`` and
    synced to the disk (``os.fsync``), then deleted; ``bytes_written`` is ``size``. Measured beside the run, as
    :func:`read_floor`, so that :func:`with_write_floors` prices each stage's writes at that hour's speed."""
    chunk = os.urandom(min(size, 64 << 20))          # bytes that no file system compresses
    path = Path(root) / ".write_floor"
    start, cpu = time.perf_counter(), time.process_time()
    try:
        with open(path, "wb") as f:
            for _ in range(max(1, size // len(chunk))):
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        written = path.stat().st_size
    finally:
        path.unlink(missing_ok=True)
    return {"points": points, "frames": frames, "stage": "write_disk", "wall_s": time.perf_counter() - start,
            "cpu_s": time.process_time() - cpu, "max_rss_mb": None, "bytes_written": written}


def with_write_floors(rows: Sequence[dict]) -> list[dict]:
    """``rows`` with ``write_floor_s`` on each stage's: the seconds its ``io_out_mib`` takes at the speed of the
    ``write_disk`` row of the same run (points, frames); None where either is missing."""
    speed = {(r["points"], r["frames"]): r["bytes_written"] / r["wall_s"] for r in rows
             if r["stage"] == "write_disk" and r.get("wall_s")}
    out = []
    for r in rows:
        rate = speed.get((r["points"], r["frames"]))
        mib = r.get("io_out_mib")
        out.append({**r, "write_floor_s": mib * 2**20 / rate if rate and mib is not None else None})
    return out


def growth_exponent(sizes: Sequence[float], seconds: Sequence[float | None]) -> float | None:
    """The exponent b of seconds ~ a size^b: the least-squares slope of log seconds on log size over the
    pairs with positive numbers; None with fewer than two distinct sizes."""
    pairs = [(math.log(n), math.log(t)) for n, t in zip(sizes, seconds) if n and t and n > 0 and t > 0]
    if len({x for x, _ in pairs}) < 2:
        return None
    mx = sum(x for x, _ in pairs) / len(pairs)
    my = sum(y for _, y in pairs) / len(pairs)
    return (sum((x - mx) * (y - my) for x, y in pairs) / sum((x - mx) ** 2 for x, _ in pairs))


def growth_exponents(rows: Sequence[dict], points_sweep_frames: int = 480,
                     frames_sweep_points: int = 128 * 128) -> dict[str, tuple[float | None, float | None]]:
    """Per stage, the wall-time exponent in P (the runs at ``points_sweep_frames`` frames) and in F (the
    runs at ``frames_sweep_points`` points); none for ``write_disk``, the same gigabyte at every size."""
    out = {}
    for stage in dict.fromkeys(r["stage"] for r in rows if r["stage"] != "write_disk"):
        mine = [r for r in rows if r["stage"] == stage]
        by_points = [r for r in mine if r["frames"] == points_sweep_frames]
        by_frames = [r for r in mine if r["points"] == frames_sweep_points]
        out[stage] = (growth_exponent([r["points"] for r in by_points], [r["wall_s"] for r in by_points]),
                      growth_exponent([r["frames"] for r in by_frames], [r["wall_s"] for r in by_frames]))
    return out


def save_figure(fig, path: str | Path) -> Path:
    """``fig`` laid out and written to ``path`` (its folder made), then closed; returns the path."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_scale(rows: Sequence[dict], exponents: dict, path: str | Path, title: str,
               points_sweep_frames: int = 480, frames_sweep_points: int = 128 * 128) -> Path:
    """Wall seconds per stage against P (left) and F (right), log-log, each stage labelled with its
    exponent. Needs matplotlib (the ``bench`` extra)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharey=True)
    for ax, key, fixed, other, label, which in (
            (axes[0], "points", points_sweep_frames, "frames", "points P", 0),
            (axes[1], "frames", frames_sweep_points, "points", "frames F", 1)):
        for stage, exps in exponents.items():
            mine = sorted((r for r in rows if r["stage"] == stage and r[other] == fixed and r["wall_s"]),
                          key=lambda r: r[key])
            if not mine:
                continue
            b = exps[which]
            ax.plot([r[key] for r in mine], [r["wall_s"] for r in mine], "o-" if stage != "total" else "k*-",
                    lw=2.5 if stage == "total" else 1.2, label=f"{stage} ({'-' if b is None else f'{b:.2f}'})")
        ax.set_xscale("log")
        ax.set_yscale("log")
        sizes = sorted({r[key] for r in rows if r[other] == fixed})
        ax.set_xticks(sizes, [f"{math.isqrt(n)}^2" if key == "points" and math.isqrt(n) ** 2 == n else str(n)
                              for n in sizes])
        ax.minorticks_off()
        ax.set_xlabel(f"{label} ({other} = {fixed})")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, title="stage (exponent)", title_fontsize=7)
    axes[0].set_ylabel("wall seconds")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


WORKFLOW_FILES = ("Snakefile", "workflow", "config", "resources", "rig")
"""What a benchmark's own working folder links from the repository (its results stay apart)."""


def sheet_rows(sheet: str | Path, names: Sequence[str] | None, label: str) -> list[dict]:
    """The rows of a sample sheet, only those ``names`` when given; exits naming any name the sheet lacks."""
    import csv
    import sys
    with open(sheet, newline="") as f:
        rows = [r for r in csv.DictReader(f, delimiter="\t") if r.get("sample")]
    if names:
        known = {r["sample"] for r in rows}
        unknown = [s for s in names if s not in known]
        if unknown:
            sys.exit(f"{label}: {', '.join(unknown)} not in {sheet} (it lists {', '.join(sorted(known))})")
        rows = [r for r in rows if r["sample"] in names]
    return rows


def prepare_workdir(workdir: str | Path, rows: list[dict], repo: str | Path) -> None:
    """A benchmark's working folder: the workflow linked from ``repo`` and its own ``samples.tsv`` of ``rows``
    (rewritten only when it changes, so Snakemake's inputs keep their times)."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    for name in WORKFLOW_FILES:
        link = workdir / name
        if not link.is_symlink():
            link.symlink_to(Path(repo) / name)
    text = "sample\tsource\tpath\trig\n" + "".join(
        f"{r['sample']}\t{r['source']}\t{r['path']}\t{r.get('rig') or ''}\n" for r in rows)
    sheet = workdir / "samples.tsv"
    if not sheet.is_file() or sheet.read_text() != text:
        sheet.write_text(text)


def run_workflow(command: list[str], workdir: str | Path, label: str, logs: str) -> int:
    """Run a benchmark's Snakemake ``command`` in ``workdir``, saying what runs, how long it took or where the
    ``logs`` are when it failed (stderr); its exit code."""
    import subprocess
    import sys
    import time
    print(f"{label}: {' '.join(command[2:])}  (in {workdir})", file=sys.stderr, flush=True)
    start = time.monotonic()
    code = subprocess.run(command, cwd=workdir).returncode
    if code:
        print(f"{label} failed (exit {code}); logs in {workdir}/{logs}", file=sys.stderr)
    else:
        print(f"{label} done in {time.monotonic() - start:.0f} s", file=sys.stderr, flush=True)
    return code


def _cell(value):
    if value is None:
        return ""
    return round(value, 4) if isinstance(value, float) else value


def read_csv(path: str | Path) -> list[dict]:
    """tradeoff.csv back as rows (numbers as floats, empty cells as None)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for row in rows:
        out.append({k: (v if k in ("preset", "scene") else _number(v)) for k, v in row.items()})
    return out


def pareto_front(points: Sequence[tuple[float | None, float | None]]) -> list[int]:
    """Indices of the points (time, accuracy) that no other point beats: none is at most as slow and
    at least as accurate while strictly better in one of the two. Lower time and higher accuracy are
    better; points with a missing or non-finite coordinate are left out. Sorted by time."""
    valid = [i for i, (t, a) in enumerate(points)
             if t is not None and a is not None and math.isfinite(t) and math.isfinite(a)]
    front = []
    for i in valid:
        ti, ai = points[i]
        dominated = any(points[j][0] <= ti and points[j][1] >= ai and (points[j][0] < ti or points[j][1] > ai)
                        for j in valid if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (points[i][0], -points[i][1]))


def machine_description() -> str:
    """'N cores, M GB RAM' of this machine (the cores this process may use; MemTotal)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:   # not Linux
        cores = os.cpu_count() or 0
    ram = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                ram = int(line.split()[1]) / 1024 ** 2
                break
    except OSError:
        pass
    return f"{cores} cores" + (f", {ram:.0f} GB RAM" if ram is not None else "")


def plot(rows: Sequence[dict], path: str | Path, title: str, presets: Sequence[str] = ("fast", "balanced", "accurate"),
         x: str = "wall_s", y: str = "heldout_psnr_db") -> Path:
    """Time against accuracy: one thin line per scene (its presets in time order), one marker shape per
    preset, and each scene's Pareto front (dashed; scores of different scenes are not comparable, so
    each scene has its own). Needs matplotlib (the ``bench`` extra)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = dict(zip(presets, "os^DvP*"))
    fig, ax = plt.subplots(figsize=(7.5, 5))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, scene in enumerate(scenes):
        mine = sorted((r for r in rows if r["scene"] == scene and r.get(x) is not None and r.get(y) is not None),
                      key=lambda r: r[x])
        colour = colours[k % len(colours)]
        ax.plot([r[x] for r in mine], [r[y] for r in mine], "-", color=colour, alpha=0.35, lw=1, label=scene)
        for r in mine:
            ax.plot(r[x], r[y], markers.get(r["preset"], "x"), color=colour, markersize=8)
        points = [(r[x], r[y]) for r in mine]
        front = pareto_front(points)
        ax.plot([points[i][0] for i in front], [points[i][1] for i in front], "--", color=colour, lw=2,
                label=f"{scene}: Pareto front")
    for preset, marker in markers.items():
        if any(r["preset"] == preset for r in rows):
            ax.plot([], [], marker, color="grey", label=preset)
    ax.set_xlabel({"wall_s": "fit time, capture to refine (s, sum of the Snakemake benchmarks)",
                   "cpu_s": "fit CPU time, capture to refine (s, sum of the benchmarks' cpu_time)",
                   "preset_s": "fit time, rectify to refine (s)"}.get(x, x))
    ax.set_ylabel("held-out PSNR (dB)" if y == "heldout_psnr_db" else y)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


# --- real light-dome captures against the per-pixel RTI fits (make bench-real, issue 35) ----------------

#: facetsynth and the per-pixel fits the selfcheck scores on a light dome's capture (its ``baselines``;
#: ``hsh3_codes``: HSH 3 fitted to the 8-bit codes, as RTIBuilder and relight fit it).
REAL_METHODS = ("facetsynth", "lambert", "ptm", "hsh2", "hsh3", "hsh3_codes")
REAL_SUBSETS = ("relit", "heldout")
REAL_REFERENCES = ("hsh3", "hsh3_codes")   # facetsynth is compared with these on both subsets
REAL_COLUMNS = (["capture", "frames", "relit_frames", "heldout_frames"]
                + [f"{m}_{s}" for m in REAL_METHODS for s in REAL_SUBSETS]
                + ["fit_s", "rectify_to_refine_s", "peak_mem_mb"] + [f"le_{r}" for r in REAL_REFERENCES])


def real_row(results: str | Path, capture: str) -> dict:
    """One row of bench-real's table from ``results/{capture}/`` (a light dome's run up to selfcheck):
    the relative L2 on the fitting lights (``relit``) and the held-out ones (``heldout``) of facetsynth and
    of each per-pixel fit (REAL_METHODS; None where the metrics lack one); ``fit_s`` the wall seconds of
    FIT_STAGES, capture and hdr (reading and linearising the photos) included, ``rectify_to_refine_s``
    those of PRESET_STAGES, both None when a stage has no benchmark, each stage's wall as ``stage_cost``
    counts it (scatter parts: the slowest); ``peak_mem_mb`` the largest max_rss over FIT_STAGES; and
    ``le_hsh3``, ``le_hsh3_codes`` whether facetsynth's error is at most that HSH order 3's on both subsets
    (None if one is missing)."""
    root = Path(results) / capture
    metrics = _json(root / "selfcheck/metrics.json")
    row: dict = {"capture": capture, "frames": metrics.get("frames")}
    for subset in REAL_SUBSETS:
        row[f"{subset}_frames"] = (metrics.get(subset) or {}).get("frames")
        row[f"facetsynth_{subset}"] = (metrics.get(subset) or {}).get("rel_l2")
        for method in REAL_METHODS[1:]:
            row[f"{method}_{subset}"] = ((metrics.get("baselines") or {}).get(method) or {}).get(subset)
    costs = {stage: stage_cost(root, stage) for stage in FIT_STAGES}
    walls = {stage: None if cost is None else cost["wall_s"] for stage, cost in costs.items()}
    row["fit_s"] = None if None in walls.values() else sum(walls.values())
    preset = [walls[stage] for stage in PRESET_STAGES]
    row["rectify_to_refine_s"] = None if None in preset else sum(preset)
    peaks = [cost["max_rss_mb"] for cost in costs.values() if cost is not None and cost["max_rss_mb"] is not None]
    row["peak_mem_mb"] = max(peaks) if peaks else None
    for ref in REAL_REFERENCES:
        pairs = [(row[f"facetsynth_{s}"], row[f"{ref}_{s}"]) for s in REAL_SUBSETS]
        row[f"le_{ref}"] = None if any(a is None or b is None for a, b in pairs) else all(a <= b for a, b in pairs)
    return {column: row.get(column) for column in REAL_COLUMNS}


def real_table(rows: Sequence[dict]) -> str:
    """bench-real's rows as a Markdown table: per capture, relative L2 'fitting / held-out' of each method
    (3 decimals), the fit time (s), the peak memory (MB) and whether facetsynth <= each of REAL_REFERENCES on
    both subsets ('no: fitting, held-out' names where it is not)."""
    def num(value, spec):
        return "-" if value is None else format(value, spec)

    head = (["capture", "lights (fit / held-out)"] + [f"{m} rel. L2 (fit / held-out)" for m in REAL_METHODS]
            + ["fit s (capture..refine)", "peak MB"] + [f"facetsynth <= {r}" for r in REAL_REFERENCES])
    numbers = len(head) - 2 - len(REAL_REFERENCES)
    lines = ["| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] * 2 + ["---:"] * numbers + ["---"] * len(REAL_REFERENCES)) + "|"]
    for row in rows:
        fitted = None if row.get("frames") is None or row.get("heldout_frames") is None else \
            row["frames"] - row["heldout_frames"]
        cells = [str(row["capture"]), f"{num(fitted, 'd')} / {num(row.get('heldout_frames'), 'd')}"]
        cells += [f"{num(row.get(f'{m}_relit'), '.3f')} / {num(row.get(f'{m}_heldout'), '.3f')}" for m in REAL_METHODS]
        cells += [num(row.get("fit_s"), ".0f"), num(row.get("peak_mem_mb"), ".0f")]
        for ref in REAL_REFERENCES:
            if row.get(f"le_{ref}") is None:
                cells.append("-")
            elif row[f"le_{ref}"]:
                cells.append("yes")
            else:
                worse = [name for s, name in zip(REAL_SUBSETS, ("fitting", "held-out"))
                         if row[f"facetsynth_{s}"] > row[f"{ref}_{s}"]]
                cells.append("no: " + ", ".join(worse))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
