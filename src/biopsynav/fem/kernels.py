"""Numba element kernels: 8-node trilinear hexahedra, 2x2x2 Gauss, total-Lagrangian hyperelasticity.

Notation: ``X`` reference position, ``u`` displacement, ``F = I + grad_X u``, ``C = F^T F``,
``E = (C - I) / 2``, ``J = det F``; ``S`` second Piola-Kirchhoff stress (MPa), ``P = F S``.
Voigt order (11, 22, 33, 12, 23, 13), engineering shear strains.

Materials (``mu``, ``lam``: Lame constants, MPa):

* ``SVK`` (0): ``W = lam/2 (tr E)^2 + mu E:E``, ``S = lam tr(E) I + 2 mu E``.
* ``NEO_HOOKEAN`` (1): ``W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``,
  ``S = mu (I - C^-1) + lam ln(J) C^-1``,
  ``CC = lam C^-1 (x) C^-1 + 2 (mu - lam ln J) I_{C^-1}``.
* ``ISOCHORIC`` (an integration-point law of ``NEO_HOOKEAN_SPLIT_SRI``, not a material):
  ``W = mu/2 (J^-2/3 I1 - 3)``, ``S = mu J^-2/3 (I - I1/3 C^-1)``,
  ``CC = 2 mu J^-2/3 / 3 (I1 I_{C^-1} + I1/3 C^-1 (x) C^-1 - I (x) C^-1 - C^-1 (x) I)``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..grid.index import HEX_CORNERS
from ..materials import (
    KERNEL_NEO_HOOKEAN,
    KERNEL_NEO_HOOKEAN_SPLIT_SRI,
    KERNEL_NEO_HOOKEAN_SPLIT_SRI_INNER,
    KERNEL_NEO_HOOKEAN_SRI,
    KERNEL_SVK,
)

SVK = KERNEL_SVK  # the branch ids of biopsynav.materials
NEO_HOOKEAN = KERNEL_NEO_HOOKEAN
NEO_HOOKEAN_SRI = KERNEL_NEO_HOOKEAN_SRI
NEO_HOOKEAN_SPLIT_SRI = KERNEL_NEO_HOOKEAN_SPLIT_SRI
NEO_HOOKEAN_SPLIT_SRI_INNER = KERNEL_NEO_HOOKEAN_SPLIT_SRI_INNER
#: Tissue fraction from which a cell counts as wholly inside the tissue (the inner law).
WHOLE_CELL = 0.999
ISOCHORIC = -1  # the isochoric neo-Hookean point law of NEO_HOOKEAN_SPLIT_SRI

GAUSS_POINTS = (2.0 * HEX_CORNERS - 1.0) / np.sqrt(3.0)  # (8, 3) natural coordinates
NATURAL_CORNERS = 2.0 * HEX_CORNERS - 1.0  # (8, 3) corners of the reference cube [-1, 1]^3
VOIGT_PAIRS = np.array([[0, 0], [1, 1], [2, 2], [0, 1], [1, 2], [0, 2]], dtype=np.int64)


def shape_gradients_natural() -> np.ndarray:
    """dN_a/dxi_k at the 8 Gauss points: (8 gauss, 8 nodes, 3)."""
    xi = GAUSS_POINTS[:, None, :]  # (g, 1, 3)
    xa = NATURAL_CORNERS[None, :, :]  # (1, a, 3)
    lin = 1.0 + xa * xi  # (g, a, 3)
    grads = np.empty((8, 8, 3))
    for k in range(3):
        others = [m for m in range(3) if m != k]
        grads[:, :, k] = 0.125 * xa[:, :, k] * lin[:, :, others[0]] * lin[:, :, others[1]]
    return grads


def element_gradients(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference shape gradients of hexahedra with corner positions ``corners`` (n, 8, 3) mm.

    Returns ``grads`` (n, 8 gauss, 8 nodes, 3) in 1/mm and ``jw`` (n, 8) = det(J) * Gauss
    weight in mm^3 (Gauss weights are 1 for the 2x2x2 rule).
    """
    dn_dxi = shape_gradients_natural()  # (g, a, k)
    jac = np.einsum("nai,gak->ngik", corners, dn_dxi)  # dX_i/dxi_k
    det = np.linalg.det(jac)
    inv = np.linalg.inv(jac)  # (n, g, k, i): dxi_k/dX_i
    grads = np.einsum("gak,ngki->ngai", dn_dxi, inv)
    return grads, det


