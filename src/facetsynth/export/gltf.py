"""Portable export: the fitted SVBRDF as a glTF 2.0 material on a quad (issue 17 item 3).

``export_gltf(model_dir, out_dir)`` fits, per point of the sample-plane grid, the standard anisotropic GGX
material of glTF 2.0 (:mod:`facetsynth.models.ggx`: Appendix B's metallic-roughness BRDF with
KHR_materials_anisotropy, KHR_materials_specular and KHR_materials_ior) to the SVBRDF of paper 002 eq. 6,
and writes it as textures on a quad whose uv maps to the plane grid:

    sample.gltf, sample.bin      the scene: one node, one quad (POSITION, NORMAL, TANGENT, TEXCOORD_0), one material
    base_color.png               RGB, sRGB: baseColor
    metallic_roughness.png       RGB, linear: G roughness, B metallic (0; R unused, 255)
    anisotropy.png               RGB, linear: RG the anisotropy direction (x, y) * 0.5 + 0.5, B the strength
    specular.png                 RGBA: RGB the specular colour / specularColorFactor (sRGB), A the specular weight
    normal.png                   RGB, linear (only when the model has shading normals): the core spec's
                                 normalTexture, the tangent-space normal (n + 1) / 2, scale 1

The fit (:func:`fit_material`):

* NDF: an anisotropic GGX (alpha_x >= alpha_y, frame azimuth, scale c) per point by
  :func:`facetsynth.models.ggx.fit_ggx_ndf` on the point's eq. 18 mixture before its eq. 13 turn (the turn is added
  to the fitted azimuth exactly). Mixtures are fitted once per distinct weight vector, weights rounded to
  ``weight_quantum``. alpha_t = alpha_x, alpha_b = alpha_y give roughness = sqrt(alpha_y) and strength =
  sqrt((alpha_x - alpha_y) / (1 - alpha_y)); the anisotropy direction is the azimuth of alpha_x's axis.
* Specular: eq. 6's lobe is K F(|i.h|, eta) D / (4 A(i) A(o)) with K = c ks (c: the table's grid
  normalisation against the continuous GGX). glTF's is F_schlick V D with f0 = min(F0(ior) specularColor, 1)
  specular and f90 = specular. ior is one number for the material (KHR_materials_ior has no texture): the
  median fitted eta. specular = min(max(K), 1) (the grazing reflectance) and specularColor = f0 / (F0(ior)
  specular) with f0 per channel the Schlick curve's nearest K F(c, eta) over c = |v.h| in
  [``fresnel_cos_min``, 1] (:func:`schlick_f0`; 1: f0 = K F0(eta), exact at normal incidence only). Schlick's
  curve lies 10-20 % below eq. 3's at c = 0.6-0.8 for eta 1.5-1.8, where a flat sample's highlights are seen
  from 35-55 deg; the least-squares f0 takes that into the reflectance (demo: held-out loss 0.011 -> 0.001).
* Diffuse: glTF scales the base colour by (1 - max(F)); baseColor = kd / (1 - max(f0)) makes the diffuse
  term kd / pi where the Fresnel weight is f0 (everywhere but grazing |v.h|). metallic = 0.

Frames: glTF is y-up; the quad lies in glTF's x-z plane with (X, Y, Z) = (x, z, -y) of the sample plane
(a rotation; Blender's importer turns it back into the sample frame, z up). uv (0, 0) is the grid's
top-left corner (row 0 is the +y edge), u along +x, v along -y; tangent +x (w = +1), so the bitangent
n x t is +y and an anisotropy angle is the sample-plane azimuth from +x towards +y.

Shading normals: glTF's normalTexture holds the normal in tangent space, "+X right, +Y up, +Z toward the
viewer", X along the TANGENT attribute, Y along the bitangent cross(NORMAL, TANGENT.xyz) TANGENT.w, and
"up" is up in the image (towards v = 0: glTF's uv origin is the image's top-left corner). The quad's
tangent is +x (= +u), its bitangent +y (= -v, the image's up: row 0 is the +y edge), its normal +z, so
the tangent-space normal IS the model's normal in the plane's frame: RGB = (n_x, n_y, n_z) / 2 + 1/2, no
swizzle or flip, row r of the image = row r of the plane grid as the other textures. A renderer reads
n = normalize(2 RGB - 1) (8 bits: about 0.33 deg at most, a half code in each channel; n = +z itself reads
back 0.32 deg off, 0.5 having no 8-bit code; :func:`round_trip_errors`' ``normal_angle_deg``). The
BRDF fitted per point is the one of eq. 6 in the point's shading frame (the model's tables are local), so
the lobes are fitted unchanged and the normal texture turns them as the model's frames do, up to the twist
about the tilted normal of a renderer's perturbed tangent (usually the tangent made orthogonal to the new
normal, Gram-Schmidt, where facetsynth.fit.normals turns the frame by the smallest rotation): 0 for normals
leaning along x or y only, at most about tilt^2 / 4 radians otherwise (0.44 deg at a 10 deg tilt, 4.1 deg
at 30 deg), an anisotropic lobe's axis only.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from ..io.colour import srgb_decode, srgb_encode
from ..io.errors import InputError
from ..io.fileio import atomic_path, read_json
from ..models.ggx import (FIT_ALPHA_RANGE, GltfMaterial, _MomentDictionary, dielectric_f0, fit_ggx_ndf,
                          roughness_strength)
from ..models.microfacet import fresnel
from ..fit.normals import shading_frames
from ..io.outputs import output_folder
from ..geometry.plane import PlaneGrid

log = logging.getLogger(__name__)

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas" / "gltf"   # package data: KhronosGroup/glTF, unmodified
EXTENSIONS = ("KHR_materials_anisotropy", "KHR_materials_specular", "KHR_materials_ior")
GLTF_NAME, BIN_NAME = "sample.gltf", "sample.bin"
IMAGES = {"base_color": "base_color.png", "metallic_roughness": "metallic_roughness.png",
          "anisotropy": "anisotropy.png", "specular": "specular.png"}
NORMAL_IMAGE = "normal.png"       # written when the model has shading normals (the material's normalTexture)
ALL_IMAGES = dict(IMAGES, normal=NORMAL_IMAGE)
FIT_CHUNK = 256          # mixtures fitted per batch: bounds the fit's memory (256 x cells x 4 doubles)
LINEAR, LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE = 9729, 9987, 33071
FLOAT, UNSIGNED_SHORT, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 5126, 5123, 34962, 34963


def _to_byte(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(x, float) * 255.0), 0, 255).astype(np.uint8)


@dataclass
class NormalMappedMaterial(GltfMaterial):
    """A :class:`facetsynth.models.ggx.GltfMaterial` with the per-point shading normals of its normalTexture.

    ``normal`` (P, 3) unit normals in the sample plane's frame (None: flat). As for
    :class:`facetsynth.models.svbrdf.SVBRDF`, :meth:`eval_index` takes directions in each point's shading frame
    and :meth:`frames` gives the rotations R (R n = +z, :func:`facetsynth.fit.normals.shading_frames`) that take
    world directions there.
    """

    normal: np.ndarray | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.normal is not None:
            n = np.asarray(self.normal, float)
            if n.shape != (self.n_points, 3):
                raise ValueError(f"GltfMaterial normal has shape {n.shape}, expected {(self.n_points, 3)}")
            self.normal = n

    def frames(self, index: np.ndarray) -> np.ndarray:
        """The shading frames (..., 3, 3) of points ``index``; the identity where ``normal`` is None."""
        index = np.asarray(index, np.intp)
        if self.normal is None:
            return np.broadcast_to(np.eye(3), index.shape + (3, 3)).copy()
        return shading_frames(self.normal[index])


def normal_angles(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray:
    """Angles (P,) in degrees between two fields of unit normals (None: +z everywhere)."""
    flat = np.array([0.0, 0.0, 1.0])
    a = flat if a is None else np.asarray(a, float)
    b = flat if b is None else np.asarray(b, float)
    a, b = np.broadcast_arrays(a, b)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, -1)))


# --- the fit ------------------------------------------------------------------------------------------------

def schlick_f0(k: np.ndarray, eta: np.ndarray, f90: np.ndarray, cos_min: float = 0.5, nodes: int = 32) -> np.ndarray:
    """f0 (P, 3) of the Schlick Fresnel f0 + (f90 - f0) (1 - c)^5 nearest eq. 6's k F(c, eta) (eq. 3, exact
    dielectric) in L2 over c = |v.h| uniform in [``cos_min``, 1] (k (P, 3), eta (P,), f90 (P,)); ``cos_min`` = 1:
    the normal-incidence reflectance k F(1, eta). Linear least squares: one closed form for every point."""
    if cos_min >= 1.0:
        return k * fresnel(1.0, eta)[:, None]
    x, w = np.polynomial.legendre.leggauss(nodes)
    c = cos_min + (1.0 - cos_min) * 0.5 * (x + 1.0)
    s = (1.0 - c) ** 5
    target = k[:, None, :] * fresnel(c[None, :], np.asarray(eta, float)[:, None])[..., None]     # (P, Q, 3)
    rest = target - np.asarray(f90, float)[:, None, None] * s[None, :, None]
    return np.clip(np.einsum("q,pqc->pc", w * (1.0 - s), rest) / np.sum(w * (1.0 - s) ** 2), 0.0, None)


def fit_material(model, weight_quantum: float = 0.01, iterations: int = 12,
                 fresnel_cos_min: float = 0.5) -> tuple[NormalMappedMaterial, dict[str, Any]]:
    """The glTF material nearest the SVBRDF ``model`` per point (module docstring) and a record of the fit
    (per-point arrays ``alpha_x``, ``alpha_y``, ``scale``, ``ndf_rel_l2`` and summary figures). The model's
    shading normals (if any) pass through unchanged: the lobes are fitted in each point's frame."""
    start = time.perf_counter()
    p, r = model.n_points, model.ndf.shape[0]
    quantised = np.zeros((p, r), np.int32)
    steps = np.round(np.asarray(model.weights, float) / weight_quantum).astype(np.int32)
    np.add.at(quantised, (np.repeat(np.arange(p), model.neighbours.shape[1]), model.neighbours.ravel()),
              steps.ravel())
    unique, owner = np.unique(quantised, axis=0, return_inverse=True)
    owner = owner.ravel()
    flat = np.asarray(model.ndf, float).reshape(r, -1)
    dictionary = _MomentDictionary.build(model.grid)
    fits = []
    for s in range(0, len(unique), FIT_CHUNK):
        tables = np.maximum((unique[s:s + FIT_CHUNK] * weight_quantum) @ flat, 0.0)
        fits.append(fit_ggx_ndf(tables.reshape((-1,) + model.grid.shape), model.grid, iterations=iterations,
                                fit_scale=True, dictionary=dictionary))
    fit = {k: np.concatenate([f[k] for f in fits])[owner] for k in fits[0]}
    empty = ~(unique != 0).any(axis=1)[owner]      # no NDF at all: no specular lobe
    # the rounded weights' sum (the mixture's integral) back to the point's own: the scale carries it
    rounded = quantised.sum(axis=1) * weight_quantum
    with np.errstate(divide="ignore", invalid="ignore"):
        own = np.where(rounded != 0, np.asarray(model.weights, float).sum(axis=1) / rounded, 0.0)
    fit["scale"] = np.where(empty, 0.0, fit["scale"] * own)
    turn = np.zeros(p) if model.rotation is None else np.asarray(model.rotation, float)
    angle = fit["phi"] - turn                      # D(x, h) = D_mix(R(turn) h): the frame turns back by it
    angle = np.pi / 2 - np.mod(np.pi / 2 - angle, np.pi)
    roughness, strength = roughness_strength(fit["alpha_x"], fit["alpha_y"])

    eta = np.asarray(model.eta, float)
    fitted = model.eta_fitted if model.eta_fitted is not None and np.any(model.eta_fitted) else np.ones(p, bool)
    ior = float(max(np.median(eta[fitted]), 1.0))
    k = np.clip(np.asarray(model.ks, float), 0.0, None) * fit["scale"][:, None]
    specular = np.clip(k.max(axis=-1), 0.0, 1.0)
    f0_point = schlick_f0(k, eta, specular, fresnel_cos_min)
    with np.errstate(divide="ignore", invalid="ignore"):
        colour = np.where(specular[:, None] > 0, f0_point / (dielectric_f0(ior) * specular[:, None]), 1.0)
    f0 = np.minimum(dielectric_f0(ior) * colour, 1.0) * specular[:, None]
    base = np.clip(np.clip(np.asarray(model.kd, float), 0.0, None) / (1.0 - f0.max(axis=-1, keepdims=True)),
                   0.0, 1.0)
    normal = getattr(model, "normal", None)
    material = NormalMappedMaterial(plane=model.plane, base_color=base, roughness=roughness,
                                    anisotropy_strength=strength, anisotropy_angle=angle, specular=specular,
                                    specular_color=colour, ior=ior, metallic=np.zeros(p),
                                    normal=None if normal is None else np.asarray(normal, float))
    seconds = time.perf_counter() - start
    at_bound = np.isclose(fit["alpha_x"], FIT_ALPHA_RANGE[1]) | np.isclose(fit["alpha_y"], FIT_ALPHA_RANGE[0])
    record = {"alpha_x": fit["alpha_x"], "alpha_y": fit["alpha_y"], "scale": fit["scale"],
              "ndf_rel_l2": fit["rel_l2"],
              "summary": {"points": p, "mixtures_fitted": int(len(unique)), "weight_quantum": weight_quantum,
                          "iterations": iterations, "fresnel_cos_min": fresnel_cos_min,
                          "fit_seconds": seconds, "ior": ior,
                          "ndf_rel_l2_median": float(np.median(fit["rel_l2"][~empty])) if (~empty).any() else None,
                          "ndf_rel_l2_p90": float(np.percentile(fit["rel_l2"][~empty], 90)) if (~empty).any()
                          else None,
                          "alpha_at_bound_fraction": float(at_bound.mean()),
                          "ks_above_1_fraction": float((k.max(axis=-1) > 1.0).mean())}}
    log.info("GGX fit: %d points, %d distinct mixtures, %.1f s; NDF rel L2 median %.3f; ior %.3f", p, len(unique),
             seconds, record["summary"]["ndf_rel_l2_median"] or 0.0, ior)
    return material, record


