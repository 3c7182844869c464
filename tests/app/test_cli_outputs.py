"""Issue 15, parts 4 and 7: a `facetsynth` writer never overwrites an input, and no bad argument or file
ends in a traceback (each is a one-line error naming the file or the argument)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facetsynth.app import cli
from facetsynth.io.outputs import MARKER
from facetsynth.stencil import readers
from facetsynth.stencil.model import Mode, StencilModel, evaluate_utia
from facetsynth.stencil.export import model_to_json
from test_predict import captured  # noqa: F401  (the module-scoped capture + SVBRDF fixture)

from conftest import RGL_DIR


def synth(phis_deg):
    """A stencil model with one mode per axis (as tests/stencil/test_stencil_model_fit.synth)."""
    cols = [(0.2, 0.3, 0.9), (0.9, 0.2, 0.1)]
    modes = tuple(Mode(np.deg2rad(p), 0.7, 0.4, 0.04, 0.05, 1.0, 6.0, c) for p, c in zip(phis_deg, cols))
    return StencilModel(modes, (0.0,) * (len(modes) - 1), 0.05, modes[-1].m, 4.0, 60.0, 0.4, 0.04)


def run(argv, capsys):
    """``facetsynth ARGV`` in-process: (exit code, stderr); argparse errors exit 2."""
    try:
        rc = cli.main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def snapshot(*folders):
    """{path: bytes} of every file under ``folders`` (None for a folder, so a new empty one shows too)."""
    return {p: p.read_bytes() if p.is_file() else None for folder in folders for p in sorted(Path(folder).rglob("*"))}


def error_line(err, command):
    """The one error line of a failed command (argparse prints its usage first; it reports an unknown option
    as the top-level parser, ``facetsynth: error:``)."""
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert lines and lines[-1].startswith((f"facetsynth {command}: error: ", "facetsynth: error: ")), err
    return lines[-1]


@pytest.fixture
def heldout(captured, tmp_path):  # noqa: F811
    """A private copy of the capture and its model: (model folder, capture folder)."""
    shutil.copytree(captured / "capture", tmp_path / "heldout")
    shutil.copytree(captured / "svbrdf", tmp_path / "svbrdf")
    return tmp_path / "svbrdf", tmp_path / "heldout"


# --- part 4: outputs never overwrite inputs ----------------------------------------------------------

@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("where, how", [
    ("heldout", "is"),                     # the issue: OUT = the held-out capture's own folder
    ("heldout/frames", "lies inside"),
    ("heldout/predicted", "lies inside"),
    (".", "contains"),
    ("svbrdf", "is"),
    ("svbrdf/predicted", "lies inside"),
])
def test_predict_never_writes_into_its_inputs(heldout, tmp_path, capsys, where, how, force):
    """Reproduced: `predict MODEL HELDOUT HELDOUT` overwrote the measured manifest, exit 0. Now refused, even
    with --force, and every input byte is unchanged."""
    model, capture = heldout
    before = snapshot(tmp_path)
    out = tmp_path / where
    rc, err = run(["predict", model, capture, out] + (["--force"] if force else []), capsys)
    line = error_line(err, "predict")
    assert rc == 1 and err.count("\n") == 1
    assert f"{out}: output folder {how} the input folder" in line
    assert snapshot(tmp_path) == before                     # not one byte written, changed or added


def test_predict_never_writes_into_a_frame_folder_outside_the_capture(heldout, tmp_path, capsys):
    """A manifest may list frames in another folder: that folder is an input too."""
    model, capture = heldout
    m = json.loads((capture / "manifest.json").read_text())
    shutil.move(capture / "frames", tmp_path / "raw")
    for frame in m["frames"]:
        for e in frame["exposures"]:
            e["file"] = str(tmp_path / "raw" / Path(e["file"]).name)
    (capture / "manifest.json").write_text(json.dumps(m))
    before = snapshot(tmp_path)
    rc, err = run(["predict", model, capture, tmp_path / "raw"], capsys)
    assert rc == 1 and "output folder is the input folder" in error_line(err, "predict")
    assert snapshot(tmp_path) == before


def test_a_non_empty_folder_is_written_only_with_force_or_when_the_command_made_it(heldout, tmp_path, capsys):
    model, capture = heldout
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes")
    rc, err = run(["predict", model, capture, mine], capsys)
    line = error_line(err, "predict")
    assert rc == 1 and f"{mine}: output folder is not empty and was not made by facetsynth predict" in line
    assert "--force" in line and sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    assert run(["predict", model, capture, mine, "--force"], capsys)[0] == 0
    assert (mine / "notes.txt").read_text() == "my notes" and not (mine / MARKER).exists()  # not claimed
    assert len(list((mine / "frames").glob("*.exr"))) == 30
    # a folder predict made carries its marker: a rerun needs no --force
    assert run(["predict", model, capture, tmp_path / "pred"], capsys)[0] == 0
    assert json.loads((tmp_path / "pred" / MARKER).read_text()) == {"written_by": "facetsynth predict"}
    assert run(["predict", model, capture, tmp_path / "pred"], capsys)[0] == 0
    # ... but another command may not write into it
    params = tmp_path / "stencil.json"
    params.write_text(json.dumps(model_to_json(synth((20,)))))
    rc, err = run(["stencil-edit", params, "--out", tmp_path / "pred"], capsys)
    assert rc == 1 and "not made by facetsynth stencil-edit" in error_line(err, "stencil-edit")


def test_stencil_writers_refuse_to_replace_their_input(tmp_path, capsys):
    """`stencil-edit fit/stencil.json --out fit` would replace its own input: refused even with --force."""
    bin_path = tmp_path / "two-thread.bin"
    readers.write_utia_bin(bin_path, evaluate_utia(synth((20, 110))))
    fit = tmp_path / "fit"
    assert run(["stencil-fit", bin_path, "--out", fit], capsys)[0] == 0
    assert run(["stencil-fit", bin_path, "--out", fit], capsys)[0] == 0      # its own folder: rerun is fine
    before = snapshot(tmp_path)
    for extra in ([], ["--force"]):
        rc, err = run(["stencil-edit", fit / "stencil.json", "--shift-phi", "0", "30", "--out", fit] + extra, capsys)
        assert rc == 1 and "would replace the input file" in error_line(err, "stencil-edit")
    assert snapshot(tmp_path) == before
    # a BRDF file's folder is not empty: --force may add outputs beside it (nothing there is replaced)
    rc, err = run(["stencil-fit", bin_path, "--out", tmp_path], capsys)
    assert rc == 1 and "not empty" in error_line(err, "stencil-fit")
    assert run(["stencil-fit", bin_path, "--out", tmp_path, "--force"], capsys)[0] == 0
    assert bin_path.read_bytes() == before[bin_path] and (tmp_path / "stencil.json").is_file()


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")   # the NaN light, bypassed
def test_predict_never_writes_a_non_finite_pixel(heldout, tmp_path, capsys, monkeypatch):
    """Reproduced: a NaN light wrote 73 % NaN pixels, exit 0. The manifest check now refuses the NaN, and
    predict's own last guard refuses any non-finite frame even were that check bypassed."""
    model, capture = heldout
    m = json.loads((capture / "manifest.json").read_text())
    m["frames"][3]["light"]["position"][0] = float("nan")
    (capture / "nan-light.json").write_text(json.dumps(m))
    rc, err = run(["predict", model, capture / "nan-light.json", tmp_path / "out"], capsys)
    line = error_line(err, "predict")
    assert rc == 1 and "nan-light.json" in line and "frames/3/light/position" in line
    assert not (tmp_path / "out").exists()
    # bypass the manifest's check: the frame guard still refuses, and no non-finite pixel reaches a file
    monkeypatch.setattr("facetsynth.capture.manifest.validate", lambda manifest, path=None: None)
    rc, err = run(["predict", model, capture / "nan-light.json", tmp_path / "out"], capsys)
    line = error_line(err, "predict")
    assert rc == 1 and "nan-light.json: frame 3:" in line and "NaN or Inf" in line and "not written" in line
    assert not (tmp_path / "out").exists()      # issue 32: a failed run leaves nothing, not three frames


