"""BRDF Explorer shader: structure, and a transliteration of its GLSL body to Python
evaluated at sample directions against facetsynth.stencil.model.evaluate."""

import re

import numpy as np
import pytest

from facetsynth.stencil import grid, model
from facetsynth.stencil.export import to_brdf_explorer


class V(np.ndarray):
    x = property(lambda s: s[0])
    y = property(lambda s: s[1])
    z = property(lambda s: s[2])


def _vec3(*a):
    a = a * 3 if len(a) == 1 else a
    return np.array([float(v) for v in a]).view(V)


def _smoothstep(e0, e1, x):
    t = min(max((x - e0) / (e1 - e0), 0.0), 1.0)
    return t * t * (3 - 2 * t)


def _max(a, b):
    return np.maximum(a, b).view(V) if np.ndim(a) or np.ndim(b) else max(a, b)


GLSL = {"vec3": _vec3, "dot": lambda a, b: float(np.dot(a, b)), "normalize": lambda v: (v / np.linalg.norm(v)).view(V),
        "max": _max, "abs": abs, "pow": lambda a, b: float(a) ** float(b), "sin": np.sin, "cos": np.cos,
        "radians": np.deg2rad, "clamp": lambda x, a, b: min(max(x, a), b), "smoothstep": _smoothstep,
        "step": lambda e, x: 0.0 if x < e else 1.0, "mix": lambda a, b, t: a * (1 - t) + b * t}


def run_shader(text, L, V_):
    params = dict((m.group(1), float(m.group(2))) for m in
                  re.finditer(r"^float (\w+) \S+ \S+ (\S+)$", text, re.M))
    body = text.split("vec3 BRDF( vec3 L, vec3 V, vec3 N, vec3 X, vec3 Y )\n{")[1].split("\n}")[0]
    ns = dict(GLSL, **params, L=_vec3(*L), V=_vec3(*V_), N=_vec3(0, 0, 1), X=_vec3(1, 0, 0), Y=_vec3(0, 1, 0))
    for line in body.strip().splitlines():
        line = line.strip().rstrip(";")
        line = re.sub(r"^(float|vec3) ", "", line)
        line = re.sub(r"^return ", "__ret = ", line)
        exec(line, ns)
    return np.asarray(ns["__ret"], float)


def _model(n, retro=False, extended=False):
    cols = [(0.2, 0.3, 0.9), (0.9, 0.2, 0.1), (0.1, 0.8, 0.2)]
    modes = tuple(model.Mode(np.deg2rad(p), w, 0.4, 0.04, 0.05, 1.0, 6.0, c, retro=(retro and i == 1))
                  for i, (p, w, c) in enumerate(zip((20, 110, 60), (0.75, 0.65, 0.6), cols[:n])))
    # extended: the fit's second lobe, highlight colours, background elevation scaling, Schlick term, Jacobian,
    # the highlight shaped by the dominant mode's stencil
    more = dict(k2=2.0, alpha_s2=8.0, a_s2=0.3, b_s2=0.02, m_s=(1.0, 0.9, 0.8), m_s2=(0.5, 1.0, 1.5),
                a_r=1.1, b_r=-0.05, f_s=0.3, f_s2=0.1, jacobian=True, stencil_highlight=n > 0) if extended else {}
    return model.StencilModel(modes, tuple([0.3, 0.1][: max(n - 1, 0)]), 0.05,
                              modes[-1].m if modes else (0.1, 0.1, 0.1), 4.0, 60.0, 0.4, 0.04, **more)


def test_shader_structure():
    t = to_brdf_explorer(_model(2))
    assert t.startswith("analytic\n")
    for tag in ("::begin parameters", "::end parameters", "::begin shader", "::end shader"):
        assert t.count(tag) == 1
    assert "vec3 BRDF( vec3 L, vec3 V, vec3 N, vec3 X, vec3 Y )" in t
    for name in ("phi_a0", "phi_a1", "w0", "w1", "beta0", "k", "alpha_s", "r"):
        assert re.search(rf"^float {name} \S+ \S+ \S+$", t, re.M), name
    # every numeric literal is a GLSL float (has a '.' or an exponent), none an int
    nums = re.findall(r"(?<![\w.])[-+]?\d[\d.eE+-]*", t.split("::begin parameters")[1])
    assert nums and all(("." in x or "e" in x.lower()) for x in nums), nums
    assert "20.0" in t.split("phi_a0")[1].split("\n")[0]


@pytest.mark.parametrize("n,retro,extended", [(0, False, False), (1, False, False), (2, False, False),
                                              (3, False, False), (2, True, False), (0, False, True),
                                              (2, False, True)])
def test_shader_transliteration_matches_python(n, retro, extended):
    m = _model(n, retro, extended)
    text = to_brdf_explorer(m)
    rng = np.random.default_rng(n)
    wi = grid.sph_to_dir(np.arccos(rng.uniform(0.05, 1, 25)), rng.uniform(0, 2 * np.pi, 25))
    wo = grid.sph_to_dir(np.arccos(rng.uniform(0.05, 1, 25)), rng.uniform(0, 2 * np.pi, 25))
    wo[:5] = wi[:5] * [-1, -1, 1]  # mirror pairs: the specular term is exercised too
    ref = model.evaluate(m, wi, wo)
    got = np.array([run_shader(text, a, b) for a, b in zip(wi, wo)])
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    assert np.ptp(ref) > 0  # a test that can fail: the directions see varying values
