"""Exports of a fitted StencilModel: JSON parameters and a Disney BRDF Explorer shader.

JSON: angles in degrees (``phi_a_deg``), everything else as in
:class:`facetsynth.stencil.model.StencilModel`; ``scores`` holds delta_e,
rmse, psnr_db, ssim, fit_seconds. :func:`model_from_json` checks a parameter
file's structure and values first (:func:`check_params`): a bad one is an
InputError naming the file and the key.

``.brdf`` (BRDF Explorer, "analytic" type): every fitted value is a GUI
parameter (``float name min max default``) so the sec. 5.1 edits can be done
interactively; the shader function ``vec3 BRDF(vec3 L, vec3 V, vec3 N,
vec3 X, vec3 Y)`` evaluates eqs. 2-10 in the local frame (X, Y, N) and
returns fr without the cosine.  The body is written in a small GLSL subset
(one declaration per line, no branches) so that tests can transliterate it
to Python and compare it with :func:`facetsynth.stencil.model.evaluate`.
"""

from __future__ import annotations

import json

import numpy as np

from facetsynth.io.errors import InputError

from .model import COS_FLOOR, Mode, StencilModel, lobes

__all__ = ["model_to_json", "model_from_json", "check_params", "to_brdf_explorer"]

_SCORE_KEYS = ("delta_e", "rmse", "psnr_db", "ssim", "fit_seconds")


def _f(x):
    return float(x)


def model_to_json(model, scores=None):
    """StencilModel (+ scores dict) -> JSON-ready dict with ``modes`` and ``scores``."""
    modes = [{"phi_a_deg": _f(np.rad2deg(m.phi_a)), "w": _f(m.w), "a": _f(m.a), "b": _f(m.b),
              "kd": _f(m.kd), "ks": _f(m.ks), "alpha": _f(m.alpha), "m": [_f(v) for v in m.m],
              "retro": bool(m.retro)} for m in model.modes]
    out = {"model": "facetsynth.stencil (Filip et al., adaptive highlight stencils)",
           "n_modes": len(modes), "modes": modes, "beta": [_f(b) for b in model.beta],
           "r": _f(model.r), "m_bg": [_f(v) for v in model.m_bg], "k": _f(model.k),
           "alpha_s": _f(model.alpha_s), "a_s": _f(model.a_s), "b_s": _f(model.b_s),
           "dw_ratio": _f(model.dw_ratio), "k2": _f(model.k2), "alpha_s2": _f(model.alpha_s2),
           "a_s2": _f(model.a_s2), "b_s2": _f(model.b_s2),
           "m_s": None if model.m_s is None else [_f(v) for v in model.m_s],
           "m_s2": None if model.m_s2 is None else [_f(v) for v in model.m_s2],
           "a_r": _f(model.a_r), "b_r": _f(model.b_r), "f_s": _f(model.f_s), "f_s2": _f(model.f_s2),
           "jacobian": bool(model.jacobian), "stencil_highlight": bool(model.stencil_highlight)}
    sc = dict(scores or {})
    out["scores"] = {k: (None if sc.get(k) is None else _f(sc[k])) for k in _SCORE_KEYS}
    for k, v in sc.items():
        if k not in out["scores"] and isinstance(v, (int, float)):
            out["scores"][k] = _f(v)
    return out


def _preview(v, n=40):
    """A short repr of a JSON value for error messages."""
    s = json.dumps(v) if not isinstance(v, float) else repr(v)
    return s if len(s) <= n else s[:n - 3] + "..."


def _get(d, key, where):
    """``d[key]``, else ValueError '<where>: missing'."""
    if key not in d:
        raise ValueError(f"{where}: missing")
    return d[key]