# --- textures -----------------------------------------------------------------------------------------------

def orient_directions(angle: np.ndarray, strength: np.ndarray, weak: float = 0.05) -> np.ndarray:
    """``angle`` (rows, cols), a field of lines (the BRDF is the same for a and a + pi), turned by pi where that
    makes neighbouring texels' direction vectors agree: a renderer filters the anisotropy texture's RG linearly,
    and two texels at a and a + pi would average to no direction at all. Along each row a texel follows its
    left neighbour (a cumulative parity of sign changes) within runs joined by unambiguous links (strength
    above ``weak`` on both sides, lines within 30 deg of each other); each run then follows the row above by
    the strength-weighted majority of its texels. Seams remain where the line field has no continuous vector
    field (about a point where lines cross) and between runs that no anisotropic texel joins."""
    a = np.asarray(angle, float).copy()
    w = np.asarray(strength, float)
    link = np.cos(np.diff(a, axis=1))
    a[:, 1:] += np.pi * (np.cumsum(link < 0, axis=1) % 2)
    cut = (np.minimum(w[:, 1:], w[:, :-1]) <= weak) | (np.abs(link) < np.cos(np.radians(30)))
    run = np.concatenate([np.zeros((a.shape[0], 1), int), np.cumsum(cut, axis=1)], axis=1)
    for r in range(1, a.shape[0]):
        agree = np.bincount(run[r], weights=np.minimum(w[r], w[r - 1]) * np.cos(a[r] - a[r - 1]))
        a[r] += np.pi * (agree < 0)[run[r]]
    return np.angle(np.exp(1j * a))


