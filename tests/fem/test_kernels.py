"""Element-level checks: patch test, tangent against finite differences, immersed weights."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from biopsynav.fem import FEModel, internal_forces, tangent_matrix
from tests.fem.mesh import box_mesh

from .conftest import E_MPA, NU, distorted_box, pk1_exact

F_AFFINE = np.array([[1.12, 0.05, 0.02], [0.03, 0.93, 0.04], [-0.02, 0.06, 1.07]])


def _node_gradient_integrals(model: FEModel) -> np.ndarray:
    """b_a = integral of grad N_a over the mesh (n_nodes, 3), from the model's quadrature."""
    per_el = np.einsum("eg,egaj->eaj", model.jw[model.elem_set] * model.weight[:, None],
                       model.grads[model.elem_set])
    b = np.zeros((model.n_nodes, 3))
    np.add.at(b, model.hexes, per_el)
    return b


def test_patch_affine_field_gives_exact_homogeneous_stress(material):
    nodes, hexes = distorted_box()
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, np.zeros(len(nodes), bool), material)
    u = nodes @ (F_AFFINE - np.eye(3)).T
    forces = internal_forces(model, u)
    expected = _node_gradient_integrals(model) @ pk1_exact(material, F_AFFINE).T
    scale = np.abs(expected).max()
    assert np.abs(forces - expected).max() < 1e-10 * scale
    interior = np.all((nodes > 1e-9) & (nodes < 20 - 1e-9), axis=1)
    assert np.abs(forces[interior]).max() < 1e-10 * scale


def test_reference_geometry_integrates_volume():
    nodes, hexes = distorted_box()
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, np.zeros(len(nodes), bool))
    volume = float((model.jw[model.elem_set]).sum())
    assert abs(volume - 20.0**3) < 1e-9 * 20.0**3
    assert model.grads.shape[0] == len(hexes)  # distorted: one gradient set per element
    regular = FEModel(*box_mesh((3, 2, 2), (30, 20, 20)), 1.0, E_MPA, NU,
                      np.zeros(36, bool))
    assert regular.grads.shape[0] == 1  # identical cubes share one set


def _finite_difference_tangent(model: FEModel, u: np.ndarray, h: float = 1e-6) -> np.ndarray:
    free = np.flatnonzero(model.eq_of_dof.ravel() >= 0)
    columns = []
    for dof in free:
        up, down = u.copy().ravel(), u.copy().ravel()
        up[dof] += h
        down[dof] -= h
        diff = (internal_forces(model, up.reshape(-1, 3))
                - internal_forces(model, down.reshape(-1, 3))) / (2 * h)
        columns.append(diff.ravel()[free])
    return np.array(columns).T


def test_tangent_matches_finite_differences_in_a_distorted_state(material):
    nodes, hexes = distorted_box()
    fixed = nodes[:, 2] < 1e-9
    rng = np.random.default_rng(7)
    model = FEModel(nodes, hexes, rng.uniform(0.3, 1.0, len(hexes)),
                    rng.uniform(3e-3, 8e-3, len(hexes)), NU, fixed, material)
    u = rng.uniform(-1.0, 1.0, nodes.shape) + nodes @ (F_AFFINE - np.eye(3)).T
    u[fixed] = 0.0
    k = tangent_matrix(model, u).toarray()
    k_fd = _finite_difference_tangent(model, u)
    assert np.linalg.norm(k - k_fd) < 1e-6 * np.linalg.norm(k)
    assert np.allclose(k, k.T, atol=1e-14 * np.abs(k).max())


