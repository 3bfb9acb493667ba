"""The case grid's element moduli for elastic contact (:mod:`biopsynav.contact.constraints`):
the springs the network input of elastic rigid pushes is built with, on the case grid
whatever grid the teacher solved on."""

from __future__ import annotations

import numpy as np

from ..fem.tissues import grid_lame, small_strain


def case_young_moduli(case) -> np.ndarray:
    """Young's modulus (n_active_cells,) MPa of each element of ``case``'s own grid, its
    tissues mixed by volume as in its FE model, without building that model."""
    return small_strain(*grid_lame(case.grid, case.cfg, case.anatomy))[0]
