"""Issue 32 (hostile input and faults, round two), the output and model side.

Item 1: ``render -o`` never writes over an input. Item 2: a full disk or a read-only folder is a one-line
error that leaves the old output whole (or none), never a truncated picture or a partial folder. Item 8: a
model folder with non-finite or out-of-range parameters is refused by the loader, naming the file and the
count. Item 9: one writer per output folder (a lock; a dead writer's lock is taken over). Item 10: Ctrl-C,
a closed pipe, an overflowing exposure, a camera too large for memory and a NaN in an integer figure are
one line each, never a traceback.

The model is tiny (8 x 8 points, an 8 x 32 direction grid) and the capture the tiny test rig's (30 frames,
120 x 80), so that each command runs in well under a second.
"""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from facetsynth.app.cli import main
from facetsynth.io.fileio import read_exr, write_exr
from facetsynth.io.outputs import LOCK, MARKER, STAGING, folder_lock
from facetsynth.app.preview import PreviewSettings
from facetsynth.stencil.export import model_to_json
from facetsynth.models.ward import WardSVBRDF

from test_cli_outputs import error_line, run, snapshot, synth
from conftest import tiny_truth_model

EXE = Path(sys.executable).with_name("facetsynth")
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture(scope="module")
def made(tmp_path_factory, repo):
    """A tiny noise-free capture, the SVBRDF of its truth and a Ward baseline on the same plane."""
    root = tmp_path_factory.mktemp("hostile")
    model = tiny_truth_model(root, repo, 8, 8)
    plane = model.plane
    p = plane.rows * plane.cols
    WardSVBRDF(plane, model.kd, model.ks, np.full(p, 0.2), np.full(p, 0.3), np.zeros(p)).save(root / "ward")
    (root / "params.json").write_text(json.dumps(model_to_json(synth((20,)))))
    return root


@pytest.fixture
def work(made, tmp_path):
    """A private copy of the model, the Ward model, the capture and a stencil parameter file."""
    for name in ("svbrdf", "ward", "capture", "params.json"):
        (shutil.copytree if (made / name).is_dir() else shutil.copy)(made / name, tmp_path / name)
    return tmp_path


def one_line(err, command, *texts):
    """The single error line of a failed command, checked to hold every one of ``texts``; nothing else is
    printed but predict's progress bar and argparse's usage."""
    line = error_line(err, command)
    others = [ln for ln in err.strip().split("\n")[:-1]
              if ln.strip() and "\r" not in ln and not ln.startswith(("usage:", " "))]
    assert not others, err
    for text in texts:
        assert text in line, line
    return line


def leftovers(folder):
    """Temporaries, staging folders and locks left anywhere under ``folder``."""
    return [p for p in Path(folder).rglob("*") if ".tmp" in p.name or p.name.startswith((STAGING, LOCK))]


def fail_on_call(monkeypatch, target, call, exc):
    """Make ``target`` (a dotted attribute) raise ``exc`` on its ``call``-th call; earlier calls run it."""
    owner, name = target.rsplit(".", 1)
    module = __import__(owner, fromlist=[name])
    original, calls = getattr(module, name), []

    def failing(*args, **kwargs):
        calls.append(None)
        if len(calls) == call:
            raise exc
        return original(*args, **kwargs)
    monkeypatch.setattr(module, name, failing)


# --- item 1: render never writes over an input -------------------------------------------------------

@pytest.mark.parametrize("target, problem", [
    ("svbrdf/kd.exr", "output lies inside the model folder"),           # the issue: the model's kd replaced
    ("svbrdf/ks.exr", "output lies inside the model folder"),
    ("svbrdf/preview.png", "output lies inside the model folder"),      # a new file, but in the model
    ("kd-link.exr", "output lies inside the model folder"),             # a link to the model's kd map
    ("capture/frames/0000_e0.exr", "exists and was not written by facetsynth render"),   # the issue: a capture
    ("capture/truth/radiance_0003.exr", "exists and was not written by facetsynth render"),
    ("photo.png", "exists and was not written by facetsynth render"),   # the user's own picture
])
def test_render_never_writes_over_an_input(work, capsys, target, problem):
    """Reproduced: `render MODEL -o MODEL/kd.exr` replaced the kd map, exit 0, and the next render failed.
    Now refused in one line naming the output, and not one byte under the work folder changes."""
    (work / "kd-link.exr").symlink_to(work / "svbrdf" / "kd.exr")
    from PIL import Image
    Image.new("RGB", (8, 8), (200, 10, 10)).save(work / "photo.png")
    before = snapshot(work)
    rc, err = run(["render", work / "svbrdf", "--size", "32", "-o", work / target], capsys)
    assert rc == 1
    one_line(err, "render", f"{work / target}: {problem}")
    assert snapshot(work) == before
    assert run(["render", work / "svbrdf", "--size", "32", "-o", work / "after.png"], capsys)[0] == 0


