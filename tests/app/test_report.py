"""The Snakemake report (`snakemake --report`): every figure of workflow/rules/report.smk is in it, with a
caption, in its sample's and stage's category; and the figure functions of facetsynth.app.figures."""

import io
import json
import re
import shutil
import zipfile

import numpy as np
import pytest
import yaml
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from facetsynth.app import figures
from facetsynth.io.colour import srgb_decode, srgb_encode
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.stencil.grid import SHAPE, unwrap

STAGES = ["1 capture", "2 SVBRDF maps", "3 NDFs", "4 clusters", "5 held-out views", "6 stencil fits"]


def report_tables(html: str) -> tuple[dict, dict]:
    """The report's ``results`` and ``categories`` (the JSON objects its page script is built from)."""
    found = {name: json.loads(re.search(rf"var {name} = (\{{.*\}});\s*$", html, re.M).group(1))
             for name in ("results", "categories")}
    return found["results"], found["categories"]


def test_report_holds_every_figure(demo_run, repo, tmp_path):
    from test_workflow import NOISE_FREE, snakemake
    # make_workdir copies no docs/: give the run the committed benchmark plots, then only their copies run
    shutil.copytree(repo / "docs/bench", demo_run / "docs/bench", dirs_exist_ok=True)
    bench = ["results/report/bench/tradeoff.png", "results/report/bench/scale.png"]
    done = snakemake(demo_run, *bench, *NOISE_FREE)       # targets first: --configfile takes every word after it
    assert done.returncode == 0, done.stderr[-3000:]
    done = snakemake(demo_run, *NOISE_FREE, "--report", str(tmp_path / "report.zip"))
    assert done.returncode == 0, done.stderr[-3000:]

    archive = zipfile.ZipFile(tmp_path / "report.zip")
    html = archive.read("report/report.html").decode()
    assert "facetsynth fits a spatially varying" in html          # workflow/report/workflow.rst
    results, categories = report_tables(html)
    views = [v["name"] for v in yaml.safe_load((demo_run / "config/config.yaml").read_text())["validate"]["views"]]
    clusters = json.loads((demo_run / "results/demo/stencil_fit/models/stencil.json").read_text())["clusters"]
    expected = {"1 capture": ["capture.png"], "2 SVBRDF maps": ["eta.png", "kd.png", "ks.png", "relief.png"],
                "3 NDFs": ["ndf.png"], "4 clusters": ["clusters.png"],
                "5 held-out views": [f"heldout_{v}.png" for v in sorted(views)],
                "6 stencil fits": [f"stencil/cluster_{c['cluster']:03d}.png" for c in clusters]}
    assert sorted(categories["demo"]) == STAGES
    selfcheck = [f"results/demo/selfcheck/images/{n}_worst.png" for n in ("heldout", "relit")]   # issue 29
    for stage, names in expected.items():
        paths = [f"results/demo/report/{n}" for n in names]
        assert sorted(categories["demo"][stage]) == sorted(paths + (selfcheck if stage == "5 held-out views"
                                                                    else [])), stage
    assert sorted(categories["benchmarks"]["Other"]) == sorted(bench)

    pictures = {n: archive.read(n) for n in archive.namelist() if n.endswith(".png")}
    assert len(pictures) == sum(map(len, expected.values())) + len(selfcheck) + len(bench)
    for path, entry in results.items():
        assert entry["caption"].strip() and "figure" in entry["labels"], path
        data = [blob for name, blob in pictures.items() if name.endswith("/" + entry["filename"])]
        assert data, path
        image = np.asarray(Image.open(io.BytesIO(data[0])).convert("RGB"), float)
        assert 300 <= image.shape[0] <= 4000 and 400 <= image.shape[1] <= 4000, (path, image.shape)
        assert image.std() > 10, path                             # a picture, not a blank page
    assert "Delta E / RMSE / PSNR / SSIM" in results["results/demo/report/stencil/cluster_000.png"]["caption"]


# --- facetsynth.app.figures on tiny synthetic arrays -----------------------------------------------------