def encode_textures(material: GltfMaterial) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(8-bit images (rows, cols, channels) by name of :data:`ALL_IMAGES`, the material's scalar factors); the
    ``normal`` image only for a material with shading normals."""
    shape = (material.plane.rows, material.plane.cols)
    colour_factor = float(max(1.0, np.max(material.specular_color)))
    angle = orient_directions(material.anisotropy_angle.reshape(shape),
                              material.anisotropy_strength.reshape(shape)).ravel()
    direction = np.stack([np.cos(angle), np.sin(angle)], -1)
    metallic = np.zeros(material.n_points) if material.metallic is None else material.metallic
    images = {
        "base_color": _to_byte(srgb_encode(material.base_color)),
        "metallic_roughness": _to_byte(np.stack([np.ones(material.n_points), material.roughness, metallic], -1)),
        "anisotropy": _to_byte(np.concatenate([direction * 0.5 + 0.5, material.anisotropy_strength[:, None]], -1)),
        "specular": _to_byte(np.concatenate([srgb_encode(material.specular_color / colour_factor),
                                             material.specular[:, None]], -1)),
    }
    factors = {"specularColorFactor": [colour_factor] * 3, "ior": material.ior}
    normal = getattr(material, "normal", None)
    if normal is not None:
        images["normal"] = _to_byte(np.asarray(normal, float) * 0.5 + 0.5)   # tangent space = the plane's frame
        factors["normalScale"] = 1.0
    images = {k: v.reshape(shape + (v.shape[-1],)) for k, v in images.items()}
    return images, factors


def decode_textures(images: dict[str, np.ndarray], factors: dict[str, Any], plane: PlaneGrid) -> GltfMaterial:
    """The material the textures and factors describe, as a renderer reads them (the glTF and extension specs)."""
    def flat(name, channels):
        a = np.asarray(images[name], float) / 255.0
        return a.reshape(-1, a.shape[-1])[:, channels]

    rg = flat("anisotropy", [0, 1]) * 2.0 - 1.0
    mr = flat("metallic_roughness", [1, 2])
    normal = None
    if "normal" in images:     # the core spec: normalize((2 RGB - 1) (scale, scale, 1))
        scale = float(factors.get("normalScale", 1.0))
        n = (flat("normal", [0, 1, 2]) * 2.0 - 1.0) * np.array([scale, scale, 1.0])
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        normal = np.where(length > 0, n / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
    return NormalMappedMaterial(
        plane=plane, base_color=srgb_decode(flat("base_color", [0, 1, 2])) * factors.get("baseColorFactor", 1.0),
        roughness=mr[:, 0] * factors.get("roughnessFactor", 1.0),
        anisotropy_strength=flat("anisotropy", 2) * factors.get("anisotropyStrength", 1.0),
        anisotropy_angle=np.arctan2(rg[:, 1], rg[:, 0]) + factors.get("anisotropyRotation", 0.0),
        specular=flat("specular", 3) * factors.get("specularFactor", 1.0),
        specular_color=srgb_decode(flat("specular", [0, 1, 2])) * np.asarray(factors["specularColorFactor"]),
        ior=float(factors["ior"]), metallic=mr[:, 1] * factors.get("metallicFactor", 1.0), normal=normal)


def _write_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image
    mode = {3: "RGB", 4: "RGBA"}[image.shape[-1]]
    with atomic_path(path, suffix=".png") as tmp:
        Image.fromarray(np.ascontiguousarray(image), mode).save(tmp, format="PNG")


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            if im.format != "PNG":
                raise InputError(path, f"not a PNG image ({im.format})")
            return np.asarray(im.convert("RGBA" if "A" in im.getbands() else "RGB"))
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(path, f"not a readable PNG image ({exc})") from None


# --- the glTF document --------------------------------------------------------------------------------------

def _quad(plane: PlaneGrid) -> tuple[bytes, dict[str, Any]]:
    """The quad's binary buffer and its bufferViews / accessors (glTF coordinates (x, z, -y), metres)."""
    hw, hh = plane.width / 2, plane.height / 2
    xy = np.array([[-hw, hh], [hw, hh], [hw, -hh], [-hw, -hh]])          # uv (0,0), (1,0), (1,1), (0,1)
    position = np.stack([xy[:, 0], np.zeros(4), -xy[:, 1]], -1).astype(np.float32)
    normal = np.tile(np.float32([0, 1, 0]), (4, 1))
    tangent = np.tile(np.float32([1, 0, 0, 1]), (4, 1))
    uv = np.float32([[0, 0], [1, 0], [1, 1], [0, 1]])
    indices = np.uint16([0, 2, 1, 0, 3, 2])                              # counter-clockwise seen from +Y
    vertex = np.concatenate([position, normal, tangent, uv], axis=1)    # interleaved, 48 bytes a vertex
    blob = vertex.tobytes() + indices.tobytes()
    blob += b"\0" * (-len(blob) % 4)
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": vertex.nbytes, "byteStride": 48, "target": ARRAY_BUFFER},
             {"buffer": 0, "byteOffset": vertex.nbytes, "byteLength": indices.nbytes,
              "target": ELEMENT_ARRAY_BUFFER}]
    accessors = [
        {"bufferView": 0, "byteOffset": 0, "componentType": FLOAT, "count": 4, "type": "VEC3",
         "min": position.min(0).tolist(), "max": position.max(0).tolist()},
        {"bufferView": 0, "byteOffset": 12, "componentType": FLOAT, "count": 4, "type": "VEC3"},
        {"bufferView": 0, "byteOffset": 24, "componentType": FLOAT, "count": 4, "type": "VEC4"},
        {"bufferView": 0, "byteOffset": 40, "componentType": FLOAT, "count": 4, "type": "VEC2"},
        {"bufferView": 1, "byteOffset": 0, "componentType": UNSIGNED_SHORT, "count": 6, "type": "SCALAR"},
    ]
    return blob, {"bufferViews": views, "accessors": accessors}


