"""Adaptive highlight stencils BRDF model (Filip, Havlicek, Vavra; paper 000) and tools.

Public entry points: :func:`fit_file` (read + fit + score) and
:func:`model_to_json`; see the submodules for the pieces.
"""

from .export import model_from_json, model_to_json, to_brdf_explorer
from .fit import fit, fit_file
from .model import Mode, StencilModel, evaluate, evaluate_utia

__all__ = ["fit", "fit_file", "model_to_json", "model_from_json", "to_brdf_explorer",
           "Mode", "StencilModel", "evaluate", "evaluate_utia"]
