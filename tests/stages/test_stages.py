"""The per-point stages in-process (facetsynth.stages: separate -> resample -> partial_ndf -> cluster -> synthesize
-> params) on small scenes at the numerical extremes (issue 7, part 2): the four-quadrant extremes scene
(conftest's ``extreme_run``) and hand-built rectified captures (all diffuse, a single point, tiles with no
visible point). Each test states the expected behaviour in its docstring and checks it against a ground truth with
a stated tolerance. The helpers that build those captures and run the stages are shared with other test modules."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from facetsynth.models import microfacet
from facetsynth.io import tables
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.stages.common import RectifiedCapture

from test_grid import unit, upper


# ============================================================================ the whole pipeline, small scenes
def run_per_point_stages(root: Path, geometry: Path, n_theta: int = 32,
                         min_representatives: int = 8) -> dict[str, Path]:
    """separate -> resample -> partial_ndf -> cluster -> synthesize -> params, in-process, into ``root``;
    the direction grid has ``n_theta`` rings (a resample stage that chooses its grid from the data is
    pinned to it)."""
    from facetsynth.stages import cluster, params, partial_ndf, resample, separate, synthesize
    f = {"geometry": geometry}
    for stage, names in {"separate": ("kd.exr", "specular.npy", "valid.npy", "metrics.json"),
                         "resample": ("slice", "specular_colour.npy", "grid.json",
                                      "metrics.json"),
                         "partial_ndf": ("ndf", "metrics.json"),
                         "cluster": ("labels.npy", "representatives.npy", "neighbours.npy", "weights.npy",
                                     "representative_ndf.npy", "representative_confidence.npy", "rotation.npy",
                                     "metrics.json"),
                         "synthesize": ("ndf.npy", "confidence.npy", "cosine.npy", "grid.json", "metrics.json"),
                         "params": ("metrics.json",)}.items():
        for n in names:
            f[f"{stage}/{n}"] = root / stage / n
    f["svbrdf"] = root / "svbrdf"
    separate.run(separate.Inputs(geometry=geometry),
                 separate.Outputs(kd=f["separate/kd.exr"], specular=f["separate/specular.npy"],
                                     valid=f["separate/valid.npy"], metrics=f["separate/metrics.json"]),
                 separate.Settings(heldout_every=0))
    resample.run_whole(geometry=geometry, specular=f["separate/specular.npy"], valid=f["separate/valid.npy"],
         slice_out=f["resample/slice"],
         colour_out=f["resample/specular_colour.npy"], grid_out=f["resample/grid.json"],
         metrics_out=f["resample/metrics.json"], settings=resample.Settings(n_theta_range=(n_theta, n_theta)))
    partial_ndf.run_whole(geometry=geometry, slice_path=f["resample/slice"],
         grid_path=f["resample/grid.json"], ndf_out=f["partial_ndf/ndf"],
         metrics_out=f["partial_ndf/metrics.json"],
         settings=partial_ndf.Settings(per_point_view=True))
    cluster.run(cluster.Inputs(geometry=geometry, ndf=f["partial_ndf/ndf"],
         grid=f["resample/grid.json"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"],
         kd=f["separate/kd.exr"]),
         cluster.Outputs(labels=f["cluster/labels.npy"],
         representatives=f["cluster/representatives.npy"], neighbours=f["cluster/neighbours.npy"],
         weights=f["cluster/weights.npy"], rep_ndf=f["cluster/representative_ndf.npy"],
         rep_confidence=f["cluster/representative_confidence.npy"], rotation=f["cluster/rotation.npy"],
         metrics=f["cluster/metrics.json"]),
         cluster.Settings(min_representatives=min_representatives, n_init=1))
    synthesize.run(synthesize.Inputs(geometry=geometry, ndf=f["partial_ndf/ndf"],
         grid=f["resample/grid.json"], representatives=f["cluster/representatives.npy"],
         neighbours=f["cluster/neighbours.npy"], weights=f["cluster/weights.npy"],
         rep_ndf=f["cluster/representative_ndf.npy"], rep_confidence=f["cluster/representative_confidence.npy"]),
         synthesize.Outputs(ndf=f["synthesize/ndf.npy"], confidence=f["synthesize/confidence.npy"],
         fresnel_cosine=f["synthesize/cosine.npy"], grid=f["synthesize/grid.json"],
         metrics=f["synthesize/metrics.json"]))
    params.run(params.Inputs(geometry=geometry, kd=f["separate/kd.exr"], specular=f["separate/specular.npy"],
         valid=f["separate/valid.npy"], colour=f["resample/specular_colour.npy"],
         representatives=f["cluster/representatives.npy"], neighbours=f["cluster/neighbours.npy"],
         weights=f["cluster/weights.npy"], ndf=f["synthesize/ndf.npy"], fresnel_cosine=f["synthesize/cosine.npy"],
         synthesis_confidence=f["synthesize/confidence.npy"],
         grid=f["synthesize/grid.json"], rotation=f["cluster/rotation.npy"]),
         params.Outputs(svbrdf=f["svbrdf"], metrics=f["params/metrics.json"]))
    return f


def metrics_of(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def interior_truth(geometry: Path):
    """The rectified capture, the true maps at its points, and the cells away from material edges."""
    from facetsynth.stages.common import RectifiedCapture
    from facetsynth.evaluation.rectify import _near_edges
    from facetsynth.evaluation.truth import truth_of
    cap = RectifiedCapture.load(geometry)
    truth = truth_of(cap)
    region = truth.region.reshape(cap.grid.rows, cap.grid.cols)
    border = np.ones(region.shape, bool)
    border[1:-1, 1:-1] = False                         # the warp filter mixes the background into the outer cells
    interior = (~_near_edges(region) & ~border).ravel() & cap.visible & (truth.region >= 0)
    return cap, truth, interior


def test_pipeline_hdr_and_separation(extreme_run):
    """The mirror lobe saturates every exposure at some pixels (HDR flags them, rectify carries the flag,
    separate marks those samples invalid); kd of eq. 9 is exact where there is no specular (ks = 0), ~0
    where there is no diffuse (kd = 0, the near-mirror tail between lights is tiny), and every tensor is finite."""
    from facetsynth.io.fileio import read_exr
    hdr = metrics_of(extreme_run["root"] / "hdr/metrics.json")
    assert hdr["saturated_pixels"] > 0 and hdr["median_rel_error"] < 1e-3
    cap, truth, interior = interior_truth(extreme_run["geometry"])
    valid = RectifiedCapture.load(extreme_run["geometry"]).validity(extreme_run["separate/valid.npy"])[:]
    spec = np.load(extreme_run["separate/specular.npy"])
    kd = read_exr(extreme_run["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert np.isfinite(spec).all() and (spec >= 0).all() and np.isfinite(kd).all()
    mirror = truth.region == 1
    assert (~valid[mirror]).any() and valid[interior & ~mirror].all()   # saturated: the mirror quadrant, and
                                                                        # the cells the warp filter mixes with it
    diffuse = interior & (truth.region == 0)
    rel = np.abs(kd[diffuse] - truth.kd[diffuse]) / truth.kd[diffuse]
    assert rel.max() < 0.015       # measured 1.2 % everywhere: cell averaging at the grazing light eq. 9 picks
    assert kd[interior & mirror].max() < 0.01
    assert (spec[diffuse] / (truth.kd[diffuse][:, None] / np.pi)).max() < 0.02   # ks = 0: the 1.2 % above
    assert "degenerate" not in metrics_of(extreme_run["separate/metrics.json"])   # one matte quadrant of four


def test_pipeline_model_is_finite_and_predicts_the_capture(extreme_run):
    """The fitted SVBRDF of the extremes scene is finite and non-negative everywhere (grazing, below the
    horizon included; 0 at i.n = 0 and below); eta stays in its range. Against the true radiance of every
    7th frame, relative rms per quadrant (interior cells): ks = 0 within 1 %; the
    anisotropic glossy one within 25 %; the near-mirror metal (alpha 0.02, narrower than the light spacing
    and the 16 x 64 grid) loses its peak: within 1.05, i.e. no overshoot (the prediction is never worse than
    predicting nothing); alpha 1 / eta 1.05 within 2 %. Stated: on the ks = 0 quadrant the model's ks is not 0 (the 1.2 % rectification
    residual looks like a broad lobe, and ks is that lobe's scale over F(c, eta) ~ 0.04), but its radiance
    is right to 1 %."""
    from facetsynth.models.render import light_geometry
    from facetsynth.models.svbrdf import SVBRDF
    cap, truth, interior = interior_truth(extreme_run["geometry"])
    model = SVBRDF.load(extreme_run["svbrdf"])
    assert np.isfinite(model.eta).all() and model.eta.min() >= 1.05 and model.eta.max() <= 4.0
    rng = np.random.default_rng(0)
    n = 4000
    index = rng.integers(0, cap.n_points, n)
    wi, wo = upper(rng, n), upper(rng, n)
    wi[:500, 2] = 0.0                                                   # exactly grazing
    wi[500:1000, 2] = 1e-9
    wi[1000:1500, 2] *= -1                                              # below the horizon
    rho = model.eval_index(index, unit(wi), unit(wo))
    assert np.isfinite(rho).all() and (rho >= 0).all()
    assert np.all(rho[:500] == 0) and np.all(rho[1000:1500] == 0)
    # the capture's own frames: predicted against the true radiance at the rectified points
    pts = cap.points
    o = cap.view_directions(True)
    q = np.arange(0, len(cap.lights), 7)
    li, r2 = light_geometry(pts[:, None, :], cap.lights[q][None])
    irr = (np.clip(li[..., 2], 0, None) / r2)[..., None] * cap.light_intensities[q][None]
    idx = np.repeat(np.arange(cap.n_points), len(q))
    pred = model.eval_index(idx, li.reshape(-1, 3), np.repeat(o, len(q), 0)).reshape(irr.shape) * irr
    true = truth.take((slice(None), None)).rho(li, o[:, None, :]) * irr
    # measured 0.005, 0.994, 0.017, 0.24 (0.003, 0.99, 0.002, 0.19 when every representative kept its own
    # partial NDF and weight 1 on itself, before issue 13's pooled representatives and coarse eq. 18)
    for region, bound in ((0, 0.01), (1, 1.05), (2, 0.02), (3, 0.25)):
        sel = interior & (truth.region == region)
        err = np.sqrt(np.mean((pred[sel] - true[sel]) ** 2)) / np.sqrt(np.mean(true[sel] ** 2))
        assert np.isfinite(err) and err < bound


# ============================================================================ hand-built rectified captures
def rig_lights(n_x=11, n_y=9, height=0.04):
    """Lights like the rig's LED array (y from 0 to 0.2 m, 4 cm up), plus a far ring for grazing light."""
    xs, ys = np.meshgrid(np.linspace(-0.1, 0.1, n_x), np.linspace(0.0, 0.2, n_y))
    grid = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, height)], -1)
    az = np.radians(np.linspace(30, 150, 13))
    ring = np.stack([0.4 * np.cos(az), 0.4 * np.sin(az), np.full(az.size, 0.03)], -1)
    return np.concatenate([grid, ring])