def gltf_document(material: GltfMaterial, factors: dict[str, Any], bin_length: int, quad: dict[str, Any],
                  source: str) -> dict[str, Any]:
    """The glTF JSON (built with pygltflib's classes, so its field names are the library's); a normalTexture
    when the material has shading normals."""
    import pygltflib
    names = list(IMAGES) + (["normal"] if getattr(material, "normal", None) is not None else [])
    tex = {name: i for i, name in enumerate(names)}
    pbr = pygltflib.PbrMetallicRoughness(
        baseColorTexture=pygltflib.TextureInfo(index=tex["base_color"]), metallicFactor=0.0, roughnessFactor=1.0,
        metallicRoughnessTexture=pygltflib.TextureInfo(index=tex["metallic_roughness"]))
    plane = material.plane
    extensions = {
        "KHR_materials_anisotropy": {"anisotropyStrength": 1.0, "anisotropyRotation": 0.0,
                                     "anisotropyTexture": {"index": tex["anisotropy"]}},
        "KHR_materials_specular": {"specularFactor": 1.0, "specularTexture": {"index": tex["specular"]},
                                   "specularColorFactor": factors["specularColorFactor"],
                                   "specularColorTexture": {"index": tex["specular"]}},
        "KHR_materials_ior": {"ior": factors["ior"]},
    }
    normal_texture = (pygltflib.NormalMaterialTexture(index=tex["normal"],
                                                      scale=factors.get("normalScale", 1.0))
                      if "normal" in tex else None)
    extras = {"facetsynth": {"source": source, "plane_grid": {"width": plane.width, "height": plane.height,
                                                              "cols": plane.cols, "rows": plane.rows},
                             "frame": "glTF (X, Y, Z) = sample plane (x, z, -y) in metres; tangent +x, "
                                      "bitangent +y; uv (0, 0) = grid row 0 (+y edge), col 0 (-x edge); "
                                      "normalTexture (if any): tangent-space (X, Y, Z) = the plane's (x, y, z)",
                             "model": "facetsynth.models.ggx (glTF 2.0 Appendix B + KHR_materials_anisotropy, "
                                      "_specular, _ior), fitted per point to paper 002 eq. 6"}}
    doc = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="facetsynth export gltf"),
        extensionsUsed=list(EXTENSIONS), scene=0, scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, name="sample")],
        meshes=[pygltflib.Mesh(name="sample", primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=0, NORMAL=1, TANGENT=2, TEXCOORD_0=3), indices=4,
            material=0)])],
        materials=[pygltflib.Material(name="facetsynth", pbrMetallicRoughness=pbr, normalTexture=normal_texture,
                                      extensions=extensions, extras=extras)],
        textures=[pygltflib.Texture(sampler=0, source=i) for i in range(len(names))],
        samplers=[pygltflib.Sampler(magFilter=LINEAR, minFilter=LINEAR_MIPMAP_LINEAR, wrapS=CLAMP_TO_EDGE,
                                    wrapT=CLAMP_TO_EDGE)],
        images=[pygltflib.Image(uri=ALL_IMAGES[n], mimeType="image/png", name=n) for n in names],
        buffers=[pygltflib.Buffer(uri=BIN_NAME, byteLength=bin_length)],
        bufferViews=[pygltflib.BufferView(**v) for v in quad["bufferViews"]],
        accessors=[pygltflib.Accessor(**a) for a in quad["accessors"]])
    return json.loads(doc.to_json())