@pytest.mark.parametrize("target", ["svbrdf/kd.exr", "svbrdf/model.json.png", "kd-link.exr"])
def test_force_never_lifts_the_model_folder_rule(work, capsys, target):
    (work / "kd-link.exr").symlink_to(work / "svbrdf" / "kd.exr")
    before = snapshot(work)
    rc, err = run(["render", work / "svbrdf", "--size", "32", "--force", "-o", work / target], capsys)
    assert rc == 1 and "lies inside the model folder" in one_line(err, "render")
    assert snapshot(work) == before


def test_render_through_a_linked_model_folder_still_refuses_its_files(work, capsys):
    (work / "model-link").symlink_to(work / "svbrdf")
    before = snapshot(work / "svbrdf")
    rc, err = run(["render", work / "model-link", "--size", "32", "-o", work / "svbrdf" / "eta.exr"], capsys)
    assert rc == 1 and "lies inside the model folder" in one_line(err, "render")
    assert snapshot(work / "svbrdf") == before


@pytest.mark.parametrize("name", ["again.png", "again.exr", "again.tif"])
def test_render_replaces_its_own_picture_and_a_forced_one(work, capsys, name):
    """A picture render wrote says so (Software metadata): rendering it again needs no --force. A foreign
    file is replaced only with --force (the user's choice), never an input of the model."""
    out = work / name
    for _ in range(2):
        assert run(["render", work / "svbrdf", "--size", "32", "-o", out], capsys)[0] == 0
    foreign = work / "capture" / "frames" / ("0001_e1.exr" if name.endswith(".exr") else "x" + name)
    if not foreign.exists():
        foreign.write_bytes(b"not a picture")
    assert run(["render", work / "svbrdf", "--size", "32", "-o", foreign], capsys)[0] == 1
    assert run(["render", work / "svbrdf", "--size", "32", "--force", "-o", foreign], capsys)[0] == 0
    assert run(["render", work / "svbrdf", "--size", "32", "-o", foreign], capsys)[0] == 0   # now render's


# --- item 2: a full disk, a read-only folder ---------------------------------------------------------

