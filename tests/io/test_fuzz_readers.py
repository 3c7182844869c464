"""Issue 15, part 8: fuzzing the readers of user files.

Mutated capture manifests go to :func:`facetsynth.capture.manifest.load`; arbitrary and mutated bytes go to the
EXR reader (:func:`facetsynth.io.fileio.read_frame`) and to the measured-BRDF readers
(:mod:`facetsynth.stencil.readers`). Each either reads or raises :class:`facetsynth.io.errors.InputError`,
never another exception, and never hangs: every example runs under a wall-clock alarm
(:data:`HANG_SECONDS`) as well as hypothesis' deadline. Examples are few (``max_examples``) so that the
file runs in about 20 s; hypothesis keeps the failures it finds in its database and replays them first.
"""

import contextlib
import copy
import json
import math
import signal
import struct
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facetsynth.capture import manifest
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import read_frame, write_exr
from facetsynth.stencil import grid, readers

from conftest import RGL_FILES

HANG_SECONDS = 10
"""Wall-clock limit of one example: far above the slowest reader's legitimate time (about 0.3 s)."""

FUZZ = settings(max_examples=200, deadline=timedelta(seconds=5),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@contextlib.contextmanager
def no_hang(seconds=HANG_SECONDS):
    """Fail (TimeoutError) instead of hanging when the body runs longer than ``seconds``."""
    def alarm(signum, frame):
        raise TimeoutError(f"reader still running after {seconds} s: a hang")
    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def reads_or_input_error(reader, *args):
    """Call the reader: it returns, or raises InputError (which must name a problem); nothing else."""
    with no_hang():
        try:
            reader(*args)
        except InputError as exc:
            assert exc.problem and "\n" not in exc.problem.strip(), exc


# --- manifests -------------------------------------------------------------------------------------------

GOOD = {
    "version": 1, "units": "m", "sample": {"width": 0.1, "height": 0.1},
    "camera": {"width": 4, "height": 3, "K": [[100, 0, 1.5], [0, 100, 1], [0, 0, 1]],
               "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "t": [0, 0, 1], "distortion": [0, 0, 0, 0, 0]},
    "saturation": 1.0, "noise": {"read_sigma": 0.001, "shot_gain": 0.0001},
    "frames": [{"light": {"position": [0, 0.1, 0.04], "intensity": [1, 1, 1]},
                "exposures": [{"file": "frames/0000_e0.exr", "time": 0.25}, {"file": "frames/0000_e1.exr", "time": 1}],
                "truth": {"radiance": "truth/0000.exr"}}],
    "truth": {"scene": "truth/scene.yaml"},
}


def _paths(value, prefix=()):
    """Every JSON path in ``value`` (the root excluded)."""
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in items:
        yield (*prefix, key)
        yield from _paths(child, (*prefix, key))


PATHS = list(_paths(GOOD))
DELETE = object()
HOSTILE = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, -1e-300, 1e308, -1e308, 10 ** 400, -10 ** 400,
                     "", "NaN", "1.0", "\x00", "x" * 5000, None, True, False, [], {}, [None] * 3, [[]] * 3]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-10 ** 30, max_value=10 ** 30),
    st.text(max_size=30),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.lists(st.lists(st.floats(width=32), min_size=3, max_size=3), min_size=3, max_size=3),
)


def _mutate(document, path, value):
    """Set (or with DELETE remove) the value at ``path``; a path that no longer exists is skipped."""
    parent = document
    for key in path[:-1]:
        try:
            parent = parent[key]
        except (KeyError, IndexError, TypeError):
            return
    key = path[-1]
    exists = (isinstance(parent, dict) and isinstance(key, str)) or \
        (isinstance(parent, list) and isinstance(key, int) and key < len(parent))
    if exists and value is DELETE:
        parent.pop(key, None) if isinstance(parent, dict) else parent.pop(key)
    elif exists:
        parent[key] = copy.deepcopy(value)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """A folder with the GOOD manifest's frame files (4x3)."""
    folder = tmp_path_factory.mktemp("fuzz-capture")
    for name in ("frames/0000_e0.exr", "frames/0000_e1.exr", "truth/0000.exr"):
        write_exr(folder / name, {"RGB": np.full((3, 4, 3), 0.2)})
    return folder


def test_good_manifest_loads(capture_dir):
    (capture_dir / "manifest.json").write_text(json.dumps(GOOD))
    manifest.load(capture_dir)


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(PATHS), st.one_of(st.just(DELETE), HOSTILE)), min_size=1, max_size=3))
def test_mutated_manifest_loads_or_raises_input_error(capture_dir, mutations):
    document = copy.deepcopy(GOOD)
    for path, value in mutations:
        _mutate(document, path, value)
    (capture_dir / "manifest.json").write_text(json.dumps(document))   # NaN, Infinity written as literals
    reads_or_input_error(manifest.load, capture_dir)