# --- validation ---------------------------------------------------------------------------------------------

@cache
def _registry(schema_dir: Path):
    import referencing
    from referencing.jsonschema import DRAFT202012
    resources = []
    for f in sorted(schema_dir.glob("*.schema.json")):
        contents = json.loads(f.read_text())
        resources.append((contents.get("$id", f.name),
                          referencing.Resource(contents=contents, specification=DRAFT202012)))
    if not resources:
        raise InputError(schema_dir, "no glTF schema files (*.schema.json) found")
    return referencing.Registry().with_resources(resources)


def _schema_errors(document: Any, schema_name: str, schema_dir: Path) -> list[str]:
    import jsonschema
    registry = _registry(schema_dir)
    validator = jsonschema.Draft202012Validator(registry[schema_name].contents, registry=registry)
    return [f"'{'/'.join(str(p) for p in e.absolute_path) or '(top level)'}': {e.message}"
            for e in sorted(validator.iter_errors(document), key=lambda e: [str(p) for p in e.absolute_path])]


def validate_gltf(path: str | Path, schema_dir: str | Path = SCHEMA_DIR) -> None:
    """Check a .gltf against the vendored glTF 2.0 schema (and each material's KHR_materials_anisotropy,
    _specular, _ior object against its extension's schema), its indices, and its files: InputError naming
    the file and the first problem."""
    path, schema_dir = Path(path), Path(schema_dir)
    doc = read_json(path)
    problems = _schema_errors(doc, "glTF.schema.json", schema_dir)
    if not problems:
        for m, material in enumerate(doc.get("materials", [])):
            for name, ext in material.get("extensions", {}).items():
                if name in EXTENSIONS:
                    problems += [f"materials/{m}/extensions/{name}/{p}"
                                 for p in _schema_errors(ext, f"material.{name}.schema.json", schema_dir)]
    if not problems:
        problems = _reference_errors(doc, path.parent)
    if problems:
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        raise InputError(path, f"invalid glTF at {problems[0]}{more}")


