"""The fictitious domain of the cut cells: linear-elastic stiffness for the empty part.

An immersed cell that the breast surface cuts integrates the tissue's hyperelastic energy with
its tissue fraction as weight (:mod:`biopsynav.fem.model`). A nearly empty one holding contact
points can turn over under a deep push (a limit point of the discrete model that the continuum
does not have). As in the finite cell method for large deformations, the empty part of each
cell keeps a small share ``alpha`` of its material's small-strain stiffness, linear in the
displacement (no geometric softening, so it cannot buckle):

    W_f = 1/2 u_e^T K_e u_e,   K_e = alpha (1 - weight_e) K0_e,

``K0_e`` the element's tangent at rest for its own E and nu and the full cell, ``weight_e``
its integration weight (the tissue fraction, at least ``[grid] min_fraction``). The
matrices are built once per model; they add ``K_e u_e`` to the internal forces and ``K_e``
to every tangent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .model import FEModel


@dataclass(frozen=True)
class FictitiousStiffness:
    """``K_e`` (n, 24, 24) N/mm of the ``elements`` (n,) with an empty part, their nodes
    ``hexes`` (n, 8), and their sum in the model's upper CSR pattern, ``data`` (nnz,)."""

    elements: np.ndarray
    hexes: np.ndarray
    matrices: np.ndarray
    data: np.ndarray

    def forces(self, u_nodes: np.ndarray) -> tuple[np.ndarray, float]:
        """Element forces (n, 24) N at displacement ``u_nodes`` (n_nodes, 3) mm and their
        energy, mJ."""
        ue = u_nodes[self.hexes].reshape(len(self.elements), 24)
        fe = np.einsum("eij,ej->ei", self.matrices, ue)
        return fe, 0.5 * float(np.einsum("ei,ei->", fe, ue))


def fictitious_stiffness(model: FEModel) -> FictitiousStiffness | None:
    """The model's :class:`FictitiousStiffness` (None when ``model.fictitious`` is 0 or no
    cell has an empty part), built on first use and cached on the model."""
    if "fictitious" not in model.cache:
        model.cache["fictitious"] = _build(model)
    return model.cache["fictitious"]


def _build(model: FEModel) -> FictitiousStiffness | None:
    share = model.fictitious * np.clip(1.0 - model.weight, 0.0, 1.0)
    elements = np.flatnonzero(share > 0.0)
    if len(elements) == 0:
        return None
    n, hexes = len(elements), model.hexes[elements]
    ke = np.empty((n, 24, 24))
    kernels.element_kernel(np.zeros((model.n_nodes, 3)), hexes,
                           model.elem_set[elements], model.grads, model.jw,
                           np.ascontiguousarray(share[elements]), model.mu[elements],
                           model.lam[elements], kernels.NEO_HOOKEAN, True, np.empty((n, 24)),
                           ke, np.empty(n), np.empty(n))
    data = np.zeros(model.nnz)
    kernels.scatter_matrix(ke, np.ascontiguousarray(model.scatter[elements]), data)
    return FictitiousStiffness(elements, hexes, ke, data)