@pytest.mark.parametrize("value, problem", [("0", "from 1 to 16, got 0"), ("-2", "from 1 to 16, got -2"),
                                            ("1.5", "not an integer"), ("1000", "got 1000")])
def test_predict_supersample_must_be_a_small_positive_integer(heldout, tmp_path, capsys, value, problem):
    """Reproduced: --supersample 0 wrote NaN frames, exit 0; -2 ended in a traceback."""
    model, capture = heldout
    rc, err = run(["predict", model, capture, tmp_path / "out", "--supersample", value], capsys)
    line = error_line(err, "predict")
    assert rc == 2 and "argument --supersample:" in line and problem in line
    assert not (tmp_path / "out").exists()


# --- part 7: every argument and file validated (table) -----------------------------------------------

@pytest.fixture(scope="module")
def bad(tmp_path_factory):
    """Bad (and good) input files for the table below, made once."""
    d = tmp_path_factory.mktemp("bad")
    good = model_to_json(synth((20, 110)))
    (d / "params.json").write_text(json.dumps(good))
    (d / "syntax.json").write_text('{"modes": [')
    (d / "list.json").write_text("[1, 2]")

    def params(name, edit):
        p = json.loads(json.dumps(good))
        edit(p)
        (d / f"{name}.json").write_text(json.dumps(p))

    params("no-beta", lambda p: p.pop("beta"))
    params("modes-str", lambda p: p.update(modes="two"))
    params("w-str", lambda p: p["modes"][1].update(w="wide"))
    params("w-big", lambda p: p["modes"][0].update(w=1.5))
    params("m-short", lambda p: p["modes"][0].update(m=[1, 2]))
    params("k-nan", lambda p: p.update(k=float("nan")))
    params("no-alpha", lambda p: p["modes"][0].pop("alpha"))
    params("mode-list", lambda p: p["modes"].__setitem__(0, [1, 2, 3]))
    params("beta-long", lambda p: p.update(beta=[0.0, 0.5]))
    params("k-huge", lambda p: p.update(k=10 ** 400))
    params("retro-str", lambda p: p["modes"][0].update(retro="yes"))
    (d / "list-model").mkdir()
    (d / "list-model" / "model.json").write_text("[1]")
    (d / "afile").write_text("a file, not a folder")
    (d / "adir.bin").mkdir()
    (d / "empty").mkdir()
    rgl = readers.read_tensor_file(RGL_DIR / "paper_white_rgb.bsdf")
    for name, field, value in [("rgb-nan", "rgb", np.nan), ("rgb-neg", "rgb", None), ("vndf-neg", "vndf", None),
                               ("vndf-zero", "vndf", 0.0), ("theta-nan", "theta_i", np.nan),
                               ("sigma-zero", "sigma", 0.0), ("ndf-inf", "ndf", np.inf)]:
        f = dict(rgl)
        f[field] = (-np.abs(rgl[field]) - 0.1 if value is None else np.full_like(rgl[field], value))
        readers.write_tensor_file(d / f"{name}.bsdf", f)
    f = dict(rgl)
    f["rgb"] = rgl["rgb"].copy()
    f["rgb"][0, 2, 1, 5:9, 5:9] = np.nan                               # a few NaN among good values
    readers.write_tensor_file(d / "rgb-some-nan.bsdf", f)
    f = dict(rgl)
    f["rgb"] = -rgl["rgb"]                                              # sign error: no positive value
    readers.write_tensor_file(d / "rgb-flipped.bsdf", f)
    f = dict(rgl)
    f["rgb"] = rgl["rgb"] - 0.5 * rgl["rgb"].max()                      # wrong offset: far beyond noise
    readers.write_tensor_file(d / "rgb-offset.bsdf", f)
    b = evaluate_utia(synth((20,)))
    readers.write_utia_bin(d / "nan.bin", np.where(np.arange(b.size).reshape(b.shape) % 97 == 0, np.nan, b))
    readers.write_utia_bin(d / "neg.bin", -b)
    readers.write_utia_bin(d / "zero.bin", np.zeros_like(b))
    readers.write_utia_exr(d / "neg.exr", -b)
    (d / "short.bin").write_bytes(b"\0" * 100)
    (d / "notes.txt").write_text("hello")
    readers.write_utia_bin(d / "good.bin", b)
    table = np.full((3, 90, 90, 180), 0.1)
    table[1, 4, 5, 6] = np.nan
    readers.write_merl_table(d / "nan.binary", table)
    readers.write_merl_table(d / "unmeasured.binary", np.full((3, 90, 90, 180), -1.0))
    return d


