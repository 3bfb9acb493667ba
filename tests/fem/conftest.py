"""Shared meshes and closed-form stresses for the finite-element tests."""

from __future__ import annotations

import numpy as np
import pytest

from tests.fem.mesh import box_mesh

E_MPA = 5e-3
NU = 0.45


def lame(e_mpa: float = E_MPA, nu: float = NU) -> tuple[float, float]:
    return e_mpa / (2 * (1 + nu)), e_mpa * nu / ((1 + nu) * (1 - 2 * nu))


def pk1_exact(material: str, f: np.ndarray, e_mpa: float = E_MPA, nu: float = NU) -> np.ndarray:
    """First Piola-Kirchhoff stress (3, 3) MPa of a homogeneous deformation gradient."""
    mu, lam = lame(e_mpa, nu)
    if material == "svk":
        e = 0.5 * (f.T @ f - np.eye(3))
        return f @ (lam * np.trace(e) * np.eye(3) + 2 * mu * e)
    f_inv_t = np.linalg.inv(f).T
    j = np.linalg.det(f)
    if material.startswith("neo-hookean-split-sri"):  # mu/2 (J^-2/3 I1 - 3) + K/2 (ln J)^2
        i1 = float(np.sum(f * f))
        return (mu * j ** (-2 / 3) * (f - i1 / 3 * f_inv_t)
                + (lam + 2 * mu / 3) * np.log(j) * f_inv_t)
    return mu * (f - f_inv_t) + lam * np.log(j) * f_inv_t


def distorted_box(cells=(2, 2, 2), size=20.0):
    """A box whose interior nodes are moved off the regular grid (a patch-test mesh)."""
    nodes, hexes = box_mesh(cells, (size, size, size))
    rng = np.random.default_rng(3)
    interior = np.all((nodes > 1e-9) & (nodes < size - 1e-9), axis=1)
    h = size / max(cells)
    nodes[interior] += rng.uniform(-0.2, 0.2, (int(interior.sum()), 3)) * h
    return nodes, hexes


@pytest.fixture(params=["neo-hookean", "neo-hookean-sri", "neo-hookean-split-sri",
                        "neo-hookean-split-sri-inner", "svk"])
def material(request) -> str:
    return request.param