def write_rectified(folder: Path, scene_text: str, plane: PlaneGrid, lights: np.ndarray,
                    visible: np.ndarray | None = None, damage=None) -> Path:
    """A rectified capture made directly from the scene's truth (exact radiance at the cell centres):
    geometry.json and one EXR per light. ``damage(q, rgb, saturated)`` may alter frame q in place."""
    from facetsynth.io.fileio import write_exr, write_json
    from facetsynth.models.render import radiance
    from facetsynth.truth.scene import Scene
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.yaml").write_text(scene_text)
    p = plane.rows * plane.cols
    visible = np.ones(p, bool) if visible is None else np.asarray(visible, bool)
    view = np.array([0.0, -0.52, 0.9])                     # the rig's camera (60 deg), 1 m from the centre
    pts = plane.points3d()
    maps = Scene.load(folder / "scene.yaml").parameters(pts[..., :2])
    frames = []
    for q, light in enumerate(lights):
        rgb = radiance(pts, maps.rho, light, np.full(3, 0.3), view).astype(np.float32)
        rgb[~visible.reshape(plane.rows, plane.cols)] = 0.0
        saturated = np.zeros(rgb.shape[:2], np.float32)
        if damage is not None:
            damage(q, rgb, saturated)
        write_exr(folder / f"frames/{q:04d}.exr", {"RGB": rgb, "saturated": saturated})
        frames.append({"file": f"frames/{q:04d}.exr",
                       "light": {"position": light.tolist(), "intensity": [0.3, 0.3, 0.3]}})
    write_json(folder / "geometry.json", {"grid": plane.to_dict(), "visible": visible.astype(int).tolist(),
                                          "frames": frames, "view_point": [*view.tolist(), 1.0],
                                          "truth": {"scene": "scene.yaml"}})
    return folder / "geometry.json"


