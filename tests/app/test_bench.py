"""Speed against accuracy: the presets reach the rules, and the benchmark's collection (fast tests only)."""

import functools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facetsynth.app import bench

SNAKEMAKE = [sys.executable, "-m", "snakemake", "--cores", "1", "-n"]
PROBE = """include: "Snakefile"
import json
print("PROBE " + json.dumps({
    "rectify": rules.rectify.params.resolution,
    "resample": [rules.resample.params.cells_per_lobe, rules.resample.params.n_theta_range],
    "synthesize": [rules.synthesize.params.max_exemplars, rules.synthesize.params.max_iterations],
    "other": {"tiles": SCATTER_TILES, "seed": config["seed"], "noise": config["virtual"]["noise"]},
}))
"""


@pytest.fixture(scope="module")
def workdir(repo, tmp_path_factory):
    """The workflow with a probe Snakefile that includes the real one and prints the preset knobs as
    the rules' params hold them."""
    dest = tmp_path_factory.mktemp("presets")
    for part in ("Snakefile", "workflow", "config", "resources", "rig"):
        src = repo / part
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dest / part)
    (dest / "probe.smk").write_text(PROBE)
    return dest


def dry_run(workdir: Path, *config: str, snakefile: str = "probe.smk") -> subprocess.CompletedProcess:
    args = SNAKEMAKE + ["-s", snakefile, "all"] + (["--config", *config] if config else [])
    return subprocess.run(args, cwd=workdir, capture_output=True, text=True)


def probed(done: subprocess.CompletedProcess) -> dict:
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [line for line in done.stdout.splitlines() if line.startswith("PROBE ")]
    assert len(lines) == 1, done.stdout[-2000:]
    values = json.loads(lines[0][len("PROBE "):])
    values.pop("other")
    return values


def preset_values(repo, name):
    import yaml
    p = yaml.safe_load((repo / "config/config.yaml").read_text())["presets"][name]
    return {"rectify": p["rectify"]["resolution"],
            "resample": [p["resample"]["cells_per_lobe"], p["resample"]["n_theta_range"]],
            "synthesize": [p["synthesize"]["max_exemplars"], p["synthesize"]["max_iterations"]]}


def test_balanced_is_the_default_and_keeps_the_recorded_defaults(repo, workdir):
    values = probed(dry_run(workdir))
    assert values == preset_values(repo, "balanced")
    assert values == {"rectify": "auto", "resample": [1.3, [16, 48]],
                      "synthesize": [4096, 12]}


@pytest.mark.parametrize("preset", ["fast", "accurate"])
def test_a_preset_resolves_and_reaches_the_rules(repo, workdir, preset):
    done = dry_run(workdir, f"preset={preset}")    # the probe includes the Snakefile: a dry run of its 'all'
    assert probed(done) == preset_values(repo, preset)
    assert "rule synthesize:" in done.stdout and "This was a dry-run" in done.stdout


def test_a_single_knob_overrides_the_preset(repo, workdir):
    """--config passes nested values as strings; a preset knob's string is read as YAML."""
    values = probed(dry_run(workdir, "preset=fast", "rectify={resolution: 48}"))
    assert values == {**preset_values(repo, "fast"), "rectify": 48}
    (workdir / "override.yaml").write_text("preset: accurate\nsynthesize:\n  max_exemplars: 2048\n")
    done = subprocess.run(SNAKEMAKE + ["-s", "probe.smk", "all", "--configfile", "config/config.yaml", "override.yaml"],
                          cwd=workdir, capture_output=True, text=True)
    expected = preset_values(repo, "accurate")
    assert probed(done) == {**expected, "synthesize": [2048, expected["synthesize"][1]]}


def test_config_values_from_the_command_line_are_typed_in_every_section(workdir):
    """--config gives every nested leaf as a string (YAML's BaseLoader); numbers, booleans and null are read as
    such in every section, not only the presets' (README: --config scatter='{tiles: 8}')."""
    done = dry_run(workdir, "scatter={tiles: 3}", "seed=5", "virtual={noise: false}",
                   "resample={n_theta_range: [24, 24]}")
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(line for line in done.stdout.splitlines() if line.startswith("PROBE "))
    values = json.loads(line[len("PROBE "):])
    assert values["other"] == {"tiles": 3, "seed": 5, "noise": False}
    assert values["resample"][1] == [24, 24]


