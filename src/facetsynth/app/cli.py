"""The ``facetsynth`` command: what users do outside the workflow."""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import signal
import sys
from pathlib import Path

from ..io.errors import InputError
from ..rig.protocol import RigError


def _check(args: argparse.Namespace) -> None:
    """Validate a capture as the pipeline reads it: a summary on stdout, each warning on stderr."""
    from ..stages.capture import inspect_capture
    m, warnings = inspect_capture(args.capture)
    exposures = sum(len(f["exposures"]) for f in m["frames"])
    clipping = "never clipped" if m["saturation"] is None else f"saturation {m['saturation']:g}"
    print(f"{args.capture}: valid capture, {len(m['frames'])} frames, {exposures} exposure files, "
          f"camera {m['camera']['width']}x{m['camera']['height']}, {clipping}, {len(warnings)} warning(s)")
    for warning in warnings:
        print(f"facetsynth check: warning: {args.capture}: {warning}", file=sys.stderr)


def _rig_check(args: argparse.Namespace) -> None:
    """Controller and camera found, the firmware's identity, a test move and a flash of every LED."""
    from ..rig.session import RigDescription, check
    for line in check(RigDescription.load(args.rig), port=args.port):
        print(line)


def _rig_capture(args: argparse.Namespace) -> None:
    """A capture outside the workflow, for a quick look (the workflow's ``rig`` source runs the same code)."""
    from ..rig.session import RigDescription, capture
    manifest = capture(RigDescription.load(args.rig), args.out_dir, port=args.port)
    print(f"{args.out_dir}: {len(manifest['frames'])} frames of {len(manifest['frames'][0]['exposures'])} "
          f"exposure(s); check it with: facetsynth check {args.out_dir}")


def _predict(args: argparse.Namespace) -> None:
    from .predict import predict
    out = predict(args.model_dir, args.manifest, args.out_dir, supersample=args.supersample, force=args.force)
    print(f"{args.out_dir}: {len(out['frames'])} predicted HDR frame(s) and manifest.json "
          f"(camera {out['camera']['width']}x{out['camera']['height']})")


def _inspect(args: argparse.Namespace) -> None:
    """What is done for a sample, its key figures and its warnings, in a few lines."""
    from .summary import summarise
    for line in summarise(args.sample_dir):
        print(line)


def _render(args: argparse.Namespace) -> None:
    """One tone-mapped view of a fitted model under one point light."""
    from .preview import PreviewSettings, render_preview
    settings = PreviewSettings(theta_deg=args.view[0], phi_deg=args.view[1],
                               light=None if args.light is None else tuple(args.light),
                               intensity=args.intensity, size=args.size, exposure_ev=args.exposure)
    done = render_preview(args.model_dir, args.output, settings, force=args.force)
    light = ", ".join(f"{v:.3f}" for v in done["light"])
    print(f"{done['file']}: {done['width']}x{done['height']}, {done['sample_pixels']} pixels see the sample, "
          f"light at ({light}) m, exposure x{done['exposure_scale']:.3g}")


def _export(args: argparse.Namespace) -> None:
    """A fitted SVBRDF folder as a renderer's scene and material (exact: Mitsuba 3; portable: glTF 2.0)."""
    if args.format == "mitsuba":
        from ..export.mitsuba import export_mitsuba
        done = export_mitsuba(args.model_dir, args.out_dir, force=args.force)
    else:
        from ..export.gltf import export_gltf
        done = export_gltf(args.model_dir, args.out_dir, force=args.force)
    print(f"{args.out_dir}: {args.format} export of {args.model_dir}, {len(done['files'])} file(s)")
    for line in done.get("next", []):
        print(f"  {line}")


STENCIL_OUTPUTS = ("stencil.json", "stencil.brdf")


