"""Loads of a static solve: nodal forces and prescribed displacements of embedded points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .model import FEModel, find_positions

#: loads at or below these are no load: the solve returns zero displacement at once (a rest
#: pose recomputed through a matrix inverse prescribes displacements of ~1e-13 mm)
NEGLIGIBLE_FORCE_N = 1e-12
NEGLIGIBLE_DISPLACEMENT_MM = 1e-9


@dataclass
class Loads:
    """Loads, both optional and combinable.

    Attributes:
        forces: (n_nodes, 3) nodal forces, N (dead loads; forces on fixed nodes are taken by
            the support).
        prescribed_matrix: (n_pts, n_nodes) sparse interpolation matrix ``W`` (trilinear
            weights, rows summing to 1) of points whose displacement is prescribed.
        prescribed_displacement: (n_pts, 3) target displacements ``g`` of those points, mm;
            the solve enforces ``W u = g``.
        prescribed_normals: optional (n_pts, 3) unit vectors ``n`` (rows of zeros: the whole
            vector): where given, only the component along ``n`` is prescribed,
            ``n . (W u) = n . g``, and the point slides freely normal to it (frictionless
            contact with a plane of normal ``n``).
        prescribed_stiffness: optional (n_pts,) N/mm, all > 0: where given, each point is
            tied to its target by a spring of this stiffness (elastic contact: energy
            ``k_i / 2 |W_i u - g_i|^2``) and the gap that remains is part of the answer;
            without it the targets are met (penalty and augmented-Lagrangian updates to
            ``[solver] constraint_tolerance_mm``).
    """

    forces: np.ndarray | None = None
    prescribed_matrix: sp.spmatrix | None = None
    prescribed_displacement: np.ndarray | None = None
    prescribed_normals: np.ndarray | None = None
    prescribed_stiffness: np.ndarray | None = None


@dataclass
class PreparedLoads:
    """Loads in free-equation form for one model.

    ``f`` (n_eq,) forces; ``w`` (n_pts, n_nodes) CSR prescribed-point matrix; ``g``
    (n_pts, 3); ``projector`` (n_pts, 3, 3): ``P_i`` = I for a whole prescribed vector,
    ``n n^T`` for a normal-only one (None: all whole); ``pen_pos`` / ``pen_val`` positions in
    the tangent's upper CSR data and values of ``W^T P W`` on free equations (penalty
    stiffness per unit penalty). With elastic contact (``Loads.prescribed_stiffness``)
    ``w`` and ``g`` hold each point's row times ``scale`` (n_pts,) = sqrt(k_i) (sqrt(N/mm)),
    so that ``W^T P W`` is the springs' stiffness itself; ``scale`` is None otherwise.
    """

    f: np.ndarray
    w: sp.csr_matrix | None
    g: np.ndarray | None
    pen_pos: np.ndarray | None
    pen_val: np.ndarray | None
    projector: np.ndarray | None = None
    scale: np.ndarray | None = None

    def gap(self, u_nodes: np.ndarray, t: float = 1.0) -> np.ndarray:
        """The constraint error ``P (W u - t g)`` (n_pts, 3) of node displacements
        ``u_nodes`` (n_nodes, 3) at load factor ``t``: mm, or with elastic contact mm times
        ``scale``."""
        e = self.w @ u_nodes - t * self.g
        return e if self.projector is None else np.einsum("pij,pj->pi", self.projector, e)

    def gap_mm(self, u_nodes: np.ndarray) -> np.ndarray:
        """The gap ``P (W u - g)`` (n_pts, 3) mm at full load."""
        gap = self.gap(u_nodes)
        return gap if self.scale is None else gap / self.scale[:, None]

    @property
    def elastic(self) -> bool:
        """Whether the points are tied by springs (elastic contact) rather than met."""
        return self.scale is not None

    @property
    def has_constraints(self) -> bool:
        return self.w is not None

    @property
    def is_zero(self) -> bool:
        """Whether the loads are negligible (no force above ``NEGLIGIBLE_FORCE_N``, no
        prescribed displacement above ``NEGLIGIBLE_DISPLACEMENT_MM``)."""
        no_force = not np.any(np.abs(self.f) > NEGLIGIBLE_FORCE_N)
        return no_force and (self.g is None
                             or not np.any(np.abs(self.g) > NEGLIGIBLE_DISPLACEMENT_MM))


def prepare_loads(model: FEModel, loads: Loads) -> PreparedLoads:
    """Check loads against ``model`` and bring them to free-equation form."""
    f = _prepare_forces(model, loads.forces)
    if loads.prescribed_matrix is None and loads.prescribed_displacement is None:
        return PreparedLoads(f, None, None, None, None)
    if loads.prescribed_matrix is None or loads.prescribed_displacement is None:
        raise InputError("prescribed displacements need both the matrix and the targets",
                         "Loads")
    # a copy: eliminate_zeros below prunes in place, and the caller keeps its matrix
    w_full = sp.csr_matrix(loads.prescribed_matrix, dtype=np.float64, copy=True)
    g = np.asarray(loads.prescribed_displacement, dtype=np.float64)
    if w_full.shape[1] != model.n_nodes or g.shape != (w_full.shape[0], 3):
        raise InputError(f"prescribed matrix must be (n_pts, {model.n_nodes}) and targets "
                         f"(n_pts, 3); got {w_full.shape} and {g.shape}", "Loads")
    if not np.all(np.isfinite(g)) or not np.all(np.isfinite(w_full.data)):
        raise InputError("prescribed displacements contain NaN or infinity", "Loads")
    w_full.eliminate_zeros()
    used = model.used_nodes()
    if np.any(~used[w_full.indices]):
        raise InputError("a prescribed point lies outside the active cells (it weights nodes "
                         "of no element)", "Loads")
    projector = _projectors(loads.prescribed_normals, len(g))
    scale = _spring_scale(loads.prescribed_stiffness, len(g))
    if scale is not None:
        w_full, g = sp.diags(scale) @ w_full, scale[:, None] * g
    if projector is None:
        pen_pos, pen_val = _penalty_pattern(model, w_full)
    else:
        pen_pos, pen_val = _projected_penalty_pattern(model, w_full, projector)
    return PreparedLoads(f, w_full.tocsr(), g, pen_pos, pen_val, projector, scale)


def _spring_scale(stiffness: np.ndarray | None, n_pts: int) -> np.ndarray | None:
    """sqrt of the points' spring stiffness (n_pts,), checked; None without springs."""
    if stiffness is None:
        return None
    k = np.asarray(stiffness, dtype=np.float64)
    if k.shape != (n_pts,) or not np.all(np.isfinite(k)) or np.any(k <= 0.0):
        raise InputError(f"prescribed stiffness must be (n_pts,) = ({n_pts},) finite values "
                         f"> 0 N/mm, got shape {k.shape}", "Loads")
    return np.sqrt(k)


