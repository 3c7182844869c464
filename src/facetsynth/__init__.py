"""facetsynth: spatially varying anisotropic BRDFs from single-view captures.

The numerical core is small, pure, vectorised numpy functions, one module per
concept, in packages by what they are about (docs/pipeline.md, "Layout"):

* ``geometry``: the camera, the rectified sample plane, the direction grid, the lights;
* ``models``: the paper's microfacet SVBRDF and its folder, the portable GGX material, the Ward baseline;
* ``capture``: captures in (manifest, checks, HDR, 8-bit responses, rectification);
* ``fit``: the paper's steps, separation to refine;
* ``evaluation``: scores, against a virtual capture's truth and against the capture itself;
* ``truth``: the scenes, the virtual rig and Mitsuba's captures (never imported by the fit);
* ``io``: files, tables, output folders, schemas, the one input error;
* ``app``: the ``facetsynth`` command, prediction, previews, the report's figures, benchmarks;

beside ``stages`` (one runner per workflow rule), ``stencil`` (the second paper), ``export`` (glTF,
Mitsuba), ``rti`` (light-dome captures), ``rig`` and ``calibration`` (the hardware). Nothing outside
``stages`` and ``app`` knows about Snakemake.
"""

__version__ = "0.1.0"


def __getattr__(name):
    # ``facetsynth.SVBRDF`` without importing OpenEXR etc. for every ``import facetsynth``
    if name == "SVBRDF":
        from .models.svbrdf import SVBRDF
        return SVBRDF
    raise AttributeError(f"module 'facetsynth' has no attribute {name!r}")
