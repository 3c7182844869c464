"""Per-point refinement: eq. 6 read forwards, fitted to each point's own samples (issue 29).

The paper's pipeline (secs. 5.1-5.4) gives every point an NDF (an eq. 18
mixture of completed representative NDFs, turned by the point's eq. 13
rotation), an eta, and ks and kd through clustering and eq. 9. Those are
shared by a cluster or biased by a threshold: ks was constant per cluster
(wedges on the demo's turned copper), and nothing asked the model to
reproduce the samples it was fitted on. With the NDF, shadowing and Fresnel
fixed, eq. 6 is linear in kd and ks per channel,

    rho(x, i, o) = kd(x)/pi + ks(x) g(x, i, o),   g = D(h) F(|i.h|) / (4 A(i) A(o)),

so each point's kd and ks follow from its valid samples by a 2 x 2 least
squares per channel, weighted as the capture weighs them: in radiance,
I = rho (n.i) L / r^2 (eq. 8), the quantity the self-check and the held-out
views score. A small ridge towards the pipeline's values keeps points whose
samples do not constrain ks (no highlight in view) where the pipeline put
them; kd, ks >= 0 (the constrained solution on the boundary otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NormalSums:
    """Per point and channel the sums of the weighted least squares of rho = a + b g, a = kd/pi, b = ks:
    each (N, 3) (``u`` the sample weights, ``y`` the observed rho)."""
    u: np.ndarray       # sum u
    ug: np.ndarray      # sum u g
    ugg: np.ndarray     # sum u g^2
    uy: np.ndarray      # sum u y
    ugy: np.ndarray     # sum u g y
    uyy: np.ndarray     # sum u y^2

    @classmethod
    def of(cls, point: np.ndarray, n_points: int, y: np.ndarray, g: np.ndarray, u: np.ndarray) -> "NormalSums":
        """Accumulate samples: ``point`` (S,) index in [0, n_points), ``y`` (S, 3) observed rho, ``g`` (S,)
        the specular factor, ``u`` (S, 3) weights."""
        def total(values):
            return np.stack([np.bincount(point, values[:, c], minlength=n_points) for c in range(3)], -1)
        gg = g[:, None]
        return cls(total(u), total(u * gg), total(u * gg * gg), total(u * y), total(u * gg * y), total(u * y * y))

    def sse(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(N, 3) weighted sum of squared residuals of rho = a + b g (expanded: no second pass)."""
        out = (self.uyy - 2 * a * self.uy - 2 * b * self.ugy + a * a * self.u + 2 * a * b * self.ug
               + b * b * self.ugg)
        return np.maximum(out, 0.0)


def solve(sums: NormalSums, a0: np.ndarray, b0: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """The non-negative least-squares (a, b) per point and channel, with a ridge towards (a0, b0).

    Minimises sum u (y - a - b g)^2 + lam ((a - a0)^2 + (b - b0)^2 s), lam = ridge x sum u (the prior
    counts as ``ridge`` of the point's samples), s = sum u g^2 / sum u (b's own scale). Where the samples
    do not constrain b (no g > 0: no highlight in view), b keeps b0 and a fits the samples given it. Where the
    unconstrained optimum has a < 0 or b < 0, the best with that one at 0 is taken (the 2-variable NNLS:
    the optimum with both at 0 is never better than one of these, as sum u y >= 0 when y >= 0). A point
    without samples (sum u = 0) keeps (a0, b0).
    """
    lam = ridge * sums.u
    s = np.divide(sums.ugg, sums.u, out=np.zeros_like(sums.u), where=sums.u > 0)
    m11, m12, m22 = sums.u + lam, sums.ug, sums.ugg + lam * s
    r1, r2 = sums.uy + lam * a0, sums.ugy + lam * s * b0
    det = m11 * m22 - m12 * m12
    ok = det > 1e-12 * np.maximum(m11 * m22, 1e-300)
    safe = np.where(ok, det, 1.0)
    # singular (no g > 0 among the samples: ks unconstrained): b stays b0, a fits the samples given it
    a_given_b0 = np.divide(r1 - m12 * b0, m11, out=a0.copy(), where=m11 > 0)
    a = np.where(ok, (m22 * r1 - m12 * r2) / safe, a_given_b0)
    b = np.where(ok, (m11 * r2 - m12 * r1) / safe, b0)
    # boundary solutions: b = 0 (a alone) and a = 0 (b alone)
    a_only = np.divide(r1, m11, out=np.zeros_like(r1), where=m11 > 0)
    b_only = np.divide(r2, m22, out=np.zeros_like(r2), where=m22 > 0)
    neg_b, neg_a = b < 0, a < 0
    a = np.where(neg_b, np.maximum(a_only, 0.0), a)
    b = np.where(neg_b, 0.0, b)
    b = np.where(neg_a & ~neg_b, np.maximum(b_only, 0.0), b)
    a = np.where(neg_a & ~neg_b, 0.0, a)
    empty = sums.u <= 0
    return np.where(empty, a0, a), np.where(empty, b0, b)


def radiance_weights(wi: np.ndarray, r2: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """u = ((n.i) L / r^2)^2 per sample and channel (..., 3): least squares on rho weighted by u is least
    squares on the radiance I = rho (n.i) L / r^2 of eq. 8."""
    e = np.clip(wi[..., 2], 0.0, None) / r2
    return (e[..., None] * intensity) ** 2