def _projectors(normals: np.ndarray | None, n_pts: int) -> np.ndarray | None:
    """Per-point projectors (n_pts, 3, 3): I where the normal row is zero, ``n n^T`` where it
    is a unit vector; None without normals."""
    if normals is None:
        return None
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != (n_pts, 3) or not np.all(np.isfinite(n)):
        raise InputError(f"prescribed normals must be finite (n_pts, 3) = ({n_pts}, 3), got "
                         f"{n.shape}", "Loads")
    norm = np.linalg.norm(n, axis=1)
    whole = norm == 0.0
    if np.any(np.abs(norm[~whole] - 1.0) > 1e-9):
        raise InputError("prescribed normals must be unit vectors (or zero rows)", "Loads")
    proj = np.einsum("pi,pj->pij", n, n)
    proj[whole] = np.eye(3)
    return proj


def _projected_penalty_pattern(model: FEModel, w: sp.csr_matrix, projector: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Positions and values of ``W^T P W`` (dof-level, components coupled by each point's
    projector) in the upper CSR tangent data."""
    w_dof = sp.kron(w, sp.identity(3), format="csr")  # (3 n_pts, 3 n_nodes)
    blocks = sp.block_diag(list(projector), format="csr")  # (3 n_pts, 3 n_pts)
    m = (w_dof.T @ blocks @ w_dof).tocoo()
    eq = model.eq_of_dof.ravel()
    eq_r, eq_c = eq[m.row], eq[m.col]
    keep = (eq_r >= 0) & (eq_c >= 0) & (eq_r <= eq_c) & (m.data != 0.0)
    return _penalty_positions(model, eq_r[keep], eq_c[keep]), m.data[keep]


def _prepare_forces(model: FEModel, forces: np.ndarray | None) -> np.ndarray:
    if forces is None:
        return np.zeros(model.n_eq)
    forces = np.asarray(forces, dtype=np.float64)
    if forces.shape != (model.n_nodes, 3):
        raise InputError(f"forces must be (n_nodes, 3) = ({model.n_nodes}, 3), got "
                         f"{forces.shape}", "Loads")
    if not np.all(np.isfinite(forces)):
        raise InputError("forces contain NaN or infinity", "Loads")
    if np.any(forces[~model.used_nodes()]):
        raise InputError("forces act on nodes of no element (outside the active cells)",
                         "Loads")
    return model.to_free(forces)


def _penalty_pattern(model: FEModel, w: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Positions and values of ``W^T W`` (per component) in the upper CSR tangent data."""
    wtw = (w.T @ w).tocoo()
    eq_r = model.eq_of_dof[wtw.row].ravel()  # (nnz * 3,) component-wise
    eq_c = model.eq_of_dof[wtw.col].ravel()
    vals = np.repeat(wtw.data, 3)
    keep = (eq_r >= 0) & (eq_c >= 0) & (eq_r <= eq_c)
    return _penalty_positions(model, eq_r[keep], eq_c[keep]), vals[keep]


def _penalty_positions(model: FEModel, eq_r: np.ndarray, eq_c: np.ndarray) -> np.ndarray:
    """Positions of penalty entries (free equations, ``eq_r <= eq_c``) in the upper CSR
    tangent data; InputError where one lies outside the element pattern."""
    pos = find_positions(model, eq_r, eq_c)
    if np.any(pos < 0):
        raise InputError("a prescribed point couples nodes that share no element (each point "
                         "must weight the nodes of one cell)", "Loads")
    return pos
