"""An independent reference: the same problem written with scikit-fem's own forms and assembly.

Used by the tests (cross-check) and ``benchmarks/fem_solve.py`` (speed comparison); needs
scikit-fem (the ``dev`` extra). Weak forms are written with :mod:`skfem.helpers` from the
continuum expressions (no code shared with :mod:`biopsynav.fem.kernels`); the Newton loop is
plain: SciPy's default sparse solver (``scipy.sparse.linalg.spsolve``), uniform load
increments (more of them when an increment fails), the same convergence test as
:func:`biopsynav.fem.solve` (|R| <= tol |R0| and |du| <= tol |u|).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from biopsynav.errors import SolverError
from biopsynav.materials import lame_constants


def _stress_and_increment(material: str, f, mu, lam):
    """S (second Piola-Kirchhoff) and dS(dE) for deformation gradient field ``f``."""
    from skfem.helpers import ddot, det, eye, inv, mul, trace, transpose

    ident = eye(np.ones_like(f[0, 0]), 3)
    c = mul(transpose(f), f)
    if material == "svk":
        e = 0.5 * (c - ident)
        s = lam * trace(e) * ident + 2.0 * mu * e
        return s, lambda de: lam * trace(de) * ident + 2.0 * mu * de
    ci = inv(c)
    log_j = np.log(det(f))
    s = mu * (ident - ci) + lam * log_j * ci
    return s, lambda de: (lam * ddot(ci, de) * ci
                          + 2.0 * (mu - lam * log_j) * mul(ci, mul(de, ci)))


class SkfemModel:
    """The hexahedral model in scikit-fem: mesh of the used nodes, vector trilinear basis with
    the 2x2x2 Gauss rule, per-element Lame constants and immersed weights."""

    def __init__(self, nodes: np.ndarray, hexes: np.ndarray, weight: np.ndarray,
                 E_mpa: np.ndarray, nu: np.ndarray, fixed: np.ndarray, material: str) -> None:
        import meshio
        import skfem
        from skfem.io.meshio import from_meshio

        used = np.unique(hexes)
        local = np.full(len(nodes), -1)
        local[used] = np.arange(len(used))
        self.used = used
        mesh = from_meshio(meshio.Mesh(nodes[used], [("hexahedron", local[hexes])]))
        if not np.array_equal(np.sort(mesh.t.T, axis=1), np.sort(local[hexes], axis=1)):
            raise RuntimeError("scikit-fem reordered the elements")
        self.basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementHex1()), intorder=3)
        nqp = self.basis.X.shape[1]
        mu, lam = lame_constants(np.broadcast_to(E_mpa, len(hexes)),
                                 np.broadcast_to(nu, len(hexes)))
        per_qp = np.ones((1, nqp))
        self.params = {"mu": mu[:, None] * per_qp, "lam": lam[:, None] * per_qp,
                       "frac": np.broadcast_to(weight, len(hexes))[:, None] * per_qp}
        self.material = material
        fixed = np.asarray(fixed, dtype=bool)
        fixed = np.repeat(fixed[:, None], 3, axis=1) if fixed.ndim == 1 else fixed
        self.fixed_dofs = np.sort(self.basis.nodal_dofs.T[fixed[used]])
        self._forms()

    def _forms(self) -> None:
        from skfem import BilinearForm, LinearForm
        from skfem.helpers import ddot, eye, grad, mul, transpose

        material = self.material

        def deformation(w):
            g = grad(w["u"])
            return eye(np.ones_like(g[0, 0]), 3) + g

        @LinearForm
        def internal_force(v, w):
            f = deformation(w)
            s, _ = _stress_and_increment(material, f, w["mu"], w["lam"])
            return ddot(mul(f, s), grad(v)) * w["frac"]

        @BilinearForm
        def tangent(du, v, w):
            f = deformation(w)
            s, ds = _stress_and_increment(material, f, w["mu"], w["lam"])
            dfm = grad(du)
            de = 0.5 * (mul(transpose(dfm), f) + mul(transpose(f), dfm))
            return ddot(mul(dfm, s) + mul(f, ds(de)), grad(v)) * w["frac"]

        self.internal_force, self.tangent = internal_force, tangent

    def nodal_to_dofs(self, field: np.ndarray) -> np.ndarray:
        """Node field (n_nodes, 3) of the full grid -> scikit-fem dof vector."""
        out = np.zeros(self.basis.N)
        out[self.basis.nodal_dofs.T.ravel()] = np.asarray(field)[self.used].ravel()
        return out

    def dofs_to_nodal(self, x: np.ndarray, n_nodes: int) -> np.ndarray:
        out = np.zeros((n_nodes, 3))
        out[self.used] = x[self.basis.nodal_dofs.T]
        return out

    def residual(self, x: np.ndarray, f_ext: np.ndarray) -> np.ndarray:
        u = self.basis.interpolate(x)
        return self.internal_force.assemble(self.basis, u=u, **self.params) - f_ext

    def stiffness(self, x: np.ndarray):
        u = self.basis.interpolate(x)
        return self.tangent.assemble(self.basis, u=u, **self.params)

    def solve(self, forces: np.ndarray, tol: float = 1e-8, increments: int = 1,
              max_iterations: int = 30, max_increments: int = 64) -> tuple[np.ndarray, dict]:
        """Newton with ``increments`` equal load steps (doubled on failure) -> (u, info)."""
        f_ext = self.nodal_to_dofs(forces)
        r0 = float(np.linalg.norm(np.delete(f_ext, self.fixed_dofs)))
        while increments <= max_increments:
            try:
                with np.errstate(invalid="raise", divide="raise", over="raise"):
                    x, iterations = self._solve_steps(f_ext, r0, tol, increments,
                                                      max_iterations)
                return x, {"iterations": iterations, "increments": increments}
            except (FloatingPointError, np.linalg.LinAlgError, RuntimeError):
                increments *= 2
        raise SolverError("scikit-fem Newton did not converge", "skfem_peer")

    def _solve_steps(self, f_ext, r0, tol, increments, max_iterations):
        x = np.zeros(self.basis.N)
        total = 0
        for step in range(1, increments + 1):
            load = f_ext * step / increments
            r = self.residual(x, load)
            for _ in range(max_iterations):
                dx = _condensed_solve(self.stiffness(x), -r, self.fixed_dofs)
                x += dx
                total += 1
                r = self.residual(x, load)
                r_norm = float(np.linalg.norm(np.delete(r, self.fixed_dofs)))
                if not np.isfinite(r_norm):
                    raise RuntimeError("diverged")
                if r_norm <= tol * r0 and np.linalg.norm(dx) <= tol * np.linalg.norm(x):
                    break
            else:
                raise RuntimeError("no convergence")
        return x, total


def _condensed_solve(k, rhs, fixed_dofs):
    """Solve K dx = rhs with dx = 0 on ``fixed_dofs`` (SciPy spsolve)."""
    from skfem import condense
    from skfem import solve as skfem_solve

    return skfem_solve(*condense(k, rhs, D=fixed_dofs), solver=spla.spsolve)
