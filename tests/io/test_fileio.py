"""Atomic writes and clear read errors (DESIGN.md sec. 4)."""

import os
import subprocess
import sys

import numpy as np
import pytest

from facetsynth.io.errors import InputError
from facetsynth.io.fileio import atomic_dir, read_exr, read_npy, read_rgb, write_exr, write_json, write_npy


def test_exr_round_trip_keeps_channels_and_header(tmp_path):
    rgb = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    mask = np.eye(5, 7, dtype=np.float32)
    write_exr(tmp_path / "a.exr", {"RGB": rgb, "saturated": mask}, {"exposure_time": 0.25, "units": "W/sr/m2"})
    channels, header = read_exr(tmp_path / "a.exr")
    np.testing.assert_array_equal(channels["RGB"], rgb)
    np.testing.assert_array_equal(channels["saturated"], mask)
    assert header["exposure_time"] == 0.25 and header["units"] == "W/sr/m2"
    write_exr(tmp_path / "b.exr", {"RGB": np.ones((2, 3, 3))})   # another size: fresh header each time
    assert read_rgb(tmp_path / "b.exr").shape == (2, 3, 3)


def test_measured_frames_keep_the_float32_range_to_fifteen_mantissa_bits(tmp_path):
    """precision="float24" (PXR24, the hdr and rectify frames): relative error <= 2^-16 over float32's
    range, where half floats (65504 at most) would overflow a 16-bit camera's radiance."""
    rng = np.random.default_rng(1)
    rgb = (10.0 ** rng.uniform(-30, 30, (16, 16, 3))).astype(np.float32)
    rgb[0, 0] = [0.0, 1.0, 65535.0 / 1e-4]
    mask = (rng.random((16, 16)) > 0.5).astype(np.float32)
    write_exr(tmp_path / "m.exr", {"RGB": rgb, "saturated": mask}, precision="float24")
    channels, _ = read_exr(tmp_path / "m.exr")
    relative = np.abs(channels["RGB"] - rgb) / rgb.clip(np.finfo(np.float32).tiny)
    assert relative.max() <= 2.0**-16 and relative.max() > 0                  # lossy, within its bound
    assert channels["RGB"][0, 0, :2].tolist() == [0.0, 1.0] and np.isfinite(channels["RGB"]).all()
    np.testing.assert_array_equal(channels["saturated"], mask)
    with pytest.raises(KeyError):
        write_exr(tmp_path / "x.exr", {"RGB": rgb}, precision="float8")


def test_truncated_exr_is_an_error_naming_the_file(tmp_path):
    write_exr(tmp_path / "full.exr", {"RGB": np.ones((64, 64, 3))})
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.exr: not a readable OpenEXR image"):
        read_rgb(tmp_path / "cut.exr")


