"""Camera response of 8-bit exposures (Debevec and Malik 1997, "Recovering High Dynamic Range Radiance
Maps from Photographs", SIGGRAPH '97).

An 8-bit camera (JPEG) stores code ``Z = f(t I)`` of the exposure value ``t I`` through an unknown monotone
response ``f``. Debevec and Malik recover ``g = ln f^-1`` from pixels ``i`` seen at exposures ``j``:

    g(Z_ij) = ln E_i + ln t_j                                      (eq. 2)

solved in the least-squares sense with a hat weighting ``w(z)`` and a smoothness term
``lambda * sum w(z) g''(z)^2`` (eq. 3), over the 256 values of ``g`` and the ``P`` unknown ``ln E_i``;
``N (P - 1) > Z_max - Z_min`` samples are needed (sec. 2.1). The solver is OpenCV's
``cv2.createCalibrateDebevec`` (which fixes g(128) = 0), fed with pixels picked by this module.

The scale: the recovered ``f^-1`` is determined up to one factor per channel. It is fixed so that the
clipping level -- the exposure value where code 255 starts -- is exposure value 1, in every channel:
``value = min(1, t I)``, as the rig's RAW path has it (:func:`facetsynth.rig.cameras.decode_raw`) and as
the manifest's ``saturation`` 1 says, the JPEG's white balance kept (255, 255, 255 is white). The level is
found in the data (:func:`_clipping_exposure`): at each exposure, the pixels whose radiance is known from
the other exposures split into those with code 255 and the others at the level that misclassifies the
fewest (robust to sensor noise: the tests state the figures). A bracket in which
nothing clips falls back on a power law: ``ln f^-1`` against ``ln z`` fitted over codes ``fit_codes``
(default 128..250; gamma-like curves are nearly straight there), extrapolated to 1 at code 255 (close
for gamma-like curves, too low an exposure for a curve with a shoulder). Codes above 250, the least
constrained by eq. 3, follow that line (or the chord to 1 at code 254.5); code 0 is exposure 0 (below the
noise floor).

The linearized values are merged by :func:`facetsynth.capture.hdr.merge_exposures` with the sensor model
:meth:`Response.sensor_model`: code 255 is clipped, code 0 is the noise floor, and the noise is the 8-bit
quantisation's, var = step(v)^2 / 12 with ``step`` the linearized width of one code (fitted as
read_sigma^2 + shot_gain v).

A manifest may instead declare the transfer function (:mod:`facetsynth.capture.transfer`: sRGB, linear, gamma)
and a black level: :meth:`Response.from_transfer` then stands in for the recovered curve (no bracket
needed), with the same scale (code 255 decodes to 1) and the same sensor model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..io.errors import InputError
from .hdr import SensorModel
from .transfer import Transfer, table

LEVELS = 256

TRANSFER_HINT = ('or, without a bracket, declare "transfer": "srgb" in the manifest for sRGB photos (JPEG) '
                 '("linear" or {"gamma": G} for other codings; one exposure per frame is then enough)')
"""How to do without a bracket, for the errors of :func:`recover_response`."""


@dataclass(frozen=True)
class ResponseSettings:
    """How the response is recovered: ``samples`` pixels (a square number is used: OpenCV samples a grid),
    the smoothness weight ``smoothness`` (lambda of eq. 3), the codes ``fit_codes`` that fix the scale, and
    the least coverage of the codes by unclipped samples (``min_coverage``, a fraction of the 16-code bins
    of 1..254) below which the bracket is refused."""

    samples: int = 400
    smoothness: float = 10.0
    fit_codes: tuple[int, int] = (128, 250)
    min_coverage: float = 0.5


@dataclass(frozen=True)
class Response:
    """An 8-bit camera's inverse response: ``linear[z, c]`` is the exposure value ``t I`` of code ``z`` in
    channel ``c`` (non-decreasing; 0 at code 0 -- and at the codes at or below a declared black level --,
    1 at code 255)."""

    linear: np.ndarray                    # (256, 3) float64
    scale_from: tuple[str, ...] = ()      # per channel: "clipping", "power law" (module docstring) or "transfer"

    @classmethod
    def from_transfer(cls, transfer: Transfer, black_level: float = 0.0) -> "Response":
        """The response of a declared transfer function and black level (:func:`facetsynth.capture.transfer.table`:
        ``max(0, L - b) / (1 - b)``, so code 255 is 1 and the codes at or below the black level are 0), the
        same in every channel."""
        lut = table(transfer, black_level)
        return cls(np.repeat(lut[:, None], 3, axis=1), ("transfer",) * 3)

    def linearize(self, codes: np.ndarray) -> np.ndarray:
        """Exposure values (float32) of 8-bit ``codes`` (..., 3): ``f^-1`` looked up per channel."""
        codes = np.asarray(codes)
        lut = self.linear.astype(np.float32)
        return np.stack([lut[codes[..., c], c] for c in range(codes.shape[-1])], axis=-1)

    def sensor_model(self, floor_sigmas: float = 3.0) -> SensorModel:
        """The 8-bit merge's sensor model: saturation 1 with a margin that puts the clip level halfway
        between code 254 and 255 (only 255 is clipped); read_sigma the quantisation noise of the lowest code
        above 0 (code 1, or the first code above a declared black level), so that with the default
        ``floor_sigmas`` 3 (< sqrt 12) only the codes at 0 are at the noise floor; shot_gain the
        least-squares slope of the quantisation variance step(v)^2 / 12 - read_sigma^2 against v."""
        lin = self.linear
        margin = float(np.min(1.0 - lin[254])) / 2.0
        positive = np.where(lin > 0, lin, np.inf).min(axis=0)     # per channel: its lowest value above 0
        read_sigma = float(np.min(np.where(np.isfinite(positive), positive, 0.0))) / np.sqrt(12.0)
        step = np.diff(lin, axis=0)                               # (255, 3): code z -> z + 1
        v = lin[1:255]
        q = ((step[:-1] + step[1:]) / 2.0) ** 2 / 12.0            # variance at codes 1..254
        excess = q - read_sigma**2
        ratio = np.divide(v, q, out=np.zeros_like(v), where=q > 0)
        shot_gain = float(max(0.0, np.sum(ratio * excess / np.where(q > 0, q, 1.0)) / max(np.sum(ratio**2), 1e-300)))
        return SensorModel(saturation=1.0, read_sigma=read_sigma, shot_gain=shot_gain,
                           floor_sigmas=floor_sigmas, saturation_margin=max(margin, 1e-7))

    def to_json(self) -> dict:
        """The curve for metrics: ``linear`` (256 x 3 exposure values of codes 0..255) and how it was scaled."""
        declared = set(self.scale_from) == {"transfer"}
        return {"linear": np.round(self.linear, 8).tolist(),
                "scale": ("exposure value 1 = code 255 (declared transfer)" if declared else
                          "exposure value 1 = where code 255 starts (clipping), in each channel"),
                "scale_from": list(self.scale_from)}


def pooled_series(stacks: Sequence[np.ndarray], limit: int = 250_000) -> np.ndarray:
    """The pixel series of brackets ``stacks`` (each (E, H, W, 3) uint8, the same times) pooled: (E, N, 3),
    at most ``limit`` pixels (evenly strided)."""
    series = np.concatenate([s.reshape(s.shape[0], -1, s.shape[-1]) for s in stacks], axis=1)
    stride = max(1, int(np.ceil(series.shape[1] / limit)))
    return series[:, ::stride]


def sample_pixels(series: np.ndarray, count: int) -> np.ndarray:
    """Pixels for eq. 2 from pooled pixel series (E, N, 3) uint8: (E, count, 3).

    Debevec and Malik pick pixels with values spread over the range: pixels are sorted by their mean code
    over exposures and channels (monotone in radiance), those clipped or black in every exposure left out,
    and ``count`` are taken at evenly spaced values of that mean, so bright and dark radiances are
    sampled alike whatever the image's histogram.
    """
    mean = series.mean(axis=(0, 2))
    informative = np.flatnonzero((series < 255).any(axis=(0, 2)) & (series > 0).any(axis=(0, 2)))
    if informative.size == 0:
        return series[:, :0]
    order = informative[np.argsort(mean[informative], kind="stable")]
    targets = np.linspace(mean[order[0]], mean[order[-1]], count)
    picks = np.clip(np.searchsorted(mean[order], targets), 0, order.size - 1)
    return series[:, order[picks]]


def recover_response(stacks: Sequence[np.ndarray], times: Sequence[float],
                     settings: ResponseSettings = ResponseSettings(), source: str | None = None) -> Response:
    """Recover the inverse response from exposure brackets (Debevec and Malik 1997, eq. 2-3).

    ``stacks``: brackets of one or more frames, each (E, H, W, 3) uint8 taken with ``times`` (E,) seconds.
    Raises InputError (naming ``source``) when the bracket cannot determine a response: fewer than 2
    distinct times, or unclipped samples covering less than ``min_coverage`` of the codes.
    """
    import cv2

    times = np.asarray(times, np.float64).ravel()
    where = "" if source else "exposure bracket: "
    distinct = np.unique(np.round(np.log2(times), 3)) if times.size else times
    if distinct.size < 2:
        raise InputError(source, f"{where}{times.size} exposure(s) at {distinct.size} distinct time(s): the camera "
                                 "response of 8-bit files needs a bracket of at least 2 (better 3 or more, a stop or "
                                 f"more apart); {TRANSFER_HINT}")
    side = max(int(np.ceil(np.sqrt(settings.samples))), 2)
    series = pooled_series(stacks)
    picked = sample_pixels(series, side * side)                          # (E, P, 3)
    covered = _coverage(picked)
    if picked.shape[1] == 0 or covered < settings.min_coverage:
        raise InputError(source, f"{where}the {times.size} exposures ({', '.join(f'{t:g}' for t in times)} s) "
                                 f"cover {covered:.0%} of the 8-bit codes in unclipped pixels (need "
                                 f"{settings.min_coverage:.0%}): too short a bracket, or a too uniform scene, to "
                                 f"recover the camera response; {TRANSFER_HINT}")
    images = [np.ascontiguousarray(picked[e].reshape(side, side, 3)) for e in range(times.size)]
    calibrate = cv2.createCalibrateDebevec(samples=side * side, lambda_=float(settings.smoothness), random=False)
    curve = calibrate.process(images, times.astype(np.float32)).reshape(LEVELS, 3).astype(np.float64)
    return _normalise(curve, series, times, settings.fit_codes, source)


def _coverage(picked: np.ndarray) -> float:
    """The fraction of the 16 code bins of 1..254 holding some unclipped sample value."""
    values = picked[(picked > 0) & (picked < 255)]
    return float(np.unique(values // 16).size) / 16.0


def _normalise(curve: np.ndarray, series: np.ndarray, times: np.ndarray, fit_codes: tuple[int, int],
               source: str | None = None) -> "Response":
    """The response at the module docstring's scale: monotone, 0 at code 0, 1 at code 255, finite.

    Each channel's factor comes from where pixels start to clip (:func:`_clipping_exposure`: exposure 1
    at code 254.5) when the bracket has clipped pixels, codes above ``fit_codes[1]`` then on the log-log
    chord up to it; otherwise from the power law of codes ``fit_codes`` extrapolated to 255,
    which then also replaces the curve above ``fit_codes[1]``.
    """
    curve = np.where(np.isfinite(curve) & (curve > 0), curve, np.nan)
    log_curve = np.log(curve)
    lo, hi = fit_codes
    z = np.log(np.arange(lo, hi + 1))
    out = np.empty_like(curve)
    anchors = []
    for c in range(curve.shape[1]):
        y = log_curve[lo:hi + 1, c]
        ok = np.isfinite(y)
        if ok.sum() < 2:
            raise InputError(source, "camera response: no finite values to fix its scale (codes "
                                   f"{lo}..{hi}); the bracket did not reach them")
        slope, intercept = np.polyfit(z[ok], y[ok], 1)
        if not slope > 0:
            raise InputError(source, f"camera response: channel {c} does not increase over codes {lo}..{hi} "
                                   f"(slope {slope:.3g} of ln exposure against ln code); not an 8-bit bracket")
        relative = np.nan_to_num(curve[:, c], nan=0.0)
        clip_at = _clipping_exposure(relative, series[..., c], times)
        if clip_at is not None:
            col = relative / clip_at
            # Codes above ``hi`` (the least constrained) follow the log-log chord from code hi to exposure 1
            # at code 254.5, where code 255 starts: below 1, so only 255 is clipped.
            top = np.arange(hi + 1, LEVELS - 1)
            if col[hi] > 0:
                col[top] = col[hi] ** ((np.log(254.5) - np.log(top)) / (np.log(254.5) - np.log(hi)))
            anchors.append("clipping")
        else:
            # ln f^-1 against ln z is nearly straight for gamma-like curves: codes above ``hi`` follow the
            # line, which reaches exposure 1 at code 255.
            col = np.exp(np.nan_to_num(log_curve[:, c], nan=-np.inf) - (slope * np.log(255.0) + intercept))
            top = np.arange(hi + 1, LEVELS)
            col[top] = np.exp(slope * (np.log(top) - np.log(255.0)))
            anchors.append("power law")
        col[0], col[255] = 0.0, 1.0
        out[:, c] = np.minimum(np.maximum.accumulate(np.nan_to_num(col, nan=0.0, posinf=1.0)), 1.0)
    return Response(out, tuple(anchors))


def _clipping_exposure(relative: np.ndarray, series: np.ndarray, times: np.ndarray, least: int = 5) -> float | None:
    """The exposure value, on the relative curve's scale, at which one channel clips (code 255); None when
    no exposure of the bracket has at least ``least`` clipped and ``least`` unclipped pixels.

    At each exposure t_j, every pixel's relative exposure rate E is taken from its OTHER exposures (eq. 6:
    a hat-weighted mean of relative[Z_k] / t_k, codes 0 and 255 weighing nothing); the pixels with code
    255 should be those with t_j E above the clipping level. The level is the split of t_j E that
    misclassifies the fewest pixels (so a few noisy or JPEG-ringing pixels on either side do not move it),
    at the geometric mean of its two neighbours; the median over the exposures with both kinds.
    """
    codes = series.astype(np.intp)                                # (E, N)
    weight = np.minimum(codes, 255 - codes).astype(np.float64)
    terms = weight * relative[codes] / times[:, None]
    weight_all, terms_all = weight.sum(axis=0), terms.sum(axis=0)
    levels = []
    for j, t in enumerate(times):
        weight_other = weight_all - weight[j]
        known = (weight_other > 0) & (codes[j] > 0)
        clipped = codes[j][known] == 255
        if clipped.sum() < least or (~clipped).sum() < least:
            continue
        exposure = t * (terms_all - terms[j])[known] / weight_other[known]
        order = np.argsort(exposure, kind="stable")
        x, y = exposure[order], clipped[order]
        # Misclassified with the split before position i: clipped below it plus unclipped from it on.
        below = np.concatenate([[0], np.cumsum(y)])
        above = np.concatenate([np.cumsum((~y)[::-1])[::-1], [0]])
        i = int(np.argmin(below + above))
        if 0 < i < x.size:
            level = np.sqrt(x[i - 1] * x[i])
            if np.isfinite(level) and level > 0:
                levels.append(level)
    return float(np.median(levels)) if levels else None
