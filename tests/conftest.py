"""Shared fixtures: small ground-truth captures made by the virtual rig."""

from __future__ import annotations

import fcntl
import os
import shutil
import sys
from pathlib import Path

import pytest

from facetsynth.io.pages import memory_defaults

memory_defaults()   # before the test modules import numpy; the workflows the tests run inherit it

REPO = Path(__file__).resolve().parents[1]
# The test folders mirror the package's (tests/fit/ tests facetsynth.fit, ...). A test module imports another's
# helpers by its name (``from test_grid import sph``), as when they were one folder: pytest puts the folder of
# each test module it collects on sys.path, and a module collected later may need one collected before it.
sys.path[:0] = sorted(str(p) for p in Path(__file__).parent.iterdir() if p.is_dir() and p.name not in
                      ("data", "cluster", "__pycache__"))
# The seven measured RGL BRDFs (CC0), vendored from shared/data/rgl: real reflectance nobody here made.
RGL_DIR = REPO / "resources" / "brdfs" / "rgl"
RGL_FILES = sorted(RGL_DIR.glob("*.bsdf"))
assert len(RGL_FILES) == 7, f"{RGL_DIR}: expected the seven RGL .bsdf files"


def toy_manifest(lights, times=(0.25, 1.0)) -> dict:
    """A valid manifest of a 4 x 3 capture: one frame per point light at ``lights`` (positions, metres) of unit
    intensity, an exposure ``frames/{q:04d}_e{e}.exr`` per time of ``times`` each."""
    return {
        "version": 1, "units": "m", "sample": {"width": 0.1, "height": 0.1},
        "camera": {"width": 4, "height": 3, "K": [[100, 0, 1.5], [0, 100, 1], [0, 0, 1]],
                   "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "t": [0, 0, 1], "distortion": [0, 0, 0, 0, 0]},
        "saturation": 1.0,
        "frames": [{"light": {"position": list(p), "intensity": [1, 1, 1]},
                    "exposures": [{"file": f"frames/{q:04d}_e{e}.exr", "time": t} for e, t in enumerate(times)]}
                   for q, p in enumerate(lights)],
    }


def exposure_files(manifest: dict) -> list[str]:
    """Every exposure file a manifest lists, frame by frame."""
    return [e["file"] for f in manifest["frames"] for e in f["exposures"]]


def write_manifest(folder: Path, data) -> Path:
    """Write ``data`` as the folder's manifest.json (Python's json writes NaN and Infinity literals)."""
    import json
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(json.dumps(data))
    return folder / "manifest.json"


def write_toy_capture(folder: Path, manifest: dict, value: float = 0.2) -> Path:
    """``manifest`` (a :func:`toy_manifest`) and its exposures, 4 x 3 pixels of ``value``, in ``folder``."""
    import numpy as np
    from facetsynth.io.fileio import write_exr
    for name in exposure_files(manifest):
        write_exr(folder / name, {"RGB": np.full((3, 4, 3), value)})
    write_manifest(folder, manifest)
    return folder


def hdr_outputs(folder: Path):
    """hdr's outputs in ``folder`` as the workflow lays them out: frames/, manifest.json, metrics.json."""
    from facetsynth.stages import hdr
    return hdr.Outputs(frames=folder / "frames", manifest=folder / "manifest.json", metrics=folder / "metrics.json")


def tiny_truth_model(root: Path, repo: Path, cells: int, rings: int):
    """test_predict's SCENE captured noise-free by the test rig (30 frames) into ``root``/capture, and the SVBRDF
    of its truth on a ``cells`` x ``cells`` plane grid and a ``rings`` x 4 ``rings`` direction grid in
    ``root``/svbrdf; returns the model."""
    from facetsynth.geometry.grid import DirectionGrid
    from facetsynth.geometry.plane import PlaneGrid
    from facetsynth.truth.scene import Scene
    from facetsynth.models.svbrdf import tabulate_truth
    from facetsynth.truth.virtual_rig import VirtualRig, capture
    from test_predict import SCENE
    (root / "scene.yaml").write_text(SCENE)
    capture(root / "scene.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"), root / "capture", seed=1,
            noise=False)
    plane = PlaneGrid(0.1, 0.1, cells, cells)
    maps = Scene.load(root / "scene.yaml").parameters(plane.points3d().reshape(-1, 3)[:, :2])
    model = tabulate_truth(maps, DirectionGrid(rings, 4 * rings), plane)
    model.save(root / "svbrdf")
    return model


def rectify_into(manifest: Path, folder: Path, resolution: int | str) -> dict:
    """rectify of the hdr ``manifest`` into ``folder`` (frames/, geometry.json, metrics.json) at ``resolution``;
    returns its metrics."""
    import json

    from facetsynth.stages import rectify
    rectify.run(rectify.Inputs(manifest=manifest),
                rectify.Outputs(frames=folder / "frames", geometry=folder / "geometry.json",
                                metrics=folder / "metrics.json"), rectify.Settings(resolution=resolution))
    return json.loads((folder / "metrics.json").read_text())


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


# The test files that take longest (pytest --durations, clean clone, 2 idle cores), run first: `make test`
# hands whole files to its two workers (--dist loadfile, so that a file's module fixtures are made once), in
# collection order, and the 3.5 min of tests/workflow/test_workflow.py, collected last, ran alone at the end
# (6 min 46 s; longest first: see the closing note of issue 31).
LONGEST_FIRST = ("workflow/test_workflow.py", "fit/test_adaptive_model.py", "truth/test_mitsuba_capture.py",
                 "rti/test_rti_lp.py", "fit/test_synthesis.py")


