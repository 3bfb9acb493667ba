"""Numba element kernels of the P2 reference (:mod:`biopsynav.evaluate.p2`): 10-node
tetrahedra, compressible neo-Hookean in the spatial form, one element per thread.

Written for the reference alone, in its own formulation (nothing shared with the hexahedral
kernels of :mod:`biopsynav.fem.kernels`, which work in the reference configuration). At each
quadrature point of an element, from the reference shape-function gradients ``G`` (10, 3)
1/mm and the element's nodal displacements ``u`` (10, 3) mm:

* ``F = I + u^T G``, ``J = det F``, ``b = F F^T``; spatial gradients ``g = G F^-1``;
* energy density ``W = mu/2 (tr b - 3) - mu ln J + lam/2 (ln J)^2`` (MPa = N/mm^2);
* Kirchhoff stress ``tau = mu (b - I) + lam ln J I``; nodal forces ``f_a = w tau g_a`` (N);
* tangent ``K_(ai)(bk) = w [(g_a . tau g_b) d_ik + lam g_ai g_bk + m (d_ik g_a . g_b
  + g_ak g_bi)]`` with ``m = mu - lam ln J`` (N/mm),

``w`` the quadrature weight times the element's volume (mm^3). An element with ``J <= 0`` at
one of its points is reported, not evaluated (the caller raises FloatingPointError).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _det_and_inverse(f: np.ndarray, inv: np.ndarray) -> float:
    """det ``f`` (3, 3); ``inv`` (3, 3) filled with ``f^-1`` when the determinant is > 0."""
    c00 = f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1]
    c01 = f[1, 2] * f[2, 0] - f[1, 0] * f[2, 2]
    c02 = f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]
    det = f[0, 0] * c00 + f[0, 1] * c01 + f[0, 2] * c02
    if det <= 0.0:
        return det
    s = 1.0 / det
    inv[0, 0], inv[1, 0], inv[2, 0] = c00 * s, c01 * s, c02 * s
    inv[0, 1] = (f[0, 2] * f[2, 1] - f[0, 1] * f[2, 2]) * s
    inv[1, 1] = (f[0, 0] * f[2, 2] - f[0, 2] * f[2, 0]) * s
    inv[2, 1] = (f[0, 1] * f[2, 0] - f[0, 0] * f[2, 1]) * s
    inv[0, 2] = (f[0, 1] * f[1, 2] - f[0, 2] * f[1, 1]) * s
    inv[1, 2] = (f[0, 2] * f[1, 0] - f[0, 0] * f[1, 2]) * s
    inv[2, 2] = (f[0, 0] * f[1, 1] - f[0, 1] * f[1, 0]) * s
    return det


@njit(cache=True, inline="always")
def _deformation(ue: np.ndarray, g0: np.ndarray, f: np.ndarray) -> None:
    """``f`` (3, 3) = I + sum_a ue[a] (x) g0[a] for ``ue``, ``g0`` (10, 3)."""
    for i in range(3):
        for j in range(3):
            s = 1.0 if i == j else 0.0
            for a in range(10):
                s += ue[a, i] * g0[a, j]
            f[i, j] = s


@njit(cache=True, inline="always")
def _point_energy(f: np.ndarray, log_j: float, mu: float, lam: float) -> float:
    """Energy density (MPa) at a point of deformation gradient ``f`` and ln J ``log_j``."""
    i1 = 0.0
    for i in range(3):
        for j in range(3):
            i1 += f[i, j] * f[i, j]
    return 0.5 * mu * (i1 - 3.0) - mu * log_j + 0.5 * lam * log_j * log_j


@njit(cache=True, inline="always")
def _stress(f: np.ndarray, log_j: float, mu: float, lam: float, tau: np.ndarray) -> None:
    """``tau`` (3, 3) = mu (F F^T - I) + lam ln J I, MPa."""
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += f[i, k] * f[j, k]
            tau[i, j] = mu * s
        tau[i, i] += lam * log_j - mu


@njit(cache=True, inline="always")
def _add_tangent(k: np.ndarray, g: np.ndarray, tau: np.ndarray, w: float, m: float,
                 lam: float, tg: np.ndarray) -> None:
    """Add one point's tangent (30, 30) N/mm to ``k`` from spatial gradients ``g`` (10, 3),
    stress ``tau``, weight ``w``, ``m = mu - lam ln J``; ``tg`` (10, 3) scratch."""
    for a in range(10):
        for i in range(3):
            tg[a, i] = tau[i, 0] * g[a, 0] + tau[i, 1] * g[a, 1] + tau[i, 2] * g[a, 2]
    for a in range(10):
        for b in range(10):
            gg = g[a, 0] * g[b, 0] + g[a, 1] * g[b, 1] + g[a, 2] * g[b, 2]
            diag = w * (g[a, 0] * tg[b, 0] + g[a, 1] * tg[b, 1] + g[a, 2] * tg[b, 2] + m * gg)
            for i in range(3):
                row = 3 * a + i
                k[row, 3 * b + i] += diag
                for c in range(3):
                    k[row, 3 * b + c] += w * (lam * g[a, i] * g[b, c] + m * g[a, c] * g[b, i])


@njit(cache=True)
def _element(ue: np.ndarray, g0: np.ndarray, w: np.ndarray, mu: float, lam: float,
             f_out: np.ndarray, k_out: np.ndarray, tangent: bool) -> tuple[float, bool]:
    """One element: energy (N mm) and whether it is valid (J > 0 at every point); forces
    (10, 3) into ``f_out`` and, with ``tangent``, the (30, 30) tangent into ``k_out``."""
    f, inv, tau = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    g, tg = np.empty((10, 3)), np.empty((10, 3))
    energy = 0.0
    for q in range(g0.shape[0]):
        _deformation(ue, g0[q], f)
        det = _det_and_inverse(f, inv)
        if det <= 0.0:
            return 0.0, False
        log_j = np.log(det)
        energy += w[q] * _point_energy(f, log_j, mu, lam)
        for a in range(10):
            for i in range(3):
                g[a, i] = (g0[q, a, 0] * inv[0, i] + g0[q, a, 1] * inv[1, i]
                           + g0[q, a, 2] * inv[2, i])
        _stress(f, log_j, mu, lam, tau)
        for a in range(10):
            for i in range(3):
                f_out[a, i] += w[q] * (tau[i, 0] * g[a, 0] + tau[i, 1] * g[a, 1]
                                       + tau[i, 2] * g[a, 2])
        if tangent:
            _add_tangent(k_out, g, tau, w[q], mu - lam * log_j, lam, tg)
    return energy, True


@njit(cache=True, parallel=True)
def element_terms(ue: np.ndarray, grads: np.ndarray, weights: np.ndarray, mu: float,
                  lam: float, tangent: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray]:
    """Per element: forces (t, 10, 3) N, tangents (t, 30, 30) N/mm (zero-size without
    ``tangent``), energies (t,) N mm and validity (t,) bool, from nodal displacements ``ue``
    (t, 10, 3) mm, reference gradients ``grads`` (t, q, 10, 3) 1/mm and weights ``weights``
    (t, q) mm^3 (quadrature weight x volume)."""
    n = ue.shape[0]
    forces = np.zeros((n, 10, 3))
    tangents = np.zeros((n if tangent else 0, 30, 30))
    energies = np.zeros(n)
    valid = np.ones(n, dtype=np.bool_)
    scratch = np.zeros((30, 30))
    for e in prange(n):
        k_out = tangents[e] if tangent else scratch
        energies[e], valid[e] = _element(ue[e], grads[e], weights[e], mu, lam, forces[e],
                                         k_out, tangent)
    return forces, tangents, energies, valid


@njit(cache=True)
def scatter_add(slot: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """``out`` (size,) with ``out[slot[i]] += values[i]`` (a bincount without its copies)."""
    out = np.zeros(size)
    for i in range(slot.shape[0]):
        out[slot[i]] += values[i]
    return out


def compile_p2_kernels() -> None:
    """Compile these kernels, or load them from numba's on-disk cache, on one undeformed
    element (as :func:`biopsynav.fem.compile_kernels` does for the FE's)."""
    grads = np.zeros((1, 1, 10, 3))
    for tangent in (False, True):
        element_terms(np.zeros((1, 10, 3)), grads, np.ones((1, 1)), 1.0, 1.0, tangent)
    scatter_add(np.zeros(1, dtype=np.int64), np.zeros(1), 1)
