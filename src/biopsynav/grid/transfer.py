"""A finer teacher grid for the same anatomy, and its displacement fields on the case grid.

The network predicts on the case grid (real-time), but that grid's FE is not converged under a
10 mm probe face (docs/fem.md). With ``[dataset] teacher_refine = r`` the training samples are
solved on a grid of cells ``r`` times smaller (:func:`refined_grid`), and each solution is
brought to the case grid by :class:`FieldTransfer`: the case-grid node field whose trilinear
interpolation is nearest, in the least-squares sense, to the fine field over the tissue (the
centre of every fine active cell, weighted by its tissue volume), with a small penalty on
differences between neighbouring nodes so that nodes the tissue barely touches follow their
neighbours. Fixed (chest-wall) nodes stay zero. The operator is factorised once per grid pair.

:class:`PointFit` is the same fit from values at any points (the P2 teacher's,
:mod:`biopsynav.dataset.converged`, at the cell centres of a finer grid that lie in its
tetrahedra), each push's points its own.

Given the contact points of a rigid probe, the fit also holds them (``held``): the case-grid
field moves them as the fine field does, so that the network input built from a stored target
is the contact displacement the tracker measures. Without it the least-squares fit smooths
the jump under a 10 mm face and moved the contact points up to 1.3 mm less than the probe.
A rigid motion of the points is in the trilinear space; the point-by-point displacements of
a force patch are not, and holding them distorts the field (docs/experiments.md, "A finer
teacher").
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..anatomy.model import Anatomy
from ..config import GridSection
from ..errors import InputError
from . import index
from .build import build_grid
from .embedding import Embedding
from .model import Grid

#: weight of the neighbour-difference penalty, relative to the mean diagonal of the data term
SMOOTHING = 1e-3
#: held contact points: the inverse of their penalty weight, relative to the mean diagonal of
#: their Schur complement (near-exact where the cells can move them as asked, stable where
#: more points than the cells' free nodes ask for what trilinear cells cannot do)
HOLD_SOFTNESS = 1e-6


def refined_grid(anatomy: Anatomy, settings: GridSection, refine: float,
                 max_fixed_share: float = 1.0, chest_tol_mm: float = 1.0) -> Grid:
    """The immersed grid of ``anatomy`` with cells of ``settings.cell_size_mm / refine``."""
    if not float(refine) >= 1.0:
        raise InputError(f"the teacher's refinement must be at least 1, got {refine}",
                         "[dataset] teacher_refine")
    fine = dataclasses.replace(settings, cell_size_mm=settings.cell_size_mm / float(refine))
    return build_grid(anatomy, fine, max_fixed_share, chest_tol_mm)


class PointFit:
    """Values at points (n_points, 3) mm -> the case-grid node field (n_nodes, 3) mm whose
    trilinear interpolation is nearest them in the least-squares sense (each point weighted),
    with the neighbour-difference penalty (``smoothing``, relative to the data term's mean
    diagonal); ``sample`` (n_points, n_values) CSR, when given, makes the values at the points
    ``sample @ field`` of a field given instead.

    Attributes:
        free: (n_free,) flat case-grid nodes that carry values (active, not fixed).
    """

    def __init__(self, coarse: Grid, points: np.ndarray, weights: np.ndarray,
                 sample: sp.csr_matrix | None = None, smoothing: float = SMOOTHING,
                 where: str = "teacher grid") -> None:
        emb = Embedding.build(coarse, points, require_active=False, where=where)
        keep = coarse.active_cells.ravel()[emb.cells]
        weight = np.asarray(weights, dtype=np.float64)
        sample = sp.identity(len(points), format="csr") if sample is None else sample
        self.n_nodes = coarse.n_nodes
        self.free = np.flatnonzero(np.asarray(coarse.active_nodes & ~coarse.fixed_nodes).ravel())
        col = np.full(coarse.n_nodes, -1, dtype=np.int64)
        col[self.free] = np.arange(len(self.free))
        n = _restricted(emb.matrix[keep], col, len(self.free))  # (n_pts, n_free)
        data = n.T @ sp.diags(weight[keep]) @ n
        scale = float(data.diagonal().mean()) if data.nnz else 1.0
        diff = neighbour_differences(coarse, col, len(self.free))
        self._lu = splu((data + smoothing * scale * (diff.T @ diff)).tocsc())
        self._rhs = (n.T @ sp.diags(weight[keep]) @ sample[keep]).tocsr()

        self._col = col

    def __call__(self, values: np.ndarray,
                 held: tuple[sp.spmatrix, np.ndarray] | None = None) -> np.ndarray:
        """The case-grid field (n_nodes, 3) mm of the values (n_values, 3) mm (at the points,
        or of the field ``sample`` reads them from).

        ``held``: (W, g), the trilinear weights (m, n_nodes) of points in the case grid and
        their displacements (m, 3) mm, which the field must reproduce (``W u = g``, as nearly
        as the cells allow) while fitting the rest."""
        out_free = self._lu.solve(np.asarray(self._rhs @ np.asarray(values, np.float64)))
        if held is not None and held[0].shape[0]:
            out_free = self._held(out_free, held[0], np.asarray(held[1], np.float64))
        out = np.zeros((self.n_nodes, 3))
        out[self.free] = out_free
        return out

    def _held(self, values: np.ndarray, weights: sp.spmatrix, target: np.ndarray
              ) -> np.ndarray:
        """The free values (n_free, 3) corrected so that the points move by ``target``: the
        minimiser of the fit plus a stiff penalty on ``W u - g``, by the Woodbury identity
        on the factorised fit (``u0 + Y (S + s I)^-1 (g - C u0)``, ``Y = K^-1 C^T``,
        ``S = C Y``). Points on fixed or inactive nodes only cannot be moved and are left out."""
        c = _restricted(sp.csr_matrix(weights), self._col, len(self.free))
        c.eliminate_zeros()
        movable = np.diff(c.indptr) > 0
        if not movable.any():
            return values
        c, target = c[movable], target[movable]
        y = self._lu.solve(np.asarray(c.T.todense()))
        schur = np.asarray(c @ y)
        soft = HOLD_SOFTNESS * float(np.mean(np.diag(schur)))
        gap = target - c @ values
        return values + y @ np.linalg.solve(schur + soft * np.eye(len(schur)), gap)


class FieldTransfer(PointFit):
    """Fine-grid node fields (n_fine_nodes, 3) -> case-grid node fields (n_nodes, 3), mm: the
    :class:`PointFit` of the field at the centre of every fine active cell, weighted by its
    tissue volume."""

    def __init__(self, coarse: Grid, fine: Grid, smoothing: float = SMOOTHING) -> None:
        centres, weight, sample = fine_cell_samples(fine)
        super().__init__(coarse, centres, weight, sample, smoothing)


def fine_cell_samples(fine: Grid) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
    """Centres (n, 3) mm of the fine active cells, their tissue volume fractions (n,), and
    the CSR (n, n_fine_nodes) matrix averaging each cell's 8 nodes (the field at the centre)."""
    ijk = fine.active_cell_ijk()
    centres = fine.origin + (ijk + 0.5) * fine.spacing
    hexes = index.hex_connectivity(ijk, fine.node_shape)
    rows = np.repeat(np.arange(len(ijk)), 8)
    sample = sp.csr_matrix((np.full(rows.size, 0.125), (rows, hexes.ravel())),
                           shape=(len(ijk), fine.n_nodes))
    return centres, fine.active_fraction().astype(np.float64), sample