# Runs `facetsynth ARGV` with a file size limit of LIMIT bytes: a write beyond it fails with EFBIG, as a full
# disk's fails with ENOSPC (SIGXFSZ ignored, as it would kill the process instead).
LIMITED = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
from facetsynth.app import cli
sys.exit(cli.main(sys.argv[2:]))
"""


@pytest.mark.parametrize("name", ["r.png", "r.exr", "r.tif"])
def test_a_picture_that_does_not_fit_on_the_disk_is_an_error_and_the_old_one_stays(work, capsys, name):
    """Reproduced: `render -o r.png` onto a nearly full disk exited 0 leaving a truncated PNG (OpenImageIO
    reports the failed write only through geterror). Now one line, exit 1, and the old picture is unchanged."""
    out = work / name
    assert run(["render", work / "svbrdf", "--size", "32", "-o", out], capsys)[0] == 0
    old = out.read_bytes()
    done = subprocess.run([sys.executable, "-c", LIMITED, "2000", "render", str(work / "svbrdf"), "--size", "256",
                           "--view", "10", "30", "-o", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    one_line(done.stderr, "render", f"{out}: cannot write (", "nothing written")
    assert ".tmp" not in done.stderr                       # the temporary's name is not the user's business
    assert out.read_bytes() == old and not leftovers(work)


@pytest.mark.parametrize("argv, writer, call", [
    ("predict {w}/svbrdf {w}/capture {out}", "facetsynth.app.predict.write_exr", 7),
    ("predict {w}/svbrdf {w}/capture {out}", "facetsynth.capture.manifest.save", 1),
    ("export mitsuba {w}/svbrdf {out}", "facetsynth.export.mitsuba.write_json", 1),
    ("export mitsuba {w}/svbrdf {out}", "facetsynth.export.mitsuba._write_text", 2),
    ("export gltf {w}/svbrdf {out}", "facetsynth.export.gltf._write_png", 2),
    ("stencil-edit {w}/params.json --out {out}", "facetsynth.io.fileio.atomic_path", 2),
])
def test_a_full_disk_leaves_no_partial_folder_and_keeps_the_old_output(work, capsys, monkeypatch, argv, writer,
                                                                       call):
    """Reproduced: predict and export mitsuba on a full disk raised tracebacks and left partial folders. Now:
    one line naming the output folder, no folder when there was none, the old output byte for byte when
    there was one (a rerun into its own folder)."""
    args = argv.format(w=work, out=work / "out").split()
    assert run(args, capsys)[0] == 0                        # the old output
    old = snapshot(work / "out")
    fail_on_call(monkeypatch, writer, call, ENOSPC)
    rc, err = run(args, capsys)
    assert rc == 1
    one_line(err, args[0], f"{work / 'out'}: cannot write (No space left on device); nothing written")
    assert snapshot(work / "out") == old
    monkeypatch.undo()
    shutil.rmtree(work / "out")
    fail_on_call(monkeypatch, writer, call, ENOSPC)
    rc, err = run(args, capsys)
    assert rc == 1 and "No space left on device" in one_line(err, args[0])
    assert not (work / "out").exists() and not leftovers(work)


def test_a_read_only_folder_for_a_picture_is_one_line(work, capsys, monkeypatch):
    """Reproduced: `render -o READONLY/r.exr` ended in a traceback. (Tests run as root, who may write
    anywhere: the folder's permission and the write's failure are simulated.)"""
    real_access = os.access
    monkeypatch.setattr("facetsynth.io.outputs.os.access",
                        lambda path, mode: False if Path(path) == work / "ro" else real_access(path, mode))
    (work / "ro").mkdir()
    for name in ("r.exr", "r.png"):
        rc, err = run(["render", work / "svbrdf", "--size", "32", "-o", work / "ro" / name], capsys)
        assert rc == 1
        one_line(err, "render", f"{work / 'ro'}: folder is not writable")
    monkeypatch.undo()
    denied = PermissionError(errno.EACCES, os.strerror(errno.EACCES))
    fail_on_call(monkeypatch, "facetsynth.app.preview.write_exr", 1, denied)
    fail_on_call(monkeypatch, "facetsynth.app.preview._write_picture", 1, denied)
    for name in ("r.exr", "r.png"):
        rc, err = run(["render", work / "svbrdf", "--size", "32", "-o", work / "ro" / name], capsys)
        assert rc == 1
        one_line(err, "render", f"{work / 'ro' / name}: cannot write (Permission denied)")
    assert not any((work / "ro").iterdir())


# --- item 8: corrupt model values --------------------------------------------------------------------

def _edit_map(file, channel, edit):
    channels, header = read_exr(file)
    data = {c: a for c, a in channels.items()}
    edit(data[channel])
    write_exr(file, data)


def _edit_npy(file, edit, dtype=None):
    a = np.load(file)
    a = a.astype(dtype) if dtype else a
    edit(a)
    np.save(file, a)


def _edit_json(file, edit):
    meta = json.loads(file.read_text())
    edit(meta)
    file.write_text(json.dumps(meta))


def _set(a, index, value):
    a.reshape(-1)[index] = value


CORRUPTIONS = {
    "kd NaN": (lambda m: _edit_map(m / "kd.exr", "RGB", lambda a: _set(a, [0, 5, 40], np.nan)),
               "kd.exr: 3 kd value(s) NaN or Inf"),
    "kd negative": (lambda m: _edit_map(m / "kd.exr", "RGB", lambda a: _set(a, [1, 2], -0.3)),
                    "kd.exr: 2 kd value(s) below 0"),
    "ks Inf": (lambda m: _edit_map(m / "ks.exr", "RGB", lambda a: _set(a, [7], np.inf)),
               "ks.exr: 1 ks value(s) NaN or Inf"),
    "eta NaN": (lambda m: _edit_map(m / "eta.exr", "eta", lambda a: _set(a, [3, 4], np.nan)),
                "eta.exr: 2 eta value(s) NaN or Inf"),
    "eta zero": (lambda m: _edit_map(m / "eta.exr", "eta", lambda a: _set(a, [3], 0.0)),
                 "eta.exr: 1 eta value(s) <= 0"),
    "weights NaN": (lambda m: _edit_npy(m / "weights.npy", lambda a: _set(a, [0, 9, 10, 11], np.nan)),
                    "weights.npy: 4 weights value(s) NaN or Inf"),
    "ndf Inf": (lambda m: _edit_npy(m / "ndf.npy", lambda a: _set(a, [5], -np.inf)),
                "ndf.npy: 1 ndf value(s) NaN or Inf"),
    "neighbour out of range": (lambda m: _edit_npy(m / "neighbours.npy", lambda a: _set(a, [6, 7], 999)),
                               "neighbours.npy: 2 neighbour index(es) outside the 2 representatives (0 to 1)"),
    "neighbour negative": (lambda m: _edit_npy(m / "neighbours.npy", lambda a: _set(a, [6], -1)),
                           "neighbours.npy: 1 neighbour index(es) outside the 2 representatives"),
    "neighbours float": (lambda m: _edit_npy(m / "neighbours.npy", lambda a: _set(a, [0], np.nan), float),
                         "neighbours.npy: data type float64, expected integers"),
    "plane width NaN": (lambda m: _edit_json(m / "model.json", lambda d: d["plane_grid"].update(width=float("nan"))),
                        "model.json: plane_grid.width must be a finite number > 0, found nan"),
    "plane cols zero": (lambda m: _edit_json(m / "model.json", lambda d: d["plane_grid"].update(cols=0)),
                        "model.json: plane_grid.cols must be an integer from 1"),
    "grid a string": (lambda m: _edit_json(m / "model.json", lambda d: d["grid"].update(n_phi="32")),
                      "model.json: grid.n_phi must be an integer"),
}
COMMANDS = {"render": "render {m} --size 32 -o {w}/out.png", "predict": "predict {m} {w}/capture {w}/out",
            "export mitsuba": "export mitsuba {m} {w}/out", "export gltf": "export gltf {m} {w}/out"}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("corruption", CORRUPTIONS)
def test_a_corrupt_model_is_refused_naming_the_file_and_the_count(work, capsys, corruption, command):
    """Reproduced: NaN kd or weights, a negative kd, an Inf ks, a NaN plane width rendered black, zero or NaN
    pictures (and NaN in the glTF) with exit 0; a neighbour index out of range was an IndexError traceback,
    a negative one a plausible wrong picture. Now every command refuses the model in one line."""
    _refused(work / "svbrdf", CORRUPTIONS[corruption], command, capsys)
    assert not (work / "out").exists() and not (work / "out.png").exists()


def _refused(model, corruption, command, capsys):
    """``command`` (a COMMANDS key) on the ``model`` folder, corrupted by ``corruption`` (its edit, the error's
    text after the folder), exits 1 with that one line."""
    corrupt, text = corruption
    corrupt(model)
    args = COMMANDS[command].format(m=model, w=model.parent).split()
    rc, err = run(args, capsys)
    assert rc == 1
    one_line(err, args[0], f"{model}/{text}")


WARD_CORRUPTIONS = {
    "kd NaN": (lambda m: _edit_map(m / "kd.exr", "RGB", lambda a: _set(a, [2], np.nan)),
               "kd.exr: 1 kd value(s) NaN or Inf"),
    "ks negative": (lambda m: _edit_map(m / "ks.exr", "RGB", lambda a: _set(a, [2, 3, 4], -1.0)),
                    "ks.exr: 3 ks value(s) below 0"),
    "alpha zero": (lambda m: _edit_map(m / "lobe.exr", "alpha_x", lambda a: _set(a, [9], 0.0)),
                   "lobe.exr: 1 alpha_x value(s) <= 0"),
    "width NaN": (lambda m: _edit_json(m / "model.json", lambda d: d["plane_grid"].update(height=float("inf"))),
                  "model.json: plane_grid.height must be a finite number > 0"),
}


@pytest.mark.parametrize("command", ["render", "predict"])
@pytest.mark.parametrize("corruption", WARD_CORRUPTIONS)
def test_a_corrupt_ward_baseline_is_refused_too(work, capsys, corruption, command):
    _refused(work / "ward", WARD_CORRUPTIONS[corruption], command, capsys)


def test_the_gltf_never_holds_nan_even_past_the_loader(work, capsys, monkeypatch):
    """The loader's check bypassed, a NaN eta reaches the glTF material's ior: the writer refuses it (NaN is
    not JSON) instead of writing it, and publishes nothing."""
    _edit_map(work / "svbrdf" / "eta.exr", "eta", lambda a: a.fill(np.nan))
    monkeypatch.setattr("facetsynth.models.svbrdf.SVBRDF.check_values", lambda self, path: self)
    rc, err = run(["export", "gltf", work / "svbrdf", work / "out"], capsys)
    assert rc == 1
    one_line(err, "export", f"{work / 'svbrdf'}: the fitted glTF material holds NaN or Inf values")
    assert not (work / "out").exists()


def test_render_refuses_a_picture_that_overflows(work, capsys):
    """A huge but finite kd times the light overflows float32 radiance: refused, not an Inf picture."""
    _edit_map(work / "svbrdf" / "kd.exr", "RGB", lambda a: a.fill(3e38))
    for name in ("o.exr", "o.png"):
        rc, err = run(["render", work / "svbrdf", "--size", "32", "-o", work / name], capsys)
        assert rc == 1
        one_line(err, "render", f"{work / 'svbrdf'}: ", "overflow to Inf")
        assert not (work / name).exists()


# --- item 9: one writer per output folder ------------------------------------------------------------

WRITERS = {"predict": "predict {w}/svbrdf {w}/capture {out}", "export mitsuba": "export mitsuba {w}/svbrdf {out}",
           "export gltf": "export gltf {w}/svbrdf {out}", "stencil-edit": "stencil-edit {w}/params.json --out {out}"}


@pytest.mark.parametrize("writer", WRITERS)
def test_a_second_writer_into_one_folder_is_refused(work, capsys, writer):
    """Reproduced: two predicts into one folder both exited 0 and mixed their frames. Now the folder is locked
    while a command writes: a second one is refused naming the first, and the output is the first's."""
    args = WRITERS[writer].format(w=work, out=work / "out").split()
    assert run(args, capsys)[0] == 0
    before = snapshot(work / "out")
    with folder_lock(work / "out", writer):
        rc, err = run(args, capsys)
        assert rc == 1
        one_line(err, args[0], f"{work / 'out'}: output folder is being written by facetsynth {writer} "
                               f"(process {os.getpid()})")
        assert snapshot(work / "out") == before | {work / "out" / LOCK: (work / "out" / LOCK).read_bytes()}
    assert run(args, capsys)[0] == 0 and not (work / "out" / LOCK).exists()


