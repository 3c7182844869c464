"""Figures of the Snakemake report (``snakemake --report``; workflow/rules/report.smk).

Small pure functions: arrays in, a matplotlib :class:`~matplotlib.figure.Figure` out (no pyplot, no global
state: the Agg canvas renders it), :func:`save_png` writes it. Nothing here reads the workflow's files; the
rule scripts (workflow/scripts/report_*.py) load, call one function, save.

Conventions shared by every figure:

* radiance and BRDF values are linear; RGB pictures are shown through :func:`tonemap` (divide by a scale,
  clip to [0, 1], sRGB-encode) beside a grey bar that maps the displayed grey back to the linear value;
* non-finite values never reach a picture (:func:`finite`); points off the sample are drawn light grey;
* rectified maps are drawn as seen from above, x to the right and y up, in millimetres (row 0 is the +y
  edge, :class:`facetsynth.geometry.plane.PlaneGrid`);
* NDFs and light directions are drawn on a polar plot of the hemisphere: the angle is the azimuth phi
  (from +x towards +y, +x to the right as on the maps), the radius the elevation theta from the normal.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.colors import BoundaryNorm, FuncNorm, ListedColormap, Normalize, PowerNorm
from matplotlib.figure import Figure

from ..io.colour import srgb_decode, srgb_encode
from ..io.fileio import atomic_dir, atomic_path
from ..stages.common import StageSettings

LUMA = np.array([0.2126, 0.7152, 0.0722])   # Rec. 709 luminance of linear RGB
OFF_SAMPLE = (0.85, 0.85, 0.85)             # grey of points off the sample / without data
DPI = 110


# --- values to pixels ------------------------------------------------------------------------------

def finite(a: np.ndarray) -> np.ndarray:
    """``a`` as float with NaN and +-Inf replaced by 0 (nothing non-finite reaches a picture)."""
    return np.nan_to_num(np.asarray(a, float), nan=0.0, posinf=0.0, neginf=0.0)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB (..., 3)."""
    return finite(rgb) @ LUMA


def display_scale(images: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.5) -> float:
    """A positive linear value shown as white: the ``percentile`` of the largest channel over the (masked)
    pixels of ``images`` (..., 3), so that a few hot pixels do not darken the rest; 1 when all are 0."""
    peak = finite(images).max(axis=-1)
    if mask is not None:
        peak = peak[..., np.asarray(mask, bool)]
    peak = peak[peak > 0]
    s = float(np.percentile(peak, percentile)) if peak.size else 0.0
    return s if np.isfinite(s) and s > 0 else 1.0


def tonemap(rgb: np.ndarray, scale: float) -> np.ndarray:
    """Linear RGB (..., 3) to displayable sRGB in [0, 1]: rgb / scale, clipped, sRGB-encoded."""
    return srgb_encode(finite(rgb) / max(float(scale), 1e-30))


def grey_bar(fig: Figure, axes, scale: float, label: str):
    """A grey colour bar beside ``axes``: the displayed grey (sRGB) against the linear value it shows,
    0 to ``scale`` (what :func:`tonemap` maps to white)."""
    scale = max(float(scale), 1e-30)
    norm = FuncNorm((lambda v: srgb_encode(np.asarray(v) / scale), lambda g: srgb_decode(g) * scale), vmin=0.0, vmax=scale)
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap="gray"), ax=axes, fraction=0.046, pad=0.03)
    bar.set_label(label)
    bar.set_ticks(np.linspace(0.0, scale, 5))
    bar.ax.set_yticklabels([f"{t:.3g}" for t in np.linspace(0.0, scale, 5)])
    return bar


