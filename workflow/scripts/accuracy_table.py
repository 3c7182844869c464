"""The README's accuracy table (issue 13) from the validate, cluster and params records of a sample sheet.

    snakemake --cores 2 --config samples=config/samples-accuracy.tsv
    python workflow/scripts/accuracy_table.py config/samples-accuracy.tsv [results]

Prints one markdown row per sample that has results: held-out relative L2 of radiance (all, and the
specular part where the truth is eq. 6), ours against the per-point Ward baseline on the same views; the
self-check's (no truth: the fitting view relit, and the held-out lights, selfcheck/metrics.json); the
representatives, and the largest within-region median NDF spread of the delivered model (refine's, scored by
rule score_refine), params' in brackets.
"""

import csv
import json
import sys
from pathlib import Path


def read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def cell(x, digits=3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def main(sheet: str, results: str = "results") -> None:
    with open(sheet, newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    print("| sample | lights | held-out rel. L2, ours / Ward | specular part, ours / Ward | self-check: relit / "
          "held-out lights | representatives | NDF spread (largest region median), refine (params) |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        base = Path(results) / row["sample"]
        v, c, p, sc = (read(base / s / "metrics.json") for s in ("validate", "cluster", "params", "selfcheck"))
        r = read(base / "truth" / "refine.json")         # rule score_refine's
        h = read(base / "hdr" / "metrics.json")
        if v is None:
            continue
        print(f"| {row['sample']} | {h['frames'] if h else '-'} | {cell(v.get('heldout_rel_l2'))} / "
              f"{cell(v.get('baseline_ward_rel_l2'))} | {cell(v.get('heldout_specular_rel_l2'))} / "
              f"{cell(v.get('baseline_ward_specular_rel_l2'))} | "
              f"{cell(sc['relit']['rel_l2']) if sc else '-'} / {cell(sc['heldout']['rel_l2']) if sc else '-'} | "
              f"{c['representatives'] if c else '-'} | "
              f"{cell(r.get('ndf_spread_max_median') if r else None)} "
              f"({cell(p.get('ndf_spread_max_median') if p else None)}) |")


if __name__ == "__main__":
    main(*sys.argv[1:])
