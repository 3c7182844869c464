"""Benchmark: stencil model vs. two-lobe Kurt et al. on the seven RGL BRDFs and on anisotropic cases.

Run ``python -m facetsynth.stencil.benchmark [RGL_DIR] [--no-kurt] [--csv PATH]`` from the
repository root; RGL_DIR defaults to the vendored ``resources/brdfs/rgl``. Prints markdown
tables and writes ``results/bench/stencil.csv`` (columns ``set, material, model, modes,
delta_e, rmse, psnr_db, ssim, fit_s, fit_cpu_s``: wall-clock and process CPU seconds of the
fit alone). Both models are scored against the same data on the same UTIA grid
(:func:`facetsynth.stencil.scores.score_brdf`).

Anisotropic cases (issue 18, item 3): fabric-like materials with two or three rotated
lobes of different widths and colours, rendered on the UTIA grid

* from the project's microfacet model (:func:`facetsynth.models.microfacet.rho`, GGX lobes with
  alpha_u != alpha_v at rotated frames), and
* from a measured isotropic RGL BRDF made anisotropic by stretching both directions
  along a rotated tangent axis, w -> normalize(diag(s, 1, 1) R(phi) w) (reciprocal, the
  same map on both), then mixing two or three rotations with different colours.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from . import grid, kurt, readers, scores
from ..app.bench import write_csv
from ..models.microfacet import rho
from .fit import axis_error_deg, fit
from .model import Mode, StencilModel, evaluate_utia

RGL_DIR = Path("resources/brdfs/rgl")
CSV_PATH = Path("results/bench/stencil.csv")
COLUMNS = ("set", "material", "model", "modes", "delta_e", "rmse", "psnr_db", "ssim", "fit_s", "fit_cpu_s")


def ggx_lobes(lobes, kd=0.03):
    """Sum of rotated anisotropic GGX lobes ``[(phi_frame_deg, alpha_u, alpha_v, ks_rgb), ...]`` + grey diffuse."""
    wi, wo = grid.utia_directions()
    out = sum(rho(wi, wo, np.full(3, kd if i == 0 else 0.0), np.asarray(col, float), 1.5, au, av, np.deg2rad(pf))
              for i, (pf, au, av, col) in enumerate(lobes))
    return np.ascontiguousarray(np.moveaxis(out, -1, 0))


def stretched_mix(brdf, parts, s=4.0):
    """Mix of a measured isotropic BRDF (``eval(wi, wo)``) stretched along rotated axes.

    ``parts = [(phi_deg, weight, rgb), ...]``: each term is weight * rgb * f(T wi, T wo) with
    T w = normalize(diag(s, 1, 1) R(phi) w).
    """
    wi, wo = (d.reshape(-1, 3) for d in grid.utia_directions())
    out = 0.0
    for phi, weight, col in parts:
        c, sn = np.cos(np.deg2rad(phi)), np.sin(np.deg2rad(phi))
        T = np.diag([s, 1.0, 1.0]) @ np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]])

        def warp(d):
            d = d @ T.T
            return d / np.linalg.norm(d, axis=-1, keepdims=True)
        out = out + weight * np.asarray(col, float) * brdf.eval(warp(wi), warp(wo))
    return np.ascontiguousarray(np.moveaxis(out.reshape(grid.SHAPE[1:] + (3,)), -1, 0))


def anisotropic_cases(rgl_dir=RGL_DIR):
    """name -> BRDF ``(3, 6, 48, 6, 48)``: the issue-18 anisotropic test set."""
    cases = {
        "GGX 2 lobes at 10/100 deg": ggx_lobes([(10, 0.05, 0.4, (0.5, 0.3, 0.2)), (100, 0.08, 0.5, (0.2, 0.3, 0.6))]),
        "GGX 3 lobes at 0/60/120 deg": ggx_lobes([(0, 0.04, 0.35, (0.6, 0.15, 0.1)), (60, 0.06, 0.45, (0.1, 0.5, 0.15)),
                                                  (120, 0.1, 0.5, (0.1, 0.2, 0.6))]),
    }
    rgl = Path(rgl_dir)
    if (rgl / "satin_rosaline_rgb.bsdf").exists():
        satin = readers.RGLBRDF(rgl / "satin_rosaline_rgb.bsdf")
        cases["satin_rosaline stretched x4 at 20/110 deg"] = stretched_mix(
            satin, [(20, 0.6, (1.0, 0.8, 0.6)), (110, 0.4, (0.5, 0.7, 1.0))])
    if (rgl / "vch_golden_yellow_rgb.bsdf").exists():
        gold = readers.RGLBRDF(rgl / "vch_golden_yellow_rgb.bsdf")
        cases["vch_golden_yellow stretched x4 at 0/60/120 deg"] = stretched_mix(
            gold, [(0, 0.4, (1.0, 1.0, 1.0)), (60, 0.3, (0.4, 1.0, 0.4)), (120, 0.3, (0.5, 0.5, 1.0))])
    return cases


def compare(brdf, kurt_fit=True):
    """Fit both models to one BRDF and score them against it -> list of row dicts (stencil, Kurt)."""
    t, c = time.perf_counter(), time.process_time()
    m = fit(brdf)
    ts, cs = time.perf_counter() - t, time.process_time() - c
    rows = [dict(model="stencil", modes=len(m.modes), fit_s=ts, fit_cpu_s=cs,
                 **scores.score_brdf(brdf, evaluate_utia(m)))]
    if kurt_fit:
        c = time.process_time()
        km, tk = kurt.fit_kurt(brdf)
        rows.append(dict(model="Kurt 2 lobes", modes="", fit_s=tk, fit_cpu_s=time.process_time() - c,
                         **scores.score_brdf(brdf, kurt.kurt_evaluate_utia(km))))
    return rows


def _md(rows):
    lines = ["| material | model | modes | Delta E (CIEDE2000) | RMSE | PSNR dB | SSIM | fit time (CPU) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['material']} | {r['model']} | {r['modes'] if r['modes'] != '' else '-'} | "
                     f"{r['delta_e']:.2f} | {r['rmse']:.4f} | {r['psnr_db']:.1f} | {r['ssim']:.3f} | "
                     f"{r['fit_s'] * 1000:.0f} ms ({r['fit_cpu_s'] * 1000:.0f} ms) |")
    return "\n".join(lines)


def run(rgl_dir=RGL_DIR, kurt_fit=True):
    """All comparison rows: the seven RGL BRDFs (set 'rgl') and the anisotropic cases (set 'anisotropic')."""
    fit(np.zeros(grid.SHAPE))  # warm the geometry cache (one-off ~0.05 s per process)
    files = sorted(Path(rgl_dir).glob("*.bsdf"))
    if not files:
        raise SystemExit(f"{rgl_dir}: no .bsdf files (run from the repository root or pass the folder)")
    rows = []
    for p in files:
        rows += [dict(set="rgl", material=p.stem, **r) for r in compare(readers.read_rgl(p), kurt_fit)]
    for name, b in anisotropic_cases(rgl_dir).items():
        rows += [dict(set="anisotropic", material=name, **r) for r in compare(b, kurt_fit)]
    return rows


def _synth(phis):
    cols = [(0.2, 0.3, 0.9), (0.9, 0.2, 0.1), (0.1, 0.8, 0.2)]
    ws = (0.75, 0.65, 0.6)
    modes = tuple(Mode(np.deg2rad(p), w, 0.4, 0.04, 0.05, 1.0, 6.0, c) for p, w, c in zip(phis, ws, cols))
    return StencilModel(modes, (0.0,) * max(len(modes) - 1, 0), 0.05,
                        modes[-1].m if modes else (0.1, 0.1, 0.1), 4.0, 60.0, 0.4, 0.04)


def synthetic_lines():
    lines = ["| case | true phi_a (deg) | found phi_a (deg) | modes ok | max phi_a error | fit time |",
             "|---|---|---|---|---|---|"]
    for phis in [(), (30,), (20, 110), (100, 160), (10, 70, 140)]:
        b = evaluate_utia(_synth(phis))
        t = time.perf_counter()
        m = fit(b)
        t = time.perf_counter() - t
        got = [float(np.rad2deg(x.phi_a)) for x in m.modes]
        lines.append(f"| stencil {len(phis)} modes | {list(phis)} | {[round(g, 2) for g in got]} | "
                     f"{len(got) == len(phis)} | {axis_error_deg(got, phis):.2f} | {t * 1000:.0f} ms |")
    for pf in [(10, 100), (35, 150), (60, 95)]:
        b = ggx_lobes([(pf[0], 0.05, 0.4, (0.5, 0.3, 0.2)), (pf[1], 0.08, 0.5, (0.2, 0.3, 0.6))], kd=0.05)
        t = time.perf_counter()
        m = fit(b)
        t = time.perf_counter() - t
        exp = [(90 - p) % 180 for p in pf]
        got = [float(np.rad2deg(x.phi_a)) for x in m.modes]
        lines.append(f"| GGX 2 lobes, phi_frame {list(pf)} | {exp} | {[round(g, 2) for g in got]} | "
                     f"{len(got) == 2} | {axis_error_deg(got, exp):.2f} | {t * 1000:.0f} ms |")
    return "\n".join(lines)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    csv_path = Path(argv[argv.index("--csv") + 1]) if "--csv" in argv else CSV_PATH
    folders = [a for i, a in enumerate(argv) if not a.startswith("--") and (i == 0 or argv[i - 1] != "--csv")]
    kurt_fit = "--no-kurt" not in argv
    with threadpool_limits(limits=1):   # as in the workflow (stages.runner): BLAS on the job's one thread
        rows = run(folders[0] if folders else RGL_DIR, kurt_fit)
        synthetic = synthetic_lines()
    write_csv(rows, csv_path, COLUMNS)
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load = ", load average %.1f" % os.getloadavg()[0] if hasattr(os, "getloadavg") else ""
    print(f"{when}, {platform.node()} ({platform.machine()}, {os.cpu_count()} cores{load}, "
          f"Python {platform.python_version()}, BLAS 1 thread); written {csv_path}\n")
    for name, title in (("rgl", "RGL BRDFs"), ("anisotropic", "Anisotropic cases")):
        part = [r for r in rows if r["set"] == name]
        print(f"## {title} (stencil vs Kurt)\n\n{_md(part)}\n")
        for model in ("stencil", "Kurt 2 lobes"):
            t = [(r["fit_s"], r["fit_cpu_s"]) for r in part if r["model"] == model]
            if t:
                wall, cpu = np.median(t, axis=0)
                print(f"median fit time {model}: {wall * 1000:.1f} ms wall, {cpu * 1000:.1f} ms CPU")
        print()
    print("## Synthetic BRDFs\n")
    print(synthetic)


if __name__ == "__main__":
    main()