def grey_off(rgb: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Displayable RGB (H, W, 3) with the pixels outside ``mask`` (H, W) set to the off-sample grey."""
    out = np.array(rgb, float)
    if mask is not None:
        out[~np.asarray(mask, bool)] = OFF_SAMPLE
    return out


def plane_extent(width_m: float, height_m: float) -> tuple[float, float, float, float]:
    """imshow extent (left, right, bottom, top) in mm of a rectified map: x right, y up."""
    return (-500.0 * width_m, 500.0 * width_m, -500.0 * height_m, 500.0 * height_m)


def save_png(fig: Figure, path: str | Path, dpi: int = DPI) -> None:
    """Write ``fig`` as a PNG (atomically: a killed job leaves no half picture)."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)


# --- capture ---------------------------------------------------------------------------------------

def mosaic_frames(n_frames: int, count: int = 12) -> np.ndarray:
    """Indices of ``count`` frames evenly spread over a capture of ``n_frames`` (all when fewer)."""
    if n_frames <= 0:
        return np.zeros(0, np.intp)
    return np.unique(np.linspace(0, n_frames - 1, min(count, n_frames)).round().astype(np.intp))


def capture_mosaic(frames: Sequence[np.ndarray], titles: Sequence[str], columns: int = 4,
                   suptitle: str = "") -> Figure:
    """Captured HDR frames (each (H, W, 3), linear radiance) in a grid, all at one display scale (the
    brighter frame is the brighter picture), with one grey bar of radiance."""
    frames = [finite(f) for f in frames]
    n = len(frames)
    columns = max(1, min(columns, n))
    rows = -(-n // columns)
    h, w = frames[0].shape[:2]
    fig = Figure(figsize=(2.6 * columns + 1.2, 2.6 * rows * h / w + 0.8), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False)
    scale = display_scale(np.stack(frames))
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, frame, title in zip(axes.ravel(), frames, titles):
        ax.imshow(tonemap(frame, scale), interpolation="nearest")
        ax.set_title(title, fontsize=8)
    grey_bar(fig, axes, scale, "radiance (linear; white = 99.5th percentile)")
    if suptitle:
        fig.suptitle(suptitle)
    return fig


# --- SVBRDF maps -----------------------------------------------------------------------------------

def rgb_map(rgb: np.ndarray, mask: np.ndarray | None, extent, title: str, label: str) -> Figure:
    """An RGB parameter map (H, W, 3), e.g. kd or ks: the RGB picture (display scale from the data) with
    a grey bar of the channel value, and each channel's own map with a shared viridis scale."""
    rgb = finite(rgb)
    on = np.ones(rgb.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    scale = display_scale(rgb, on, 99.9)
    fig = Figure(figsize=(13.5, 3.6), layout="constrained")
    axes = fig.subplots(1, 4)
    axes[0].imshow(grey_off(tonemap(rgb, scale), on), extent=extent, interpolation="nearest")
    axes[0].set_title(f"{title}: RGB")
    grey_bar(fig, axes[0], scale, label)
    norm = Normalize(0.0, scale)
    cmap = colormaps["viridis"].with_extremes(bad=OFF_SAMPLE)
    for k, (ax, name) in enumerate(zip(axes[1:], "RGB")):
        image = ax.imshow(np.ma.masked_array(rgb[..., k], ~on), extent=extent, cmap=cmap, norm=norm,
                          interpolation="nearest")
        ax.set_title(f"{title}: {name}")
    fig.colorbar(image, ax=axes[1:], fraction=0.03, pad=0.02).set_label(label)
    for ax in axes:
        ax.set_xlabel("x (mm)")
    axes[0].set_ylabel("y (mm)")
    return fig


def scalar_maps(maps: Sequence[tuple[str, np.ndarray, str, str]], mask: np.ndarray | None, extent,
                suptitle: str = "") -> Figure:
    """Scalar maps side by side, each ``(title, values (H, W), colour-bar label, colormap)``, each with its
    own colour bar (range from the sample's points); off-sample points grey. A fifth element, a list of
    names, makes a map categorical: values 0..n-1, one colour and colour-bar entry per name."""
    fig = Figure(figsize=(4.4 * len(maps), 3.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(maps)))
    for ax, (title, values, label, cmap, *categories) in zip(axes, maps):
        values = finite(values)
        on = np.ones(values.shape, bool) if mask is None else np.asarray(mask, bool)
        shown = values[on]
        lo, hi = (float(shown.min()), float(shown.max())) if shown.size else (0.0, 1.0)
        if hi - lo < 1e-9:
            lo, hi = lo - 0.5, hi + 0.5
        names = categories[0] if categories else None
        if names:   # integer categories 0..n-1, one colour each
            cm = ListedColormap(colormaps[cmap](np.linspace(0.15, 0.85, len(names))))
            norm = BoundaryNorm(np.arange(len(names) + 1) - 0.5, len(names))
        else:
            cm, norm = colormaps[cmap], Normalize(lo, hi)
        image = ax.imshow(np.ma.masked_array(values, ~on), extent=extent, interpolation="nearest",
                          cmap=cm.with_extremes(bad=OFF_SAMPLE), norm=norm)
        ax.set_title(title)
        ax.set_xlabel("x (mm)")
        bar = fig.colorbar(image, ax=ax, fraction=0.046, pad=0.03, ticks=np.arange(len(names)) if names else None)
        bar.set_label(label)
        if names:
            bar.ax.set_yticklabels(names)
    axes[0].set_ylabel("y (mm)")
    if suptitle:
        fig.suptitle(suptitle)
    return fig


# --- clusters --------------------------------------------------------------------------------------

def cluster_colours(n: int) -> np.ndarray:
    """``n`` distinct RGB colours (tab10, then tab20, then a sampled hsv)."""
    if n <= 10:
        return np.asarray(colormaps["tab10"].colors)[:n, :3]
    if n <= 20:
        return np.asarray(colormaps["tab20"].colors)[:n, :3]
    return colormaps["hsv"](np.linspace(0.0, 1.0, n, endpoint=False))[:, :3]


def cluster_map(labels: np.ndarray, representatives: Sequence[tuple[int, int]], extent, plane_shape,
                suptitle: str = "") -> Figure:
    """The cluster label of every point (H, W) (-1: no cluster, grey) in a categorical colour map with
    one colour-bar entry per cluster (its point count); each cluster's representative point is a
    black-edged circle of its colour, numbered."""
    labels = np.asarray(labels)
    n = int(labels.max()) + 1 if labels.size and labels.max() >= 0 else 0
    colours = cluster_colours(max(n, 1))
    cmap = ListedColormap(colours).with_extremes(bad=OFF_SAMPLE)
    fig = Figure(figsize=(6.2, 5.0), layout="constrained")
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_less(labels, 0), extent=extent, cmap=cmap,
                      norm=BoundaryNorm(np.arange(max(n, 1) + 1) - 0.5, max(n, 1)), interpolation="nearest")
    rows, cols = plane_shape
    left, right, bottom, top = extent
    for k, (r, c) in enumerate(representatives):
        x = left + (c + 0.5) * (right - left) / cols
        y = top - (r + 0.5) * (top - bottom) / rows
        ax.plot(x, y, "o", ms=11, mfc=colours[k % len(colours)], mec="black", mew=1.5)
        ax.annotate(str(k), (x, y), ha="center", va="center", fontsize=7, fontweight="bold")
    counts = np.bincount(labels[labels >= 0], minlength=n) if n else np.zeros(0, int)
    bar = fig.colorbar(image, ax=ax, ticks=np.arange(max(n, 1)), fraction=0.046, pad=0.03)
    bar.ax.set_yticklabels([f"{k} ({counts[k]} pts)" for k in range(n)] if n else ["none"])
    bar.set_label("cluster (points)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    if suptitle:
        ax.set_title(suptitle)
    return fig


# --- NDFs ------------------------------------------------------------------------------------------

def pick_points(visible: np.ndarray, fractions: Sequence[tuple[float, float]]) -> list[tuple[int, int]]:
    """Grid points (row, col) at the given (x, y) fractions of the sample (0..1 from the -x / -y edge),
    each moved to the nearest visible point; duplicates dropped."""
    visible = np.asarray(visible, bool)
    rows, cols = visible.shape
    rr, cc = np.nonzero(visible)
    out: list[tuple[int, int]] = []
    if rr.size == 0:
        return out
    for fx, fy in fractions:
        r, c = (1.0 - fy) * rows - 0.5, fx * cols - 0.5
        k = int(np.argmin((rr - r) ** 2 + (cc - c) ** 2))
        if (int(rr[k]), int(cc[k])) not in out:
            out.append((int(rr[k]), int(cc[k])))
    return out


def peak_normalised(table: np.ndarray, support: np.ndarray | None = None) -> np.ndarray:
    """An NDF table (T, F) divided by its largest value (over ``support``), non-negative and finite;
    masked where ``support`` is False (no data)."""
    t = np.clip(finite(table), 0.0, None)
    on = np.ones(t.shape, bool) if support is None else np.asarray(support, bool)
    peak = float(t[on].max()) if on.any() else 0.0
    t = t / peak if peak > 0 else t
    return np.ma.masked_array(t, ~on)


def polar_table(ax, table: np.ndarray, theta_max_deg: float = 90.0, norm=None, cmap="viridis"):
    """Draw a hemisphere table (T, F) on the polar grid of :class:`facetsynth.geometry.grid.DirectionGrid` (cell
    (t, p): theta in [t, t+1) * 90 deg / T, phi in [p, p+1) * 360 deg / F) on polar axes ``ax``: angle
    phi (0 = +x, to the right, counter-clockwise to +y), radius theta in degrees. Cells are drawn as
    they are (no interpolation); masked cells are grey."""
    n_theta, n_phi = np.shape(table)
    phi_edges = np.linspace(0.0, 2.0 * np.pi, n_phi + 1)
    theta_edges = np.linspace(0.0, 90.0, n_theta + 1)
    cm = colormaps[cmap].with_extremes(bad=OFF_SAMPLE)
    mesh = ax.pcolormesh(phi_edges, theta_edges, table, cmap=cm, norm=norm or Normalize(0.0, 1.0),
                         shading="flat", rasterized=True)
    ax.set_ylim(0.0, theta_max_deg)
    ax.set_yticks([t for t in (15, 30, 45, 60, 75, 90) if t <= theta_max_deg])
    ax.set_yticklabels([f"{t}°" for t in (15, 30, 45, 60, 75, 90) if t <= theta_max_deg], fontsize=6,
                       color="white")
    ax.set_xticks(np.deg2rad([0, 90, 180, 270]))
    ax.set_xticklabels(["+x", "+y", "-x", "-y"], fontsize=7)
    ax.grid(True, color="white", alpha=0.35, lw=0.5)
    return mesh


def ndf_theta_max(tables: Sequence[np.ndarray], fraction: float = 0.05) -> float:
    """An elevation (deg, multiple of 15, at least 30) that holds every cell of the (peak-normalised)
    tables above ``fraction`` of its peak: the lobes fill the plot, the empty horizon is cut."""
    reach = 30.0
    for t in tables:
        t = np.ma.filled(t, 0.0)
        rows = np.nonzero((t >= fraction).any(axis=1))[0]
        if rows.size:
            reach = max(reach, (rows.max() + 1) * 90.0 / t.shape[0])
    return float(min(90.0, 15.0 * np.ceil(reach / 15.0)))


def ndf_figure(points: Sequence[str], columns: dict[str, list[np.ndarray | None]],
               locator: np.ndarray | None = None, locator_extent=None,
               locator_xy: Sequence[tuple[float, float]] = (), suptitle: str = "") -> Figure:
    """Per point (one row each, ``points`` its labels), one polar NDF picture per column: ``columns`` maps a
    column title (e.g. partial, completed, true) to per-point peak-normalised tables (T, F) (masked: no
    data), None where a column has nothing for the point. An optional first column shows ``locator`` (an
    RGB map) with every point marked and numbered at ``locator_xy`` (mm)."""
    names = list(columns)
    n, extra = len(points), int(locator is not None)
    if n == 0:
        fig = Figure(figsize=(6.0, 2.0), layout="constrained")
        fig.text(0.5, 0.5, "no point of the sample is visible: no NDF to draw", ha="center", va="center")
        fig.suptitle(suptitle)
        return fig
    fig = Figure(figsize=(2.9 * (len(names) + extra) + 1.0, 2.8 * n + 0.6), layout="constrained")
    grid = fig.add_gridspec(n, len(names) + extra)
    theta_max = ndf_theta_max([t for col in columns.values() for t in col if t is not None])
    mesh = None
    for i, label in enumerate(points):
        if locator is not None:
            ax = fig.add_subplot(grid[i, 0])
            ax.imshow(locator, extent=locator_extent, interpolation="nearest")
            for j, (x, y) in enumerate(locator_xy):
                ax.plot(x, y, "o", ms=9 if j == i else 5, mfc="white" if j == i else "none", mec="red",
                        mew=1.5)
            ax.set_title(label, fontsize=8)
            ax.tick_params(labelsize=6)
        for j, name in enumerate(names):
            table = columns[name][i]
            ax = fig.add_subplot(grid[i, j + extra], projection="polar")
            if table is None:
                ax.set_axis_off()
                ax.text(0.5, 0.5, f"{name}:\nnone here", transform=ax.transAxes, ha="center", va="center")
                continue
            mesh = polar_table(ax, table, theta_max)
            if i == 0:
                ax.set_title(name, fontsize=10, pad=12)
    if mesh is not None:
        fig.colorbar(mesh, ax=fig.axes, fraction=0.02, pad=0.01, shrink=0.6).set_label(
            "D / max D (grey: no data)")
    if suptitle:
        fig.suptitle(suptitle)
    return fig


# --- held-out views --------------------------------------------------------------------------------

def heldout_figure(rows: Sequence[dict], suptitle: str = "") -> Figure:
    """Held-out frames, one row each: ``rows`` of dicts with ``truth``, ``ours``, optional ``ward``
    (H, W, 3 linear radiance), ``mask`` (H, W: the sample's pixels), ``title``. Truth and predictions
    share the row's display scale (the truth's peak on the sample) and a grey bar; the differences
    |prediction - truth| (luminance, sample pixels only) share one square-root magma scale and colour bar
    per row."""
    n = len(rows)
    has_ward = any(r.get("ward") is not None for r in rows)
    cols = 5 if has_ward else 3
    h, w = np.shape(rows[0]["truth"])[:2]
    fig = Figure(figsize=(3.0 * cols + 1.6, 3.0 * n * h / w + 0.8), layout="constrained")
    axes = fig.subplots(n, cols, squeeze=False)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    for i, row in enumerate(rows):
        mask = np.asarray(row["mask"], bool)
        truth = finite(row["truth"])
        scale = max(float(truth[mask].max()) if mask.any() else 0.0, 1e-12)
        preds = [("truth", truth), ("ours", finite(row["ours"]))]
        if has_ward:
            preds.append(("Ward", finite(row["ward"])) if row.get("ward") is not None else ("Ward", None))
        for j, (name, image) in enumerate(preds):
            if image is None:
                axes[i, j].set_axis_off()
                continue
            axes[i, j].imshow(tonemap(image, scale), interpolation="nearest")
            axes[i, j].set_title(name if i == 0 else "", fontsize=10)
        axes[i, 0].set_ylabel(row.get("title", ""), fontsize=8)
        grey_bar(fig, axes[i, len(preds) - 1], scale, "radiance")
        diffs = [(f"|{name} - truth|", luminance(np.abs(image - truth)))
                 for name, image in preds[1:] if image is not None]
        top = max(float(d[mask].max()) if mask.any() else 0.0 for _, d in diffs)
        norm = PowerNorm(0.5, 0.0, max(top, 1e-12))    # square-root scale: the smaller error stays visible
        cmap = colormaps["magma"].with_extremes(bad=OFF_SAMPLE)
        for j, (name, d) in enumerate(diffs):
            ax = axes[i, len(preds) + j]
            image = ax.imshow(np.ma.masked_array(d, ~mask), cmap=cmap, norm=norm, interpolation="nearest")
            ax.set_title(name if i == 0 else "", fontsize=10)
        fig.colorbar(image, ax=axes[i, len(preds) + len(diffs) - 1], fraction=0.046, pad=0.03).set_label(
            "|difference| (luminance)")
    if suptitle:
        fig.suptitle(suptitle)
    return fig


# --- stencil fits (paper 000 Fig. 9) ---------------------------------------------------------------

UTIA_THETA_DEG = (0, 15, 30, 45, 60, 75)


class UnwrappedBRDFFigure:
    """Paper 000 Fig. 9: a BRDF and its model as unwrapped images (each (288, 288, 3), the UTIA layout of
    :func:`facetsynth.stencil.grid.unwrap`: row = 48 theta_i index + phi_i index, column = 48 theta_v index
    + phi_v index, linear 1/sr), side by side at one display scale (the data's), and their difference
    ``difference_gain`` x |model - data| (luminance) on a magma scale in the same units.

    The axes, ticks and colour bars are made once; :meth:`show` puts one BRDF and its model in them. A sample
    has a picture per material cluster (up to 64): made afresh each, 0.8 s went to building the same figure.
    """

    def __init__(self, difference_gain: float = 3.0):
        self.gain = difference_gain
        self.fig = fig = Figure(figsize=(14.0, 4.6), layout="constrained")
        axes = fig.subplots(1, 3)
        blank = np.zeros((288, 288, 3))
        self.data, self.model = (ax.imshow(blank, interpolation="nearest") for ax in axes[:2])
        self.diff = axes[2].imshow(blank[..., 0], cmap="magma", norm=Normalize(0.0, 1.0), interpolation="nearest")
        axes[0].set_title("data (fitted SVBRDF at the representative)", fontsize=9)
        axes[1].set_title("stencil model", fontsize=9)
        self.grey = grey_bar(fig, axes[1], 1.0, "BRDF (1/sr)")       # ticks in units of the scale: see show
        axes[2].set_title(f"{difference_gain:g} x |model - data| (luminance)", fontsize=9)
        fig.colorbar(self.diff, ax=axes[2], fraction=0.046, pad=0.03).set_label(
            f"{difference_gain:g} x |difference| (1/sr)")
        ticks = 48 * np.arange(6) + 23.5
        for ax in axes:
            ax.set_xticks(ticks, [f"{t}°" for t in UTIA_THETA_DEG], fontsize=7)
            ax.set_yticks(ticks, [f"{t}°" for t in UTIA_THETA_DEG], fontsize=7)
            ax.set_xticks(48 * np.arange(1, 6) - 0.5, minor=True)
            ax.set_yticks(48 * np.arange(1, 6) - 0.5, minor=True)
            ax.grid(which="minor", color="white", alpha=0.4, lw=0.5)
            ax.tick_params(which="minor", length=0)
            ax.set_xlabel("view: theta_v block, phi_v 0..352.5° within")
        axes[0].set_ylabel("light: theta_i block, phi_i 0..352.5° within")
        self.title = fig.suptitle("")

    def show(self, data: np.ndarray, model: np.ndarray, title: str = "") -> Figure:
        """The figure, showing ``data`` and ``model`` (each (288, 288, 3), linear) under ``title``."""
        data, model = finite(data), finite(model)
        scale = display_scale(data, percentile=99.0)
        self.data.set_data(tonemap(data, scale))
        self.model.set_data(tonemap(model, scale))
        self.diff.set_data(self.gain * luminance(np.abs(model - data)))
        self.diff.set_clim(0.0, scale)
        self.grey.ax.set_yticklabels([f"{t:.3g}" for t in np.linspace(0.0, scale, 5)])   # grey_bar's, at scale
        self.title.set_text(title)
        return self.fig


def unwrapped_brdf_figure(data: np.ndarray, model: np.ndarray, title: str = "", difference_gain: float = 3.0
                          ) -> Figure:
    """One :class:`UnwrappedBRDFFigure` of ``data`` and its ``model``."""
    return UnwrappedBRDFFigure(difference_gain).show(data, model, title)


# --- pages: a stage's files to a written figure (called by workflow/scripts/report_*.py) ------------

NDF_POINTS = ((0.5, 0.5), (0.25, 0.5), (0.5, 0.25), (0.3, 0.7))   # (x, y) fractions of the sample


class FigureSettings(StageSettings):
    """The report figures' choices (rule params, workflow/rules/report.smk)."""

    mosaic_frames: int = 12                                  # HDR frames in the capture mosaic
    heldout_frames: int = 2                                  # brightest frames per held-out view
    ndf_points: tuple[tuple[float, float], ...] = NDF_POINTS   # where NDFs are drawn: (x, y) fractions


def _plane_and_visible(geometry: str | Path):
    from ..stages.common import RectifiedCapture
    capture = RectifiedCapture.load(geometry)
    grid = capture.grid
    return capture, grid, capture.visible.reshape(grid.rows, grid.cols), plane_extent(grid.width, grid.height)


def write_capture(manifest: str | Path, out: str | Path, sample: str,
                  settings: FigureSettings = FigureSettings()) -> None:
    """A mosaic of ``count`` HDR frames evenly spread over the capture (stage ``hdr``)."""
    from ..io.fileio import read_rgb
    from ..capture.manifest import load
    m = load(manifest)
    picks = mosaic_frames(len(m["frames"]), settings.mosaic_frames)
    frames = [read_rgb(m["frames"][q]["exposures"][0]["file"]) for q in picks]
    titles = []
    for q in picks:
        light = m["frames"][q]["light"]
        if "direction" in light:
            x, y, z = light["direction"]
            titles.append(f"frame {q}: light towards ({x:.2f}, {y:.2f}, {z:.2f})")
        else:
            x, y, z = (1000.0 * v for v in light["position"])
            titles.append(f"frame {q}: light ({x:.0f}, {y:.0f}, {z:.0f}) mm")
    save_png(capture_mosaic(frames, titles, suptitle=f"{sample}: HDR frames ({len(picks)} of "
                                                    f"{len(m['frames'])}, one display scale)"), out)


def write_maps(svbrdf: str | Path, geometry: str | Path, kd_out: str | Path, ks_out: str | Path,
               eta_out: str | Path, sample: str) -> None:
    """The kd, ks and eta maps of the fitted SVBRDF (stage ``params``)."""
    from ..models.svbrdf import SVBRDF
    model = SVBRDF.load(svbrdf)
    _, grid, visible, extent = _plane_and_visible(geometry)
    shape = (grid.rows, grid.cols)
    save_png(rgb_map(model.kd.reshape(shape + (3,)), visible, extent, f"{sample} kd", "diffuse albedo kd"), kd_out)
    save_png(rgb_map(model.ks.reshape(shape + (3,)), visible, extent, f"{sample} ks", "specular albedo ks"), ks_out)
    maps = [("eta", model.eta.reshape(shape), "relative refraction index eta", "viridis")]
    if model.eta_fitted is not None:
        maps.append(("where grazing data fitted eta", model.eta_fitted.reshape(shape).astype(float), "",
                     "cividis", ["default eta", "fitted"]))
    if model.eta_lo is not None and model.eta_hi is not None:
        maps.append(("95 % interval width", (model.eta_hi - model.eta_lo).reshape(shape),
                     "eta_hi - eta_lo", "magma"))
    save_png(scalar_maps(maps, visible, extent, f"{sample}: Fresnel eta"), eta_out)


def write_ndf(svbrdf: str | Path, partial: str | Path, partial_grid: str | Path, geometry: str | Path,
              out: str | Path, sample: str, settings: FigureSettings = FigureSettings()) -> None:
    """Partial (stage ``partial_ndf``), completed (the SVBRDF's eq. 18 mixture) and, for a virtual
    sample, true NDFs at a few points of the sample."""
    from ..evaluation.truth import truth_of
    from ..io.fileio import read_json
    from ..geometry.grid import DirectionGrid
    from ..models.svbrdf import SVBRDF
    from ..io.tables import SupportTable
    model = SVBRDF.load(svbrdf)
    capture, grid, visible, extent = _plane_and_visible(geometry)
    points = pick_points(visible, settings.ndf_points)
    index = np.array([r * grid.cols + c for r, c in points], np.intp)
    table = SupportTable(partial)
    if table.shape[1:] != DirectionGrid.from_dict(read_json(partial_grid)).shape:
        raise ValueError(f"{partial}: table {table.shape[1:]} is not on the grid of {partial_grid}")
    support = table.support(index)
    partial_d = table.rows("ndf")[index]
    columns: dict[str, list] = {
        "partial (measured)": [peak_normalised(d, s) for d, s in zip(partial_d, support)],
        "completed (SVBRDF)": [peak_normalised(d) for d in model.point_ndf(index)]}
    truth = truth_of(capture)
    if truth is not None:
        maps = truth.take(index)
        d = maps.take((slice(None), None)).ndf(model.grid.directions.reshape(1, -1, 3))
        d = d.reshape((len(index),) + model.grid.shape)
        analytic = np.asarray(maps.analytic, bool).reshape(-1)
        columns["true"] = [peak_normalised(t) if ok and np.any(t > 0) else None for t, ok in zip(d, analytic)]
    xy = [(1000.0 * x, 1000.0 * y) for x, y in grid.cell_centres()[tuple(np.array(points).T)]]
    labels = [f"point {k}: ({round(x):d}, {round(y):d}) mm" for k, (x, y) in enumerate(xy)]
    locator = grey_off(tonemap(model.kd.reshape(grid.rows, grid.cols, 3),
                               display_scale(model.kd.reshape(grid.rows, grid.cols, 3), visible, 99.9)), visible)
    save_png(ndf_figure(labels, columns, locator, extent, xy, f"{sample}: NDFs, each divided by its peak"), out)


def write_clusters(labels: str | Path, representatives: str | Path, geometry: str | Path, out: str | Path,
                   sample: str) -> None:
    """The cluster map of stage ``cluster`` with the representative points."""
    from ..io.fileio import read_npy
    _, grid, visible, extent = _plane_and_visible(geometry)
    lab = np.asarray(read_npy(labels)).reshape(grid.rows, grid.cols)
    lab = np.where(visible, lab, -1)
    reps = [divmod(int(p), grid.cols) for p in np.asarray(read_npy(representatives)).ravel()]
    save_png(cluster_map(lab, reps, extent, (grid.rows, grid.cols),
                         f"{sample}: {int(lab.max()) + 1} material clusters"), out)


def write_heldout(view: str, heldout: str | Path, predictions: str | Path, svbrdf: str | Path,
                  metrics: str | Path, out: str | Path, sample: str,
                  settings: FigureSettings = FigureSettings()) -> None:
    """The ``settings.heldout_frames`` brightest frames of a held-out view (stage ``validate``): truth, our
    prediction, Ward's, and their differences."""
    from ..capture import manifest
    from ..io.fileio import read_json, read_rgb
    from .predict import FrameRenderer, load_model
    m = manifest.load(Path(heldout) / "manifest.json", check_files=False)
    mask = FrameRenderer(load_model(svbrdf), manifest.camera(m)).sample_mask
    truth = [read_rgb(f["truth"]["radiance"]) for f in m["frames"]]
    brightest = np.argsort([float(finite(t).sum()) for t in truth])[::-1][:settings.heldout_frames]
    preds = {}
    for name in ("ours", "ward"):
        folder = Path(predictions) / name
        if (folder / "manifest.json").is_file():
            p = manifest.load(folder / "manifest.json", check_files=False)
            preds[name] = {q: p["frames"][q]["exposures"][0]["file"] for q in brightest}
    record = read_json(metrics).get("views", {}).get(view, {})
    rows = [{"truth": truth[q], "ours": read_rgb(preds["ours"][q]),
             "ward": read_rgb(preds["ward"][q]) if "ward" in preds else None, "mask": mask,
             "title": f"frame {q}"} for q in brightest]
    scores = f"rel. L2 ours {_num(record.get('heldout_rel_l2'))}, Ward {_num(record.get('baseline_ward_rel_l2'))}"
    save_png(heldout_figure(rows, f"{sample}, held-out view {view} ({scores}; the view's {len(m['frames'])} "
                                  "frames)"), out)


def write_stencils(svbrdf: str | Path, models: str | Path, out_dir: str | Path, sample: str) -> None:
    """One paper 000 Fig. 9 picture per material cluster (stage ``stencil_fit``): the fitted SVBRDF at the
    cluster's representative on the UTIA grid beside its stencil model, unwrapped, and their difference."""
    from ..io.fileio import read_json
    from ..stencil import evaluate_utia, model_from_json
    from ..stencil.grid import sample_utia, unwrap
    from ..models.svbrdf import SVBRDF
    model = SVBRDF.load(svbrdf)
    record = read_json(Path(models) / "stencil.json")
    sheet = UnwrappedBRDFFigure()
    with atomic_dir(out_dir) as tmp:
        for entry in record["clusters"]:
            point = int(entry["representative"])
            data = sample_utia(lambda wi, wo: model.eval_index(np.full(len(wi), point, np.intp), wi, wo))
            fitted = evaluate_utia(model_from_json(entry["stencil"]))
            s = entry["stencil"].get("scores", {})
            modes = entry["stencil"].get("n_modes", len(entry["stencil"].get("modes", [])))
            title = (f"{sample}, cluster {entry['cluster']} ({entry['points']} points, representative {point}): "
                     f"{modes} anisotropy mode(s); dE {_num(s.get('delta_e'))} / RMSE {_num(s.get('rmse'))} / "
                     f"PSNR {_num(s.get('psnr_db'))} dB / SSIM {_num(s.get('ssim'))}")
            name = f"cluster_{int(entry['cluster']):03d}.png"
            save_png(sheet.show(unwrap(data), unwrap(fitted), title), Path(tmp) / name, dpi=80)   # 288-pixel images
            # drawn at 1.2 screen pixels per cell


def _num(v) -> str:
    return "n/a" if v is None else f"{float(v):.3g}"


def relief_figure(normals: np.ndarray, mask: np.ndarray, extent, factors: dict | None, elevations: np.ndarray,
                  title: str) -> Figure:
    """The shading normals (H, W, 3) as a normal map, RGB = (n + 1) / 2 (flat: (0.5, 0.5, 1)), their tilt from
    the plane, and the lights' estimated intensity factors (separate's ``light_factors``, or None: as the
    capture stated them) against each light's elevation (deg)."""
    fig = Figure(figsize=(13.5, 3.6), layout="constrained")
    axes = fig.subplots(1, 3)
    axes[0].imshow(grey_off(np.clip((normals + 1.0) / 2.0, 0.0, 1.0), mask), extent=extent, interpolation="nearest")
    axes[0].set_title(f"{title}: shading normals, (n + 1) / 2")
    tilt = np.degrees(np.arccos(np.clip(normals[..., 2], -1.0, 1.0)))
    image = axes[1].imshow(np.ma.masked_array(tilt, ~mask), extent=extent, interpolation="nearest",
                           cmap=colormaps["magma"].with_extremes(bad=OFF_SAMPLE), vmin=0.0,
                           vmax=max(5.0, float(np.percentile(tilt[mask], 99))) if mask.any() else 5.0)
    fig.colorbar(image, ax=axes[1], fraction=0.05).set_label("tilt from the plane (deg)")
    axes[1].set_title("tilt")
    for ax in axes[:2]:
        ax.set_xlabel("x (mm)")
    axes[0].set_ylabel("y (mm)")
    ax = axes[2]
    if factors is None:
        ax.text(0.5, 0.5, "light intensities as the capture states them", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_axis_off()
    else:
        rgb, nominal = np.asarray(factors["rgb"], float), np.asarray(factors["fallback"], bool)
        for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.scatter(elevations[~nominal], rgb[~nominal, k], s=12, color=colour, alpha=0.7)
        ax.scatter(elevations[nominal], rgb[nominal].mean(axis=1), s=40, marker="x", color="black",
                   label="held out: from its neighbours")
        ax.axhline(1.0, color="grey", lw=0.8)
        ax.set_xlabel("light elevation (deg)")
        ax.set_ylabel("intensity factor (R, G, B)")
        ax.set_title("lights' intensities, estimated from the photos")
        if nominal.any():
            ax.legend(loc="best", fontsize=8)
    return fig


def write_relief(geometry: str | Path, separate_metrics: str | Path, out: str | Path, sample: str) -> None:
    """The shading normals and the lights' estimated intensities (stage ``separate``)."""
    from ..io.fileio import read_json
    capture, grid, visible, extent = _plane_and_visible(geometry)
    normals = np.tile([0.0, 0.0, 1.0], (capture.n_points, 1)) if capture.normals is None else capture.normals
    d = capture.lights[:, :3]            # towards each light from the sample's centre (the origin), either kind
    elevations = np.degrees(np.arcsin(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0)))
    save_png(relief_figure(normals.reshape(grid.rows, grid.cols, 3), visible, extent,
                           read_json(separate_metrics).get("light_factors"), elevations, sample), out)