def _reference_errors(doc: dict[str, Any], folder: Path) -> list[str]:
    """What the schema cannot check: indices in range, the files present, the buffer's length."""
    problems = []

    def check(kind: str, index: Any, where: str) -> None:
        if not isinstance(index, int) or not 0 <= index < len(doc.get(kind, [])):
            problems.append(f"'{where}': {kind} index {index!r} out of range")

    for t, tex in enumerate(doc.get("textures", [])):
        check("images", tex.get("source"), f"textures/{t}/source")
        if "sampler" in tex:
            check("samplers", tex["sampler"], f"textures/{t}/sampler")
    for m, material in enumerate(doc.get("materials", [])):
        infos = [(f"pbrMetallicRoughness/{k}", v) for k, v in material.get("pbrMetallicRoughness", {}).items()
                 if k.endswith("Texture")]
        infos += [(k, v) for k, v in material.items() if k.endswith("Texture")]     # normalTexture, ...
        infos += [(f"extensions/{e}/{k}", v) for e, ext in material.get("extensions", {}).items()
                  for k, v in ext.items() if k.endswith("Texture")]
        for where, info in infos:
            check("textures", info.get("index"), f"materials/{m}/{where}/index")
    for a, acc in enumerate(doc.get("accessors", [])):
        if "bufferView" in acc:
            check("bufferViews", acc["bufferView"], f"accessors/{a}/bufferView")
    for v, view in enumerate(doc.get("bufferViews", [])):
        check("buffers", view.get("buffer"), f"bufferViews/{v}/buffer")
    for i, image in enumerate(doc.get("images", [])):
        if "uri" in image and not (folder / image["uri"]).is_file():
            problems.append(f"'images/{i}/uri': {image['uri']} not found")
    for b, buf in enumerate(doc.get("buffers", [])):
        if "uri" in buf:
            f = folder / buf["uri"]
            if not f.is_file():
                problems.append(f"'buffers/{b}/uri': {buf['uri']} not found")
            elif f.stat().st_size < buf["byteLength"]:
                problems.append(f"'buffers/{b}': {buf['uri']} holds {f.stat().st_size} bytes, "
                                f"byteLength {buf['byteLength']}")
    return problems