@FUZZ
@given(st.data())
def test_manifest_text_with_damaged_bytes_loads_or_raises_input_error(capture_dir, data):
    text = bytearray(json.dumps(GOOD).encode())
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(text)))
        cut = data.draw(st.integers(0, 8))
        text[at:at + cut] = data.draw(st.binary(max_size=8))
    (capture_dir / "manifest.json").write_bytes(bytes(text))
    reads_or_input_error(manifest.load, capture_dir)


def test_deeply_nested_manifest_is_an_input_error(capture_dir):
    (capture_dir / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    reads_or_input_error(manifest.load, capture_dir)


# --- EXR --------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def exr_file(tmp_path_factory):
    """A valid small EXR frame (R, G, B and ``saturated``)."""
    path = tmp_path_factory.mktemp("exr") / "frame.exr"
    write_exr(path, {"RGB": np.random.default_rng(0).uniform(0, 1, (3, 4, 3)),
                     "saturated": np.zeros((3, 4))})
    return path


def _damaged(data, original):
    """``original`` with a few byte ranges overwritten, or truncated, as hypothesis draws."""
    raw = bytearray(original)
    for _ in range(data.draw(st.integers(1, 3))):
        at = data.draw(st.integers(0, len(raw)))
        raw[at:at + data.draw(st.integers(0, 8))] = data.draw(st.binary(max_size=8))
    if data.draw(st.booleans()):
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    return bytes(raw)


@FUZZ
@given(st.binary(max_size=2048))
def test_exr_reader_on_arbitrary_bytes(tmp_path, raw):
    path = tmp_path / "frame.exr"
    path.write_bytes(raw)
    reads_or_input_error(read_frame, path)


@FUZZ
@given(st.data())
def test_exr_reader_on_damaged_exr(tmp_path, exr_file, data):
    path = tmp_path / "frame.exr"
    path.write_bytes(_damaged(data, exr_file.read_bytes()))
    reads_or_input_error(read_frame, path)
    reads_or_input_error(read_frame, path, False)


# --- measured BRDFs ---------------------------------------------------------------------------------------

BRDF_READERS = {".bin": readers.read_utia_bin, ".exr": readers.read_utia_exr, ".bsdf": readers.read_rgl,
                ".binary": readers.read_merl_table}


@FUZZ
@given(suffix=st.sampled_from(sorted(BRDF_READERS)), raw=st.binary(max_size=1024))
def test_brdf_readers_on_arbitrary_bytes(tmp_path, suffix, raw):
    path = tmp_path / f"brdf{suffix}"
    path.write_bytes(raw)
    reads_or_input_error(BRDF_READERS[suffix], path)
    reads_or_input_error(readers.read_brdf, path)


@FUZZ
@given(suffix=st.sampled_from([".bsdf", ".binary"]), raw=st.binary(max_size=512))
def test_brdf_readers_on_bytes_behind_a_valid_header(tmp_path, suffix, raw):
    """Past the magic number (RGL) or the dimensions (MERL), the parser meets arbitrary bytes."""
    head = readers._MAGIC + struct.pack("<BB", 1, 0) if suffix == ".bsdf" else struct.pack("<3i", 90, 90, 180)
    path = tmp_path / f"brdf{suffix}"
    path.write_bytes(head + raw)
    reads_or_input_error(BRDF_READERS[suffix], path)


FLOAT64_PATTERNS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([-1.0, -1e300, 1e300]))


@FUZZ
@given(st.lists(st.tuples(st.integers(0, int(np.prod(grid.SHAPE)) - 1), FLOAT64_PATTERNS), max_size=8))
def test_utia_bin_with_hostile_values(tmp_path, values):
    brdf = np.full(grid.SHAPE, 0.5)
    for index, value in values:
        brdf.flat[index] = value
    path = tmp_path / "brdf.bin"
    readers.write_utia_bin(path, brdf)
    reads_or_input_error(readers.read_utia_bin, path)


@pytest.fixture(scope="module")
def utia_exr_file(tmp_path_factory):
    """A valid UTIA .exr (288x288)."""
    path = tmp_path_factory.mktemp("utia") / "brdf.exr"
    readers.write_utia_exr(path, np.full(grid.SHAPE, 0.5))
    return path


@FUZZ
@given(st.data())
def test_utia_exr_damaged(tmp_path, utia_exr_file, data):
    path = tmp_path / "brdf.exr"
    path.write_bytes(_damaged(data, utia_exr_file.read_bytes()))
    reads_or_input_error(readers.read_utia_exr, path)


RGL_SMALLEST = min(RGL_FILES, key=lambda p: p.stat().st_size)


