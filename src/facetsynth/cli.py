"""The ``facetsynth`` command: what users do outside the workflow."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .errors import InputError


def _check(args: argparse.Namespace) -> None:
    from .stages.capture import check_capture
    m = check_capture(args.capture)
    exposures = sum(len(f["exposures"]) for f in m["frames"])
    print(f"{args.capture}: valid capture, {len(m['frames'])} frames, {exposures} exposure files, "
          f"camera {m['camera']['width']}x{m['camera']['height']}")


def _predict(args: argparse.Namespace) -> None:
    from .predict import predict
    out = predict(args.model_dir, args.manifest, args.out_dir, supersample=args.supersample)
    print(f"{args.out_dir}: {len(out['frames'])} predicted HDR frame(s) and manifest.json "
          f"(camera {out['camera']['width']}x{out['camera']['height']})")


def _write_stencil_outputs(args: argparse.Namespace, model, scores: dict | None) -> dict:
    """Print or write the model's JSON parameters and its BRDF Explorer shader."""
    from .fileio import atomic_path
    from .stencil import model_to_json, to_brdf_explorer
    params = model_to_json(model, scores)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for name, text in (("stencil.json", json.dumps(params, indent=2)), ("stencil.brdf", to_brdf_explorer(model))):
            with atomic_path(out / name) as tmp:
                tmp.write_text(text + "\n")
    if args.json:
        print(json.dumps(params, indent=2))
    return params


def _stencil_fit(args: argparse.Namespace) -> None:
    from .stencil import fit_file
    model, scores = fit_file(args.brdf)
    params = _write_stencil_outputs(args, model, scores)
    if not args.json:
        axes = ", ".join(f"{m['phi_a_deg']:.1f}" for m in params["modes"]) or "none"
        s = params["scores"]
        print(f"{args.brdf}: {params['n_modes']} anisotropy mode(s), phi_a (deg): {axes}; "
              f"Delta E {s['delta_e']:.2f}, RMSE {s['rmse']:.4f}, PSNR {s['psnr_db']:.1f} dB, "
              f"SSIM {s['ssim']:.3f}, fit {1000 * s['fit_seconds']:.0f} ms")


def _stencil_edit(args: argparse.Namespace) -> None:
    """Paper 000 sec. 5.1 / Fig. 16 edits, applied in the order given on the command line."""
    import numpy as np

    from .fileio import read_json
    from .stencil import edit, model_from_json
    model = model_from_json(read_json(args.params))
    try:
        for mode, degrees in args.shift_phi or []:
            model = edit.shift_phi_a(model, int(mode), np.deg2rad(degrees))
        for mode, w in args.width or []:
            model = edit.set_width(model, int(mode), w)
        for i, j in args.swap_colours or []:
            model = edit.swap_mode_colours(model, i, j)
    except (IndexError, ValueError) as exc:
        raise InputError(args.params, str(exc)) from None
    _write_stencil_outputs(args, model, None)


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
    pred.add_argument("--supersample", type=int, default=1, help="sub-pixels per pixel side (box filter)")
    pred.set_defaults(run=_predict)

    fit = commands.add_parser("stencil-fit", help="fit the adaptive highlight stencil model (paper 000) to a "
                                                  "measured BRDF: UTIA .bin/.exr, RGL .bsdf, MERL .binary")
    fit.add_argument("brdf", help="BRDF file")
    fit.add_argument("--json", action="store_true", help="print the fitted model (modes, scores) as JSON")
    fit.add_argument("--out", metavar="DIR", help="write DIR/stencil.json and the BRDF Explorer shader "
                                                  "DIR/stencil.brdf")
    fit.set_defaults(run=_stencil_fit)

    ed = commands.add_parser("stencil-edit", help="edit a fitted stencil model (paper 000 sec. 5.1): rotate an "
                                                  "anisotropy axis, change a support width, swap mode colours")
    ed.add_argument("params", help="stencil.json written by stencil-fit")
    ed.add_argument("--shift-phi", nargs=2, type=float, action="append", metavar=("MODE", "DEG"),
                    help="rotate the axis phi_a of MODE by DEG degrees")
    ed.add_argument("--width", nargs=2, type=float, action="append", metavar=("MODE", "W"),
                    help="set the support width w of MODE (0 < W < 1)")
    ed.add_argument("--swap-colours", nargs=2, type=int, action="append", metavar=("I", "J"),
                    help="swap the colours m of modes I and J")
    ed.add_argument("--json", action="store_true", help="print the edited model as JSON")
    ed.add_argument("--out", metavar="DIR", help="write DIR/stencil.json and DIR/stencil.brdf")
    ed.set_defaults(run=_stencil_edit)

    args = parser.parse_args(argv)
    try:
        args.run(args)
    except InputError as exc:
        print(f"facetsynth {args.command}: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