# --- reading back -------------------------------------------------------------------------------------------

def read_gltf(path: str | Path) -> GltfMaterial:
    """The per-point material of an exported .gltf (its textures decoded as a renderer reads them)."""
    path = Path(path)
    doc = read_json(path)
    try:
        material = doc["materials"][0]
        grid = material["extras"]["facetsynth"]["plane_grid"]
        plane = PlaneGrid(float(grid["width"]), float(grid["height"]), int(grid["cols"]), int(grid["rows"]))
        pbr, ext = material["pbrMetallicRoughness"], material["extensions"]

        def image(info):
            uri = doc["images"][doc["textures"][info["index"]]["source"]]["uri"]
            return _read_png(path.parent / uri)

        aniso, spec = ext["KHR_materials_anisotropy"], ext["KHR_materials_specular"]
        images = {"base_color": image(pbr["baseColorTexture"]),
                  "metallic_roughness": image(pbr["metallicRoughnessTexture"]),
                  "anisotropy": image(aniso["anisotropyTexture"]), "specular": image(spec["specularTexture"])}
        if spec["specularColorTexture"]["index"] != spec["specularTexture"]["index"]:
            raise InputError(path, "expected one RGBA texture for specularTexture and specularColorTexture")
        if "normalTexture" in material:
            images["normal"] = image(material["normalTexture"])
        factors = {"baseColorFactor": np.asarray(pbr.get("baseColorFactor", [1.0] * 4), float)[:3],
                   "metallicFactor": pbr.get("metallicFactor", 1.0), "roughnessFactor": pbr.get("roughnessFactor", 1.0),
                   "anisotropyStrength": aniso.get("anisotropyStrength", 0.0),
                   "anisotropyRotation": aniso.get("anisotropyRotation", 0.0),
                   "specularFactor": spec.get("specularFactor", 1.0),
                   "specularColorFactor": spec.get("specularColorFactor", [1.0] * 3),
                   "ior": ext.get("KHR_materials_ior", {}).get("ior", 1.5),
                   "normalScale": material.get("normalTexture", {}).get("scale", 1.0)}
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a facetsynth glTF export (missing {exc})") from None
    for name, a in images.items():
        if a.shape[:2] != (plane.rows, plane.cols):
            raise InputError(path, f"{name} texture is {a.shape[1]}x{a.shape[0]}, the plane grid "
                                   f"{plane.cols}x{plane.rows}")
    return decode_textures(images, factors, plane)


