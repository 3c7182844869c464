"""Benchmark: stencil model vs. two-lobe Kurt et al. on the seven RGL BRDFs, plus synthetic checks.

Run ``python -m facetsynth.stencil.benchmark [RGL_DIR] [--no-kurt]`` from the repository root;
RGL_DIR defaults to the vendored ``resources/brdfs/rgl``. Prints markdown tables.
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

import numpy as np

from . import grid, kurt, model as Mo, readers, scores
from facetsynth.microfacet import rho

F = importlib.import_module("facetsynth.stencil.fit")
RGL_DIR = Path("resources/brdfs/rgl")


def _row(name, n, sc, t):
    return (f"| {name} | {n} | {sc['delta_e']:.2f} | {sc['rmse']:.4f} | {sc['psnr_db']:.1f} | "
            f"{sc['ssim']:.3f} | {t * 1000:.0f} ms |")


def rgl_table(rgl_dir=RGL_DIR, kurt_fit=True):
    lines = ["| material | model | modes | Delta E (CIEDE2000) | RMSE | PSNR dB | SSIM | fit time |",
             "|---|---|---|---|---|---|---|---|"]
    st_times, ku_times = [], []
    F.fit(np.zeros(grid.SHAPE))  # warm the geometry cache (one-off ~0.05 s per process)
    files = sorted(Path(rgl_dir).glob("*.bsdf"))
    if not files:
        raise SystemExit(f"{rgl_dir}: no .bsdf files (run from the repository root or pass the folder)")
    for p in files:
        b = readers.read_rgl(p)
        t = time.perf_counter()
        m = F.fit(b)
        ts = time.perf_counter() - t
        st_times.append(ts)
        sc = scores.score_brdf(b, Mo.evaluate_utia(m))
        lines.append(_row(f"{p.stem} | stencil", len(m.modes), sc, ts))
        if kurt_fit:
            km, tk = kurt.fit_kurt(b)
            ku_times.append(tk)
            lines.append(_row(f"{p.stem} | Kurt 2 lobes", "-", scores.score_brdf(b, kurt.kurt_evaluate_utia(km)), tk))
    lines.append("")
    lines.append(f"median fit time: stencil {np.median(st_times) * 1000:.1f} ms"
                 + (f", Kurt {np.median(ku_times):.2f} s" if ku_times else ""))
    return "\n".join(lines)


def _synth(phis):
    cols = [(0.2, 0.3, 0.9), (0.9, 0.2, 0.1), (0.1, 0.8, 0.2)]
    ws = (0.75, 0.65, 0.6)
    modes = tuple(Mo.Mode(np.deg2rad(p), w, 0.4, 0.04, 0.05, 1.0, 6.0, c) for p, w, c in zip(phis, ws, cols))
    return Mo.StencilModel(modes, (0.0,) * max(len(modes) - 1, 0), 0.05,
                           modes[-1].m if modes else (0.1, 0.1, 0.1), 4.0, 60.0, 0.4, 0.04)


def synthetic_lines():
    lines = ["| case | true phi_a (deg) | found phi_a (deg) | modes ok | max phi_a error | fit time |",
             "|---|---|---|---|---|---|"]
    for phis in [(), (30,), (20, 110), (100, 160), (10, 70, 140)]:
        b = Mo.evaluate_utia(_synth(phis))
        t = time.perf_counter()
        m = F.fit(b)
        t = time.perf_counter() - t
        got = [float(np.rad2deg(x.phi_a)) for x in m.modes]
        lines.append(f"| stencil {len(phis)} modes | {list(phis)} | {[round(g, 2) for g in got]} | "
                     f"{len(got) == len(phis)} | {F.axis_error_deg(got, phis):.2f} | {t * 1000:.0f} ms |")
    wi, wo = grid.utia_directions()
    for pf in [(10, 100), (35, 150), (60, 95)]:
        b = rho(wi, wo, np.full(3, 0.05), np.array([0.5, 0.3, 0.2]), 1.5, 0.05, 0.4, np.deg2rad(pf[0])) \
            + rho(wi, wo, np.zeros(3), np.array([0.2, 0.3, 0.6]), 1.5, 0.08, 0.5, np.deg2rad(pf[1]))
        t = time.perf_counter()
        m = F.fit(np.moveaxis(b, -1, 0))
        t = time.perf_counter() - t
        exp = [(90 - p) % 180 for p in pf]
        got = [float(np.rad2deg(x.phi_a)) for x in m.modes]
        lines.append(f"| GGX 2 lobes, phi_frame {list(pf)} | {exp} | {[round(g, 2) for g in got]} | "
                     f"{len(got) == 2} | {F.axis_error_deg(got, exp):.2f} | {t * 1000:.0f} ms |")
    return "\n".join(lines)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    print("## RGL BRDFs (stencil vs Kurt)\n")
    folders = [a for a in argv if not a.startswith("--")]
    print(rgl_table(folders[0] if folders else RGL_DIR, kurt_fit="--no-kurt" not in argv))
    print("\n## Synthetic BRDFs\n")
    print(synthetic_lines())


if __name__ == "__main__":
    main()