def test_an_unknown_preset_fails_naming_it(workdir):
    done = dry_run(workdir, "preset=fastest", snakefile="Snakefile")
    assert done.returncode != 0
    message = done.stdout + done.stderr
    assert "unknown preset 'fastest'" in message and "choose one of: fast, balanced, accurate" in message


def test_pareto_front():
    points = [(10, 30.0), (20, 32.0), (15, 29.0), (40, 31.0), (5, 25.0), (20, 32.0), (60, 33.0), (None, 40.0),
              (70, float("nan"))]
    # (15, 29) loses to (10, 30); (40, 31) to (20, 32); the two (20, 32) tie and both stay
    assert bench.pareto_front(points) == [4, 0, 1, 5, 6]
    assert bench.pareto_front([]) == []
    assert bench.pareto_front([(3.0, 1.0)]) == [0]


def _benchmark(path: Path, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    header = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    path.write_text(header + "".join(f"{s}\t0:00:00\t{rss}\t1\t1\t1\t0\t0\t50\t{s}\n" for s, rss in rows))


def test_rows_from_a_results_tree(tmp_path):
    results = tmp_path / "results"
    root = results / "demo"
    for k, stage in enumerate(bench.FIT_STAGES):
        _benchmark(root / f"benchmarks/{stage}.tsv", [(k + 1.0, 100.0 * (k + 1))])
    _benchmark(root / "benchmarks/baseline_ward.tsv", [(500.0, 9999.0)])     # not a fit stage
    _benchmark(root / "benchmarks/synthesize.tsv", [(7.0, 700.0), (9.0, "NA")])   # repeat(): mean s, max rss
    (root / "validate").mkdir()
    (root / "validate/metrics.json").write_text(json.dumps({"heldout_psnr_db": 33.5, "heldout_ssim": 0.9,
                                                            "baseline_ward_psnr_db": 30.1}))
    (root / "synthesize").mkdir()
    (root / "synthesize/metrics.json").write_text(json.dumps({"ndf_rel_l2_median": 0.21, "representatives": 41,
                                                              "exemplars": 4096}))
    (root / "rectify").mkdir()
    (root / "rectify/geometry.json").write_text(json.dumps({"grid": {"cols": 64, "rows": 64}}))
    row = bench.collect_row(results, "balanced", "demo")
    seconds = {stage: k + 1.0 for k, stage in enumerate(bench.FIT_STAGES)} | {"synthesize": 8.0}
    assert row["preset"] == "balanced" and row["scene"] == "demo"
    assert row["wall_s"] == pytest.approx(sum(seconds.values()))
    assert row["preset_s"] == pytest.approx(sum(v for k, v in seconds.items() if k not in ("capture", "hdr")))
    assert row["synthesize_s"] == 8.0 and row["capture_s"] == 1.0
    assert row["cpu_s"] == pytest.approx(row["wall_s"])     # the fake files' cpu_time equals s
    assert row["peak_mem_mb"] == 1000.0         # refine (the 10th stage); baseline_ward left out
    assert (row["heldout_psnr_db"], row["ndf_rel_l2_median"], row["resolution"]) == (33.5, 0.21, 64)
    assert row["partial_ndf_rel_l2_median"] is None and row["n_phi"] is None     # absent records stay empty

    (root / "benchmarks/params.tsv").unlink()   # an unfinished run: no total
    partial = bench.collect_row(results, "balanced", "demo")
    assert partial["wall_s"] is None and partial["params_s"] is None

    path = bench.write_csv([row, partial], tmp_path / "bench/tradeoff.csv")
    back = bench.read_csv(path)
    assert list(back[0]) == bench.COLUMNS
    assert back[0]["wall_s"] == pytest.approx(row["wall_s"]) and back[1]["wall_s"] is None
    assert back[0]["preset"] == "balanced" and back[0]["heldout_psnr_db"] == 33.5


def test_machine_description():
    assert "cores" in bench.machine_description()


def write_benchmark(path: Path, seconds: float, cpu: float, rss: float, io_out: float = 0.0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
                    f"{seconds}\t0:00:01\t{rss}\t1\t1\t1\t0\t{io_out}\t50\t{cpu}\n")


def test_scale_rows_join_scatter_parts_and_total_rectify_to_params(tmp_path):
    """A stage split in scatter parts (run side by side) costs its slowest part plus the join in wall time
    and the sum in CPU time and in MiB written; 'total' sums rectify through refine; bytes are the stage
    folders' sizes."""
    root = tmp_path / "results/scale"
    for k, stage in enumerate(bench.FIT_STAGES):
        write_benchmark(root / "benchmarks" / f"{stage}.tsv", 1.0 + k, 0.5 + k, 100.0 * (k + 1), io_out=2.0 * k)
        (root / stage).mkdir(parents=True)
        (root / stage / "out.npy").write_bytes(b"x" * (10 * (k + 1)))
    write_benchmark(root / "benchmarks/partial_ndf/1-of-2.tsv", 30.0, 29.0, 2000.0, io_out=300.0)
    write_benchmark(root / "benchmarks/partial_ndf/2-of-2.tsv", 40.0, 39.0, 1500.0, io_out=400.0)
    (root / "svbrdf").mkdir()
    (root / "svbrdf/model.json").write_bytes(b"y" * 7)
    rows = {r["stage"]: r for r in bench.scale_rows(root, 4096, 480)}
    k = bench.FIT_STAGES.index("partial_ndf")
    assert rows["partial_ndf"]["wall_s"] == 40.0 + 1.0 + k and rows["partial_ndf"]["cpu_s"] == 29 + 39 + 0.5 + k
    assert rows["partial_ndf"]["max_rss_mb"] == 2000.0
    assert rows["partial_ndf"]["io_out_mib"] == 300.0 + 400.0 + 2.0 * k   # the parts' tables and the join's
    assert rows["total"]["io_out_mib"] == sum(2.0 * bench.FIT_STAGES.index(s) for s in bench.TOTAL_STAGES) + 700.0
    assert rows["params"]["bytes_written"] == 10 * (bench.FIT_STAGES.index("params") + 1)
    assert rows["refine"]["bytes_written"] == 10 * (bench.FIT_STAGES.index("refine") + 1) + 7   # with svbrdf/
    fit = [bench.FIT_STAGES.index(s) for s in bench.TOTAL_STAGES]
    assert rows["total"]["wall_s"] == sum(1.0 + k for k in fit) + 40.0
    assert rows["total"]["points"] == 4096 and rows["total"]["frames"] == 480
    path = bench.write_csv(rows.values(), tmp_path / "scale.csv", bench.SCALE_COLUMNS)
    assert path.read_text().splitlines()[0] == ",".join(bench.SCALE_COLUMNS)


def test_each_stage_writes_at_the_disks_speed_measured_beside_it(tmp_path):
    """write_disk's row: the bytes it wrote and synced, and the file gone; with_write_floors prices a stage's
    MiB at that run's speed (not another run's), and leaves a stage with no io_out without a floor."""
    floor = bench.write_floor(tmp_path, 4096, 480, size=8 << 20)
    assert floor["stage"] == "write_disk" and floor["bytes_written"] == 8 << 20 and floor["wall_s"] > 0
    assert not any(tmp_path.iterdir())
    rows = [{"points": 4096, "frames": 480, "stage": "write_disk", "wall_s": 2.0, "bytes_written": 1 << 30},
            {"points": 9, "frames": 480, "stage": "write_disk", "wall_s": 1.0, "bytes_written": 1 << 30},
            {"points": 4096, "frames": 480, "stage": "resample", "wall_s": 9.0, "io_out_mib": 1536.0},
            {"points": 4096, "frames": 480, "stage": "synthesize", "wall_s": 1.0, "io_out_mib": None}]
    priced = {r["stage"] + str(r["points"]): r for r in bench.with_write_floors(rows)}
    assert priced["resample4096"]["write_floor_s"] == pytest.approx(3.0)    # 1.5 GiB at 0.5 GiB/s
    assert priced["synthesize4096"]["write_floor_s"] is None
    assert "write_disk" not in bench.growth_exponents(rows)


def test_growth_exponents_recover_power_laws():
    rows = [{"points": p, "frames": 480, "stage": "cluster", "wall_s": 2e-3 * p ** 1.5} for p in (64**2, 128**2, 256**2)]
    rows += [{"points": 128**2, "frames": f, "stage": "cluster", "wall_s": 2e-3 * (128**2) ** 1.5 * (f / 480)}
             for f in (120, 1360, 2600)]
    rows += [{"points": 64**2, "frames": 480, "stage": "params", "wall_s": 3.0}]
    exponents = bench.growth_exponents(rows)
    assert exponents["cluster"][0] == pytest.approx(1.5) and exponents["cluster"][1] == pytest.approx(1.0)
    assert exponents["params"] == (None, None)       # one size: no exponent


def test_bench_scale_records_a_run_before_pruning_it(tmp_path, repo, monkeypatch):
    """make bench-scale --prune: a run's rows (stages, total, floor) are recorded right after it, in
    benchmarks/scale_rows.json; pruning deletes its frames and per-point tables but keeps metrics, logs,
    benchmarks and the SVBRDF; the recorded rows still give the sizes the tables had."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("bench_scale", repo / "workflow/scripts/bench_scale.py")
    bench_scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_scale)
    root = tmp_path / "results/scale"
    for k, stage in enumerate(bench.FIT_STAGES):
        write_benchmark(root / "benchmarks" / f"{stage}.tsv", 1.0 + k, 0.5 + k, 100.0 * (k + 1))
        (root / stage).mkdir(parents=True)
        (root / stage / "table.npy").write_bytes(b"x" * 1000 * (k + 1))
        (root / stage / "metrics.json").write_text("{}")
    (root / "hdr/frames").mkdir(parents=True)
    (root / "svbrdf").mkdir()
    (root / "svbrdf/model.json").write_text("{}")
    monkeypatch.setattr(bench, "write_floor", functools.partial(bench.write_floor, size=1 << 20))   # not 1 GiB
    rows = bench_scale.recorded(root, 64, 480)
    bench_scale.prune(root)
    assert not (root / "partial_ndf/table.npy").exists() and not (root / "resample/table.npy").exists()
    assert (root / "partial_ndf/metrics.json").is_file() and (root / "svbrdf/model.json").is_file()
    assert (root / "cluster/table.npy").is_file()                     # small tables are kept
    again = bench_scale.recorded(root, 64, 480)
    assert again == rows
    by_stage = {r["stage"]: r for r in again}
    assert by_stage["partial_ndf"]["bytes_written"] == 1000 * (bench.FIT_STAGES.index("partial_ndf") + 1) + 2
    assert by_stage["read_frames"]["points"] == 64 * 64 and "total" in by_stage
    assert by_stage["write_disk"]["bytes_written"] == 1 << 20 and by_stage["refine"]["write_floor_s"] == 0.0


def test_real_rows_and_table_from_a_results_tree(tmp_path):
    """make bench-real's row: facetsynth and the per-pixel fits' relative L2 from the selfcheck's metrics, the
    fit time over FIT_STAGES (capture and hdr included; a scattered stage counts its slowest part), the peak
    memory, whether facetsynth <= HSH3 (fitted to the linear frames, and to the codes) on both subsets; and the
    Markdown table of the rows."""
    results = tmp_path / "results"
    root = results / "rti-leaf"
    for k, stage in enumerate(bench.FIT_STAGES):
        write_benchmark(root / "benchmarks" / f"{stage}.tsv", 1.0 + k, 0.5 + k, 100.0 * (k + 1))
    write_benchmark(root / "benchmarks/resample/1-of-2.tsv", 20.0, 19.0, 3000.0)
    write_benchmark(root / "benchmarks/resample/2-of-2.tsv", 30.0, 29.0, 2500.0)
    write_benchmark(root / "benchmarks/selfcheck.tsv", 500.0, 500.0, 9999.0)     # not a fit stage
    scores = {"lambert": (0.30, 0.32), "ptm": (0.20, 0.25), "hsh2": (0.15, 0.24), "hsh3": (0.12, 0.26),
              "hsh3_codes": (0.10, 0.20)}
    metrics = {"frames": 48, "relit": {"frames": 42, "rel_l2": 0.11}, "heldout": {"frames": 6, "rel_l2": 0.21},
               "baselines": {m: {"relit": r, "heldout": h} for m, (r, h) in scores.items()}}
    (root / "selfcheck").mkdir()
    (root / "selfcheck/metrics.json").write_text(json.dumps(metrics))

    row = bench.real_row(results, "rti-leaf")
    assert list(row) == bench.REAL_COLUMNS
    assert (row["capture"], row["frames"], row["relit_frames"], row["heldout_frames"]) == ("rti-leaf", 48, 42, 6)
    assert (row["facetsynth_relit"], row["facetsynth_heldout"]) == (0.11, 0.21)
    assert (row["ptm_relit"], row["hsh3_heldout"]) == (0.20, 0.26)
    stages = {stage: 1.0 + k for k, stage in enumerate(bench.FIT_STAGES)}
    assert row["fit_s"] == pytest.approx(sum(stages.values()) + 30.0)    # resample: join + its slowest part
    assert row["rectify_to_refine_s"] == pytest.approx(row["fit_s"] - stages["capture"] - stages["hdr"])
    assert row["peak_mem_mb"] == 3000.0         # a resample part; selfcheck left out
    assert row["le_hsh3"] is True and row["le_hsh3_codes"] is False     # 0.11 > 0.10, 0.21 > 0.20

    metrics["relit"]["rel_l2"] = 0.13           # worse than HSH3 on the fitting lights only
    del metrics["baselines"]["lambert"]         # a fit the metrics lack stays empty
    (root / "selfcheck/metrics.json").write_text(json.dumps(metrics))
    (root / "benchmarks/refine.tsv").unlink()   # an unfinished run: no fit time
    worse = bench.real_row(results, "rti-leaf")
    assert worse["le_hsh3"] is False and worse["lambert_relit"] is None and worse["fit_s"] is None
    assert bench.real_row(results, "missing")["le_hsh3"] is None

    lines = bench.real_table([row, worse]).splitlines()
    assert len(lines) == 4 and all(line.startswith("| ") or line.startswith("|-") for line in lines)
    assert all(line.count("|") == lines[0].count("|") for line in lines[1:])
    assert "| rti-leaf | 42 / 6 | 0.110 / 0.210 | 0.300 / 0.320 |" in lines[2]
    assert lines[2].endswith("| 0.100 / 0.200 | 85 | 3000 | yes | no: fitting, held-out |")
    assert "| - / - |" in lines[3] and lines[3].endswith("| - | 3000 | no: fitting | no: fitting, held-out |")
    path = bench.write_csv([row, worse], tmp_path / "table.csv", bench.REAL_COLUMNS)
    assert path.read_text().splitlines()[0] == ",".join(bench.REAL_COLUMNS)


def test_bench_real_names_a_missing_photo_folder(tmp_path, repo):
    """Without the photos (../shared/data/rti on this machine only) the script stops before any run, naming
    the folder that is missing."""
    sheet = tmp_path / "samples.tsv"
    sheet.write_text(f"sample\tsource\tpath\nrti-leaf\tlp\t{tmp_path}/no-such/rti/item7/dirs.lp\n")
    done = subprocess.run([sys.executable, str(repo / "workflow/scripts/bench_real.py"), "--samples", str(sheet),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert done.returncode != 0
    assert f"{tmp_path}/no-such does not exist" in done.stderr and not (tmp_path / "out").exists()
