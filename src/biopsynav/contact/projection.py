"""Contact consistency: a prediction that moves the contact points exactly as measured.

The surrogate predicts ``u = u_lin(g) + r``: the linear-elastic baseline for the contact-point
displacement ``g`` (mm, ``W_P u = g`` with ``W_P`` the trilinear weights of the points, (n,
n_nodes)) plus the network's non-linear residual ``r``. The FE solution moves the points by
``g`` exactly, so its residual is invisible at the points (``W_P r_FE = 0``); the network's
residual is not, quite. :class:`ContactProjection` removes what the points see of ``r`` and lets
the linear-elastic field carry the rest of the measurement:

    u' = u + u_lin(g - W_P u),   u = u_lin(g) + r

so that ``W_P u' = g`` again while a residual the points do not see (the FE one) passes
unchanged: the projection, orthogonal in the linear-elastic energy, onto the fields that honour
the measured contact. ``u_lin`` is the elastic contact input followed by the hard baseline, a
regularised least-squares fit of the points (:data:`biopsynav.probe.ELASTIC_REGULARISATION`),
so ``g - W_P u`` also holds what the baseline of the (float32) input left of ``g`` (about
1e-3 mm); fitting it too is part of the measured gain. A prediction costs what the baseline
alone did: one weighted sum of the Green's functions, everything else precomputed per contact
set. Measured on the phantom's 200 held-out samples it lowers mean e by
7 % and max e by 7-16 % (two models, docs/network.md).

It needs the contact points themselves, not only the network input: the tracker has them (the
skin under the probe at the rest pose) and Table 1 redraws them from the data set's protocol
(:func:`biopsynav.dataset.contacts.sample_contact_matrices`). It applies to models with the
elastic contact input and the hard (``spring = None``) linear-elastic baseline.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from ..errors import InputError
from ..probe import ContactInputOperator, contact_input_operator
from ..threads import one_thread
from .baseline import LinearElasticBaseline


class ContactProjection:
    """The projection of one contact set (see the module doc); build with :meth:`build`.

    Attributes:
        contact: CSR (n, n_nodes) ``W_P``, trilinear weights of the contact points.
        input_op: the elastic :class:`~biopsynav.probe.ContactInputOperator` of the set (what
            the tracker writes into the network input).
        positions: (k,) channel-major flat positions of the contact dofs (the baseline's).
        sel: (k,) their rows of the Green's functions ``zt``.
        forces_of_input: (k, k) float64, contact forces (N) per mm of input on ``positions``
            (``Z_cc^-1``).
        forces_of_points: (k, 3n) float64, contact forces (N) per mm of point displacement
            (point-major flat): ``Z_cc^-1`` times the input operator.
    """

    def __init__(self, baseline: LinearElasticBaseline, contact: sp.csr_matrix,
                 input_op: ContactInputOperator, positions: np.ndarray, sel: np.ndarray,
                 forces_of_input: torch.Tensor, forces_of_points: torch.Tensor) -> None:
        self.baseline = baseline
        self.contact = contact
        self.input_op = input_op
        self.positions = positions
        self.sel = sel
        self.forces_of_input = forces_of_input
        self.forces_of_points = forces_of_points

    @classmethod
    def build(cls, baseline: LinearElasticBaseline, contact: sp.spmatrix,
              input_op: ContactInputOperator | None = None) -> ContactProjection:
        """The projection for contact points of trilinear weights ``contact`` (n, n_nodes).

        ``input_op``: the set's elastic input operator when already built (the tracker's).
        Raises InputError for a baseline with soft springs (its input is not the point
        constraint) or a contact matrix of the wrong shape.
        """
        if baseline.spring is not None:
            raise InputError("the contact projection needs the hard linear-elastic baseline "
                             "(a model trained with the elastic contact input)", "projection")
        contact = sp.csr_matrix(contact, dtype=np.float64)
        if contact.ndim != 2 or contact.shape[1] != baseline.n_nodes or contact.shape[0] == 0:
            raise InputError(f"contact matrix of shape {contact.shape} is not (n > 0, "
                             f"{baseline.n_nodes})", "projection")
        if input_op is None:
            input_op = contact_input_operator(contact, "elastic", baseline.compliance)
        positions, sel, w = baseline.contact_dofs(input_op.weights)
        rows = input_op.rows_at(positions)
        if len(rows) != len(input_op.positions) or (rows < 0).any():
            raise InputError("the input operator and the baseline disagree on the contact dofs",
                             "projection")
        f_in = baseline.force_matrix(sel, w)
        with torch.inference_mode():
            f_pts = f_in @ torch.from_numpy(input_op.matrix[rows])
        return cls(baseline, contact, input_op, positions, sel, f_in, f_pts)

    @property
    def n_points(self) -> int:
        return int(self.contact.shape[0])

    def point_displacement(self, field: np.ndarray) -> np.ndarray:
        """Displacement (n, 3) mm of the contact points for a grid field (C >= 3, nx, ny, nz)
        (channels 0-2; the network input's channel 3 is ignored)."""
        flat = np.asarray(field).reshape(np.shape(field)[0], -1)[:3]
        c = self.contact
        return np.add.reduceat(flat[:, c.indices] * c.data, c.indptr[:-1], axis=1).T

    def _checked_points(self, contact_disp: np.ndarray) -> np.ndarray:
        g = np.asarray(contact_disp, dtype=np.float64)
        if g.shape != (self.n_points, 3):
            raise InputError(f"contact displacement of shape {g.shape} is not "
                             f"({self.n_points}, 3)", "projection")
        return g

    def input_forces(self, inputs: np.ndarray, contact_disp: np.ndarray) -> torch.Tensor:
        """The contact forces (k,) N of the projection that do not need the network (run it
        meanwhile): the baseline's for the input (4, nx, ny, nz) plus those that move the
        points by what the input leaves of ``contact_disp`` (n, 3) mm."""
        x = np.asarray(inputs)
        misfit = self._checked_points(contact_disp) - self.point_displacement(x)
        g = np.asarray(x, dtype=np.float64).reshape(-1)[self.positions]
        with torch.inference_mode():
            return (self.forces_of_input @ torch.from_numpy(g)
                    + self.forces_of_points @ torch.from_numpy(misfit.reshape(-1)))

    def baseline_field(self, inputs: np.ndarray, contact_disp: np.ndarray,
                       residual: np.ndarray, input_forces: torch.Tensor | None = None
                       ) -> np.ndarray:
        """``u_lin(x) + u_lin(g - W_P (u_lin(x) + r))`` (3, nx, ny, nz) float32 mm for the
        input ``x`` (4, nx, ny, nz), the measured contact displacement ``g`` (n, 3) mm and
        the network's residual ``r`` (3, nx, ny, nz); ``input_forces``: :meth:`input_forces`
        when already computed. Add ``residual`` for the projected prediction."""
        a0 = (self.input_forces(inputs, contact_disp) if input_forces is None
              else input_forces)
        seen = torch.from_numpy(self.point_displacement(residual).reshape(-1))
        with torch.inference_mode():
            a = a0 - self.forces_of_points @ seen
        return self.baseline.response(self.sel, a).reshape(3, *self.baseline.node_shape)

    def project(self, inputs: np.ndarray, contact_disp: np.ndarray,
                residual: np.ndarray) -> np.ndarray:
        """The projected prediction (3, nx, ny, nz) float32 mm: ``u + u_lin(g - W_P u)`` with
        ``u = u_lin(x) + r`` (see the module doc)."""
        return (np.asarray(residual, dtype=np.float32)
                + self.baseline_field(inputs, contact_disp, residual))

    def lesion_operator(self, out_rows: sp.spmatrix) -> np.ndarray:
        """``u_lin`` of point displacements at ``out_rows`` (r, 3 n_nodes; e.g. the lesion
        interpolation) as one matrix (r, 3n) on the point-major flat point displacement, for
        ``out_rows @ u_lin(d).ravel() == matrix @ d.ravel()``."""
        return self.baseline.response_at(self.sel, out_rows) @ self.forces_of_points.numpy()


#: A stored input must equal the input rebuilt from its redrawn contact points' displacement
#: to this (mm, plus this share of the input's largest value): float32 storage and the solve's
#: rounding only.
INPUT_MATCH_MM = 1e-3
INPUT_MATCH_REL = 1e-4


def sample_projections(baseline: LinearElasticBaseline, contacts: list[sp.spmatrix],
                       inputs: np.ndarray, targets: np.ndarray, samples: np.ndarray,
                       where: str) -> list[tuple[ContactProjection, np.ndarray]]:
    """For stored samples: the projection of each one's contact points ``contacts[i]`` (from
    :func:`biopsynav.dataset.contacts.sample_contact_matrices`) and their displacement ``g =
    W_P u_FE`` (n, 3) mm, from which the dataset stage built the input.

    ``inputs`` (N, 4, nx, ny, nz) and ``targets`` (N, 3, nx, ny, nz) are the data set's stored
    arrays, ``samples`` (m,) the ids of the samples (one per contact matrix), ``where`` the
    data set's path. Raises
    InputError when ``g`` does not rebuild the stored input: the data set was made by another
    version.
    """
    out = []
    with one_thread():  # many small dense solves: threads only wait on each other
        for i, w in zip(samples, contacts, strict=True):  # set-up, once per sample
            proj = ContactProjection.build(baseline, w)
            g = proj.point_displacement(targets[i])
            op = proj.input_op
            stored = np.asarray(inputs[i]).reshape(-1)[op.positions]
            off = float(np.abs(op.matrix @ g.ravel() - stored).max(initial=0.0))
            if off > INPUT_MATCH_MM + INPUT_MATCH_REL * float(np.abs(stored).max(initial=0.0)):
                raise InputError(f"sample {int(i)}: its redrawn contact points give an "
                                 f"input {off:.3g} mm off the stored one; the data set was made "
                                 "by another version: regenerate it", where)
            out.append((proj, g))
    return out


class BatchProjection:
    """Training through the projection: what the contact points see of a batch of residuals,
    each sample with its own contact set (padded, so that a batch is a few batched products).

    ``seen(r, idx)`` is ``u_lin(W_P r)`` (B, 3, nx, ny, nz) mm for residuals ``r`` (same shape,
    mm) of the samples ``idx`` (B,): the projected residual is ``r - seen(r, idx)`` (see the
    module doc). float32, differentiable in ``r``.
    """

    def __init__(self, baseline: LinearElasticBaseline, projections: list[ContactProjection],
                 device: torch.device | str = "cpu") -> None:
        n_max = max(p.n_points for p in projections)
        k_max = max(len(p.sel) for p in projections)
        count = len(projections)
        self.node_shape = baseline.node_shape
        self.n_points = n_max
        self.nodes = torch.zeros((count, n_max * 8), dtype=torch.int64)
        self.weights = torch.zeros((count, n_max * 8), dtype=torch.float32)
        self.sel = torch.zeros((count, k_max), dtype=torch.int64)
        self.forces = torch.zeros((count, k_max, 3 * n_max), dtype=torch.float32)
        for i, p in enumerate(projections):  # set-up, once per sample
            nodes, weights = _padded_rows(p.contact)
            self.nodes[i, :nodes.size] = torch.from_numpy(nodes.ravel())
            self.weights[i, :nodes.size] = torch.from_numpy(weights.ravel())
            k, n = len(p.sel), p.n_points
            self.sel[i, :k] = torch.from_numpy(p.sel)
            # point-major flat columns (point, axis) -> padded (point, axis) layout
            self.forces[i, :k].view(k, n_max, 3)[:, :n] = \
                p.forces_of_points.to(torch.float32).view(k, n, 3)
        self.zt = baseline.zt_torch.to(torch.float32)
        self.out_pos = torch.from_numpy(baseline.out_pos)
        self.n_nodes = baseline.n_nodes
        self.to(device)

    def to(self, device: torch.device | str) -> BatchProjection:
        for name in ("nodes", "weights", "sel", "forces", "zt", "out_pos"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    def seen(self, residual: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """``u_lin(W_P r)`` (B, 3, nx, ny, nz) mm of residuals (B, 3, nx, ny, nz) mm of the
        samples ``idx`` (B,)."""
        b = residual.shape[0]
        flat = residual.float().reshape(b, 3, -1)
        nodes = self.nodes[idx][:, None, :].expand(b, 3, -1)
        at_points = (torch.gather(flat, 2, nodes) * self.weights[idx][:, None, :])
        at_points = at_points.reshape(b, 3, self.n_points, 8).sum(-1)  # (B, 3, n)
        point_major = at_points.transpose(1, 2).reshape(b, -1, 1)  # (B, 3n, 1)
        forces = torch.bmm(self.forces[idx], point_major)[:, :, 0]  # (B, k)
        # sum_k forces[b, k] * zt[sel[b, k]] without copying the rows (B, k, n_eq) first
        k = forces.shape[1]
        offsets = torch.arange(0, b * k, k, device=forces.device)
        field = torch.nn.functional.embedding_bag(
            self.sel[idx].reshape(-1), self.zt, offsets, mode="sum",
            per_sample_weights=forces.reshape(-1))  # (B, n_eq)
        out = torch.zeros((b, 3 * self.n_nodes), dtype=field.dtype, device=field.device)
        return out.index_copy(1, self.out_pos, field).reshape(b, 3, *self.node_shape)


def _padded_rows(contact: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Node ids and trilinear weights (n, 8) of each row of ``contact`` (at most 8 entries per
    row; padded with node 0 and weight 0)."""
    count = np.diff(contact.indptr)
    if count.max(initial=0) > 8:
        raise InputError("a contact point with more than 8 trilinear weights", "projection")
    slot = np.arange(contact.nnz) - np.repeat(contact.indptr[:-1], count)
    row = np.repeat(np.arange(contact.shape[0]), count)
    nodes = np.zeros((contact.shape[0], 8), dtype=np.int64)
    weights = np.zeros((contact.shape[0], 8), dtype=np.float32)
    nodes[row, slot] = contact.indices
    weights[row, slot] = contact.data
    return nodes, weights


__all__ = ["BatchProjection", "ContactProjection", "sample_projections"]
