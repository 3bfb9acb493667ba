"""Green's functions of the linearised FE model for loads on the skin: :class:`ContactCompliance`.

``Z = K^-1 E``: the displacement of every free equation (mm) for a unit force (N) on each
*candidate* degree of freedom, ``K`` the tangent at u = 0 (linear elasticity with the case's
E, nu, immersed weights and fixed chest wall). Candidate nodes are the 8 nodes of every grid
cell that holds a skin vertex off the chest wall: the only nodes a probe contact can load.
``Z`` is computed once (one factorisation of ``K``, blocks of right-hand sides) and held
transposed, ``zt`` (candidate dofs x free equations), so that the columns of a contact set are
contiguous rows. A case's ``Z`` is kept in its ``cache`` folder
(:data:`~biopsynav.layout.CACHE_DIR`), named by a hash of ``K`` and the candidate equations,
so that the processes of one run (data workers, training, the evaluation's workers, the
tracker) compute it once and a changed model can never read a stale one (its file replaces
the stale one).

Used by the elastic contact input (:func:`biopsynav.probe.contact_input_operator`) and by the
network's physics baseline (:class:`biopsynav.contact.baseline.LinearElasticBaseline`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from ..case import Case
    from ..fem.model import FEModel


class ContactCompliance:
    """``Z`` for the candidate dofs of one FE model (see the module docstring).

    Attributes:
        zt: (m, n_eq) ``Z`` transposed, mm/N, in ``dtype`` (float32: 4 bytes per entry).
        cols: (m,) free equation of each candidate dof.
        col_of: (n_nodes, 3) row of ``zt`` for (node, component), -1 where not a free
            candidate dof.
        out_pos: (n_eq,) channel-major flat position (``component * n_nodes + node``) of each
            free equation in a (3, nx, ny, nz) field.
        z_ref: median diagonal compliance of the candidate dofs, mm/N.
        setup_s: seconds spent computing ``Z``.
    """

    def __init__(self, model: FEModel, candidate_nodes: np.ndarray,
                 node_shape: tuple[int, int, int], dtype: type = np.float32,
                 cache: Path | None = None) -> None:
        start = time.perf_counter()
        self.node_shape = tuple(int(n) for n in node_shape)
        self.n_nodes = int(np.prod(self.node_shape))
        if model.n_nodes != self.n_nodes:
            raise InputError(f"FE model has {model.n_nodes} nodes, grid {self.n_nodes}",
                             "contact compliance")
        eq = model.eq_of_dof  # (n_nodes, 3), -1 fixed or unused
        cand = np.unique(np.asarray(candidate_nodes, dtype=np.int64))
        cand_eq = eq[cand]
        keep = cand_eq >= 0
        self.cols = cand_eq[keep]
        self.col_of = np.full((self.n_nodes, 3), -1, dtype=np.int64)
        self.col_of[np.repeat(cand, 3).reshape(-1, 3)[keep],
                    np.tile(np.arange(3), len(cand)).reshape(-1, 3)[keep]] = \
            np.arange(len(self.cols))
        node_of_eq = np.empty(model.n_eq, dtype=np.int64)
        comp_of_eq = np.empty(model.n_eq, dtype=np.int64)
        nodes, comps = np.nonzero(eq >= 0)
        node_of_eq[eq[nodes, comps]] = nodes
        comp_of_eq[eq[nodes, comps]] = comps
        self.out_pos = comp_of_eq * self.n_nodes + node_of_eq
        self.zt = greens_rows(model, self.cols, dtype, cache)
        diag = self.zt[np.arange(len(self.cols)), self.cols] if len(self.cols) else np.ones(1)
        self.z_ref = float(np.median(diag))
        self.setup_s = time.perf_counter() - start

    @classmethod
    def from_case(cls, case: Case, dtype: type = np.float32) -> ContactCompliance:
        """The compliance of a case: its FE model and the nodes around its free skin, kept in
        (and read from) the case folder's cache where the folder exists here (a Dask worker
        on another machine computes it)."""
        from ..fem.model import FEModel

        paths = case.paths
        return cls(FEModel.from_case(case), candidate_nodes(case), case.grid.node_shape, dtype,
                   cache=paths.cache if paths.config.is_file() else None)

    @property
    def n_candidate_dofs(self) -> int:
        return int(self.cols.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.zt.nbytes)

    def block(self, rows: np.ndarray) -> np.ndarray:
        """``Z[c, c]`` (k, k) float64, symmetrised, for candidate rows ``rows`` (k,)."""
        # one flat take: half the time of np.ix_ fancy indexing (0.21 against 0.36-0.46 ms
        # for k = 210 on the phantom)
        flat = rows[:, None] * self.zt.shape[1] + self.cols[rows][None, :]
        zcc = np.take(self.zt.reshape(-1), flat).astype(np.float64)
        return 0.5 * (zcc + zcc.T)

    def contact_dofs(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For flat node ids ``nodes`` (n,): ``rows`` (k,) of ``zt`` of their free dofs, and
        ``local`` (n, 3), the index of each (node, component) in ``rows`` (-1: a fixed dof,
        or a node that is not a candidate; its displacement is taken as zero)."""
        sel = self.col_of[np.asarray(nodes, dtype=np.int64)]
        ok = sel >= 0
        local = np.full(sel.shape, -1, dtype=np.int64)
        local[ok] = np.arange(int(ok.sum()))
        return sel[ok], local


