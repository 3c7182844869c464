"""The per-point Ward baseline stage (facetsynth.stages.baseline): its scatter parts (issue 14) on the extremes
scene of issue 7, part 2 (conftest's ``extreme_run``). The Ward fit itself: tests/models/test_ward_batched.py."""

from test_stages import metrics_of


def test_ward_baseline_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """The per-point Ward fits (the slowest per-point stage: 915 s at the demo's native 168 x 168) in 3 parts of
    whole tiles (64 points: 2, 1 and 1 tiles of the 256 points), joined in any order: the same model folder, bit
    for bit, and the same metrics but the time."""
    from facetsynth.stages import baseline
    monkeypatch.setattr(baseline, "TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"])
    baseline.run_whole(**inputs, kd_path=f["separate/kd.exr"], colour=f["resample/specular_colour.npy"],
                       model_out=tmp_path / "whole", metrics_out=tmp_path / "whole.json")
    for k in range(3):
        baseline.run_part(**inputs, part=k, parts=3, record_out=tmp_path / f"part{k}.npz")
    baseline.gather(f["geometry"], f["separate/kd.exr"], f["resample/specular_colour.npy"], f["separate/specular.npy"],
                    [tmp_path / f"part{k}.npz" for k in (2, 0, 1)], tmp_path / "joined", tmp_path / "joined.json")
    for a in sorted((tmp_path / "whole").iterdir()):
        assert a.read_bytes() == (tmp_path / "joined" / a.name).read_bytes(), a.name
    whole, joined = metrics_of(tmp_path / "whole.json"), metrics_of(tmp_path / "joined.json")
    assert whole.pop("fit_seconds") > 0 and joined.pop("fit_seconds") > 0 and whole == joined
