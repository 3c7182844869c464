"""What a sample's results folder holds, in a few lines (``facetsynth inspect RESULTS/SAMPLE``).

One line per stage in pipeline order: done (its ``metrics.json`` is there)
with its key figures, or not yet. Then the warnings: every stage's
``degenerate`` reason and the ``WARNING`` lines of the stage logs
(``results/SAMPLE/logs/``), each once. Figures against ground truth appear
only where the stage had the truth (virtual samples): in its metrics, or
scored beside the fit in ``truth/STAGE.json`` (rectify's registration, refine's kd and ks).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Callable

from ..io.errors import InputError


def _num(value: Any, fmt: str) -> str | None:
    """``value`` formatted by ``fmt``, None when it is not a number; ValueError for a NaN, an Inf or a fraction
    given to an integer format (``d``)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return None
    if fmt.endswith("d") and not isinstance(value, int):
        if not (math.isfinite(value) and value == int(value)):
            raise ValueError(f"expected an integer, found {value!r}")
        value = int(value)
    return format(value, fmt)


# stage -> (metrics file under the sample folder, [(label, key, format)] or a function of the metrics)
Figures = list[tuple[str, str, str]]
STAGES: list[tuple[str, str, Figures | Callable[[dict], list[str]]]] = [
    ("capture", "capture/manifest.json",
     lambda m: [f"{len(m.get('frames', []))} frames",
                f"camera {m['camera']['width']}x{m['camera']['height']}" if "camera" in m else ""]),
    ("hdr", "hdr/metrics.json", [("frames", "frames", "d"), ("saturated pixels", "saturated_pixels", "d"),
                                 ("dark frames", "dark_frames", "d"), ("vs truth", "median_rel_error", ".4f")]),
    ("rectify", "rectify/metrics.json",
     lambda m: [f"{m.get('cols')}x{m.get('rows')} points ({m.get('resolution_rule', '?')})",
                *([f"registration {m['registration_error_px']:.2f} px"] if "registration_error_px" in m else [])]),
    ("separate", "separate/metrics.json", lambda m: _figures(m, [
        ("kd vs truth", "kd_median_rel_error", ".4f"), ("specular signal at", "specular_signal_fraction", ".0%"),
        ("points without kd", "points_without_diffuse_estimate", "d"),
        ("normals tilt median", "normal_tilt_median_deg", ".1f"), ("p99", "normal_tilt_p99_deg", ".1f")])
     + _light_factors(m.get("light_factors"))),
    ("resample", "resample/metrics.json",
     lambda m: [f"direction grid {m.get('n_theta')} x {m.get('n_phi')}"]),
    ("partial_ndf", "partial_ndf/metrics.json", [("NDF vs truth", "ndf_rel_l2_median", ".3f"),
                                                 ("converged", "converged_fraction", ".0%")]),
    ("cluster", "cluster/metrics.json", [("representatives", "representatives", "d")]),
    ("synthesize", "synthesize/metrics.json", [("NDF vs truth", "ndf_rel_l2_median", ".3f"),
                                               ("coverage before fill", "coverage_before_fill", ".0%"),
                                               ("stalled", "stalled_representatives", "d")]),
    ("params", "params/metrics.json", [("materials", "materials", "d"), ("eta median", "eta_median", ".3f"),
                                       ("ks vs truth", "ks_median_rel_error", ".3f")]),
    ("refine", "refine/metrics.json", [("samples rel. L2", "fitting_samples_rel_l2_after", ".3f"),
                                       ("before", "fitting_samples_rel_l2_before", ".3f"),
                                       ("ks vs truth", "ks_median_rel_error", ".3f")]),
    ("selfcheck", "selfcheck/metrics.json",
     lambda m: [f"{name} rel. L2 {m[name]['rel_l2']:.3f} (specular {m[name]['specular_rel_l2']:.3f}, worst frame "
                f"{m[name]['frame_psnr_worst_db']:.1f} dB)" for name in ("relit", "heldout")
                if isinstance(m.get(name), dict) and m[name].get("rel_l2") is not None
                and m[name].get("specular_rel_l2") is not None and m[name].get("frame_psnr_worst_db") is not None]
     + (["POOR FIT"] if m.get("poor_fit") else [])),
    ("validate", "validate/metrics.json", [("held-out rel. L2", "heldout_rel_l2", ".3f"),
                                           ("Ward", "baseline_ward_rel_l2", ".3f"),
                                           ("PSNR dB", "heldout_psnr_db", ".1f")]),
    ("stencil_fit", "stencil_fit/metrics.json", [("clusters", "clusters", "d"),
                                                 ("Delta E median", "delta_e_median", ".2f"),
                                                 ("Kurt's", "kurt_delta_e_median", ".2f"),
                                                 ("PSNR dB", "psnr_db_median", ".1f")]),
    ("export", "export/metrics.json", [("glTF held-out rel. L2", "heldout_portable_rel_l2", ".3f"),
                                       ("full SVBRDF", "heldout_full_rel_l2", ".3f"),
                                       ("loss", "heldout_loss_rel_l2", "+.4f")]),
]
WARNING = re.compile(r"\bWARNING\b\s+(?P<message>.*)")