def candidate_nodes(case: Case) -> np.ndarray:
    """Flat ids of the nodes of every cell that holds a skin vertex off the chest wall."""
    from ..grid.embedding import Embedding

    verts = case.anatomy.vertices[~np.asarray(case.anatomy.fixed_vertices, dtype=bool)]
    emb = Embedding.build(case.grid, verts, require_active=False, where="skin surface")
    return np.unique(emb.nodes.ravel())


def greens_rows(model: FEModel, cols: np.ndarray, dtype: type,
                cache: Path | None = None) -> np.ndarray:
    """``Z^T = (K^-1 E)^T`` (m, n_eq) for unit loads on equations ``cols`` (K symmetric):
    read from ``cache`` (a folder) where it holds them (:func:`cache_file`), else computed
    and written there (where it can be: a folder that cannot be written only costs the
    computation next time)."""
    from ..fem.solver import tangent_matrix

    k = tangent_matrix(model, np.zeros((model.n_nodes, 3))).tocsr()
    k.sort_indices()
    path = None if cache is None else cache_file(cache, k, cols, dtype)
    kept = None if path is None else read_kept(path, (len(cols), model.n_eq), dtype)
    if kept is not None:
        return kept
    out = solved_rows(k, cols, dtype)
    if path is not None:
        keep(path, out)
    return out


def cache_file(cache: Path, k, cols: np.ndarray, dtype: type) -> Path:
    """``cache/contact_compliance-<sha256>.npz``: the hash of ``k`` (CSR, sorted indices),
    the candidate equations ``cols`` and the storage ``dtype``."""
    import hashlib

    from ..layout import COMPLIANCE_CACHE

    h = hashlib.sha256()
    for a in (k.indptr, k.indices, k.data, np.asarray(cols, np.int64)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.dtype(dtype).str.encode())
    return Path(cache) / f"{COMPLIANCE_CACHE}-{h.hexdigest()}.npz"


def read_kept(path: Path, shape: tuple[int, int], dtype: type) -> np.ndarray | None:
    """The array kept at ``path`` when it is there, whole (the zip's CRC-32 of its bytes) and
    of ``shape`` and ``dtype``; else None (computed again and written over)."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as kept:
            out = kept["zt"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    return out if out.shape == shape and out.dtype == np.dtype(dtype) else None


def keep(path: Path, rows: np.ndarray) -> None:
    """Write ``rows`` to ``path`` atomically (an uncompressed zip: a CRC-32 of the bytes),
    first deleting what a write of it killed midway left, then the folder's other kept
    compliances (of a model the case no longer has: a folder keeps the one of its model); a
    folder that cannot be written is passed by. (A write of the same file by another process
    at the same moment may then fail: passed by too, the other's lands.)"""
    from ..errors import WriteError
    from ..fileio import remove_partial_writes, write_atomic

    if path.parent.is_dir():
        remove_partial_writes(path.parent, [path.name])
    try:
        write_atomic(path, lambda fh: np.savez(fh, zt=rows))
    except WriteError:
        return
    remove_other_compliances(path)


def remove_other_compliances(path: Path) -> list[Path]:
    """Delete the kept compliances beside ``path`` other than it (``contact_compliance-*.npz``
    of other hashes); a file that cannot be deleted stays. Returns the deleted paths."""
    from ..layout import COMPLIANCE_CACHE

    removed = []
    for other in path.parent.glob(f"{COMPLIANCE_CACHE}-*.npz"):
        if other.name != path.name:
            try:
                other.unlink()
            except OSError:
                continue
            removed.append(other)
    return removed


def solved_rows(k, cols: np.ndarray, dtype: type) -> np.ndarray:
    """``Z^T`` (m, n_eq) of the stiffness ``k`` (CSR) for unit loads on equations ``cols``:
    one factorisation and blocks of many right-hand sides (MKL Pardiso through pypardiso when
    installed: one call solves a whole block; else SciPy's SuperLU)."""
    n_eq = k.shape[0]
    solve = _factorised(k)
    out = np.empty((len(cols), n_eq), dtype=dtype)
    block = 1024
    for start in range(0, len(cols), block):  # blocks of right-hand sides (memory)
        c = cols[start:start + block]
        rhs = np.zeros((n_eq, len(c)))
        rhs[c, np.arange(len(c))] = 1.0
        out[start:start + len(c)] = np.asarray(solve(rhs)).reshape(n_eq, len(c)).T
    return out


def _factorised(k):
    """A function solving ``k x = b`` for a block ``b`` (n, m), factorised once."""
    from ..fem.linsolve import available_backends, pypardiso_solver

    if "pardiso" in available_backends():
        import scipy.sparse as sp

        upper = sp.triu(k, format="csr")
        upper.sort_indices()
        solver = pypardiso_solver(mtype=2)  # SPD: K(u = 0) is positive definite
        solver.factorize(upper)
        solver.iparm[7] = 0  # no iterative refinement: 3x faster, same result to 1e-15

        def solve(b: np.ndarray) -> np.ndarray:
            return solver.solve(upper, np.asfortranarray(b))

        return solve
    import scipy.sparse.linalg as spla

    lu = spla.splu(k.tocsc())
    return lu.solve
