"""The displacement of a few points (lesion centres, lesion mesh vertices) as the deployed
surrogate predicts it, without the full-grid field: :class:`PointOperator`.

With the linear-elastic baseline the surrogate predicts ``u = u_lin(x) + r`` (and, with the
contact projection, ``u' = u + u_lin(u_c - W_P u)``), ``x = M u_c`` the network input of the
contact displacements ``u_c`` (n, 3) mm and ``r`` the network's residual. Everything but ``r``
is linear in ``u_c``, so at the points

    u(points) = E r + A u_c                      (no projection)
    u'(points) = E r + A u_c - L W_P r           (projection)

with ``E`` the points' trilinear interpolation, ``A`` one dense matrix folding ``M`` into the
baseline's rows at the points (and, with the projection, ``u_lin(u_c - W_P M u_c)``), and
``L`` the projection's ``u_lin`` of point displacements at the points. ``A`` and ``L`` are
built once per contact set; a prediction then costs the network and two small products.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..grid.embedding import Embedding
from ..probe import ContactInputOperator
from .baseline import LinearElasticBaseline
from .projection import ContactProjection


@dataclass(frozen=True)
class PointOperator:
    """``u(points) = E r + A u_c (- L W_P r)`` for one contact set (module doc).

    ``embedding``: ``E`` (m points); ``linear``: ``A`` (3 m axis-major, 3 n point-major);
    ``projected``: ``L`` (3 m, 3 n_p) or None without the projection; ``projection``: the
    :class:`ContactProjection` whose ``W_P`` it applies, or None."""

    embedding: Embedding
    linear: np.ndarray
    projected: np.ndarray | None = None
    projection: ContactProjection | None = None

    @property
    def n_points(self) -> int:
        return len(self.embedding.weights)

    def displacement(self, residual: np.ndarray, contact_disp: np.ndarray) -> np.ndarray:
        """Displacement (m, 3) mm of the points for the network's ``residual`` (3, nx, ny, nz)
        mm (its output) and the contact displacements (n, 3) mm."""
        base = self.linear @ np.asarray(contact_disp).ravel()  # (3 m,), axis-major
        if self.projected is not None:  # - u_lin(W_P r) at the points
            base -= self.projected @ self.projection.point_displacement(residual).ravel()
        return self.embedding.interpolate(residual.reshape(3, -1).T) + base.reshape(3, -1).T

    def first(self, m: int) -> PointOperator:
        """The operator of the first ``m`` points only (e.g. the lesion centres)."""
        rows = np.concatenate([k * self.n_points + np.arange(m) for k in range(3)])
        return PointOperator(self.embedding.subset(np.arange(m)), self.linear[rows],
                             None if self.projected is None else self.projected[rows],
                             self.projection)


def point_operator(baseline: LinearElasticBaseline, input_op: ContactInputOperator,
                   points: Embedding, projection: ContactProjection | None = None
                   ) -> PointOperator:
    """The :class:`PointOperator` at ``points`` for the contact set of ``input_op`` (the
    network input ``x = M u_c``), with ``projection`` when predictions are projected."""
    rows = sp.kron(sp.identity(3), points.matrix, format="csr")  # (3 m, 3 n_nodes)
    if projection is None:
        positions, operator = baseline.contact_operator(input_op.weights, rows)
        at = input_op.rows_at(positions)  # the input operator's row of each dof (-1: none)
        linear = operator @ np.where((at >= 0)[:, None], input_op.matrix[np.maximum(at, 0)],
                                     0.0)
        return PointOperator(points, linear)
    projected = projection.lesion_operator(rows)
    # the baseline's contact forces for the input x = M u_c are the projection's
    # ``forces_of_points @ u_c``, so at the points u_lin(x) = L u_c and
    # u_lin(x) + u_lin(u_c - W_P x) = L (2 u_c - W_P M u_c)
    w_p_m = _points_of_input(projection, input_op, baseline.n_nodes) @ input_op.matrix
    linear = projected @ (2.0 * np.eye(w_p_m.shape[0]) - w_p_m)
    return PointOperator(points, linear, projected, projection)


def _points_of_input(projection: ContactProjection, input_op: ContactInputOperator,
                     n_nodes: int) -> np.ndarray:
    """``W_P`` restricted to the input's written dofs: (3 n_p, q), point-major rows."""
    comp, node = np.divmod(input_op.positions, n_nodes)
    w = projection.contact[:, node].toarray()  # (n_p, q) weights of the written dofs
    out = np.zeros((w.shape[0], 3, len(node)))
    out[:, comp, np.arange(len(node))] = w
    return out.reshape(-1, len(node))