HOLDER = """
import sys, time
from pathlib import Path
from facetsynth.io.outputs import folder_lock
with folder_lock(Path(sys.argv[1]), "predict"):
    print("locked", flush=True)
    time.sleep(600)
"""


@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM])
def test_another_process_holds_the_lock_until_it_dies_then_it_is_taken_over(work, capsys, signum):
    """A live writer in another process is named; once it is killed its lock file stays behind (SIGKILL
    runs no cleanup) but holds nothing: the next predict takes it over."""
    args = ["predict", work / "svbrdf", work / "capture", work / "out"]
    assert run(args, capsys)[0] == 0
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(work / "out")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        rc, err = run(args, capsys)
        assert rc == 1
        one_line(err, "predict", f"is being written by facetsynth predict (process {holder.pid})")
    finally:
        holder.send_signal(signum)
        holder.wait(timeout=30)
    if signum == signal.SIGKILL:
        assert (work / "out" / LOCK).exists()                 # stale: its pid is gone
    assert run(args, capsys)[0] == 0
    assert not (work / "out" / LOCK).exists() and (work / "out" / MARKER).exists()


# --- item 10: one line instead of a traceback --------------------------------------------------------

@pytest.mark.parametrize("argv, writer", [
    ("predict {w}/svbrdf {w}/capture {out}", "facetsynth.app.predict.write_exr"),
    ("export mitsuba {w}/svbrdf {out}", "facetsynth.export.mitsuba._write_text"),
    ("export gltf {w}/svbrdf {out}", "facetsynth.export.gltf._write_png"),
    ("stencil-edit {w}/params.json --out {out}", "facetsynth.io.fileio.atomic_path"),
])
def test_ctrl_c_exits_130_in_one_line_and_leaves_no_partial_folder(work, capsys, monkeypatch, argv, writer):
    args = argv.format(w=work, out=work / "out").split()
    fail_on_call(monkeypatch, writer, 2, KeyboardInterrupt())
    rc, err = run(args, capsys)
    assert rc == 130
    assert err.splitlines()[-1] == f"facetsynth {args[0]}: interrupted; no partial output left"
    assert "Traceback" not in err
    assert not (work / "out").exists() and not leftovers(work)
    monkeypatch.undo()
    assert run(args, capsys)[0] == 0                         # an old output: an interrupted rerun keeps it
    before = snapshot(work / "out")
    fail_on_call(monkeypatch, writer, 2, KeyboardInterrupt())
    assert run(args, capsys)[0] == 130
    assert snapshot(work / "out") == before