def _light_factors(record: dict | None) -> list[str]:
    """The estimated per-light intensity factors (separate), as their luminance range."""
    if not isinstance(record, dict) or not record.get("rgb"):
        return []
    luminance = [sum(rgb) / 3 for rgb, nominal in zip(record["rgb"], record.get("fallback", [])) if not nominal]
    if not luminance:
        return []
    return [f"light factors {min(luminance):.2f}-{max(luminance):.2f} (estimated, {len(luminance)} lights)"]


def _figures(metrics: dict, spec: Figures | Callable[[dict], list[str]], path: Path | None = None) -> list[str]:
    """The figures ``spec`` reads from ``metrics``; InputError naming ``path`` and the key for a value of the
    wrong kind (a NaN where an integer belongs, a string where an object does), never a traceback."""
    if callable(spec):
        try:
            return [s for s in spec(metrics) if s]
        except InputError as exc:                      # a nested table's value (separate's)
            raise InputError(path, exc.problem) from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise InputError(path, f"unexpected content ({type(exc).__name__}: {str(exc)[:80]})") from None
    out = []
    for label, key, fmt in spec:
        try:
            text = _num(metrics.get(key), fmt)
        except ValueError as exc:
            raise InputError(path, f"{key!r}: {str(exc)[:80]}") from None
        if text is not None:
            out.append(f"{label} {text}")
    return out


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, f"unreadable ({exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, f"unreadable: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except RecursionError:
        raise InputError(path, "unreadable: nested too deeply") from None
    if not isinstance(data, dict):
        raise InputError(path, f"expected a JSON object, found {type(data).__name__}")
    return data


def log_warnings(logs: Path) -> list[str]:
    """The ``WARNING`` messages of every stage log in ``logs``, each once, as ``stage: message``."""
    seen, out = set(), []
    for log in sorted(logs.glob("**/*.log")) if logs.is_dir() else []:
        for line in log.read_text(errors="replace").splitlines():
            match = WARNING.search(line)
            if match and (log.stem, match["message"]) not in seen:
                seen.add((log.stem, match["message"]))
                out.append(f"{log.stem}: {match['message']}")
    return out


def summarise(sample_dir: str | Path) -> list[str]:
    """The lines ``facetsynth inspect`` prints for ``sample_dir`` (results/SAMPLE)."""
    sample_dir = Path(sample_dir)
    if not sample_dir.is_dir():
        raise InputError(sample_dir, "not a folder; expected a sample's results folder such as results/demo")
    done = {stage: sample_dir / path for stage, path, _ in STAGES if (sample_dir / path).is_file()}
    if not done:
        raise InputError(sample_dir, "holds no stage output (no capture/manifest.json, no */metrics.json): "
                                     "is it results/SAMPLE?")
    lines = [f"{sample_dir}: {len(done)} of {len(STAGES)} stages done"]
    warnings = []
    width = max(len(stage) for stage, _, _ in STAGES)
    for stage, _, spec in STAGES:
        if stage not in done:
            lines.append(f"  {stage:<{width}}  -")
            continue
        metrics = _read_json(done[stage])
        truth = sample_dir / "truth" / f"{stage}.json"       # scored beside the fit (rule score_STAGE)
        if truth.is_file():
            metrics = {**metrics, **_read_json(truth)}
        lines.append(f"  {stage:<{width}}  done: " + (", ".join(_figures(metrics, spec, done[stage]))
                                                      or "no figures"))
        if metrics.get("degenerate"):
            warnings.append(f"{stage}: degenerate: {metrics['degenerate']}")
    warnings += log_warnings(sample_dir / "logs")
    lines.append(f"{len(warnings)} warning(s)" + (":" if warnings else ""))
    lines += [f"  {w}" for w in warnings]
    return lines
