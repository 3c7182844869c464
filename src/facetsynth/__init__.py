"""facetsynth: spatially varying anisotropic BRDFs from single-view captures.

The numerical core of the pipeline: small, pure, vectorised numpy functions,
one module per concept. Nothing here knows about Snakemake.
"""

__version__ = "0.1.0"


def __getattr__(name):
    # ``facetsynth.SVBRDF`` without importing OpenEXR etc. for every ``import facetsynth``
    if name == "SVBRDF":
        from .svbrdf import SVBRDF
        return SVBRDF
    raise AttributeError(f"module 'facetsynth' has no attribute {name!r}")
