"""facetsynth: spatially varying anisotropic BRDFs from single-view captures.

The numerical core of the pipeline: small, pure, vectorised numpy functions,
one module per concept. Nothing here knows about Snakemake.
"""

__version__ = "0.1.0"