def test_a_real_sigint_stops_predict_cleanly(work):
    """The installed command, interrupted by SIGINT while writing frames (supersample 16: about 0.3 s a
    frame): exit 130, one line, no output folder, no staging folder. The command starts with SIGINT's default
    action, as from a terminal: a suite started in the background (`cmd &`) ignores SIGINT, its children inherit
    that, and Python then installs no KeyboardInterrupt (predict ran to its end and the test failed)."""
    out = work / "out"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)   # a handler: exec resets it to default
    try:
        proc = subprocess.Popen([str(EXE), "predict", str(work / "svbrdf"), str(work / "capture"), str(out),
                                 "--supersample", "16"], stderr=subprocess.PIPE, text=True)
    finally:
        signal.signal(signal.SIGINT, previous)
    deadline = time.monotonic() + 60
    while not list(out.glob(f"{STAGING}*/frames/*.exr")) and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "facetsynth predict: interrupted; no partial " \
                                                                       "output left"
    assert not out.exists()


@pytest.mark.parametrize("argv", [
    "stencil-edit {w}/params.json --json",
    "stencil-fit {w}/t.bin --json",
    "inspect {w}/results",
    "render {w}/svbrdf --size 16 -o {w}/p.png",
])
def test_a_closed_pipe_ends_quietly(work, argv):
    """Reproduced: `stencil-fit --json | (exit)` ended in a BrokenPipeError traceback. Now the command ends
    quietly, as Unix tools do: exit 141 (128 + SIGPIPE), nothing on stderr."""
    from facetsynth.stencil import readers
    from facetsynth.stencil.model import evaluate_utia
    readers.write_utia_bin(work / "t.bin", evaluate_utia(synth((20,))))
    (work / "results" / "hdr").mkdir(parents=True)
    (work / "results" / "hdr" / "metrics.json").write_text('{"frames": 3}')
    read, write = os.pipe()
    os.close(read)                                            # the reader is gone before anything is written
    try:
        done = subprocess.run([str(EXE), *argv.format(w=work).split()], stdout=write, stderr=subprocess.PIPE,
                              text=True, timeout=120)
    finally:
        os.close(write)
    assert (done.returncode, done.stderr) == (141, "")