def test_half_filled_element_contributes_half_stiffness():
    nodes, hexes = box_mesh((2, 1, 1), (20, 10, 10))
    fixed = nodes[:, 0] < 1e-9
    full = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed)
    weights = np.array([1.0, 0.5])
    half = FEModel(nodes, hexes, weights, E_MPA, NU, fixed)
    only_second = FEModel(nodes, hexes[1:], 1.0, E_MPA, NU, np.zeros(len(nodes), bool))
    u = np.zeros_like(nodes)
    k_full, k_half = tangent_matrix(full, u).toarray(), tangent_matrix(half, u).toarray()
    k_el = tangent_matrix(only_second, u).toarray()
    free = np.flatnonzero(full.eq_of_dof.ravel() >= 0)
    k_el_free = k_el[np.ix_(only_second.eq_of_dof.ravel()[free],
                            only_second.eq_of_dof.ravel()[free])]
    assert np.allclose(k_full - k_half, 0.5 * k_el_free, atol=1e-14)
    uniform = FEModel(nodes, hexes, 0.5, E_MPA, NU, fixed)
    assert np.allclose(tangent_matrix(uniform, u).toarray(), 0.5 * k_full, atol=1e-15)


def test_largest_edge_stretch_of_a_stretched_and_a_resting_box():
    from biopsynav.fem import largest_edge_stretch

    nodes, hexes = distorted_box()
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, np.zeros(len(nodes), bool))
    assert largest_edge_stretch(model, np.zeros_like(nodes)) == 1.0
    stretched = nodes @ (np.diag([2.5, 1.0, 0.8]) - np.eye(3)).T  # every x extent 2.5 times
    assert abs(largest_edge_stretch(model, stretched) - 2.5) < 1e-12
    none = np.zeros(len(hexes), dtype=bool)
    assert largest_edge_stretch(model, stretched, none) == 1.0  # no element selected
    assert largest_edge_stretch(model, stretched, ~none) == largest_edge_stretch(model, stretched)


def test_inner_law_is_split_sri_in_whole_cells_and_neo_hookean_in_cut_cells():
    nodes, hexes = box_mesh((1, 1, 1), (10, 10, 10))
    u = nodes @ (F_AFFINE - np.eye(3)).T + np.random.default_rng(1).uniform(-1, 1, nodes.shape)

    def forces(law: str, weight: float) -> np.ndarray:
        model = FEModel(nodes, hexes, weight, E_MPA, NU, np.zeros(len(nodes), bool), law)
        return internal_forces(model, u)

    inner_whole, inner_cut = forces("neo-hookean-split-sri-inner", 1.0), forces(
        "neo-hookean-split-sri-inner", 0.5)
    assert np.array_equal(inner_whole, forces("neo-hookean-split-sri", 1.0))
    assert np.array_equal(inner_cut, forces("neo-hookean", 0.5))
    assert not np.allclose(inner_whole, forces("neo-hookean", 1.0))


COMPILE_THEN_SOLVE = """
import sys
import numpy as np
from biopsynav.case import as_case
from biopsynav.fem import FEModel, Loads, compile_kernels, kernels, solve

compile_kernels()
jitted = (kernels.element_kernel, kernels.scatter_matrix, kernels.scatter_vector)
compiled = [list(f.signatures) for f in jitted]
assert all(len(s) == 1 for s in compiled), compiled
model = FEModel.from_case(as_case(sys.argv[1]))
used = np.unique(model.hexes)
top = used[model.nodes[used, 2] >= model.nodes[used, 2].max() - 1e-9]
forces = np.zeros((model.n_nodes, 3))
forces[top, 2] = -0.05 / len(top)  # N, down on the highest nodes of the breast
u, _ = solve(model, Loads(forces=forces))
assert np.abs(u).max() > 0
added = [sorted(set(map(str, f.signatures)) - set(map(str, s))) for f, s in zip(jitted, compiled)]
assert not any(added), f"specialisations that compile_kernels did not compile: {added}"
"""


def test_compile_kernels_compiles_what_a_case_model_runs(phantom_case):
    """`compile_kernels` (run before the test workers start, so that they load numba's cache)
    must compile the argument types that a case's model solves with: otherwise each process
    would still compile its own specialisation. In a new process, where nothing else has
    called the kernels first."""
    proc = subprocess.run([sys.executable, "-c", COMPILE_THEN_SOLVE, str(phantom_case.dir)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