@settings(FUZZ, max_examples=40)
@given(st.data())
def test_rgl_damaged(tmp_path, data):
    """Damage anywhere, and mostly in the header (its first 400 bytes: names, dtypes, shapes, offsets)."""
    raw = bytearray(RGL_SMALLEST.read_bytes())
    for _ in range(data.draw(st.integers(1, 3))):
        at = data.draw(st.one_of(st.integers(12, 400), st.integers(0, len(raw) - 1)))
        chunk = data.draw(st.binary(min_size=1, max_size=8))
        raw[at:at + len(chunk)] = chunk
    path = tmp_path / "brdf.bsdf"
    path.write_bytes(bytes(raw))
    reads_or_input_error(readers.read_rgl, path)


SHAPES = st.lists(st.integers(0, 5), min_size=0, max_size=5).map(tuple)


FIELD = st.tuples(SHAPES, st.sampled_from(["<f4", "<f8", "u1", "<i4", "<f2"]), FLOAT64_PATTERNS)


@settings(FUZZ, max_examples=100)
@given(st.fixed_dictionaries({name: FIELD for name in readers.RGLBRDF.REQUIRED},
                             optional={"description": FIELD, "other": FIELD}))
def test_rgl_tensor_file_with_hostile_fields(tmp_path, fields):
    """A well-formed tensor_file with every field RGL needs, each of any shape, dtype and value."""
    arrays = {}
    for name, (shape, dtype, value) in fields.items():
        with np.errstate(all="ignore"):
            arrays[name] = np.full(shape, value).astype(dtype)
    path = tmp_path / "brdf.bsdf"
    readers.write_tensor_file(path, arrays)
    reads_or_input_error(readers.read_rgl, path)


@st.composite
def rgl_fields(draw):
    """RGL fields of consistent ranks and leading sizes (past the shape check), of any sizes and values."""
    size = st.sampled_from([0, 1, 2, 3, 3, 4])          # 2..4 can read; 0 and 1 are refused
    nphi, nth = draw(size), draw(size)
    value = draw(st.one_of(FLOAT64_PATTERNS, st.just(0.5)))
    ramp = draw(st.booleans())        # varying values, so that the warp's tables are not all equal

    def field(*shape):
        if ramp:
            return np.arange(1, np.prod(shape) + 1, dtype=np.float32).reshape(shape)
        with np.errstate(over="ignore"):   # a float64 pattern beyond float32's range is stored as inf, on purpose
            return np.full(shape, value, dtype=np.float32)
    return {"theta_i": np.linspace(0, 1.5, nth, dtype=np.float32), "phi_i": np.linspace(0, 6.28, nphi, dtype=np.float32),
            "ndf": field(draw(size), draw(size)), "sigma": field(draw(size), draw(size)),
            "vndf": field(nphi, nth, draw(size), draw(size)), "rgb": field(nphi, nth, 3, draw(size), draw(size)),
            "jacobian": np.full(draw(st.integers(0, 2)), draw(st.integers(0, 1)), dtype=np.uint8)}


@settings(FUZZ, max_examples=100)
@given(rgl_fields())
def test_rgl_tensor_file_with_consistent_but_hostile_tables(tmp_path, fields):
    path = tmp_path / "brdf.bsdf"
    readers.write_tensor_file(path, fields)
    reads_or_input_error(readers.read_rgl, path)


@pytest.fixture(scope="module")
def merl_path(tmp_path_factory):
    """A valid MERL .binary (35 MB), written once."""
    path = tmp_path_factory.mktemp("merl") / "brdf.binary"
    readers.write_merl_table(path, np.full((3, 90, 90, 180), 0.5))
    return path


@settings(FUZZ, max_examples=8)
@given(st.lists(st.tuples(st.integers(0, 3 * 90 * 90 * 180 - 1), FLOAT64_PATTERNS), max_size=8))
def test_merl_with_hostile_values(merl_path, values):
    with open(merl_path, "r+b") as f:
        for index, value in values:
            f.seek(12 + 8 * index)
            f.write(struct.pack("<d", value))
    try:
        reads_or_input_error(readers.read_merl_table, merl_path)
    finally:
        with open(merl_path, "r+b") as f:
            for index, _ in values:
                f.seek(12 + 8 * index)
                f.write(struct.pack("<d", 0.5 * 1500))


def test_a_long_bad_axis_is_named_on_one_line():
    """Found by the fuzzer (test_rgl_damaged, 2026-12-02): eight denormal angles printed by numpy wrapped onto
    a second line of the error message."""
    values = np.array([4.0371e-40, 4.15e-34, 0.0, 3.5873e-43, 0.0, 2.8699e-42, 0.0, 1.1479e-41])
    with pytest.raises(InputError) as caught:
        readers._check_axis("brdf.bsdf", "theta_i", values, 0.0, np.pi / 2)
    assert "\n" not in caught.value.problem and "theta_i" in caught.value.problem