def test_npy_tensors_round_trip_and_bad_ones_name_the_file(tmp_path):
    write_npy(tmp_path / "a.npy", np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(read_npy(tmp_path / "a.npy", mmap_mode="r"), np.arange(6.0).reshape(2, 3))
    with pytest.raises(InputError, match=r"missing\.npy: file not found"):
        read_npy(tmp_path / "missing.npy")
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    with pytest.raises(InputError, match=r"junk\.npy: not a readable \.npy tensor"):
        read_npy(tmp_path / "junk.npy")


def test_nan_pixels_are_an_error_naming_file_and_pixel(tmp_path):
    rgb = np.ones((4, 4, 3), np.float32)
    rgb[2, 3, 1] = np.nan
    write_exr(tmp_path / "nan.exr", {"RGB": rgb})
    with pytest.raises(InputError, match=r"nan\.exr: 1 pixel\(s\) are NaN or Inf \(first at row 2, col 3\)"):
        read_rgb(tmp_path / "nan.exr")


def test_failed_write_leaves_nothing_that_looks_whole(tmp_path):
    with pytest.raises(TypeError):
        write_json(tmp_path / "m.json", {"bad": object()})
    assert list(tmp_path.iterdir()) == []


def test_atomic_dir_publishes_only_when_complete_and_resumes_after_a_crash(tmp_path):
    out = tmp_path / "frames"
    with pytest.raises(RuntimeError):
        with atomic_dir(out, key={"gain": 1}) as staging:
            (staging / "0000.exr").write_text("done")
            raise RuntimeError("crash mid-stage")
    assert not out.exists()
    with atomic_dir(out, key={"gain": 1}) as staging:        # same inputs: resume, nothing lost
        assert (staging / "0000.exr").read_text() == "done"
        (staging / "0001.exr").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["0000.exr", "0001.exr"]
    assert not (tmp_path / ".frames.partial").exists()


def test_atomic_dir_starts_afresh_when_the_inputs_changed(tmp_path):
    out = tmp_path / "frames"
    with pytest.raises(RuntimeError):
        with atomic_dir(out, key={"gain": 1}) as staging:
            (staging / "0000.exr").write_text("stale")
            raise RuntimeError("crash")
    with atomic_dir(out, key={"gain": 2}) as staging:
        assert not (staging / "0000.exr").exists()


def gone_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_a_write_removes_the_temporaries_killed_writers_left_in_its_folder(tmp_path):
    """A killed job's temporaries (.NAME.PID-TID.tmpSUFFIX, of this file or another) go at the first write
    into their folder; a live process's temporary (a concurrent writer's) and other files stay."""
    dead, live = gone_pid(), os.getppid()
    stale = [f".m.json.{dead}-1.tmp", f".specular.npy.{dead}-140213.tmp.npy", f".m.{dead}-2.tmp"]
    kept = [f".m.json.{live}-1.tmp", "m.json.tmp", ".m.json.tmp", "notes.txt"]
    for name in stale + kept:
        (tmp_path / name).write_text("left behind")
    write_json(tmp_path / "m.json", {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept + ["m.json"])


def test_atomic_dir_resumes_without_a_killed_writers_temporaries(tmp_path):
    """A resumed staging folder loses the temporaries of killed writers (at any depth), so the published
    folder never holds one."""
    out, dead = tmp_path / "frames", gone_pid()
    with pytest.raises(RuntimeError):
        with atomic_dir(out, key={"gain": 1}) as staging:
            (staging / "0000.exr").write_text("done")
            (staging / f".0001.exr.{dead}-7.tmp.exr").write_text("half")     # as SIGKILL leaves it
            (staging / "sub").mkdir()
            (staging / f"sub/.a.npy.{dead}-7.tmp.npy").write_text("half")
            raise RuntimeError("killed")
    with atomic_dir(out, key={"gain": 1}) as staging:
        (staging / "0001.exr").write_text("new")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["0000.exr", "0001.exr", "sub"]


def test_atomic_dir_never_publishes_a_folder_with_a_temporary_in_it(tmp_path):
    out = tmp_path / "frames"
    with pytest.raises(RuntimeError, match=r"frames: not published: 1 temporary file\(s\) still in .*\.frames\.part"):
        with atomic_dir(out, key={"gain": 1}) as staging:
            (staging / f".0000.exr.{os.getppid()}-1.tmp.exr").write_text("being written")    # a live writer
    assert not out.exists() and (tmp_path / ".frames.partial").is_dir()


def test_atomic_dir_replaces_a_published_folder_whole(tmp_path):
    """The old folder is moved aside, then deleted; one left aside by a run killed while publishing is
    deleted by the next run."""
    out = tmp_path / "frames"
    with atomic_dir(out) as staging:
        (staging / "old.exr").write_text("old")
    (tmp_path / ".frames.replaced").mkdir()                    # a kill while publishing left it
    with atomic_dir(out) as staging:
        (staging / "new.exr").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]
    assert [p.name for p in out.iterdir()] == ["new.exr"]


def test_npy_writer_writes_np_saves_bytes_and_npy_rows_reads_them(tmp_path):
    """The per-point stages stream their (P, T, F) outputs in row blocks and read their inputs by rows
    (issue 14: peak RSS without the memory maps' pages): the bytes are np.save's, the rows read are the
    array's, and blocks that do not fill the shape are an error."""
    from facetsynth.io.fileio import NpyRows, npy_writer
    a = np.random.default_rng(0).random((10, 4, 6)).astype(np.float32)
    np.save(tmp_path / "saved.npy", a)
    with npy_writer(tmp_path / "streamed.npy", np.float32, a.shape) as write:
        for start in range(0, 10, 3):
            write(a[start:start + 3])
    assert (tmp_path / "streamed.npy").read_bytes() == (tmp_path / "saved.npy").read_bytes()
    rows = NpyRows(tmp_path / "streamed.npy")
    assert len(rows) == 10 and rows.shape == a.shape and rows.dtype == np.float32
    assert np.array_equal(rows[[7, 2, 2]], a[[7, 2, 2]]) and np.array_equal(rows[3], a[3])
    with pytest.raises(ValueError, match="9 rows written of 10"):
        with npy_writer(tmp_path / "short.npy", np.float32, a.shape) as write:
            write(a[:9])
    assert not (tmp_path / "short.npy").exists() and list(tmp_path.glob(".short*")) == []
    with pytest.raises(ValueError, match="does not fit"):
        with npy_writer(tmp_path / "wide.npy", np.float32, a.shape) as write:
            write(np.zeros((2, 4, 7), np.float32))


def test_bit_rows_read_packed_validity_as_the_bool_table_it_packs(tmp_path):
    """separate keeps the sample validity (P, F) as bits along F (issue 31's disk: 0.31 -> 0.04 GB at 800^2 x
    480): every row read back is the bool row packed, for any index the stages use, with F not a multiple of 8;
    a bool table (what facetsynth wrote before) reads as it is; a table of the wrong width or rows is refused,
    naming the file."""
    from facetsynth.io.fileio import BitRows
    valid = np.random.default_rng(0).random((11, 13)) > 0.4
    np.save(tmp_path / "bits.npy", np.packbits(valid, axis=1))
    np.save(tmp_path / "bool.npy", valid)
    assert (tmp_path / "bits.npy").stat().st_size < (tmp_path / "bool.npy").stat().st_size
    for name in ("bits.npy", "bool.npy"):
        rows = BitRows(tmp_path / name, 13, 11)
        assert len(rows) == 11 and rows.shape == (11, 13) and rows.dtype == bool
        for index in (slice(None), slice(2, 7), 4, np.array([9, 0, 9]), [3]):
            got = rows[index]
            assert got.dtype == bool and np.array_equal(got, valid[index])
    for count, n, match in ((17, 11, r"shape \(11, 2\), expected \(11, 3\) uint8 bits or \(11, 17\) bool"),
                            (8, 11, r"shape \(11, 2\), expected \(11, 1\) uint8"), (13, 12, r"expected \(12, 2\)")):
        with pytest.raises(InputError, match=match) as caught:
            BitRows(tmp_path / "bits.npy", count, n, "sample validity")
        assert "bits.npy" in str(caught.value) and "sample validity" in str(caught.value)
    np.save(tmp_path / "float.npy", valid.astype(np.float32))
    with pytest.raises(InputError, match="float32 tensor"):
        BitRows(tmp_path / "float.npy", 13)


def test_half_float_tensors_saturate_instead_of_overflowing():
    """The per-point tensors between stages are half floats (issue 14's disk budget): rounding within
    2^-11 of the value, values beyond the half range saturated at +-65504 (never Inf), NaN kept for the
    reader's checks to see."""
    from facetsynth.io.half import as_half
    values = np.array([0.0, 1e-3, 0.1234567, 3.14159, 1234.567, 65504.0, 7e4, -1e9, 1e300])
    half = as_half(values)
    assert half.dtype == np.float16 and np.isfinite(half).all()
    assert np.allclose(half[:5], values[:5], rtol=2.0 ** -11, atol=0)
    assert half[5] == half[6] == 65504.0 and half[7] == -65504.0 and half[8] == 65504.0
    assert np.isnan(as_half(np.array([np.nan]))).all()


def test_the_compiled_cast_to_half_is_numpys_to_the_bit():
    """io.half.as_half (one compiled pass) against numpy's clip and cast: every finite half, the ties between
    neighbours (round to even) and one ulp either side of them, the subnormals and the underflow to +-0,
    saturation beyond 65504, +-Inf, NaN with payloads, float64 subnormals, a log-uniform spread of magnitudes;
    from float32 too (the same real values: no double rounding either way)."""
    from facetsynth.io.half import as_half
    every = np.arange(0, 0x7C00, dtype=np.uint16).view(np.float16).astype(np.float64)
    ties = (every[:-1] + every[1:]) / 2
    rng = np.random.default_rng(5)
    nans = np.array([0x7FF8000000000001, 0x7FF0000000000001, 0xFFF4000000000000, 0x7FF0040000000000],
                    np.uint64).view(np.float64)
    values = np.concatenate([every, -every, ties, -ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf),
                             rng.choice([-1.0, 1.0], 200_000) * 2.0 ** rng.uniform(-40, 20, 200_000), nans,
                             [0.0, -0.0, np.nan, np.inf, -np.inf, 1e300, -1e300, 5e-324, -5e-324, 2.0 ** -25,
                              -(2.0 ** -25), 2.0 ** -25 * (1 + 2.0 ** -52), 65519.99, 65520.0, 65536.0]])
    for v in (values, values[np.abs(values) < 3e38].astype(np.float32)):
        expected = np.clip(v, -65504.0, 65504.0).astype(np.float16)
        np.testing.assert_array_equal(as_half(v).view(np.uint16), expected.view(np.uint16))
    assert as_half(np.ones((2, 3, 4))).shape == (2, 3, 4) and as_half(np.ones(3)).dtype == np.float16
