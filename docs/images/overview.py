"""docs/images/overview.png, the README's picture: python docs/images/overview.py results/demo (after make run)."""

import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from facetsynth.io.fileio import read_rgb  # noqa: E402
from facetsynth.app.preview import PreviewSettings, display_encode, exposure_scale, render_preview  # noqa: E402
from facetsynth.models.svbrdf import SVBRDF  # noqa: E402

sample = Path(sys.argv[1] if len(sys.argv) > 1 else "results/demo")
out = Path(__file__).with_suffix(".png")
frames = sorted((sample / "hdr/frames").glob("*.exr"))
picked = (len(frames) // 4, len(frames) // 2)
captured = [read_rgb(frames[q]) for q in picked]
model = SVBRDF.load(sample / "svbrdf")
shape = (model.plane.rows, model.plane.cols, 3)
labels = np.load(sample / "cluster/labels.npy").reshape(shape[:2])
with tempfile.TemporaryDirectory() as scratch:      # render never replaces a file it did not write
    render_preview(sample / "svbrdf", Path(scratch) / "preview.exr", PreviewSettings(theta_deg=45, phi_deg=-30, size=400))
    preview = read_rgb(Path(scratch) / "preview.exr")

panels = [(display_encode(c * exposure_scale(c, c.max(axis=-1) > 0, None)), f"captured frame {q} of {len(frames)}")
          for q, c in zip(picked, captured)]
panels += [(display_encode(model.kd.reshape(shape) / model.kd.max()), "fitted kd (diffuse albedo)"),
           (display_encode(model.ks.reshape(shape) / model.ks.max()), "fitted ks (specular albedo)"),
           (labels, f"{labels.max() + 1} NDF clusters (eq. 18 representatives)"),
           (display_encode(preview * exposure_scale(preview, preview.max(axis=-1) > 0, None)),
            "facetsynth render: a new view and light")]
fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), 3.4))
for ax, (image, title) in zip(axes, panels):
    ax.imshow(image, cmap="tab20" if image.ndim == 2 else None, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.axis("off")
fig.suptitle("facetsynth on the demo sample: captures in, an SVBRDF out, rendered anywhere", fontsize=11)
fig.tight_layout()
fig.savefig(out, dpi=90)
print(out)
