"""The ``facetsynth`` command: what users do outside the workflow."""

from __future__ import annotations

import argparse
import sys

from .errors import InputError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="facetsynth", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    check = commands.add_parser("check", help="validate a capture folder (manifest.json and frame files) "
                                              "before importing it")
    check.add_argument("capture", help="capture folder holding manifest.json, or the manifest itself")
    args = parser.parse_args(argv)
    try:
        if args.command == "check":
            from .stages.capture import check_capture
            m = check_capture(args.capture)
            exposures = sum(len(f["exposures"]) for f in m["frames"])
            print(f"{args.capture}: valid capture, {len(m['frames'])} frames, {exposures} exposure files, "
                  f"camera {m['camera']['width']}x{m['camera']['height']}")
    except InputError as exc:
        print(f"facetsynth {args.command}: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