def _restricted(matrix: sp.csr_matrix, col: np.ndarray, n_free: int) -> sp.csr_matrix:
    """Columns of ``matrix`` (n, n_nodes) renumbered to the free nodes; fixed or inactive
    columns dropped (they hold zero)."""
    m = matrix.tocoo()
    c = col[m.col]
    ok = c >= 0
    return sp.csr_matrix((m.data[ok], (m.row[ok], c[ok])), shape=(m.shape[0], n_free))


def neighbour_differences(grid: Grid, col: np.ndarray, n_free: int) -> sp.csr_matrix:
    """Rows ``u_a - u_b`` (n_edges, n_free) for every grid edge between active nodes with at
    least one free end (a fixed end contributes ``u_a - 0``)."""
    active = np.asarray(grid.active_nodes).ravel()
    flat = np.arange(grid.n_nodes).reshape(grid.node_shape)
    rows, cols, vals, r = [], [], [], 0
    for axis in range(3):
        a = np.moveaxis(flat, axis, 0)[:-1].ravel()
        b = np.moveaxis(flat, axis, 0)[1:].ravel()
        keep = active[a] & active[b] & ((col[a] >= 0) | (col[b] >= 0))
        a, b = a[keep], b[keep]
        edge = r + np.arange(len(a))
        for node, sign in ((a, 1.0), (b, -1.0)):
            free = col[node] >= 0
            rows.append(edge[free])
            cols.append(col[node][free])
            vals.append(np.full(int(free.sum()), sign))
        r += len(a)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(r, n_free))