@pytest.mark.parametrize("value", ["5000", "-5000", "1e308", "65", "-64.5"])
def test_render_exposure_outside_float_range_is_an_argument_error(work, capsys, value):
    """Reproduced: `render --exposure 5000` ended in an OverflowError traceback (2^5000)."""
    rc, err = run(["render", work / "svbrdf", "--size", "32", "--exposure", value, "-o", work / "p.png"], capsys)
    assert rc == 2
    one_line(err, "render", "argument --exposure: must be from -64 to 64 EV")
    assert not (work / "p.png").exists()
    with pytest.raises(ValueError, match="--exposure must be from -64 to 64 EV"):
        PreviewSettings(exposure_ev=float(value))


@pytest.mark.parametrize("argv, problem", [
    (["--intensity", "-1"], "--intensity must be above 0"),
    (["--intensity", "0"], "--intensity must be above 0"),
    (["--intensity", "1e300"], "at most 1e+12 W/sr"),
    (["--intensity", "1e38"], "at most 1e+12 W/sr"),
])
def test_render_refuses_intensities_that_give_no_picture(work, capsys, argv, problem):
    """A negative or zero intensity rendered a black picture, exit 0; 1e300 an Inf one."""
    rc, err = run(["render", work / "svbrdf", "--size", "32", *argv, "-o", work / "p.png"], capsys)
    assert rc in (1, 2)
    one_line(err, "render", problem)
    assert not (work / "p.png").exists()


