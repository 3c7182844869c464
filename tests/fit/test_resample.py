"""The resample stage (facetsynth.stages.resample): its scatter parts (issue 14) on the extremes scene of issue 7,
part 2 (conftest's ``extreme_run``)."""

from facetsynth.io import tables


def test_resample_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """resample in 3 parts of whole tiles (64 points: 2, 1 and 1 tiles of the 256 points), joined in any
    order: the unsplit run's slices, colour, grid and metrics, bit for bit (every part decides the
    same grid from the same strided points)."""
    from facetsynth.stages import resample
    monkeypatch.setattr(resample, "TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"])
    names = ("slice", "colour.npy", "grid.json", "metrics.json")
    resample.run_whole(**inputs, **{k: tmp_path / "whole" / n for k, n in zip(
        ("slice_out", "colour_out", "grid_out", "metrics_out"), names)})
    parts = [tmp_path / f"part{k}" for k in range(3)]
    for k in (1, 2, 0):
        resample.run_part(**inputs, part=k, parts=3, slice_out=parts[k] / "slice", record_out=parts[k] / "record.npz")
    shuffled = [parts[k] for k in (2, 0, 1)]
    resample.gather(**inputs, slice_parts=[p / "slice" for p in shuffled],
                    records=[p / "record.npz" for p in shuffled],
                    **{k: tmp_path / "joined" / n for k, n in zip(
                        ("slice_out", "colour_out", "grid_out", "metrics_out"), names)})
    for name in ("slice/table.json", "slice/mask.npy", "slice/offsets.npy", "slice/values.npy") + names[1:]:
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "joined" / name).read_bytes(), name
    assert len(tables.SupportTable(parts[0] / "slice")) == 128