# (case, argv with {d} the bad-files folder, {model} {capture} the fitted model and capture, expected exit code,
#  text the one error line must hold)
CASES = [
    # stencil-fit: measured BRDF files with bad values are an error naming the field (issue: "perfect fit")
    ("fit RGL rgb all NaN", "stencil-fit {d}/rgb-nan.bsdf", 1, "rgb-nan.bsdf: field 'rgb': 24576 NaN or Inf"),
    ("fit RGL rgb some NaN", "stencil-fit {d}/rgb-some-nan.bsdf", 1, "field 'rgb': 16 NaN or Inf value(s)"),
    ("fit RGL rgb all negative", "stencil-fit {d}/rgb-neg.bsdf", 1, "field 'rgb': 24576 negative value(s)"),
    ("fit RGL rgb sign-flipped", "stencil-fit {d}/rgb-flipped.bsdf", 1, "field 'rgb':"),
    ("fit RGL rgb offset beyond noise", "stencil-fit {d}/rgb-offset.bsdf", 1, "more than measurement noise"),
    ("fit RGL vndf negative", "stencil-fit {d}/vndf-neg.bsdf", 1, "field 'vndf': 131072 negative value(s)"),
    ("fit RGL vndf zero", "stencil-fit {d}/vndf-zero.bsdf", 1, "field 'vndf': 8 slice(s) hold no mass"),
    ("fit RGL theta_i NaN", "stencil-fit {d}/theta-nan.bsdf", 1, "field 'theta_i': 8 NaN or Inf"),
    ("fit RGL sigma zero", "stencil-fit {d}/sigma-zero.bsdf", 1, "field 'sigma': 256 zero value(s)"),
    ("fit RGL ndf Inf", "stencil-fit {d}/ndf-inf.bsdf", 1, "field 'ndf': 256 NaN or Inf"),
    ("fit UTIA .bin NaN", "stencil-fit {d}/nan.bin", 1, "nan.bin: field 'rgb':"),
    ("fit UTIA .bin negative", "stencil-fit {d}/neg.bin", 1, "neg.bin: field 'rgb':"),
    ("fit UTIA .bin all zero", "stencil-fit {d}/zero.bin", 1, "zero.bin: no reflectance"),
    ("fit UTIA .exr negative", "stencil-fit {d}/neg.exr", 1, "neg.exr: field 'RGB':"),
    ("fit MERL NaN", "stencil-fit {d}/nan.binary", 1, "nan.binary: field 'rgb': 1 NaN or Inf"),
    ("fit MERL all unmeasured", "stencil-fit {d}/unmeasured.binary", 1, "no positive value"),
    ("fit truncated .bin", "stencil-fit {d}/short.bin", 1, "short.bin: wrong size"),
    ("fit unknown suffix", "stencil-fit {d}/notes.txt", 1, "notes.txt: unknown BRDF file type"),
    ("fit missing file", "stencil-fit {d}/missing.bin", 1, "missing.bin: file does not exist"),
    ("fit folder as file", "stencil-fit {d}/adir.bin", 1, "adir.bin: is a folder"),
    ("fit --out is a file", "stencil-fit {d}/good.bin --out {d}/afile", 1, "afile: exists and is a file"),
    ("fit --out under a file", "stencil-fit {d}/good.bin --out {d}/afile/x", 1, "afile is a file"),
    ("fit no file", "stencil-fit", 2, "required: brdf"),
    # stencil-edit: malformed parameter files (issue: tracebacks) and bad edit arguments
    ("edit JSON syntax error", "stencil-edit {d}/syntax.json", 1, "syntax.json: not valid JSON"),
    ("edit JSON list", "stencil-edit {d}/list.json", 1, "list.json: not valid stencil parameters: expected a "
                                                        "JSON object"),
    ("edit missing key", "stencil-edit {d}/no-beta.json", 1, "no-beta.json: not valid stencil parameters: 'beta': "
                                                             "missing"),
    ("edit missing mode key", "stencil-edit {d}/no-alpha.json", 1, "'modes'[0]['alpha']: missing"),
    ("edit modes not a list", "stencil-edit {d}/modes-str.json", 1, "'modes': expected a list"),
    ("edit mode not an object", "stencil-edit {d}/mode-list.json", 1, "'modes'[0]: expected an object"),
    ("edit w a string", "stencil-edit {d}/w-str.json", 1, "'modes'[1]['w']: expected a number"),
    ("edit w out of range", "stencil-edit {d}/w-big.json", 1, "'modes'[0]['w']: 1.5 is outside (0, 1)"),
    ("edit m of 2", "stencil-edit {d}/m-short.json", 1, "'modes'[0]['m']: expected a list of 3"),
    ("edit k NaN", "stencil-edit {d}/k-nan.json", 1, "'k': must be finite"),
    ("edit beta too long", "stencil-edit {d}/beta-long.json", 1, "'beta': expected a list of 1"),
    ("edit k a 400-digit integer", "stencil-edit {d}/k-huge.json", 1, "'k': must be finite"),
    ("edit retro not a boolean", "stencil-edit {d}/retro-str.json", 1, "'modes'[0]['retro']: expected true or"),
    ("edit missing file", "stencil-edit {d}/missing.json", 1, "missing.json: file not found"),
    ("edit folder as file", "stencil-edit {d}/empty", 1, "empty: is a folder"),
    ("edit --width above 1", "stencil-edit {d}/params.json --width 0 1.5", 2, "argument --width: must be between"),
    ("edit --width 0", "stencil-edit {d}/params.json --width 0 0", 2, "argument --width: must be between"),
    ("edit --width NaN", "stencil-edit {d}/params.json --width 0 nan", 2, "argument --width: must be finite"),
    ("edit --width text", "stencil-edit {d}/params.json --width 0 wide", 2, "argument --width: not a number"),
    ("edit --shift-phi Inf", "stencil-edit {d}/params.json --shift-phi 0 inf", 2,
     "argument --shift-phi: must be finite"),
    ("edit --shift-phi NaN", "stencil-edit {d}/params.json --shift-phi 0 nan", 2,
     "argument --shift-phi: must be finite"),
    ("edit mode negative", "stencil-edit {d}/params.json --shift-phi -1 30", 2,
     "argument --shift-phi: mode index must be >= 0"),
    ("edit mode fractional", "stencil-edit {d}/params.json --shift-phi 1.5 30", 2,
     "argument --shift-phi: not an integer"),
    ("edit mode out of range", "stencil-edit {d}/params.json --width 2 0.5", 1,
     "params.json: mode 2 out of range (model has 2 modes)"),
    ("edit swap out of range", "stencil-edit {d}/params.json --swap-colours 0 7", 1, "mode 7 out of range"),
    ("edit swap not an int", "stencil-edit {d}/params.json --swap-colours 0 x", 2,
     "argument --swap-colours: not an integer"),
    ("edit one value only", "stencil-edit {d}/params.json --width 0", 2, "argument --width: expected 2"),
    ("edit --out is a file", "stencil-edit {d}/params.json --out {d}/afile", 1, "afile: exists and is a file"),
    # predict
    ("predict model missing", "predict {d}/nowhere {capture} {d}/o1", 1, "nowhere: not found; expected a fitted "
                                                                          "model folder holding model.json"),
    ("predict model is a file", "predict {d}/afile {capture} {d}/o2", 1, "afile: is a file; expected a fitted"),
    ("predict model lacks model.json", "predict {d}/empty {capture} {d}/o3", 1, "model.json: file not found"),
    ("predict model.json a list", "predict {d}/list-model {capture} {d}/o11", 1,
     "model.json: expected a JSON object, found list"),
    ("predict manifest missing", "predict {model} {d}/nowhere.json {d}/o4", 1, "nowhere.json: file not found"),
    ("predict manifest folder without it", "predict {model} {d}/empty {d}/o5", 1,
     "manifest.json: file not found"),
    ("predict manifest syntax", "predict {model} {d}/syntax.json {d}/o6", 1, "syntax.json: not valid JSON"),
    ("predict OUT is a file", "predict {model} {capture} {d}/afile", 1, "afile: exists and is a file"),
    ("predict OUT under a file", "predict {model} {capture} {d}/afile/sub", 1, "afile is a file"),
    ("predict --supersample 0", "predict {model} {capture} {d}/o7 --supersample 0", 2,
     "argument --supersample: must be an integer from 1 to 16, got 0"),
    ("predict --supersample -2", "predict {model} {capture} {d}/o8 --supersample -2", 2,
     "argument --supersample: must be an integer from 1 to 16, got -2"),
    ("predict --supersample text", "predict {model} {capture} {d}/o9 --supersample two", 2,
     "argument --supersample: not an integer"),
    ("predict missing OUT", "predict {model} {capture}", 2, "required: OUT_DIR"),
    ("predict unknown option", "predict {model} {capture} {d}/o10 --frobnicate", 2, "unrecognized arguments"),
    # check (its own checks are another part of the issue: only that it never ends in a traceback here)
    ("check missing", "check {d}/nowhere", 1, "nowhere"),
    ("check not JSON", "check {d}/afile", 1, "afile"),
]


