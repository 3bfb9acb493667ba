"""Finite elements: static total-Lagrangian hyperelasticity on the immersed hexahedral grid.

``FEModel`` (plain arrays or ``FEModel.from_case``), ``Loads``, ``solve`` -> displacement and
``SolveReport``; ``SolverSettings.from_config(cfg.solver)``. See ``docs/fem.md``.
"""

from .loads import Loads
from .model import FEModel, lame_constants
from .solver import (
    SolveReport,
    SolverSettings,
    compile_kernels,
    internal_forces,
    largest_edge_stretch,
    smallest_det_f,
    solve,
    tangent_matrix,
)

__all__ = ["FEModel", "Loads", "SolveReport", "SolverSettings", "compile_kernels",
           "internal_forces", "lame_constants", "largest_edge_stretch", "smallest_det_f", "solve",
           "tangent_matrix"]