def eq9_truth(kd, ks, lights, point=np.zeros(3), eta=1.5, alpha=(0.2, 0.3), angle=20.0, lowest=0.03):
    """kd that eq. 9 must give for a point of ``one_material`` (written out: of the true rho at the lights
    whose radiance exceeds 5 % of the mean, the mean of the round(lowest x n) (at least one) with the smallest
    channel mean, the stage's default ``separate.lowest``, times pi; the specular tail there is its bias)."""
    view = np.array([0.0, -0.52, 0.9])
    wi = lights - point
    r2 = np.sum(wi**2, -1)
    wi = wi / np.sqrt(r2)[:, None]
    rho = microfacet.rho(wi, unit(view - point), np.array(kd, float), np.array(ks, float), eta, alpha[0], alpha[1],
                         np.radians(angle))
    intensity = (rho * (np.clip(wi[:, 2], 0, None) / r2)[:, None] * 0.3).mean(axis=1)
    qualifying = rho[intensity > 0.05 * intensity.mean()]
    m = max(1, int(np.round(lowest * len(qualifying))))
    return np.pi * qualifying[np.argsort(qualifying.mean(axis=1))[:m]].mean(axis=0)


def one_material(kd, ks, eta=1.5, alpha=(0.2, 0.3), angle=20.0, name="m") -> str:
    return f"""\
name: {name}
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: all
    where: {{all: true}}
    kd: {list(kd)}
    ks: {list(ks)}
    eta: {eta}
    alpha: {list(alpha)}
    frame: {{angle_deg: {angle}}}
"""