@pytest.mark.parametrize("case, argv, code, text", CASES, ids=[c[0] for c in CASES])
def test_bad_arguments_and_files_are_one_line_errors(bad, captured, capsys, case, argv, code, text):  # noqa: F811
    args = argv.format(d=bad, model=captured / "svbrdf", capture=captured / "capture").split()
    before = {p for p in bad.rglob("*")}
    rc, err = run(args, capsys)
    line = error_line(err, args[0])
    assert rc == code, err
    assert text in line, line
    if code == 1:
        assert err.count("\n") == 1, err                               # exactly one line
    assert {p for p in bad.rglob("*")} == before                        # a failed command writes nothing


def test_the_installed_command_prints_no_traceback(bad):
    """The console script, as users run it: the one error line and exit codes 1 and 2."""
    exe = Path(sys.executable).with_name("facetsynth")
    for argv, code in ([str(bad / "rgb-neg.bsdf")], 1), ([str(bad / "params.json"), "--width", "0", "nan"], 2):
        cmd = "stencil-fit" if argv[0].endswith(".bsdf") else "stencil-edit"
        done = subprocess.run([str(exe), cmd] + argv, capture_output=True, text=True, timeout=120)
        assert done.returncode == code and "Traceback" not in done.stderr, done.stderr
        assert done.stderr.strip().splitlines()[-1].startswith(f"facetsynth {cmd}: error: ")
