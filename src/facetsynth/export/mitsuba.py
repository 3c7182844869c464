"""Exact export of a fitted SVBRDF to Mitsuba 3 (``facetsynth export mitsuba MODEL OUT``, issue 17 item 2).

The exported folder is self-contained (numpy and Mitsuba 3 only, no facetsynth):

    model.npz           the model's tables: kd, ks, eta per point, the representative NDFs and their eq. 5
                        projected areas on their polar grids, the eq. 18 neighbours and weights, the per-point
                        rotation and shading normal (when the model has them), the plane grid and the
                        direction grids
    facetsynth_bsdf.py  the BSDF plugin (:mod:`facetsynth.export.mitsuba_bsdf`): a registered Python
                        ``mi.BSDF`` ("facetsynth_svbrdf") that evaluates rho exactly as
                        :meth:`facetsynth.models.svbrdf.SVBRDF.eval` and importance-samples it; with shading
                        normals it turns Mitsuba's directions (the quad's frame, the sample plane's) into
                        each point's shading frame itself (facetsynth.fit.normals' R(x); its docstring says
                        why not Mitsuba's ``normalmap`` BSDF), so the scene is the same with or without them
    scene.xml           Mitsuba 3 scene: the sample as a ``rectangle`` of the model's width x height on z = 0
                        (uv: u = x/W + 1/2, v = y/H + 1/2; shading frame s = +x, t = +y, n = +z: the sample
                        plane's), a perspective sensor, a point light, the ``direct`` integrator, a box
                        filter and a float32 RGB ``hdrfilm`` (facetsynth.truth.mitsuba_capture's conventions);
                        camera, light, size and samples are ``$`` parameters with defaults
    render.py           renders a view (camera theta, phi, distance; or a capture manifest's camera and
                        frame light) with a point light and writes an EXR (:mod:`.mitsuba_render`)
    export.json         what was exported, from where, and how to use it

Only the ``scalar_rgb`` variant runs the Python plugin (one Python call per shading point: about 4.5 s
for the demo's 240 x 160 held-out view at 4 spp on one core, tests/export/test_export_mitsuba.py).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from ..io.errors import InputError
from ..io.fileio import atomic_path, write_json
from ..truth.mitsuba_capture import VARIANT
from ..io.outputs import output_folder
from ..models.svbrdf import SVBRDF
from . import fitted_svbrdf, mitsuba_bsdf, mitsuba_render

COMMAND = "export mitsuba"
PLUGIN_FILE = "facetsynth_bsdf.py"
FILES = ("model.npz", PLUGIN_FILE, "scene.xml", "render.py", "export.json")
DEFAULT_VIEW = {"theta": 30.0, "phi": 0.0, "distance": 0.3, "fov": 25.0, "width": 480, "height": 320}


def model_arrays(model: SVBRDF) -> dict[str, np.ndarray]:
    """The arrays of ``model.npz``: everything :class:`~facetsynth.export.mitsuba_bsdf.TabulatedSVBRDF` reads,
    in the dtypes the loaded model evaluates with (so the plugin's float64 copies equal SVBRDF's)."""
    p = model.n_points
    arrays = {
        "version": np.array(mitsuba_bsdf.FORMAT_VERSION, np.int64),
        "size": np.array([model.plane.width, model.plane.height], np.float64),
        "plane_shape": np.array([model.plane.rows, model.plane.cols], np.int64),
        "grid": np.array([model.grid.n_theta, model.grid.n_phi], np.int64),
        "shadowing_grid": np.array([model.shadowing_grid.n_theta, model.shadowing_grid.n_phi], np.int64),
        "kd": np.asarray(model.kd, np.float64).reshape(p, 3),
        "ks": np.asarray(model.ks, np.float64).reshape(p, 3),
        "eta": np.asarray(model.eta, np.float64).reshape(p),
        "ndf": np.asarray(model.ndf),
        "projected_area": np.asarray(model.area),
        "neighbours": np.asarray(model.neighbours).astype(np.int32),
        "weights": np.asarray(model.weights),
    }
    if model.rotation is not None:
        arrays["rotation"] = np.asarray(model.rotation, np.float64).reshape(p)
    if getattr(model, "normal", None) is not None:
        arrays["normal"] = np.asarray(model.normal, np.float64).reshape(p, 3)
    if model.representatives is not None:
        arrays["representatives"] = np.asarray(model.representatives, np.int64)
    return arrays


def scene_xml(width: float, height: float, model_file: str = "model.npz") -> str:
    """The Mitsuba 3 XML scene of a width x height (metres) sample; ``$`` parameters as render.py sets them."""
    view = DEFAULT_VIEW
    sensor = mitsuba_render.view_camera(view["theta"], view["phi"], view["distance"], view["fov"],
                                        view["width"], view["height"])
    params = mitsuba_render.scene_parameters(sensor, (0.0, 0.0, 0.3), (0.1, 0.1, 0.1))
    defaults = "\n".join(f'    <default name="{k}" value="{v}"/>' for k, v in params.items())
    return f"""<?xml version="1.0" encoding="utf-8"?>