@njit(cache=True, inline="always")
def _stress_svk(f, mu, lam, s, d):
    """SVK: fill S (3, 3) and Voigt tangent d (6, 6) for deformation gradient f."""
    e = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            c = 0.0
            for k in range(3):
                c += f[k, i] * f[k, j]
            e[i, j] = 0.5 * (c - (1.0 if i == j else 0.0))
    tr = e[0, 0] + e[1, 1] + e[2, 2]
    for i in range(3):
        for j in range(3):
            s[i, j] = 2.0 * mu * e[i, j] + (lam * tr if i == j else 0.0)
    d[:, :] = 0.0
    for p in range(3):
        for q in range(3):
            d[p, q] = lam
        d[p, p] += 2.0 * mu
        d[p + 3, p + 3] = mu


@njit(cache=True, inline="always")
def _right_cauchy_green_inverse(f, det_f):
    """C = F^T F (3, 3) and its inverse (3, 3)."""
    c = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += f[k, i] * f[k, j]
            c[i, j] = acc
    ci = np.empty((3, 3))
    det_c = det_f * det_f
    ci[0, 0] = (c[1, 1] * c[2, 2] - c[1, 2] * c[2, 1]) / det_c
    ci[0, 1] = (c[0, 2] * c[2, 1] - c[0, 1] * c[2, 2]) / det_c
    ci[0, 2] = (c[0, 1] * c[1, 2] - c[0, 2] * c[1, 1]) / det_c
    ci[1, 1] = (c[0, 0] * c[2, 2] - c[0, 2] * c[2, 0]) / det_c
    ci[1, 2] = (c[0, 2] * c[1, 0] - c[0, 0] * c[1, 2]) / det_c
    ci[2, 2] = (c[0, 0] * c[1, 1] - c[0, 1] * c[1, 0]) / det_c
    ci[1, 0] = ci[0, 1]
    ci[2, 0] = ci[0, 2]
    ci[2, 1] = ci[1, 2]
    return c, ci


@njit(cache=True, inline="always")
def _stress_neo_hookean(f, det_f, mu, lam, s, d, pairs):
    """Compressible neo-Hookean: fill S (3, 3) and Voigt tangent d (6, 6)."""
    _, ci = _right_cauchy_green_inverse(f, det_f)
    log_j = np.log(det_f)
    for i in range(3):
        for j in range(3):
            s[i, j] = (mu if i == j else 0.0) + (lam * log_j - mu) * ci[i, j]
    g = mu - lam * log_j
    for p in range(6):
        i = pairs[p, 0]
        j = pairs[p, 1]
        for q in range(p, 6):
            k = pairs[q, 0]
            m = pairs[q, 1]
            v = lam * ci[i, j] * ci[k, m] + g * (ci[i, k] * ci[j, m] + ci[i, m] * ci[j, k])
            d[p, q] = v
            d[q, p] = v


@njit(cache=True, inline="always")
def _stress_isochoric(f, det_f, mu, s, d, pairs):
    """Isochoric neo-Hookean ``mu/2 (J^-2/3 I1 - 3)``: fill S (3, 3) and Voigt tangent d."""
    c, ci = _right_cauchy_green_inverse(f, det_f)
    i1 = c[0, 0] + c[1, 1] + c[2, 2]
    j23 = det_f ** (-2.0 / 3.0)
    for i in range(3):
        for j in range(3):
            s[i, j] = mu * j23 * ((1.0 if i == j else 0.0) - i1 / 3.0 * ci[i, j])
    a = 2.0 * mu * j23 / 3.0
    for p in range(6):
        i = pairs[p, 0]
        j = pairs[p, 1]
        dij = 1.0 if i == j else 0.0
        for q in range(p, 6):
            k = pairs[q, 0]
            m = pairs[q, 1]
            dkm = 1.0 if k == m else 0.0
            v = a * (0.5 * i1 * (ci[i, k] * ci[j, m] + ci[i, m] * ci[j, k])
                     + i1 / 3.0 * ci[i, j] * ci[k, m] - dij * ci[k, m] - ci[i, j] * dkm)
            d[p, q] = v
            d[q, p] = v


