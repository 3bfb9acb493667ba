"""The FE model that teaches the network: on the case grid, or on a finer grid of the same
anatomy (``[dataset] teacher_refine``) whose solutions are fitted to the case grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp


@dataclass
class Teacher:
    """What a worker solves samples with.

    Attributes:
        model: the :class:`biopsynav.fem.FEModel` solved.
        skin: CSR (n_vertices, n_model_nodes) trilinear embedding of every skin vertex in the
            model's grid (loads and contact displacements).
        skin_cells: (n_vertices,) the model grid's flat cell of each skin vertex.
        transfer: model node field (n_model_nodes, 3) mm -> case-grid node field (n_nodes, 3)
            mm; None when the model is on the case grid.
        cell_mm: the model grid's cell size, mm.
        grid: the model's :class:`~biopsynav.grid.model.Grid`.
    """

    model: Any
    skin: sp.csr_matrix
    skin_cells: np.ndarray
    transfer: Any
    cell_mm: float
    grid: Any = None

    def case_field(self, u: np.ndarray) -> np.ndarray:
        """A solution (n_model_nodes, 3) mm on the case grid (n_nodes, 3) mm."""
        return u if self.transfer is None else self.transfer(u)


def build_teacher(case: Any) -> Teacher:
    """The teacher of ``case``: its own grid's FE model, or with ``[dataset] teacher_refine``
    > 1 the model of the refined grid and the transfer back."""
    from ..grid.embedding import surface_embedding
    from ..grid.transfer import FieldTransfer, refined_grid
    from .model import FEModel

    cfg, refine = case.cfg, int(case.cfg.dataset.teacher_refine)
    if refine == 1:
        grid, transfer = case.grid, None
    else:
        grid = refined_grid(case.anatomy, cfg.grid, refine, 1.0,
                            cfg.anatomy.chest_wall_tolerance_mm)
        transfer = FieldTransfer(case.grid, grid)
    skin = surface_embedding(grid, case.anatomy)
    return Teacher(FEModel.from_grid(grid, cfg, case.anatomy), skin.matrix, skin.cells,
                   transfer, float(grid.spacing), grid)
