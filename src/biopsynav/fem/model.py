"""The finite-element model on plain arrays: geometry, materials, equations and sparsity.

Built once per grid and reused by every solve: shape-function gradients (one set for all the
identical cubes of a regular grid), the numbering of free degrees of freedom, the sparsity
pattern of the upper triangle of the tangent (CSR) and the scatter map from element matrices
into it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import InputError
from ..materials import MATERIAL_LAWS, lame_constants
from . import kernels

if TYPE_CHECKING:
    from ..anatomy.model import Anatomy
    from ..case import Case
    from ..config import CaseConfig
    from ..grid.model import Grid



class FEModel:
    """Static total-Lagrangian hyperelastic model on 8-node hexahedra with immersed weights.

    Args:
        nodes: (n_nodes, 3) reference positions, mm.
        hexes: (n_el, 8) flat node ids per element, VTK hexahedron order.
        weight: (n_el,) tissue volume fraction in (0, 1] scaling each element's Gauss weights.
        E_mpa: (n_el,) Young's modulus, MPa.  nu: (n_el,) Poisson ratio (for a law with
            other parameters, :meth:`from_parameters`).
        fixed: (n_nodes,) bool, Dirichlet nodes (u = 0 on all three components), or
            (n_nodes, 3) bool per component (rollers).
        material: a registered law (:mod:`biopsynav.materials`: 'neo-hookean', 'svk').
        fictitious: share in [0, 1] of its small-strain stiffness that the empty part of each
            cell keeps, linear in the displacement (:mod:`biopsynav.fem.fictitious`); 0: none.

    Nodes used by no element carry no equation; solves return zero displacement there.
    """

    def __init__(self, nodes: np.ndarray, hexes: np.ndarray, weight: np.ndarray,
                 E_mpa: np.ndarray, nu: np.ndarray, fixed: np.ndarray,
                 material: str = "neo-hookean", lame: tuple | None = None,
                 fictitious: float = 0.0) -> None:
        self.nodes = np.ascontiguousarray(nodes, dtype=np.float64)
        self.hexes = np.ascontiguousarray(hexes, dtype=np.int64)
        n_el = self.hexes.shape[0]
        self.weight = _per_element(weight, n_el, "weight")
        self.E_mpa = _per_element(E_mpa, n_el, "E_mpa")
        self.nu = _per_element(nu, n_el, "nu")
        self.fixed = _fixed_components(fixed, len(self.nodes))
        self.material = material
        self.fictitious = float(fictitious)
        _validate(self)
        law = MATERIAL_LAWS[material]
        self.material_id = law.kernel
        self.mu, self.lam = lame if lame is not None else lame_constants(self.E_mpa, self.nu)
        self.grads, self.jw, self.elem_set = _unique_gradients(self.nodes[self.hexes])
        self.eq_of_dof, self.n_eq = _number_equations(self.hexes, self.fixed, len(self.nodes))
        self.elem_eq = self.eq_of_dof[self.hexes].reshape(n_el, 24)
        self.indptr, self.indices, self.scatter = _upper_pattern(self.elem_eq, self.n_eq)
        self.diag_pos = self.indptr[:-1].copy()  # first entry of each upper row is its diagonal
        self.cache: dict[str, Any] = {}  # linear-solver handles (symbolic analysis) per backend

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def n_elements(self) -> int:
        return int(self.hexes.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.indices.shape[0])

    def to_free(self, field: np.ndarray) -> np.ndarray:
        """Node field (n_nodes, 3) -> vector (n_eq,) of its free components."""
        mask = self.eq_of_dof >= 0
        out = np.zeros(self.n_eq)
        out[self.eq_of_dof[mask]] = np.asarray(field, dtype=np.float64)[mask]
        return out

    def to_nodes(self, vec: np.ndarray) -> np.ndarray:
        """Vector (n_eq,) of free components -> node field (n_nodes, 3), zero elsewhere."""
        out = np.zeros((self.n_nodes, 3))
        mask = self.eq_of_dof >= 0
        out[mask] = vec[self.eq_of_dof[mask]]
        return out

    def check_anchored(self) -> None:
        """Raise InputError if a connected piece of the mesh has no fixed node (a singular
        stiffness); checked once, by the first solve."""
        if not self.cache.get("anchored"):
            _check_anchored(self)
            self.cache["anchored"] = True

    def used_nodes(self) -> np.ndarray:
        """(n_nodes,) bool: nodes that belong to at least one element."""
        used = np.zeros(self.n_nodes, dtype=bool)
        used[self.hexes.ravel()] = True
        return used

    @classmethod
    def from_case(cls, case: Case) -> FEModel:
        """The model of a case: active grid cells, each the volume-weighted mixture of its
        tissues (:mod:`biopsynav.fem.tissues`), chest wall fixed."""
        return cls.from_grid(case.grid, case.cfg, case.anatomy)

    @classmethod
    def from_grid(cls, grid: Grid, cfg: CaseConfig, anatomy: Anatomy,
                  min_fraction: float | None = None) -> FEModel:
        """The model of ``anatomy`` on ``grid`` (the case's grid, or a finer teacher grid)
        with the materials, law, fictitious stiffness and chest wall of ``cfg``; the cells'
        integration weights are their tissue fractions, at least ``min_fraction`` (default
        ``[grid] min_fraction``)."""
        from .tissues import grid_lame, small_strain

        mu, lam = grid_lame(grid, cfg, anatomy)
        e_mpa, nu = small_strain(mu, lam)
        floor = cfg.grid.min_fraction if min_fraction is None else min_fraction
        weight = np.clip(grid.active_fraction(), floor, 1.0)
        return cls(grid.node_coords(), grid.active_hexes(), weight, e_mpa, nu,
                   np.asarray(grid.fixed_nodes).ravel(), cfg.material.model, (mu, lam),
                   cfg.material.fictitious_stiffness)


def _per_element(values: np.ndarray, n_el: int, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n_el, float(arr))
    if arr.shape != (n_el,):
        raise InputError(f"{name} must have one value per element ({n_el}), got shape "
                         f"{arr.shape}", "FEModel")
    return np.ascontiguousarray(arr)


def _fixed_components(fixed: np.ndarray, n_nodes: int) -> np.ndarray:
    """Dirichlet mask (n_nodes, 3) from a node mask (n_nodes,) or a component mask."""
    fixed = np.asarray(fixed, dtype=bool)
    if fixed.shape == (n_nodes,):
        return np.repeat(fixed[:, None], 3, axis=1)
    if fixed.shape != (n_nodes, 3):
        raise InputError(f"fixed must be (n_nodes,) or (n_nodes, 3) with n_nodes = {n_nodes}, "
                         f"got {fixed.shape}", "FEModel")
    return fixed


def _validate(m: FEModel) -> None:
    where = "FEModel"
    if m.nodes.ndim != 2 or m.nodes.shape[1] != 3:
        raise InputError(f"nodes must be (n_nodes, 3), got {m.nodes.shape}", where)
    if m.hexes.ndim != 2 or m.hexes.shape[1] != 8 or len(m.hexes) == 0:
        raise InputError(f"hexes must be (n_el, 8) with n_el > 0, got {m.hexes.shape}", where)
    if m.hexes.min() < 0 or m.hexes.max() >= len(m.nodes):
        raise InputError("hexes refer to nodes that do not exist", where)
    if m.material not in MATERIAL_LAWS:
        raise InputError(f"material must be one of {', '.join(MATERIAL_LAWS)}, got "
                         f"{m.material!r}", where)
    if not np.all(np.isfinite(m.nodes)):
        raise InputError("nodes contain NaN or infinity", where)
    if not np.all((m.weight > 0) & (m.weight <= 1)):
        raise InputError("weight (volume fraction) must be in (0, 1]", where)
    if not 0.0 <= m.fictitious <= 1.0:
        raise InputError(f"fictitious must be in [0, 1], got {m.fictitious}", where)
    if not np.all(m.E_mpa > 0):
        raise InputError("E_mpa must be positive", where)
    if not np.all((m.nu > -1) & (m.nu < 0.5)):
        raise InputError("nu must be in (-1, 0.5)", where)


def _unique_gradients(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradients per distinct element shape: (n_sets, 8, 8, 3), jw (n_sets, 8), set per element.

    Elements equal to the first up to translation (all cells of a regular grid) share set 0;
    any other element gets its own set.
    """
    rel = corners - corners[:, :1, :]
    same = np.all(np.abs(rel - rel[:1]) <= 1e-9 * (1.0 + np.abs(rel[:1]).max()), axis=(1, 2))
    distinct = np.flatnonzero(~same)
    representatives = np.concatenate([[0], distinct])
    grads, jw = kernels.element_gradients(corners[representatives])
    if np.any(jw <= 0):
        raise InputError("an element is inverted or degenerate (det J <= 0); hexes must follow "
                         "the VTK corner order", "FEModel")
    elem_set = np.zeros(len(corners), dtype=np.int64)
    elem_set[distinct] = np.arange(1, len(distinct) + 1)
    return np.ascontiguousarray(grads), np.ascontiguousarray(jw), elem_set


def _number_equations(hexes: np.ndarray, fixed: np.ndarray,
                      n_nodes: int) -> tuple[np.ndarray, int]:
    """Equation number (n_nodes, 3) of each free component (-1: fixed or unused node),
    node by node (x, y, z of a node are consecutive)."""
    used = np.zeros(n_nodes, dtype=bool)
    used[hexes.ravel()] = True
    free = used[:, None] & ~fixed
    eq = np.full((n_nodes, 3), -1, dtype=np.int64)
    n_eq = int(free.sum())
    eq[free] = np.arange(n_eq)
    return eq, n_eq


def _check_anchored(m: FEModel) -> None:
    """Every connected piece of the mesh must hold a fixed node (else K is singular)."""
    n_el = m.n_elements
    rows = np.repeat(np.arange(n_el), 8)
    incidence = sp.csr_matrix((np.ones(8 * n_el), (rows, m.hexes.ravel())),
                              shape=(n_el, m.n_nodes))
    n_comp, comp = connected_components(incidence.T @ incidence, directed=False)
    used = m.used_nodes()
    anchored = np.zeros(n_comp, dtype=bool)
    anchored[comp[used & m.fixed.any(axis=1)]] = True
    floating = np.unique(comp[used][~anchored[comp[used]]])
    if floating.size:
        count = int(np.isin(comp, floating).sum() - np.isin(comp[~used], floating).sum())
        raise InputError(f"{floating.size} piece(s) of the mesh ({count} nodes) touch no fixed "
                         "node; the stiffness would be singular", "FEModel")
    if m.n_eq == 0:
        raise InputError("every node is fixed; nothing to solve", "FEModel")


def _upper_pattern(elem_eq: np.ndarray, n_eq: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper-triangle CSR pattern (indptr, indices) and scatter map (n_el, 24, 24).

    ``scatter[e, i, j]`` is the position in the CSR data of the global entry (row, col) of
    the element entry (i, j) when both are free and row <= col, else -1.
    """
    rows = elem_eq[:, :, None]
    cols = elem_eq[:, None, :]
    keep = (rows >= 0) & (cols >= 0) & (rows <= cols)
    keys = np.where(keep, rows * n_eq + cols, -1)
    unique = np.unique(keys[keep])
    indptr = np.zeros(n_eq + 1, dtype=np.int64)
    np.cumsum(np.bincount(unique // n_eq, minlength=n_eq), out=indptr[1:])
    indices = (unique % n_eq).astype(np.int64)
    scatter = np.where(keep, np.searchsorted(unique, keys), -1).astype(np.int64)
    return indptr, indices, np.ascontiguousarray(scatter)


def upper_rows(model: FEModel) -> np.ndarray:
    """The row (equation) of each entry of the upper CSR data, (nnz,)."""
    return np.repeat(np.arange(model.n_eq, dtype=np.int64), np.diff(model.indptr))


def find_positions(model: FEModel, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Positions in the upper CSR data of entries (rows <= cols); -1 where not in the pattern."""
    n = model.n_eq
    keys = upper_rows(model) * n + model.indices
    query = rows * n + cols
    pos = np.searchsorted(keys, query)
    pos_c = np.minimum(pos, len(keys) - 1)
    return np.where(keys[pos_c] == query, pos_c, -1)