@njit(cache=True, inline="always")
def _strain_energy(f, det_f, mu, lam, material):
    """Strain energy density W (MPa = mJ/mm^3) at deformation gradient f."""
    if material == SVK:
        tr = 0.0
        ee = 0.0
        for i in range(3):
            for j in range(3):
                c = 0.0
                for k in range(3):
                    c += f[k, i] * f[k, j]
                e = 0.5 * (c - (1.0 if i == j else 0.0))
                ee += e * e
                if i == j:
                    tr += e
        return 0.5 * lam * tr * tr + mu * ee
    i1 = 0.0
    for i in range(3):
        for j in range(3):
            i1 += f[i, j] * f[i, j]
    if material == ISOCHORIC:
        return 0.5 * mu * (det_f ** (-2.0 / 3.0) * i1 - 3.0)
    log_j = np.log(det_f)
    return 0.5 * mu * (i1 - 3.0) - mu * log_j + 0.5 * lam * log_j * log_j


@njit(cache=True, inline="always")
def _add_point(ue, dn, w, mu, lam, material, want_tangent, f_el, k_el, f, s, d, b, db, gsn,
               sv, pairs):
    """Add one integration point (shape gradients ``dn`` (8, 3), weight ``w`` mm^3) to the
    element force ``f_el`` (24,) and tangent ``k_el`` (24, 24, upper triangle); returns
    (energy mJ, det F). Nothing is added where det F <= 0."""
    for i in range(3):
        for j in range(3):
            acc = 1.0 if i == j else 0.0
            for a in range(8):
                acc += ue[a, i] * dn[a, j]
            f[i, j] = acc
    det_f = (f[0, 0] * (f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1])
             - f[0, 1] * (f[1, 0] * f[2, 2] - f[1, 2] * f[2, 0])
             + f[0, 2] * (f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]))
    if det_f <= 0.0:
        return 0.0, det_f
    if material == SVK:
        _stress_svk(f, mu, lam, s, d)
    elif material == ISOCHORIC:
        _stress_isochoric(f, det_f, mu, s, d, pairs)
    else:
        _stress_neo_hookean(f, det_f, mu, lam, s, d, pairs)
    energy = w * _strain_energy(f, det_f, mu, lam, material)
    for a in range(8):
        for i in range(3):
            col = 3 * a + i
            b[0, col] = f[i, 0] * dn[a, 0]
            b[1, col] = f[i, 1] * dn[a, 1]
            b[2, col] = f[i, 2] * dn[a, 2]
            b[3, col] = f[i, 0] * dn[a, 1] + f[i, 1] * dn[a, 0]
            b[4, col] = f[i, 1] * dn[a, 2] + f[i, 2] * dn[a, 1]
            b[5, col] = f[i, 0] * dn[a, 2] + f[i, 2] * dn[a, 0]
    sv[0] = s[0, 0]
    sv[1] = s[1, 1]
    sv[2] = s[2, 2]
    sv[3] = s[0, 1]
    sv[4] = s[1, 2]
    sv[5] = s[0, 2]
    for col in range(24):
        acc = 0.0
        for p in range(6):
            acc += b[p, col] * sv[p]
        f_el[col] += w * acc
    if not want_tangent:
        return energy, det_f
    for p in range(6):
        for col in range(24):
            acc = 0.0
            for q in range(6):
                acc += d[p, q] * b[q, col]
            db[p, col] = w * acc
    for r in range(24):
        for col in range(r, 24):
            acc = 0.0
            for p in range(6):
                acc += b[p, r] * db[p, col]
            k_el[r, col] += acc
    for a in range(8):
        for j in range(3):
            acc = 0.0
            for i in range(3):
                acc += s[j, i] * dn[a, i]
            gsn[a, j] = w * acc
    for a in range(8):
        for bb in range(a, 8):
            geo = dn[a, 0] * gsn[bb, 0] + dn[a, 1] * gsn[bb, 1] + dn[a, 2] * gsn[bb, 2]
            for i in range(3):
                k_el[3 * a + i, 3 * bb + i] += geo
    return energy, det_f


