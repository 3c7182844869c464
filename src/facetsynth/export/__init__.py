"""Renderer exports of a fitted SVBRDF folder (``facetsynth export``).

* :mod:`.mitsuba`: exact. A Mitsuba 3 scene and a registered Python ``mi.BSDF`` that evaluates and
  samples the fitted SVBRDF itself (tabulated NDFs, eq. 18 weights, eq. 5 shadowing, Fresnel).
* :mod:`.gltf`: portable. A per-point anisotropic GGX fit written as a glTF 2.0 material with
  ``KHR_materials_anisotropy`` and ``KHR_materials_specular`` textures on a quad.

Shading normals (SVBRDF ``normal``): glTF writes them as the material's ``normalTexture`` (the quad's tangent
space is the sample plane's frame); the Mitsuba plugin turns each query into the point's frame itself.
"""

from pathlib import Path

from ..io.errors import InputError


def fitted_svbrdf(model_dir: str | Path, export: str):
    """The fitted SVBRDF in ``model_dir`` (:func:`facetsynth.app.predict.load_model`); InputError naming its
    model.json for a Ward baseline folder, which ``export`` (the exporter's name) cannot write."""
    from ..app.predict import load_model
    from ..models.svbrdf import SVBRDF
    model = load_model(model_dir)
    if not isinstance(model, SVBRDF):
        raise InputError(Path(model_dir) / "model.json", f"a Ward baseline model; the {export} export takes a "
                                                         "fitted facetsynth SVBRDF folder (results/SAMPLE/svbrdf)")
    return model