def round_trip_errors(fitted: GltfMaterial, read: GltfMaterial) -> dict[str, float]:
    """Largest differences between the fitted material and the one read from the files (8-bit quantisation:
    linear channels within 0.5/255; sRGB ones within half a code in linear terms; the anisotropy direction
    where the strength is above 0.02; ``normal_angle_deg`` the angle between the shading normals, degrees,
    about 0.33 at most for 8 bits; 0 when neither has normals)."""
    aniso = fitted.anisotropy_strength > 0.02
    turn = np.angle(np.exp(2j * (read.anisotropy_angle - fitted.anisotropy_angle))) / 2   # a direction: mod pi
    return {"base_color": float(np.max(np.abs(read.base_color - fitted.base_color))),
            "roughness": float(np.max(np.abs(read.roughness - fitted.roughness))),
            "anisotropy_strength": float(np.max(np.abs(read.anisotropy_strength - fitted.anisotropy_strength))),
            "anisotropy_angle_rad": float(np.max(np.abs(turn[aniso]))) if aniso.any() else 0.0,
            "specular": float(np.max(np.abs(read.specular - fitted.specular))),
            "specular_color_relative": float(np.max(np.abs(read.specular_color - fitted.specular_color))
                                             / max(1.0, float(np.max(fitted.specular_color)))),
            "normal_angle_deg": float(np.max(normal_angles(getattr(fitted, "normal", None),
                                                           getattr(read, "normal", None))))
            if getattr(fitted, "normal", None) is not None or getattr(read, "normal", None) is not None else 0.0}


# --- the entry point ----------------------------------------------------------------------------------------

def write_gltf(out_dir: Path, material: GltfMaterial, source: str) -> list[str]:
    """Write the textures, the buffer and the .gltf (each atomically, the .gltf last); the names written."""
    images, factors = encode_textures(material)
    for name, image in images.items():
        _write_png(out_dir / ALL_IMAGES[name], image)
    blob, quad = _quad(material.plane)
    with atomic_path(out_dir / BIN_NAME, suffix=".bin") as tmp:
        tmp.write_bytes(blob)
    doc = gltf_document(material, factors, len(blob), quad, source)
    try:
        text = json.dumps(doc, indent=1, allow_nan=False)      # NaN is not JSON: never written
    except ValueError:
        raise InputError(source, "the fitted glTF material holds NaN or Inf values; nothing written") from None
    with atomic_path(out_dir / GLTF_NAME, suffix=".gltf") as tmp:
        tmp.write_text(text + "\n")
    return [ALL_IMAGES[n] for n in images] + [BIN_NAME, GLTF_NAME]


def output_names(model) -> list[str]:
    """The files :func:`write_gltf` writes for ``model``, in the order they are published (the .gltf last)."""
    images = list(IMAGES.values()) + ([NORMAL_IMAGE] if getattr(model, "normal", None) is not None else [])
    return images + [BIN_NAME, GLTF_NAME]


def export_gltf(model_dir: str | Path, out_dir: str | Path, *, force: bool = False, weight_quantum: float = 0.01,
                iterations: int = 12, fresnel_cos_min: float = 0.5) -> dict[str, Any]:
    """Fit the portable glTF material to the SVBRDF in ``model_dir`` and write it to ``out_dir`` (module docstring).

    The output folder follows :func:`facetsynth.io.outputs.output_folder` (never overlapping the model; a
    non-empty folder not made by this command only with ``force``; one writer at a time). The written file is
    read back, checked against the vendored glTF schema (:func:`validate_gltf`) and its textures against the
    fit before it is published (a failure publishes nothing). Returns a
    summary: ``files`` (paths written), ``fit`` (:func:`fit_material`'s summary), ``round_trip``
    (:func:`round_trip_errors`), ``gltf`` (the .gltf path).
    """
    from . import fitted_svbrdf
    model = fitted_svbrdf(model_dir, "glTF")
    with output_folder(out_dir, "export-gltf", input_dirs=[model_dir], writes=output_names(model),
                       force=force) as stage:
        material, record = fit_material(model, weight_quantum=weight_quantum, iterations=iterations,
                                        fresnel_cos_min=fresnel_cos_min)
        names = write_gltf(stage, material, source=str(model_dir))
        validate_gltf(stage / GLTF_NAME)              # checked before it is published
        read = read_gltf(stage / GLTF_NAME)
    out = Path(out_dir)
    return {"files": [str(out / n) for n in names], "gltf": str(out / GLTF_NAME), "fit": record["summary"],
            "round_trip": round_trip_errors(material, read)}