@njit(cache=True, parallel=True)
def element_kernel(u, hexes, elem_set, grads, jw, scale, mu, lam, material, want_tangent,
                   fe, ke, min_det, energy):
    """Per-element internal forces, tangents, energies and smallest det F.

    Args:
        u: (n_nodes, 3) displacement, mm.
        hexes: (n_el, 8) node ids, VTK order.
        elem_set: (n_el,) index into ``grads``/``jw`` (identical cubes share one set).
        grads: (n_sets, 8 gauss, 8 nodes, 3) dN/dX, 1/mm.  jw: (n_sets, 8) det J * weight, mm^3.
        scale: (n_el,) integration-weight factor (tissue volume fraction).
        mu, lam: (n_el,) Lame constants, MPa.  material: SVK, NEO_HOOKEAN or
            NEO_HOOKEAN_SRI (the neo-Hookean energy with its ``lam`` term integrated at one
            point with the cell's whole weight and the volume average of the shape gradients,
            ``(1/V) int grad N dV``: selective reduced integration, free of volumetric
            locking; the ``mu`` terms keep the 2x2x2 rule, so no hourglass modes) or
            NEO_HOOKEAN_SPLIT_SRI (the decoupled energy ``mu/2 (J^-2/3 I1 - 3)`` at the 2x2x2
            points plus ``K/2 (ln J)^2``, ``K = lam + 2 mu / 3``, at that one point: the
            same small-strain response, but a corner crushed at constant cell volume costs
            shear energy without bound) or NEO_HOOKEAN_SPLIT_SRI_INNER (that in the cells
            whose ``scale`` is at least WHOLE_CELL, NEO_HOOKEAN in the cut cells).
        want_tangent: fill ``ke`` too.
    Outputs (filled in place): fe (n_el, 24) N; ke (n_el, 24, 24) N/mm; min_det (n_el,);
    energy (n_el,) mJ (N mm). An element with det F <= 0 at an integration point gets an
    infinite energy; callers reject such states through ``min_det``.
    """
    n_el = hexes.shape[0]
    pairs = VOIGT_PAIRS
    for e in prange(n_el):
        ue = np.empty((8, 3))
        for a in range(8):
            for i in range(3):
                ue[a, i] = u[hexes[e, a], i]
        f_el = np.zeros(24)
        k_el = np.zeros((24, 24))
        f = np.empty((3, 3))
        s = np.empty((3, 3))
        d = np.empty((6, 6))
        b = np.empty((6, 24))
        db = np.empty((6, 24))
        gsn = np.empty((8, 3))
        sv = np.empty(6)
        dn_c = np.zeros((8, 3))
        w_el = 0.0
        w_c = 0.0
        dmin = np.inf
        gset = elem_set[e]
        inner = material == NEO_HOOKEAN_SPLIT_SRI_INNER
        decoupled = material == NEO_HOOKEAN_SPLIT_SRI or (inner and scale[e] >= WHOLE_CELL)
        split = decoupled or material == NEO_HOOKEAN_SRI
        law = ISOCHORIC if decoupled else (NEO_HOOKEAN if split or inner else material)
        lam_g = 0.0 if split else lam[e]
        lam_c = lam[e] + 2.0 / 3.0 * mu[e] if decoupled else lam[e]
        # the 8 Gauss points, then (split laws) the volumetric point: a single call site, so
        # numba inlines (and compiles) the point kernel once rather than twice
        for g in range(9):
            if g < 8:
                dn = grads[gset, g]
                w = jw[gset, g] * scale[e]
                mu_p, lam_p, law_p = mu[e], lam_g, law
            elif split:
                for a in range(8):
                    for i in range(3):
                        dn_c[a, i] /= w_c
                dn = dn_c
                w = w_c
                mu_p, lam_p, law_p = 0.0, lam_c, NEO_HOOKEAN
            else:
                break
            en, det_f = _add_point(ue, dn, w, mu_p, lam_p, law_p, want_tangent,
                                   f_el, k_el, f, s, d, b, db, gsn, sv, pairs)
            w_el += en
            dmin = min(dmin, det_f)
            if split and g < 8:
                w_c += w
                for a in range(8):
                    for i in range(3):
                        dn_c[a, i] += w * grads[gset, g, a, i]
        for i in range(24):
            fe[e, i] = f_el[i]
        if want_tangent:
            for r in range(24):
                ke[e, r, r] = k_el[r, r]
                for col in range(r + 1, 24):
                    ke[e, r, col] = k_el[r, col]
                    ke[e, col, r] = k_el[r, col]
        min_det[e] = dmin
        energy[e] = w_el if dmin > 0.0 else np.inf


@njit(cache=True)
def scatter_matrix(ke, scatter, data):
    """data[scatter[e, i, j]] += ke[e, i, j] for scatter >= 0 (data zeroed first)."""
    data[:] = 0.0
    n_el = ke.shape[0]
    for e in range(n_el):
        for i in range(24):
            for j in range(24):
                pos = scatter[e, i, j]
                if pos >= 0:
                    data[pos] += ke[e, i, j]


@njit(cache=True)
def scatter_vector(fe, elem_eq, out):
    """out[elem_eq[e, i]] += fe[e, i] for elem_eq >= 0 (out zeroed first)."""
    out[:] = 0.0
    n_el = fe.shape[0]
    for e in range(n_el):
        for i in range(24):
            q = elem_eq[e, i]
            if q >= 0:
                out[q] += fe[e, i]