def test_all_diffuse_sample_gives_a_lambertian_model(tmp_path):
    """Purely diffuse (ks = 0) everywhere: eq. 9 gives kd exactly; the specular residual and the partial
    NDFs are float32 rounding noise (<= 1e-7, relative 1e-7 of kd / pi). Stated: cluster and synthesize
    run on that noise (eq. 15 is scale-free, so noise looks like 36 distinct NDFs), but params turns it
    into ks <= 1e-5, so the model is Lambertian (rho = kd / pi to 1e-5) in every direction pair, and eta
    keeps the default (no specular signal at grazing)."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.svbrdf import SVBRDF
    kd = (0.45, 0.25, 0.05)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0, 0, 0)), PlaneGrid(0.1, 0.1, 6, 6), rig_lights())
    f = run_per_point_stages(tmp_path, geometry, n_theta=16)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    np.testing.assert_allclose(got, np.tile(kd, (36, 1)), rtol=1e-5)          # float32 frames
    assert np.all(np.load(f["separate/specular.npy"]) <= 1e-7)          # measured 1.5e-8
    separated = metrics_of(f["separate/metrics.json"])                  # never a silent model (issue 15)
    assert separated["specular_signal_fraction"] == 0.0
    assert separated["degenerate"].startswith("no specular signal: 0.0 % of the lit points")
    assert np.all(tables.load(f["partial_ndf/ndf"], "ndf") <= 1e-6)            # measured 3.2e-8
    model = SVBRDF.load(f["svbrdf"])                                    # ks measured 2.9e-6
    assert np.all(model.ks <= 1e-5) and not model.eta_fitted.any()
    rng = np.random.default_rng(1)
    idx = rng.integers(0, 36, 3000)
    rho = model.eval_index(idx, upper(rng, 3000), upper(rng, 3000))
    np.testing.assert_allclose(rho, np.tile(kd, (3000, 1)) / np.pi, rtol=1e-5, atol=1e-7)


def test_single_point_sample_runs_every_stage(tmp_path):
    """A sample of a single rectified cell: every per-point stage runs (k-means with one point, synthesis
    with one exemplar, eta with one representative); kd is exact, the model finite, and it predicts the
    point's own frames within 15 % rms (one partial NDF, completed only from its own rotations)."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.render import light_geometry
    from facetsynth.models.svbrdf import SVBRDF
    kd, ks = (0.2, 0.3, 0.1), (0.6, 0.6, 0.6)
    lights = rig_lights(21, 17)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, ks, alpha=(0.25, 0.25)), PlaneGrid(0.1, 0.1, 1, 1),
                               lights)
    f = run_per_point_stages(tmp_path, geometry)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert got.shape == (1, 3)
    np.testing.assert_allclose(got[0], eq9_truth(kd, ks, lights, alpha=(0.25, 0.25)), rtol=1e-5)
    assert np.all(got[0] > kd) and np.all(got[0] - kd < 0.01)    # eq. 9's bias: the specular tail, stated
    assert metrics_of(f["cluster/metrics.json"])["representatives"] == 1
    model = SVBRDF.load(f["svbrdf"])
    assert np.isfinite(model.ndf).all() and np.isfinite(model.area).all() and model.area.min() > 0
    o = unit(np.array([0.0, -0.52, 0.9]))
    wi, _ = light_geometry(np.zeros((1, 3)), lights)
    pred = model.eval_index(np.zeros(len(lights), np.intp), wi, np.tile(o, (len(lights), 1)))
    true = microfacet.rho(wi, o, np.array(kd), np.array(ks), 1.5, 0.25, 0.25, np.radians(20.0))
    err = np.sqrt(np.mean((pred - true) ** 2) / np.mean(true**2))
    assert np.isfinite(pred).all() and err < 0.15                      # measured 0.082


