"""The FE model that teaches the network: on the case grid, or on a finer grid of the same
anatomy (``[dataset] teacher_refine``) whose solutions are fitted to the case grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Teacher:
    """What a worker solves samples with.

    Attributes:
        model: the :class:`biopsynav.fem.FEModel` solved.
        grid: the model's :class:`~biopsynav.grid.model.Grid`.
        skin: the :class:`~biopsynav.grid.embedding.Embedding` of every skin vertex in the
            model's grid (loads and contact displacements).
        transfer: model node field (n_model_nodes, 3) mm -> case-grid node field (n_nodes, 3)
            mm; None when the model is on the case grid.
    """

    model: Any
    grid: Any
    skin: Any
    transfer: Any

    def case_field(self, u: np.ndarray, held: tuple | None = None) -> np.ndarray:
        """A solution (n_model_nodes, 3) mm on the case grid (n_nodes, 3) mm; ``held``: the
        probe's contact points, (case-grid weights (m, n_nodes), displacements (m, 3) mm),
        which the fit moves as the solution does (:class:`~biopsynav.grid.transfer.
        FieldTransfer`)."""
        return u if self.transfer is None else self.transfer(u, held)


def teacher_refinement(cfg: Any) -> int:
    """How many times finer than the case grid the teacher's cells are (``[dataset]
    teacher_refine``; 1: the case grid itself)."""
    return int(cfg.dataset.teacher_refine)


def build_teacher(case: Any) -> Teacher:
    """The teacher of ``case``: its own grid's FE model, or with ``[dataset] teacher_refine``
    > 1 the model of the refined grid (cell weights at least ``[dataset]
    teacher_min_fraction``) and the transfer back."""
    from ..grid.embedding import surface_embedding
    from ..grid.transfer import FieldTransfer, refined_grid
    from .model import FEModel

    cfg, refine = case.cfg, teacher_refinement(case.cfg)
    if refine == 1:
        grid, transfer = case.grid, None
    else:
        grid = refined_grid(case.anatomy, cfg.grid, refine, 1.0,
                            cfg.anatomy.chest_wall_tolerance_mm)
        transfer = FieldTransfer(case.grid, grid)
    floor = None if refine == 1 else cfg.dataset.teacher_min_fraction
    return Teacher(FEModel.from_grid(grid, cfg, case.anatomy, floor), grid,
                   surface_embedding(grid, case.anatomy), transfer)
