"""Springs of elastic contact on a case's own grid (:mod:`biopsynav.contact.constraints`):
what the network input of elastic rigid pushes is built with."""

from __future__ import annotations

import numpy as np

from ..fem.tissues import cell_lame, label_tissues, small_strain
from .constraints import point_stiffness, vertex_areas


def case_springs(case, beta: float, vertices: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Spring stiffness (n,) N/mm of the skin ``vertices`` (n,) in the flat ``cells`` (n,) of
    ``case``'s own grid (its tissues' Young's moduli, its cell size): the springs the network
    input of elastic contact is built with (:func:`biopsynav.probe.contact_input_operator`)."""
    grid = case.grid
    tissues = label_tissues(grid.label_values, case.cfg, case.anatomy)
    e_mpa, _ = small_strain(*cell_lame(grid.active_label_share(), tissues, case.cfg))
    areas = vertex_areas(case.anatomy.vertices, case.anatomy.faces)[vertices]
    return point_stiffness(beta, e_mpa[grid.element_of_cells(cells)], areas, grid.spacing)