@pytest.mark.parametrize("width, height, supersample", [(50000, 33333, 1), (20000, 20000, 1), (3000, 2000, 16)])
def test_predict_refuses_a_camera_too_large_for_memory_before_allocating(work, capsys, monkeypatch, width, height,
                                                                         supersample):
    """Reproduced: a 50000 x 33333 camera made predict allocate 12 GiB before it failed. Now refused first
    (the pixel grid is never built), naming the manifest, the size and the limit."""
    m = json.loads((work / "capture" / "manifest.json").read_text())
    m["camera"].update(width=width, height=height)
    (work / "capture" / "manifest.json").write_text(json.dumps(m))
    monkeypatch.setattr("facetsynth.geometry.camera.Camera.pixel_plane_points", lambda *a: pytest.fail("allocated"))
    manifest = work / "capture" / "manifest.json"
    rc, err = run(["predict", work / "svbrdf", manifest, work / "out", "--supersample", supersample], capsys)
    assert rc == 1
    one_line(err, "predict", f"{manifest}: a {width}x{height} camera at supersample {supersample} needs about", "GiB to render, above the limit of 16 GiB",
             "FACETSYNTH_MEMORY_LIMIT_GIB")
    assert not (work / "out").exists()


def test_the_memory_limit_is_set_by_the_environment(work, capsys, monkeypatch):
    monkeypatch.setenv("FACETSYNTH_MEMORY_LIMIT_GIB", "0.01")      # 10 MiB: the 120 x 80 camera at 16^2 is not
    rc, err = run(["predict", work / "svbrdf", work / "capture", work / "out", "--supersample", "16"], capsys)
    assert rc == 1 and "above the limit of 0.01 GiB" in one_line(err, "predict")
    rc, err = run(["render", work / "svbrdf", "--size", "512", "-o", work / "p.png"], capsys)
    assert rc == 1 and "--size 512: a 512x512 camera at supersample 2" in one_line(err, "render")
    for bad in ("lots", "-1", "nan"):
        monkeypatch.setenv("FACETSYNTH_MEMORY_LIMIT_GIB", bad)
        rc, err = run(["predict", work / "svbrdf", work / "capture", work / "out"], capsys)
        assert rc == 1 and "FACETSYNTH_MEMORY_LIMIT_GIB must be a positive number of GiB" in one_line(err, "predict")
    assert not (work / "out").exists()


@pytest.mark.parametrize("stage, metrics, text", [
    ("hdr", '{"frames": NaN, "saturated_pixels": 3}', "'frames': expected an integer, found nan"),
    ("hdr", '{"frames": 30, "saturated_pixels": Infinity}', "'saturated_pixels': expected an integer, found inf"),
    ("cluster", '{"representatives": 2.5}', "'representatives': expected an integer, found 2.5"),
    ("separate", '{"points_without_diffuse_estimate": NaN}', "'points_without_diffuse_estimate': expected an "
                                                             "integer"),
    ("rectify", '{"cols": 4, "rows": 4, "registration_error_px": "small"}', "unexpected content (ValueError"),
    ("selfcheck", '{"relit": {"rel_l2": [1], "specular_rel_l2": 0.1, "frame_psnr_worst_db": 30}}',
     "unexpected content (TypeError"),
])
def test_inspect_names_a_metrics_value_of_the_wrong_kind(tmp_path, capsys, stage, metrics, text):
    """Reproduced: NaN in an integer field of a metrics file ended `inspect` in a traceback."""
    (tmp_path / stage).mkdir()
    (tmp_path / stage / "metrics.json").write_text(metrics)
    rc, err = run(["inspect", tmp_path], capsys)
    assert rc == 1
    one_line(err, "inspect", f"{tmp_path / stage / 'metrics.json'}: {text}")


def test_inspect_still_shows_an_integral_float_and_a_nan_ratio(tmp_path, capsys):
    (tmp_path / "hdr").mkdir()
    (tmp_path / "hdr" / "metrics.json").write_text('{"frames": 30.0, "median_rel_error": NaN}')
    assert main(["inspect", str(tmp_path)]) == 0
    assert "frames 30, vs truth nan" in capsys.readouterr().out