def _write_stencil_outputs(args: argparse.Namespace, model, scores: dict | None, source: str) -> dict:
    """Print or write the model's JSON parameters and its BRDF Explorer shader.

    ``source`` is the input file the model came from: ``--out`` may hold it
    (with ``--force``, the folder not being empty) but never replace it.
    """
    from ..io.fileio import atomic_path
    from ..io.outputs import output_folder
    from ..stencil import model_to_json, to_brdf_explorer
    params = model_to_json(model, scores)
    if args.out:
        with output_folder(args.out, args.command, input_files=[source], writes=STENCIL_OUTPUTS,
                           force=args.force) as stage:
            for name, text in zip(STENCIL_OUTPUTS, (json.dumps(params, indent=2), to_brdf_explorer(model))):
                with atomic_path(stage / name) as tmp:
                    tmp.write_text(text + "\n")
    if args.json:
        print(json.dumps(params, indent=2))
    return params


def _stencil_fit(args: argparse.Namespace) -> None:
    from ..stencil import fit_file
    model, scores = fit_file(args.brdf)
    params = _write_stencil_outputs(args, model, scores, args.brdf)
    if not args.json:
        axes = ", ".join(f"{m['phi_a_deg']:.1f}" for m in params["modes"]) or "none"
        s = params["scores"]
        print(f"{args.brdf}: {params['n_modes']} anisotropy mode(s), phi_a (deg): {axes}; "
              f"Delta E {s['delta_e']:.2f}, RMSE {s['rmse']:.4f}, PSNR {s['psnr_db']:.1f} dB, "
              f"SSIM {s['ssim']:.3f}, fit {1000 * s['fit_seconds']:.0f} ms")


def _stencil_edit(args: argparse.Namespace) -> None:
    """Paper 000 sec. 5.1 / Fig. 16 edits: every axis shift, then every width, then every colour swap.

    The three act on different parameters, so their order does not change the
    result; repeated edits of one kind apply in the order given. The argument
    values were checked by argparse; a mode index beyond the model is an
    InputError naming the parameter file.
    """
    import numpy as np

    from ..io.fileio import read_json
    from ..stencil import edit, model_from_json
    params = Path(args.params)
    if params.is_dir():
        raise InputError(params, "is a folder; expected the stencil.json written by stencil-fit")
    model = model_from_json(read_json(params), params)
    try:
        for mode, degrees in args.shift_phi or []:
            model = edit.shift_phi_a(model, mode, np.deg2rad(degrees))
        for mode, w in args.width or []:
            model = edit.set_width(model, mode, w)
        for i, j in args.swap_colours or []:
            model = edit.swap_mode_colours(model, i, j)
    except IndexError as exc:
        raise InputError(params, str(exc)) from None
    _write_stencil_outputs(args, model, None, args.params)


# --- argument types: a bad value is an argparse error (exit 2) naming the argument ----------------

MAX_SUPERSAMPLE = 16   # s x s sub-pixels per pixel: memory and time grow as s^2; 16^2 = 256 is ample for a box filter
FORCE_HELP = ("write into a non-empty output folder this command did not make (never into an input folder, "
              "never over an input file)")


def _integer(text: str) -> int:
    """``text`` as an int, else ArgumentTypeError."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None


def _supersample(text: str) -> int:
    """--supersample: an integer from 1 to MAX_SUPERSAMPLE."""
    s = _integer(text)
    if not 1 <= s <= MAX_SUPERSAMPLE:
        raise argparse.ArgumentTypeError(f"must be an integer from 1 to {MAX_SUPERSAMPLE}, got {s}")
    return s


def _mode_index(text: str) -> int:
    """A mode index: an integer >= 0 (its range is checked against the model)."""
    i = _integer(text)
    if i < 0:
        raise argparse.ArgumentTypeError(f"mode index must be >= 0, got {i}")
    return i


def _finite_float(text: str) -> float:
    """A finite number (no nan, no inf)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return x


def _exposure(text: str) -> float:
    """--exposure: a finite number of EV from -MAX_EXPOSURE_EV to MAX_EXPOSURE_EV (2^EV must be a float)."""
    from .preview import MAX_EXPOSURE_EV
    ev = _finite_float(text)
    if not -MAX_EXPOSURE_EV <= ev <= MAX_EXPOSURE_EV:
        raise argparse.ArgumentTypeError(f"must be from -{MAX_EXPOSURE_EV} to {MAX_EXPOSURE_EV} EV, got {ev:g}")
    return ev