def _number(v, where, lo=-np.inf, hi=np.inf, open_ends=False):
    """``v`` as a finite float in [lo, hi] ((lo, hi) with ``open_ends``), else ValueError naming ``where``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where}: expected a number, found {_preview(v)}")
    try:
        v = float(v)                       # an integer beyond 1.8e308 cannot be one
    except OverflowError:
        v = float("inf")
    if not np.isfinite(v):
        raise ValueError(f"{where}: must be finite, found {v}")
    inside = lo < v < hi if open_ends else lo <= v <= hi
    if not inside:
        ends = "()" if open_ends else "[]"
        raise ValueError(f"{where}: {v:g} is outside {ends[0]}{lo:g}, {hi:g}{ends[1]}")
    return v


def _key(d, key, at="", n=None, **bounds):
    """``d[key]`` checked by :func:`_number` (a list of ``n`` of them with ``n``); ``at`` locates ``d``."""
    where = f"{at}['{key}']" if at else f"'{key}'"
    v = _get(d, key, where)
    if n is None:
        return _number(v, where, **bounds)
    if not isinstance(v, list) or len(v) != n:
        raise ValueError(f"{where}: expected a list of {n} number(s), found {_preview(v)}")
    return [_number(x, f"{where}[{i}]", **bounds) for i, x in enumerate(v)]


def check_params(d):
    """Raise ValueError naming the first bad key of stencil parameters ``d`` (as written by model_to_json).

    Structure: an object with ``modes`` (a list of objects), ``beta`` (one
    value per mode but the last), ``r``, ``m_bg`` (3), ``k``, ``alpha_s``,
    ``a_s``, ``b_s``, ``dw_ratio``; optional (absent: the paper's eqs. 7 and 10)
    ``k2``, ``alpha_s2``, ``a_s2``, ``b_s2``, ``m_s``, ``m_s2`` (3 or null),
    ``a_r``, ``b_r``, ``f_s``, ``f_s2``, ``jacobian``, ``stencil_highlight`` (true or false); every
    number finite. Ranges are those the fit produces and the model needs:
    0 < w < 1, beta in [0, 1], colours m, m_bg, m_s, m_s2, ks, k, k2, alpha,
    alpha_s, alpha_s2 and dw_ratio >= 0.
    """
    if not isinstance(d, dict):
        raise ValueError(f"expected a JSON object, found {type(d).__name__}")
    modes = _get(d, "modes", "'modes'")
    if not isinstance(modes, list):
        raise ValueError(f"'modes': expected a list, found {_preview(modes)}")
    for i, m in enumerate(modes):
        at = f"'modes'[{i}]"
        if not isinstance(m, dict):
            raise ValueError(f"{at}: expected an object, found {_preview(m)}")
        for key in ("phi_a_deg", "a", "b", "kd"):
            _key(m, key, at)
        _key(m, "w", at, lo=0.0, hi=1.0, open_ends=True)
        for key in ("ks", "alpha"):
            _key(m, key, at, lo=0.0)
        _key(m, "m", at, n=3, lo=0.0)
        if not isinstance(m.get("retro", False), bool):
            raise ValueError(f"{at}['retro']: expected true or false, found {_preview(m['retro'])}")
    _key(d, "beta", n=max(len(modes) - 1, 0), lo=0.0, hi=1.0)
    _key(d, "m_bg", n=3, lo=0.0)
    for key in ("r", "a_s", "b_s"):
        _key(d, key)
    for key in ("k", "alpha_s", "dw_ratio"):
        _key(d, key, lo=0.0)
    for key, nonneg in (("k2", True), ("alpha_s2", True), ("a_s2", False), ("b_s2", False),
                        ("a_r", False), ("b_r", False), ("f_s", False), ("f_s2", False)):
        if key in d:
            _key(d, key, lo=0.0 if nonneg else -np.inf)
    for key in ("jacobian", "stencil_highlight"):
        if not isinstance(d.get(key, False), bool):
            raise ValueError(f"'{key}': expected true or false, found {_preview(d[key])}")
    for key in ("m_s", "m_s2"):
        if d.get(key) is not None:
            _key(d, key, n=3, lo=0.0)


def model_from_json(d, path=None):
    """Inverse of :func:`model_to_json` (scores are ignored).

    ``d`` is checked first (:func:`check_params`): a bad one is an InputError
    naming ``path`` and the key.
    """
    try:
        check_params(d)
    except ValueError as exc:
        raise InputError(path, f"not valid stencil parameters: {exc}") from None
    modes = tuple(Mode(phi_a=float(np.deg2rad(m["phi_a_deg"])), w=m["w"], a=m["a"], b=m["b"], kd=m["kd"],
                       ks=m["ks"], alpha=m["alpha"], m=tuple(m["m"]), retro=bool(m.get("retro", False)))
                  for m in d["modes"])
    extra = {k: d[k] for k in ("k2", "alpha_s2", "a_s2", "b_s2", "a_r", "b_r", "f_s", "f_s2", "jacobian",
                               "stencil_highlight") if k in d}
    extra.update({k: tuple(d[k]) for k in ("m_s", "m_s2") if d.get(k) is not None})
    return StencilModel(modes=modes, beta=tuple(d["beta"]), r=d["r"], m_bg=tuple(d["m_bg"]), k=d["k"],
                        alpha_s=d["alpha_s"], a_s=d["a_s"], b_s=d["b_s"], dw_ratio=d["dw_ratio"], **extra)


def _g(x):
    """GLSL float literal (always with a decimal point or exponent)."""
    s = repr(float(x))
    if s in ("inf", "-inf", "nan"):
        raise ValueError(f"cannot export non-finite value {s}")
    return s if ("." in s or "e" in s) else s + ".0"


def to_brdf_explorer(model):
    """The model as a BRDF Explorer ``.brdf`` file (text)."""
    P = []  # (name, min, max, default)

    def par(name, v, lo, hi):
        v = float(v)
        P.append((name, min(lo, v), max(hi, v), v))
        return name

    body = ["vec3 wi = vec3(dot(L, X), dot(L, Y), dot(L, N));",
            "vec3 wo = vec3(dot(V, X), dot(V, Y), dot(V, N));",
            "float vis = step(0.0, wi.z) * step(0.0, wo.z);",
            f"float cp = max(wi.z, {_g(COS_FLOOR)}) * max(wo.z, {_g(COS_FLOOR)});",
            "vec3 wr = vec3(-wi.x, -wi.y, wi.z);"]
    n = len(model.modes)
    for j, m in enumerate(model.modes):
        par(f"phi_a{j}", np.rad2deg(m.phi_a), 0.0, 180.0)
        par(f"w{j}", m.w, 0.01, 0.99)
        par(f"a{j}", m.a, -1.0, 2.0)
        par(f"b{j}", m.b, -1.0, 2.0)
        par(f"kd{j}", m.kd, 0.0, 1.0)
        par(f"ks{j}", m.ks, 0.0, 10.0)
        par(f"alpha{j}", m.alpha, 0.0, 300.0)
        for c, v in zip("rgb", m.m):
            par(f"m{j}{c}", v, 0.0, 4.0)
        src = "wr" if m.retro else "wi"
        body += [
            f"vec3 H{j} = normalize({src} + wo);",
            f"float F{j} = 1.0 - abs(dot(H{j}, vec3(sin(radians(phi_a{j})), cos(radians(phi_a{j})), 0.0)));",
            f"float E{j} = max(F{j} * (a{j} + b{j} / cp), 0.0);",
            f"float L{j} = kd{j} + ks{j} * pow(E{j}, alpha{j});",
            f"vec3 T{j} = vec3(m{j}r, m{j}g, m{j}b) * max(L{j}, 0.0);",
            f"float M{j} = smoothstep(w{j} - dw * w{j}, w{j} + dw * w{j}, F{j});",
        ]
    par("dw", model.dw_ratio, 0.01, 0.5)
    par("r", model.r, 0.0, 4.0)
    par("a_r", model.a_r, -1.0, 2.0)
    par("b_r", model.b_r, -1.0, 2.0)
    for c, v in zip("rgb", model.m_bg):
        par(f"mbg{c}", v, 0.0, 4.0)
    for j, b in enumerate(model.beta):
        par(f"beta{j}", b, 0.0, 1.0)
    for sfx, (k, al, a, b, f) in zip(("", "2"), lobes(model)):
        par(f"k{sfx}", k, 0.0, max(10.0, k))
        par(f"alpha_s{sfx}", al, 0.0, 1000.0)
        par(f"a_s{sfx}", a, -1.0, 2.0)
        par(f"b_s{sfx}", b, -1.0, 2.0)
        par(f"f_s{sfx}", f, 0.0, 2.0)
    par("jacobian", float(model.jacobian), 0.0, 1.0)
    if n:
        par("stencil_highlight", float(model.stencil_highlight), 0.0, 1.0)
    coloured = model.m_s is not None
    if coloured:
        for nm, col in (("ms", model.m_s), ("ms2", model.m_s if model.m_s2 is None else model.m_s2)):
            for c, v in zip("rgb", col):
                par(f"{nm}{c}", v, 0.0, 4.0)
    body.append(f"vec3 P{n} = r * max(a_r + b_r / cp, 0.0) * vec3(mbgr, mbgg, mbgb);")
    for j in range(n - 1, -1, -1):
        top = f"T{j}" if j == n - 1 else f"((1.0 - beta{j}) * T{j} + beta{j} * T{j + 1})"
        body.append(f"vec3 P{j} = (1.0 - M{j}) * P{j + 1} + M{j} * {top};")
    body += ["vec3 Hs = normalize(wi + wo);",
             f"float kh = clamp(dot(wi, Hs), {_g(COS_FLOOR)}, 1.0);",
             "float sch = pow(1.0 - kh, 5.0);",
             "float jac = mix(1.0, 1.0 / kh, jacobian);",
             "float shape = mix(1.0, pow(clamp(F0, 0.0, 1.0), alpha0), stencil_highlight);" if n else
             "float shape = 1.0;",
             "float l1 = k * pow(clamp(Hs.z, 0.0, 1.0), alpha_s) * max(a_s + (b_s + f_s * sch) / cp, 0.0) * jac"
             " * shape;",
             "float l2 = k2 * pow(clamp(Hs.z, 0.0, 1.0), alpha_s2) * max(a_s2 + (b_s2 + f_s2 * sch) / cp, 0.0) * jac"
             " * shape;",
             "float S = max(1.0, l1 + l2);"]
    if coloured:
        body += ["float boost = (S - 1.0) * dot(P0, vec3(0.2126, 0.7152, 0.0722)) / max(l1 + l2, 1e-30);",
                 "return vis * max(P0 + boost * (l1 * vec3(msr, msg, msb) + l2 * vec3(ms2r, ms2g, ms2b)), vec3(0.0));"]
    else:
        body.append("return vis * max(P0 * S, vec3(0.0));")
    lines = ["analytic", "",
             "# Adaptive highlight stencils BRDF (Filip, Havlicek, Vavra), fitted by facetsynth.stencil.",
             f"# {n} anisotropy mode(s); phi_a in degrees, U = [sin phi_a, cos phi_a, 0] in the (X, Y) frame.",
             "", "::begin parameters"]
    lines += [f"float {nm} {_g(lo)} {_g(hi)} {_g(v)}" for nm, lo, hi, v in P]
    lines += ["::end parameters", "", "::begin shader", "",
              "vec3 BRDF( vec3 L, vec3 V, vec3 N, vec3 X, vec3 Y )", "{"]
    lines += ["    " + s for s in body]
    lines += ["}", "", "::end shader", ""]
    return "\n".join(lines)