def pytest_collection_modifyitems(items):
    """A test that uses ``demo_run`` is a whole-workflow test: it runs with the scene tests (make test-scenes).
    The files of :data:`LONGEST_FIRST` are collected first, in that order (the rest keep theirs)."""
    for item in items:
        if "demo_run" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.scenes)

    def rank(item) -> int:
        path = Path(str(item.fspath)).as_posix()
        return next((k for k, name in enumerate(LONGEST_FIRST) if path.endswith("tests/" + name)), len(LONGEST_FIRST))
    items.sort(key=rank)


@pytest.fixture(scope="session")
def demo_run(repo, tmp_path_factory, worker_id):
    """The default demo sample, noise-free, through the whole default workflow (validate, stencil_fit, the
    report's figures, the exports): one run (about 5 min) shared by the workflow, report and export tests, which
    are therefore scene tests (``pytest_collection_modifyitems``).

    Made once per test run, not once per xdist worker: the first worker to ask makes it under a lock in the
    folder the workers share (pytest-xdist's recipe for a session fixture run once; it was made on both workers,
    592 s and 317 s of the scene suite), and every worker gets its own copy (:func:`linked_copy`), since some
    tests run Snakemake in it (``--forcerun``, ``--report``)."""
    from test_workflow import NOISE_FREE, make_workdir, snakemake
    shared = tmp_path_factory.getbasetemp()
    shared = shared if worker_id == "master" else shared.parent
    made = shared / "demo-run"
    with open(shared / "demo-run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (made / "made").exists():
            shutil.rmtree(made, ignore_errors=True)
            workdir = make_workdir(repo, made, "demo\tvirtual\tresources/scenes/demo.yaml\t\n", resolution=None)
            (workdir / "noise-free.yaml").write_text("virtual:\n  noise: false\n")
            done = snakemake(workdir, "--notemp", *NOISE_FREE)   # keeps resample's slices: the reflectance
            # test refits the partial NDFs from them
            assert done.returncode == 0, done.stderr[-3000:]
            (made / "made").touch()
    return linked_copy(made, tmp_path_factory.mktemp("wf") / "demo")


def linked_copy(source: Path, dest: Path) -> Path:
    """A copy of the workflow folder ``source`` in ``dest``: files of 1 MB and more (frames, tables) hard-linked,
    the rest copied. Snakemake deletes a job's outputs before it runs the job again and facetsynth publishes
    whole files by renaming, so a run in the copy never writes through a link into ``source``; the small
    files (logs, benchmarks, Snakemake's own records, which are rewritten in place) are the copy's own."""
    def link_or_copy(src: str, dst: str) -> str:
        if os.path.getsize(src) >= 1 << 20:
            os.link(src, dst)
            return dst
        return shutil.copy2(src, dst)
    shutil.copytree(source, dest, copy_function=link_or_copy, symlinks=True)
    return dest


# the four-quadrant scene of the numerical extremes (issue 7, part 2)
EXTREME_SCENE = """\
name: extremes
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: diffuse-only
    where: {rect: {x: [-0.05, 0.0], y: [0.0, 0.05]}}
    kd: [0.40, 0.30, 0.20]
    ks: [0.0, 0.0, 0.0]
    eta: 1.5
    alpha: [0.3, 0.3]
    frame: {angle_deg: 0}
  - name: mirror-metal
    where: {rect: {x: [0.0, 0.05], y: [0.0, 0.05]}}
    kd: [0.0, 0.0, 0.0]
    ks: [0.9, 0.7, 0.5]
    eta: 3.5
    alpha: [0.02, 0.02]
    frame: {angle_deg: 0}
  - name: rough-eta-near-1
    where: {rect: {x: [-0.05, 0.0], y: [-0.05, 0.0]}}
    kd: [0.10, 0.20, 0.30]
    ks: [0.5, 0.5, 0.5]
    eta: 1.05
    alpha: [1.0, 1.0]
    frame: {angle_deg: 0}
  - name: glossy
    where: {rect: {x: [0.0, 0.05], y: [-0.05, 0.0]}}
    kd: [0.2, 0.2, 0.2]
    ks: [0.6, 0.6, 0.6]
    eta: 1.6
    alpha: [0.15, 0.3]
    frame: {angle_deg: 30}
"""


@pytest.fixture(scope="session")
def extreme_run(tmp_path_factory):
    """The four-quadrant extremes scene (ks = 0; kd = 0 with a near-mirror alpha 0.02 metal-like eta 3.5
    lobe; alpha 1 with eta 1.05; an anisotropic glossy one), noise-free, captured by the virtual rig on
    the sparse test rig (340 lights; camera 120 x 80), merged, rectified to 16 x 16 cells, then every
    per-point stage on a 16 x 64 direction grid. One run for the session: shared by test_stages,
    test_partial_ndf, test_resample and test_baseline."""
    from facetsynth.stages import hdr
    from facetsynth.truth.virtual_rig import VirtualRig, capture
    from test_stages import run_per_point_stages
    root = tmp_path_factory.mktemp("extremes")
    (root / "scene.yaml").write_text(EXTREME_SCENE)
    rig = (REPO / "tests/data/rig-sparse.yaml").read_text().replace("width: 240", "width: 120")
    (root / "rig.yaml").write_text(rig.replace("height_px: 160", "height_px: 80"))   # a quarter of the pixels
    capture(root / "scene.yaml", VirtualRig.load(root / "rig.yaml"), root / "capture", seed=1, noise=False)
    hdr.run(hdr.Inputs(capture=root / "capture"), hdr_outputs(root / "hdr"))
    rectify_into(root / "hdr/manifest.json", root / "rectify", 16)
    files = run_per_point_stages(root, root / "rectify/geometry.json", n_theta=16)
    files["root"] = root
    return files