def _open_unit(text: str) -> float:
    """A support width w: 0 < w < 1."""
    w = _finite_float(text)
    if not 0.0 < w < 1.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 1 (exclusive), got {w:g}")
    return w


def _mode_value(value_type):
    """An argparse action for ``MODE VALUE`` pairs (appended): MODE a mode index, VALUE of ``value_type``."""
    class ModeValue(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            try:
                pair = (_mode_index(values[0]), value_type(values[1]))
            except argparse.ArgumentTypeError as exc:
                raise argparse.ArgumentError(self, str(exc)) from None
            setattr(namespace, self.dest, (getattr(namespace, self.dest) or []) + [pair])
    return ModeValue


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="facetsynth", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    check = commands.add_parser("check", help="validate a capture folder (manifest.json and frame files) "
                                              "before importing it")
    check.add_argument("capture", help="capture folder holding manifest.json, or the manifest itself")
    check.set_defaults(run=_check)

    pred = commands.add_parser("predict", help="render the frames a capture manifest describes from a fitted "
                                               "SVBRDF folder: one HDR EXR per frame, no clipping")
    pred.add_argument("model_dir", metavar="MODEL_DIR", help="fitted SVBRDF folder (results/SAMPLE/svbrdf)")
    pred.add_argument("manifest", metavar="MANIFEST", help="capture manifest (or a folder holding manifest.json)")
    pred.add_argument("out_dir", metavar="OUT_DIR", help="output folder: frames/NNNN.exr and manifest.json")
    pred.add_argument("--supersample", type=_supersample, default=1,
                      help=f"sub-pixels per pixel side (box filter), 1 to {MAX_SUPERSAMPLE}")
    pred.add_argument("--force", action="store_true", help=FORCE_HELP)
    pred.set_defaults(run=_predict)

    ins = commands.add_parser("inspect", help="what is done for a sample (results/SAMPLE), its key figures and "
                                              "warnings, in a few lines")
    ins.add_argument("sample_dir", metavar="RESULTS/SAMPLE", help="a sample's results folder, e.g. results/demo")
    ins.set_defaults(run=_inspect)

    ren = commands.add_parser("render", help="a tone-mapped preview of a fitted model from one view under one "
                                             "point light")
    ren.add_argument("model_dir", metavar="MODEL", help="fitted model folder (results/SAMPLE/svbrdf)")
    ren.add_argument("--view", nargs=2, type=_finite_float, metavar=("THETA", "PHI"), default=(30.0, 0.0),
                     help="camera elevation from the normal and azimuth from the sample's +x axis, degrees "
                          "(default 30 0)")
    ren.add_argument("--light", nargs=3, type=_finite_float, metavar=("X", "Y", "Z"),
                     help="point light position in metres, sample centre at the origin, z up (default: the view "
                          "mirrored about the normal, 2 sample diagonals away: the highlight on the sample)")
    ren.add_argument("--intensity", type=_finite_float, default=1.0, help="light intensity, W/sr (default 1)")
    ren.add_argument("--size", type=_integer, default=512, help="picture width and height in pixels (default 512)")
    ren.add_argument("--exposure", type=_exposure, default=None, metavar="EV",
                     help="scale the radiance by 2^EV before display encoding (default: auto, the lit sample's "
                          "99.5th percentile to white)")
    ren.add_argument("-o", "--output", required=True, metavar="FILE",
                     help="picture to write: .png, .jpg or .tif (tone-mapped sRGB) or .exr (linear radiance); "
                          "never in the model folder; an existing file only if render wrote it")
    ren.add_argument("--force", action="store_true", help="replace an existing picture render did not write "
                                                          "(never a file of the model)")
    ren.set_defaults(run=_render)

    exp = commands.add_parser("export", help="a fitted SVBRDF for a renderer: mitsuba (exact: scene and BSDF "
                                             "plugin) or gltf (portable anisotropic GGX material)")
    exp.add_argument("format", choices=("mitsuba", "gltf"), help="mitsuba or gltf")
    exp.add_argument("model_dir", metavar="MODEL", help="fitted SVBRDF folder (results/SAMPLE/svbrdf)")
    exp.add_argument("out_dir", metavar="OUT", help="output folder")
    exp.add_argument("--force", action="store_true", help=FORCE_HELP)
    exp.set_defaults(run=_export)

    fit = commands.add_parser("stencil-fit", help="fit the adaptive highlight stencil model (paper 000) to a "
                                                  "measured BRDF: UTIA .bin/.exr, RGL .bsdf, MERL .binary")
    fit.add_argument("brdf", help="BRDF file")
    fit.add_argument("--json", action="store_true", help="print the fitted model (modes, scores) as JSON")
    fit.add_argument("--out", metavar="DIR", help="write DIR/stencil.json and the BRDF Explorer shader "
                                                  "DIR/stencil.brdf")
    fit.add_argument("--force", action="store_true", help=FORCE_HELP)
    fit.set_defaults(run=_stencil_fit)

    ed = commands.add_parser("stencil-edit", help="edit a fitted stencil model (paper 000 sec. 5.1): rotate an "
                                                  "anisotropy axis, change a support width, swap mode colours")
    ed.add_argument("params", help="stencil.json written by stencil-fit")
    ed.add_argument("--shift-phi", nargs=2, action=_mode_value(_finite_float), metavar=("MODE", "DEG"),
                    help="rotate the axis phi_a of MODE by DEG degrees")
    ed.add_argument("--width", nargs=2, action=_mode_value(_open_unit), metavar=("MODE", "W"),
                    help="set the support width w of MODE (0 < W < 1)")
    ed.add_argument("--swap-colours", nargs=2, action=_mode_value(_mode_index), metavar=("I", "J"),
                    help="swap the colours m of modes I and J")
    ed.add_argument("--json", action="store_true", help="print the edited model as JSON")
    ed.add_argument("--out", metavar="DIR", help="write DIR/stencil.json and DIR/stencil.brdf (never over "
                                                 "the input stencil.json)")
    ed.add_argument("--force", action="store_true", help=FORCE_HELP)
    ed.set_defaults(run=_stencil_edit)

    rig = commands.add_parser("rig", help="the real rig: check it, or capture a sample outside the workflow")
    rig_commands = rig.add_subparsers(dest="rig_command", required=True)
    rig_check = rig_commands.add_parser("check", help="find the controller and the camera, report the firmware, "
                                                      "make a test move and flash every LED")
    rig_capture = rig_commands.add_parser("capture", help="capture the rig's scan into a capture folder; run it "
                                                          "again to resume an interrupted capture")
    for sub, run in ((rig_check, _rig_check), (rig_capture, _rig_capture)):
        sub.add_argument("rig", metavar="RIG", help="rig description (YAML, schema rig.schema.json)")
        sub.add_argument("--port", help="the controller's serial port (default: the description's controller.port)")
        sub.set_defaults(run=run)
    rig_capture.add_argument("out_dir", metavar="OUT_DIR", help="capture folder to write (manifest.json, frames/)")

    args = parser.parse_args(argv)
    try:
        args.run(args)
        sys.stdout.flush()                  # a closed pipe shows here, not at exit
    except (InputError, RigError) as exc:
        print(f"facetsynth {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"facetsynth {args.command}: interrupted; no partial output left", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:
        _silence_stdout()
        return BROKEN_PIPE
    return 0


INTERRUPTED = 128 + signal.SIGINT      # 130: the exit status of a command stopped by Ctrl-C
BROKEN_PIPE = 128 + signal.SIGPIPE     # 141: as a Unix tool whose reader went away (`... | head`), silently


def _silence_stdout() -> None:
    """Point stdout at /dev/null: its reader is gone, and Python's flush at exit would fail again, loudly."""
    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        pass                            # not a real file (captured by a test): nothing is flushed at exit


if __name__ == "__main__":
    sys.exit(main())
