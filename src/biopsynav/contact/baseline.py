"""Physics baseline of the surrogate: the exact small-strain linear-elastic response.

:class:`LinearElasticBaseline` predicts the grid displacement that the case's FE model, linearised
at u = 0 (tangent ``K`` = linear elasticity with the same E, nu, immersed weights and fixed chest
wall), takes when the contact nodes are moved by the network input and every other node is
force-free. The U-Net then only learns the residual (geometric and material non-linearity).

Green's-function (Schur) form, with ``Z`` of :class:`~biopsynav.contact.greens.ContactCompliance`
(unit forces on every candidate dof): the solution with prescribed values ``g`` on the contact
set ``c`` is ``u = Z[:, c] Z[c, c]^-1 g``: the forces ``f_c = Z[c, c]^-1 g`` on ``c`` reproduce
``g`` there, and no force acts elsewhere.

With the elastic contact input (``[dataset] contact_input = "elastic"``, the default) the
input already is the nodal field of the point-constrained linear solution, and hard constraints
(``spring=None``) reproduce that solution exactly. Models trained on the averaged input use soft
springs instead (``docs/network.md``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import torch

from ..errors import InputError
from .greens import ContactCompliance

if TYPE_CHECKING:
    from ..case import Case
    from ..fem import FEModel

KINDS = ("none", "linear-elastic")
# Soft contact (measured on the quick phantom, docs/network.md): spring of stiffness
# SPRING_SCALE * w**SPRING_POWER / median(diag Z) per contact node of weight sum w.
SPRING_SCALE = 0.3
SPRING_POWER = 2.0


class LinearElasticBaseline:
    """Linear-elastic response to prescribed contact-node displacements (see module doc).

    Args:
        compliance: the Green's functions (:class:`~biopsynav.contact.greens.ContactCompliance`)
            of the FE model linearised at rest; :meth:`from_case` and :meth:`from_model` make
            them.
        spring: None: hard constraints (the exact Dirichlet response, ``u_c = g``); a float
            ``s``: soft constraints, each contact node tied to its input value by a spring of
            stiffness ``s * w**power / median(diag Z)`` (w: its weight sum, channel 3).

    Why springs: the input on a node is the trilinear-weighted *average* of the contact-point
    displacements, not that node's displacement; on nodes with a small weight sum (a far
    corner of a cell that holds contact points) it can be off by tens of mm. Measured on the
    quick phantom: hard constraints mean e 1.18 mm, springs (s = 0.3, power 2) 0.30 mm, hard
    constraints on the true nodal FE displacement 0.15 mm (the non-linearity alone).
    """

    def __init__(self, compliance: ContactCompliance, spring: float | None = SPRING_SCALE,
                 power: float = SPRING_POWER) -> None:
        self.compliance = c = compliance
        self.node_shape, self.n_nodes = c.node_shape, c.n_nodes
        self.cols, self.col_of, self.out_pos, self.zt = c.cols, c.col_of, c.out_pos, c.zt
        self.z_ref = c.z_ref
        self.zt_torch = torch.from_numpy(self.zt)  # the same rows (n_cand, n_eq), shared memory
        self.spring = None if spring is None else float(spring)
        self.power = float(power)

    @classmethod
    def from_case(cls, case: Case, dtype: type = np.float32,
                  spring: float | None = SPRING_SCALE,
                  power: float = SPRING_POWER) -> LinearElasticBaseline:
        """The baseline of a case: its FE model and the nodes around its free skin."""
        return cls(ContactCompliance.from_case(case, dtype), spring, power)

    @classmethod
    def from_model(cls, model: FEModel, candidate_nodes: np.ndarray,
                   node_shape: tuple[int, int, int], dtype: type = np.float32,
                   spring: float | None = SPRING_SCALE,
                   power: float = SPRING_POWER) -> LinearElasticBaseline:
        """The baseline of any FE model, with contact possible on ``candidate_nodes`` (flat
        node ids, C order over ``node_shape`` (nx, ny, nz)); ``dtype``: storage of ``Z``."""
        return cls(ContactCompliance(model, candidate_nodes, node_shape, dtype), spring, power)

    @property
    def n_candidate_dofs(self) -> int:
        return self.compliance.n_candidate_dofs

    @property
    def nbytes(self) -> int:
        return self.compliance.nbytes

    def contact_columns(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Columns of Z (k,), prescribed values (k,) mm and weight sums (k,) of one input."""
        flat = x.reshape(4, -1)
        positions, sel, w = self.contact_dofs(flat[3])
        return sel, flat[:3].reshape(-1)[positions].astype(np.float64), w

    def contact_dofs(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For weight sums (n_nodes,) (input channel 3): the free candidate dofs of the nodes
        with weight, node-major: their positions (k,) in the channel-major flat displacement
        channels, their columns of Z (k,), and their nodes' weight sums (k,) float64."""
        nodes = np.flatnonzero(weights > 0)
        sel = self.col_of[nodes]  # (n, 3)
        ok = sel >= 0
        positions = (np.arange(3)[None, :] * self.n_nodes + nodes[:, None])[ok]
        w = np.repeat(np.asarray(weights[nodes], dtype=np.float64)[:, None], 3, axis=1)
        return positions, sel[ok], w[ok]

    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """Displacement (3, nx, ny, nz) float32 mm of input (4, nx, ny, nz); batched too."""
        x = np.asarray(inputs)
        if x.ndim == 5:
            return np.stack([self.predict(xi) for xi in x])
        if x.shape != (4, *self.node_shape):
            raise InputError(f"input shape {x.shape} is not (4, {self.node_shape})", "baseline")
        sel, g, w = self.contact_columns(x)
        if not sel.size:
            return np.zeros((3, *self.node_shape), dtype=np.float32)
        # torch, not NumPy: its kernels follow torch.set_num_threads (the Surrogate's idle
        # cores); NumPy's multi-threaded BLAS took 90 ms instead of 1 ms on the loaded 2-core
        # machine (docs/network.md)
        with torch.inference_mode():
            a = self._contact_forces(self._block(sel), sel, w, torch.from_numpy(g)[:, None])[:, 0]
        return self.response(sel, a).reshape(3, *self.node_shape)

    def force_matrix(self, sel: np.ndarray, w: np.ndarray) -> torch.Tensor:
        """Forces (k, k) float64 N on the contact dofs ``sel`` (k,) per mm prescribed on each
        (their nodes' weight sums ``w`` (k,), for springs): ``Z[c, c]^-1`` for hard
        constraints, ``D (I + D Z[c, c] D)^-1 D`` for springs."""
        with torch.inference_mode():
            return self._contact_forces(self._block(sel), sel, w,
                                        torch.eye(len(sel), dtype=torch.float64))

    def response(self, sel: np.ndarray, forces: torch.Tensor) -> np.ndarray:
        """The displacement (3 n_nodes,) float32 mm, channel-major flat, of ``forces`` (k,) N
        on the candidate dofs ``sel`` (k,): one weighted sum of Green's function rows."""
        out = np.zeros(3 * self.n_nodes, dtype=np.float32)
        with torch.inference_mode():
            out[self.out_pos] = _weighted_row_sum(self.zt_torch, sel, forces).numpy()
        return out

    def response_at(self, sel: np.ndarray, out_rows: sp.spmatrix) -> np.ndarray:
        """``out_rows`` (r, 3 n_nodes) applied to the response of a unit force on each
        candidate dof ``sel`` (k,): (r, k) float64, mm per N (e.g. at the lesion centres)."""
        return np.asarray(out_rows[:, self.out_pos] @ self._rows(sel).T)

    def _rows(self, sel: np.ndarray) -> np.ndarray:
        """The Green's function rows ``zt[sel]`` (k, n_eq) as float64."""
        with torch.inference_mode():
            return self.zt_torch.index_select(0, torch.from_numpy(sel)).double().numpy()

    def _block(self, sel: np.ndarray) -> torch.Tensor:
        """``Z[c, c]`` (k, k) float64, symmetrised, of the candidate dofs ``sel`` (k,)."""
        return torch.from_numpy(self.compliance.block(sel))

    def _contact_forces(self, zcc: torch.Tensor, sel: np.ndarray, w: np.ndarray,
                        g: torch.Tensor) -> torch.Tensor:
        """Forces (k, r) float64 on the contact dofs ``sel`` (k,) for prescribed values ``g``
        (k, r) mm, from ``zcc = Z[c, c]`` (k, k) float64: hard constraints ``Z[c, c]^-1 g`` or
        springs ``D (I + D Z[c, c] D)^-1 D g`` (``D^2`` the spring stiffnesses from the weight
        sums ``w`` (k,))."""
        if self.spring is None:  # hard: forces f with Z[c, c] f = g
            return _spd_solve(zcc, g)
        d = torch.from_numpy(np.sqrt(self.spring / self.z_ref * w ** self.power))
        eye = torch.eye(len(d), dtype=torch.float64)
        return d[:, None] * _spd_solve(eye + d[:, None] * zcc * d[None, :], d[:, None] * g)

    def contact_operator(self, weights: np.ndarray, out_rows=None
                         ) -> tuple[np.ndarray, np.ndarray]:
        """The baseline as one matrix, for a contact set that stays fixed (a tracker's rest
        pose): only the displacement channels change between predictions, and the baseline is
        linear in them.

        Args:
            weights: (n_nodes,) or (nx, ny, nz) weight sums (input channel 3).
            out_rows: optional sparse (r, 3 * n_nodes) matrix applied to the channel-major flat
                output (e.g. the trilinear interpolation at the lesion centres).

        Returns:
            ``positions`` (k,) int64 into the channel-major flat displacement channels
            (``x[:3].ravel()``) and ``operator`` (r or 3 * n_nodes, k) float64, so that
            ``operator @ x[:3].ravel()[positions]`` equals ``out_rows @ predict(x).ravel()``
            (or ``predict(x).ravel()``) for every input ``x`` with these weight sums.
        """
        positions, sel, w = self.contact_dofs(np.asarray(weights, dtype=np.float64).ravel())
        n_out = 3 * self.n_nodes if out_rows is None else out_rows.shape[0]
        if not sel.size:
            return positions, np.zeros((n_out, 0))
        forces = self.force_matrix(sel, w).numpy()
        if out_rows is None:
            operator = np.zeros((n_out, len(sel)))
            operator[self.out_pos] = self._rows(sel).T @ forces  # (n_eq, k): free equations
            return positions, operator
        return positions, self.response_at(sel, out_rows) @ forces


def _weighted_row_sum(zt: torch.Tensor, sel: np.ndarray, a: torch.Tensor) -> torch.Tensor:
    """``a @ zt[sel]`` (n_eq,) in ``zt``'s dtype in one pass over the selected rows
    (``embedding_bag``) instead of copying the rows ``zt[sel]`` (k, n_eq) first; 0.24 ms for
    k = 210 on the phantom, about what the copy-then-multiply took there."""
    bag = torch.nn.functional.embedding_bag(torch.from_numpy(sel)[None], zt, mode="sum",
                                            per_sample_weights=a.to(zt.dtype)[None])
    return bag[0]


def _spd_solve(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a^-1 b`` (b: (k, r)) for a symmetric positive definite ``a`` (least squares if it
    is not)."""
    chol, info = torch.linalg.cholesky_ex(a)
    if int(info) == 0:
        return torch.cholesky_solve(b, chol)
    return torch.linalg.lstsq(a, b).solution