def rendered(fig: Figure) -> np.ndarray:
    """The figure as an RGB array (rows from the top), as save_png would write it."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].astype(float)


def test_unwrapped_brdf_puts_a_lobe_at_its_light_and_view_cell():
    """UTIA layout (paper 000 Fig. 1): row 48 theta_i + phi_i, column 48 theta_v + phi_v; the data and the
    model at one scale; the difference panel is 3 x |model - data|."""
    data = np.zeros(SHAPE)
    data[:, 2, 5, 3, 7] = 5.0
    model = data.copy()
    model[:, 4, 0, 1, 40] = 1.0
    fig = figures.unwrapped_brdf_figure(unwrap(data), unwrap(model))
    shown, fitted, diff = (ax.images[0].get_array() for ax in fig.axes[:3] if ax.images)
    assert shown.shape == (288, 288, 3)
    assert np.unravel_index(np.argmax(shown.sum(-1)), (288, 288)) == (2 * 48 + 5, 3 * 48 + 7)
    assert np.unravel_index(np.argmax(diff), (288, 288)) == (4 * 48 + 0, 1 * 48 + 40)
    assert diff[2 * 48 + 5, 3 * 48 + 7] == 0.0
    assert diff.max() == pytest.approx(3.0, rel=1e-9)               # luminance of a grey difference
    assert np.isfinite(shown).all() and shown.min() >= 0.0 and shown.max() <= 1.0


def test_the_stencil_figure_made_once_draws_each_cluster_as_a_fresh_one():
    """report_stencil draws every cluster in one figure: after a cluster a million times brighter, the next
    one's images, colour scales and tick labels are its own (data and model at the data's scale, the grey bar
    labelled in it, the difference 3 x |model - data| on 0 .. scale), and its layout a fresh figure's within
    3 pixels (constrained layout starts from where the last drawing left the axes: measured 1.8 pixels)."""
    rng = np.random.default_rng(3)
    bright = rng.random((288, 288, 3)) * 1e3
    dim = rng.random((288, 288, 3)) * 1e-3
    dim_model = dim * rng.random(dim.shape)
    sheet = figures.UnwrappedBRDFFigure()
    rendered(sheet.show(bright, 0.5 * bright, "a much longer title of another cluster " * 3))
    height = rendered(sheet.show(dim, dim_model, "dim")).shape[0]
    scale = figures.display_scale(dim, percentile=99.0)
    shown, fitted, diff = (ax.images[0] for ax in sheet.fig.axes[:3])
    np.testing.assert_array_equal(shown.get_array(), figures.tonemap(dim, scale))
    np.testing.assert_array_equal(fitted.get_array(), figures.tonemap(dim_model, scale))
    np.testing.assert_array_equal(diff.get_array(), 3.0 * figures.luminance(np.abs(dim_model - dim)))
    assert diff.get_clim() == (0.0, scale)
    grey = sheet.fig.axes[3]
    assert [t.get_text() for t in grey.get_yticklabels()] == [f"{t:.3g}" for t in np.linspace(0.0, scale, 5)]
    assert sheet.fig._suptitle.get_text() == "dim"
    fresh = figures.unwrapped_brdf_figure(dim, dim_model, "dim")
    rendered(fresh)
    for old, new in zip(sheet.fig.axes, fresh.axes, strict=True):
        assert [t.get_text() for t in old.get_yticklabels()] == [t.get_text() for t in new.get_yticklabels()]
        np.testing.assert_allclose(old.get_position().bounds, new.get_position().bounds, atol=3.0 / height)


def test_ndf_polar_plot_draws_plus_y_up_and_theta_outwards():
    """A lobe at phi = 90 deg (+y), theta = 30 deg is drawn straight above the plot's centre, a third of
    the 90-degree radius out, like +y on the maps."""
    grid = DirectionGrid(18, 36)
    table = np.zeros(grid.shape)
    table[6, 9] = 1.0                      # theta in [30, 35) deg, phi in [90, 100) deg
    fig = Figure(figsize=(4, 4), dpi=100)
    ax = fig.add_subplot(projection="polar")
    figures.polar_table(ax, figures.peak_normalised(table), 90.0)
    image = rendered(fig)
    yellow = image[..., 0] + image[..., 1] - 2 * image[..., 2]     # viridis' top is yellow
    row, col = np.unravel_index(np.argmax(yellow), yellow.shape)
    (x0, y0), (x1, y1) = ax.transData.transform([(0.0, 0.0), (np.pi / 2, 90.0)])
    centre_row, centre_col = image.shape[0] - y0, x0
    radius = abs(y1 - y0)
    assert row < centre_row                                        # above the centre: +y is up
    assert (centre_row - row) / radius == pytest.approx(32.5 / 90.0, abs=0.05)
    assert abs(col - centre_col) / radius < 0.12


def test_pictures_are_finite_and_hot_pixels_do_not_set_the_scale():
    rgb = np.full((10, 10, 3), 0.5)
    rgb[0, 0] = [np.nan, np.inf, -np.inf]
    rgb[1, 1] = 1e6
    assert figures.display_scale(rgb, percentile=95.0) == pytest.approx(0.5)
    shown = figures.tonemap(rgb, 0.5)
    assert np.isfinite(shown).all() and shown.min() >= 0.0 and shown.max() <= 1.0
    assert shown[5, 5] == pytest.approx([1.0, 1.0, 1.0])
    assert figures.display_scale(np.zeros((4, 4, 3))) == 1.0
    assert np.allclose(srgb_decode(srgb_encode(np.linspace(0, 1, 11))), np.linspace(0, 1, 11))


def test_points_are_picked_on_the_sample_from_the_minus_x_plus_y_corner():
    visible = np.ones((21, 11), bool)
    assert figures.pick_points(visible, [(0.0, 1.0), (1.0, 0.0), (0.5, 0.5)]) == [(0, 0), (20, 10), (10, 5)]
    visible[:, :5] = False                 # the -x half hidden: the nearest visible point instead
    assert figures.pick_points(visible, [(0.0, 1.0), (0.05, 1.0)]) == [(0, 5)]
    assert figures.pick_points(np.zeros((3, 3), bool), [(0.5, 0.5)]) == []
    assert len(figures.ndf_figure([], {"partial": []}).axes) == 0


def test_cluster_map_lists_every_cluster_with_its_point_count():
    labels = np.array([[0, 0, 1], [2, 2, 2], [-1, 1, 1]])
    fig = figures.cluster_map(labels, [(0, 0), (2, 2), (1, 1)], figures.plane_extent(0.03, 0.03), (3, 3))
    bar = fig.axes[-1]
    assert [t.get_text() for t in bar.get_yticklabels()] == ["0 (2 pts)", "1 (3 pts)", "2 (3 pts)"]
    shown = fig.axes[0].images[0].get_array()
    assert shown.mask[2, 0] and shown.mask.sum() == 1          # -1: no cluster, drawn grey


def test_heldout_differences_are_zero_for_a_perfect_prediction():
    truth = np.random.default_rng(0).uniform(0.0, 2.0, (12, 16, 3))
    mask = np.ones((12, 16), bool)
    mask[:, :2] = False
    fig = figures.heldout_figure([{"truth": truth, "ours": truth, "ward": 0.5 * truth, "mask": mask,
                                   "title": "frame 0"}])
    ours_diff, ward_diff = (ax.images[0].get_array() for ax in fig.axes[3:5])
    assert float(ours_diff.max()) == 0.0 and float(ward_diff.max()) > 0.0
    assert ours_diff.mask[:, :2].all()     # off the sample: not drawn
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    assert buffer.getvalue()[:8] == b"\x89PNG\r\n\x1a\n"


def test_relief_figure_shows_the_normals_and_the_lights_factors():
    """A tilted patch in the normal map and the tilt panel; the factors plotted by elevation, held-out lights
    marked; without factors a note that the capture stated its intensities."""
    normals = np.tile([0.0, 0.0, 1.0], (20, 30, 1))
    normals[5:10, 5:10] = [np.sin(0.3), 0.0, np.cos(0.3)]
    mask = np.ones((20, 30), bool)
    factors = {"rgb": [[0.5, 0.5, 0.6], [1.0, 1.0, 1.0], [1.5, 1.4, 1.4]], "fallback": [False, True, False]}
    fig = figures.relief_figure(normals, mask, (0, 30, 0, 20), factors, np.array([10.0, 40.0, 70.0]), "t")
    tilt = fig.axes[1].images[0].get_array()
    assert tilt.max() == pytest.approx(np.degrees(0.3)) and tilt.min() == 0.0
    assert len(fig.axes[2].collections) == 4                  # R, G, B and the held-out light
    fig = figures.relief_figure(normals, mask, (0, 30, 0, 20), None, np.array([10.0]), "t")
    assert "as the capture states them" in fig.axes[2].texts[0].get_text()