def test_tiles_with_no_visible_point(tmp_path):
    """272 points, the first tile of 256 not visible: invisible points get kd = 0, label -1, zero weights,
    ks = 0 and a model that is 0; the 16 visible points of the second tile get kd exactly."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.svbrdf import SVBRDF
    plane = PlaneGrid(0.1, 0.1, 16, 17)
    visible = np.zeros(272, bool)
    visible[256:] = True
    kd = (0.3, 0.2, 0.1)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0.5, 0.5, 0.5), alpha=(0.3, 0.3)), plane,
                               rig_lights(), visible)
    f = run_per_point_stages(tmp_path, geometry, n_theta=16, min_representatives=2)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert np.all(got[:256] == 0)
    expected = [eq9_truth(kd, (0.5,) * 3, rig_lights(), pt, alpha=(0.3, 0.3))
                for pt in plane.points3d().reshape(-1, 3)[256:]]
    np.testing.assert_allclose(got[256:], expected, rtol=1e-5)
    assert not RectifiedCapture.load(geometry).validity(f["separate/valid.npy"])[:256].any()
    for name, channel in (("resample/slice", "values"), ("partial_ndf/ndf", "ndf"), ("partial_ndf/ndf", "confidence")):
        assert np.isfinite(tables.load(f[name], channel)).all()
    labels, weights = np.load(f["cluster/labels.npy"]), np.load(f["cluster/weights.npy"])
    assert np.all(labels[:256] == -1) and np.all(weights[:256] == 0) and np.all(labels[256:] >= 0)
    np.testing.assert_allclose(weights[256:].sum(axis=1), 1.0, atol=1e-5)
    model = SVBRDF.load(f["svbrdf"])
    assert np.all(model.ks[:256] == 0) and np.all(model.kd[:256] == 0)
    rng = np.random.default_rng(2)
    idx = rng.integers(0, 272, 2000)
    rho = model.eval_index(idx, upper(rng, 2000), upper(rng, 2000))
    assert np.isfinite(rho).all() and np.all(rho[idx < 256] == 0) and np.all(rho[idx >= 256] > 0)
