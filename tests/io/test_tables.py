"""Support tables (facetsynth.io.tables): the slices and partial NDFs stored on their support (issue 14's disk
budget), read back as the dense tensors they stand for."""

import json

import numpy as np
import pytest

from facetsynth.io import tables
from facetsynth.io.tables import SupportTable, join_tables, support_writer


def write(folder, support, **values):
    with support_writer(folder, support.shape, tuple(values)) as w:
        for start in range(0, len(support), 64):
            rows = slice(start, start + 64)
            w(support[rows], **{k: v[rows] for k, v in values.items()})


@pytest.fixture
def table(tmp_path):
    rng = np.random.default_rng(0)
    support = rng.random((300, 8, 32)) < 0.3
    support[17] = False                                    # a point with nothing stored
    d, w = rng.random((300, 8, 32)) * 500, rng.random((300, 8, 32))
    write(tmp_path / "t", support, ndf=d, confidence=w)
    return tmp_path / "t", support, d, w


def test_rows_read_back_dense_with_zeros_off_the_support(table):
    folder, support, d, w = table
    t = SupportTable(folder)
    dense_d = np.where(support, d.astype(np.float16), 0)
    assert t.shape == (300, 8, 32) and t.channels == ("ndf", "confidence") and len(t) == 300
    assert np.array_equal(t.rows("ndf")[:], dense_d)
    assert np.array_equal(t.rows("confidence")[:], np.where(support, w.astype(np.float16), 0))
    for index in (5, slice(60, 130), [299, 0, 17, 17, 4], np.arange(0, 300, 7), np.arange(300) % 3 == 0, []):
        assert np.array_equal(t.rows("ndf")[index], dense_d[index]), index
        assert np.array_equal(t.support(index), support[index]), index
    assert t.rows("ndf")[17].shape == (8, 32) and not t.rows("ndf")[17].any()
    meta = json.loads((folder / "table.json").read_text())
    assert meta["stored_fraction"] == pytest.approx(support.mean())
    assert np.load(folder / "ndf.npy").shape == (support.sum(),)          # only the support is on disk
    with pytest.raises(KeyError, match="no channel 'slice'"):
        t.rows("slice")



def test_sector_sums_read_from_the_support_are_numpys_sums_of_the_dense_rows_to_the_bit(table):
    """cluster's coarse grid sums the stored partial NDFs without making their dense rows: for runs of points,
    scattered points, repeated ones and the point with nothing stored, the sums over each ring's runs of 4, 8
    and 32 cells equal numpy's float64 sums of the dense half-float rows, bitwise; a ring that does not split
    is an error."""
    folder, support, d, w = table
    t = SupportTable(folder)
    for channel in ("ndf", "confidence"):
        rows = t.rows(channel)
        for index in (np.arange(300), np.arange(40, 200), np.array([299, 0, 17, 17, 4]), np.arange(0, 300, 7)):
            dense = rows[index]
            for sectors in (8, 4, 1):
                expected = dense.reshape(len(index), 8, sectors, -1).sum(axis=-1, dtype=float)
                got = rows.sector_sums(index, sectors)
                assert got.dtype == np.float64 and np.array_equal(got, expected), (channel, sectors)
    assert not t.sector_sums("ndf", [17], 8).any()
    with pytest.raises(ValueError, match="do not split into 5 sectors"):
        t.sector_sums("ndf", [0], 5)

def test_blocks_that_do_not_fit_are_errors_and_publish_nothing(tmp_path):
    with pytest.raises(ValueError, match="3 rows written of 4"):
        with support_writer(tmp_path / "short", (4, 2, 8)) as w:
            w(np.ones((3, 2, 8), bool), values=np.ones((3, 2, 8)))
    with pytest.raises(ValueError, match="does not fit"):
        with support_writer(tmp_path / "wide", (4, 2, 8)) as w:
            w(np.ones((2, 2, 9), bool), values=np.ones((2, 2, 9)))
    with pytest.raises(ValueError, match="does not fit"):
        with support_writer(tmp_path / "channels", (4, 2, 8), ("ndf", "confidence")) as w:
            w(np.ones((2, 2, 8), bool), ndf=np.ones((2, 2, 8)))
    assert not (tmp_path / "short").exists() and not (tmp_path / "wide").exists()


def test_parts_join_into_the_whole_table_bit_for_bit(table, tmp_path):
    folder, support, d, w = table
    for k, rows in enumerate((slice(0, 100), slice(100, 100), slice(100, 300))):
        write(tmp_path / f"part{k}", support[rows], ndf=d[rows], confidence=w[rows])
    join_tables([tmp_path / f"part{k}" for k in range(3)], tmp_path / "joined", 300, block=37)
    for name in ("table.json", "mask.npy", "offsets.npy", "ndf.npy", "confidence.npy"):
        assert (tmp_path / "joined" / name).read_bytes() == (folder / name).read_bytes(), name
    with pytest.raises(ValueError, match="hold 300 points, the capture 301"):
        join_tables([tmp_path / f"part{k}" for k in range(3)], tmp_path / "other", 301)


def test_values_beyond_half_floats_saturate(tmp_path):
    support = np.ones((1, 1, 8), bool)
    write(tmp_path / "t", support, values=np.array([[[1e5, -1e9, 65504, 0.5, 1e-9, 0, 3, np.inf]]]))
    assert tables.load(tmp_path / "t").ravel().tolist() == [65504, -65504, 65504, 0.5, 0, 0, 3, 65504]