<!-- A fitted facetsynth SVBRDF on its sample, for Mitsuba 3 (variant scalar_rgb).
     Register the BSDF plugin before loading:
         import mitsuba as mi; mi.set_variant("scalar_rgb")
         import facetsynth_bsdf; facetsynth_bsdf.register()
         scene = mi.load_file("scene.xml", spp="16", light_position="0, 0, 0.3")
     or run render.py. Units: metres. The sample is z = 0, normal +z; its uv (u = x/W + 1/2, v = y/H + 1/2)
     selects the model's point, its shading frame (s = +x, t = +y, n = +z) is the sample plane's (the
     plugin turns it to the point's shading normal itself when the model has them).
     to_world: the camera-to-world matrix, 16 numbers row by row (Mitsuba camera: x left, y up, z forward);
     ppx, ppy: principal point offsets (film fractions); light_intensity: radiant intensity (W/sr). -->
<scene version="3.0.0">
{defaults}

    <integrator type="direct">
        <integer name="emitter_samples" value="1"/>
        <integer name="bsdf_samples" value="$bsdf_samples"/>
    </integrator>

    <sensor type="perspective">
        <string name="fov_axis" value="x"/>
        <float name="fov" value="$fov"/>
        <float name="principal_point_offset_x" value="$ppx"/>
        <float name="principal_point_offset_y" value="$ppy"/>
        <float name="near_clip" value="0.001"/>
        <float name="far_clip" value="1000"/>
        <transform name="to_world">
            <matrix value="$to_world"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
            <integer name="seed" value="$seed"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$width"/>
            <integer name="height" value="$height"/>
            <string name="pixel_format" value="rgb"/>
            <string name="component_format" value="float32"/>
            <rfilter type="box"/>
        </film>
    </sensor>

    <shape type="rectangle" id="sample">
        <transform name="to_world">
            <scale x="{width / 2!r}" y="{height / 2!r}" z="1"/>
        </transform>
        <bsdf type="{mitsuba_bsdf.PLUGIN_NAME}" id="svbrdf">
            <string name="filename" value="{model_file}"/>
        </bsdf>
    </shape>

    <emitter type="point" id="light">
        <point name="position" value="$light_position"/>
        <rgb name="intensity" value="$light_intensity"/>
    </emitter>
</scene>
"""


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path, suffix=path.suffix) as tmp:
        tmp.write_text(text)


def export_mitsuba(model_dir: str | Path, out_dir: str | Path, *, force: bool = False) -> dict[str, Any]:
    """Write the Mitsuba 3 export of the fitted SVBRDF in ``model_dir`` into ``out_dir`` (module docstring).

    The output folder follows :func:`facetsynth.io.outputs.output_folder` (never the model folder nor inside it; a
    non-empty folder not made by this command only with ``force``; one writer at a time); the files are
    published together when all are written, export.json last.
    Returns a summary: ``files`` (the paths written), the plane grid, representatives, plugin and variant.
    """
    model_dir = Path(model_dir)
    model = fitted_svbrdf(model_dir, "Mitsuba")
    arrays = model_arrays(model)
    try:
        mitsuba_bsdf.TabulatedSVBRDF(arrays)      # the plugin reads what is written (raises on a mismatch)
    except ValueError as exc:
        raise InputError(model_dir, f"the plugin cannot read this model ({str(exc):.200})") from None
    with output_folder(out_dir, COMMAND, input_dirs=[model_dir], writes=FILES, force=force) as stage:
        with atomic_path(stage / "model.npz", suffix=".npz") as tmp:
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            tmp.write_bytes(buffer.getvalue())
        _write_text(stage / PLUGIN_FILE, Path(mitsuba_bsdf.__file__).read_text())
        _write_text(stage / "scene.xml", scene_xml(model.plane.width, model.plane.height))
        _write_text(stage / "render.py", Path(mitsuba_render.__file__).read_text())
        write_json(stage / "export.json", _summary(model, model_dir))
    out = Path(out_dir)
    return dict(_summary(model, model_dir), out=str(out), files=[str(out / name) for name in FILES],
                next=[f"cd {out} && python render.py --theta 30 --phi 0 --distance 0.3 --out view.exr "
                      "(Mitsuba 3, scalar_rgb)"])


def _summary(model: SVBRDF, model_dir: Path) -> dict[str, Any]:
    """export.json: what was exported, from where, and how to use it."""
    return {
        "format": "mitsuba3",
        "plugin": mitsuba_bsdf.PLUGIN_NAME,
        "variant": VARIANT,
        "model": str(model_dir.resolve()),
        "plane_grid": {"rows": model.plane.rows, "cols": model.plane.cols, "width": model.plane.width,
                       "height": model.plane.height},
        "grid": model.grid.to_dict(),
        "shadowing_grid": model.shadowing_grid.to_dict(),
        "representatives": int(model.ndf.shape[0]),
        "neighbours": int(model.neighbours.shape[1]),
        "rotation": model.rotation is not None,
        "normal": getattr(model, "normal", None) is not None,
        "model_format_version": mitsuba_bsdf.FORMAT_VERSION,
        "usage": "python render.py --theta 30 --phi 0 --distance 0.3 --out view.exr; "
                 "python render.py --manifest CAPTURE/manifest.json --frame Q --out frame.exr",
        "files": list(FILES),
    }
