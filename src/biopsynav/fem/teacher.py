"""The FE model that teaches the network: on the case grid, or on a finer grid of the same
anatomy (``[dataset] teacher_refine``) whose solutions are fitted to the case grid, optionally
extrapolated from the case grid's solution of the same push (``[dataset]
teacher_extrapolation``, Richardson).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: Tissue fraction of a case-grid cell from which its nodes get the extrapolation.
EXTRAPOLATE_FROM = 0.5
#: Rounds of :meth:`Teacher.extrapolate` that give cells stretched beyond the limit back the
#: fitted field (each may stretch a neighbour that shares their nodes).
LIMIT_ROUNDS = 8


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
        coarse: with ``[dataset] teacher_extrapolation``, the case grid's FE model, which
            solves every sample too; else None.
        weight: Richardson's weight ``w`` of the extrapolated field
            ``u_fine + w (u_fine - u_case)`` (:func:`extrapolation_weight`; 0 without).
        extrapolated_cells: (n_active_cells,) bool, the case grid's cells at least
            :data:`EXTRAPOLATE_FROM` full of tissue (in the order of its FE model's elements).
        extrapolated: (n_nodes,) bool, the case-grid nodes that get the extrapolation: those
            of those cells. The others (outside the tissue, of nearly empty cut cells, where a
            lone node of the case grid may be flung) keep the fine field as fitted.
    """

    model: Any
    grid: Any
    skin: Any
    transfer: Any
    coarse: Any = None
    weight: float = 0.0
    extrapolated_cells: Any = None
    extrapolated: Any = None

    def case_field(self, u: np.ndarray, held: tuple | None = None,
                   u_case: np.ndarray | None = None, max_stretch: float = 0.0) -> np.ndarray:
        """A solution (n_model_nodes, 3) mm on the case grid (n_nodes, 3) mm; ``held``: the
        probe's contact points, (case-grid weights (m, n_nodes), displacements (m, 3) mm),
        which the fit moves as the solution does (:class:`~biopsynav.grid.transfer.
        FieldTransfer`); ``u_case`` (n_nodes, 3) mm: the same push solved by
        :attr:`coarse`, from which the field is extrapolated (:meth:`extrapolate`, limited
        by ``max_stretch``)."""
        fitted = u if self.transfer is None else self.transfer(u, held)
        if u_case is None:
            return fitted
        return self.extrapolate(fitted, u_case, max_stretch)

    def extrapolate(self, fitted: np.ndarray, u_case: np.ndarray,
                    max_stretch: float = 0.0) -> np.ndarray:
        """``fitted + w (fitted - u_case)`` (n_nodes, 3) mm on the nodes of
        :attr:`extrapolated`, ``fitted`` elsewhere. With ``max_stretch`` > 0 a cell whose
        edge that field stretches beyond ``max_stretch`` times its rest length (the two
        grids far apart, as under the probe's edge at a deep push, where the expansion
        behind the extrapolation does not hold) gives its nodes back the fitted field;
        repeated for :data:`LIMIT_ROUNDS` rounds at most."""
        from .solver import edge_stretches

        nodes = self.extrapolated.copy()
        correction = self.weight * (fitted - u_case)
        field = fitted + nodes[:, None] * correction
        for _ in range(LIMIT_ROUNDS if max_stretch > 0 else 0):
            over = self.extrapolated_cells & (edge_stretches(self.coarse, field) > max_stretch)
            back = self.coarse.hexes[over].ravel()
            if not np.any(nodes[back]):
                break
            nodes[back] = False
            field = fitted + nodes[:, None] * correction
        return field


def teacher_refinement(cfg: Any) -> int | float:
    """How many times finer than the case grid the teacher's cells are (``[dataset]
    teacher_refine``; 1: the case grid itself), an int when it is whole (as data sets and
    models record it)."""
    return whole_or_float(cfg.dataset.teacher_refine)


def whole_or_float(value: float) -> int | float:
    """``value`` as an int when it is whole (2.0 -> 2), else as a float."""
    value = float(value)
    return int(value) if value.is_integer() else value


def extrapolation_weight(refine: float, order: float) -> float:
    """Richardson's weight ``w`` of ``u_fine + w (u_fine - u_case)`` for cells ``refine``
    times smaller than the case grid's and an error of order ``order`` in the cell size:
    ``h_fine^p / (h_case^p - h_fine^p) = 1 / (refine^p - 1)``."""
    return 1.0 / (float(refine) ** float(order) - 1.0)


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
    teacher = Teacher(FEModel.from_grid(grid, cfg, case.anatomy, floor), grid,
                      surface_embedding(grid, case.anatomy), transfer)
    order = float(cfg.dataset.teacher_extrapolation)
    if refine > 1 and order > 0:
        teacher.coarse = FEModel.from_case(case)
        teacher.weight = extrapolation_weight(refine, order)
        teacher.extrapolated_cells = case.grid.active_fraction() >= EXTRAPOLATE_FROM
        teacher.extrapolated = nodes_of_cells(case.grid, teacher.extrapolated_cells)
    return teacher


def nodes_of_cells(grid: Any, cells: np.ndarray) -> np.ndarray:
    """(n_nodes,) bool: the nodes of ``grid``'s active cells selected by ``cells``
    (n_active_cells,) bool."""
    out = np.zeros(grid.n_nodes, dtype=bool)
    out[grid.active_hexes()[cells].ravel()] = True
    return out
