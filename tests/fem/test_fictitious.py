"""The fictitious domain of the cut cells: linear stiffness for a cell's empty part."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.errors import InputError
from biopsynav.fem import FEModel, internal_forces, tangent_matrix
from tests.fem.mesh import box_mesh

from .conftest import E_MPA, NU, distorted_box
from .test_kernels import F_AFFINE, _finite_difference_tangent


def _models(weights: np.ndarray, share: float, material: str = "neo-hookean"):
    nodes, hexes = distorted_box()
    fixed = nodes[:, 2] < 1e-9
    args = (nodes, hexes, weights, E_MPA, NU, fixed, material)
    return FEModel(*args), FEModel(*args, fictitious=share)


def _deformed(model: FEModel, seed: int = 5) -> np.ndarray:
    u = np.random.default_rng(seed).uniform(-1.0, 1.0, model.nodes.shape)
    u += model.nodes @ (F_AFFINE - np.eye(3)).T
    u[model.fixed[:, 0]] = 0.0
    return u


def test_the_empty_part_adds_its_share_of_the_rest_stiffness_and_whole_cells_nothing():
    weights = np.linspace(0.1, 1.0, 8)
    plain, with_share = _models(weights, 0.2)
    u0 = np.zeros_like(plain.nodes)
    added = tangent_matrix(with_share, u0).toarray() - tangent_matrix(plain, u0).toarray()
    nodes, hexes = plain.nodes, plain.hexes
    expected = np.zeros_like(added)
    free = plain.eq_of_dof.ravel()
    for e in range(len(hexes)):  # each cell alone, full, its rest stiffness times 0.2 (1 - w)
        one = FEModel(nodes, hexes[e:e + 1], 1.0, E_MPA, NU, plain.fixed)
        k_e = tangent_matrix(one, u0).toarray()
        rows = one.eq_of_dof.ravel()
        keep = (rows >= 0) & (free >= 0)
        expected[np.ix_(free[keep], free[keep])] += (0.2 * (1.0 - weights[e])
                                                     * k_e[np.ix_(rows[keep], rows[keep])])
    assert np.abs(added - expected).max() < 1e-12 * np.abs(expected).max()
    whole, whole_share = _models(np.ones(8), 0.2)
    assert np.array_equal(tangent_matrix(whole, u0).toarray(),
                          tangent_matrix(whole_share, u0).toarray())


def test_the_fictitious_forces_are_linear_in_the_displacement(material):
    """The empty part's stiffness does not soften or stiffen with the deformation: the added
    forces at a large deformation are the added rest stiffness times it."""
    plain, with_share = _models(np.full(8, 0.3), 0.1, material)
    u = _deformed(plain)
    added = (internal_forces(with_share, u) - internal_forces(plain, u)).ravel()
    k_added = (tangent_matrix(with_share, 0 * u) - tangent_matrix(plain, 0 * u)).toarray()
    free = plain.eq_of_dof.ravel() >= 0
    assert np.abs(added[free] - k_added @ u.ravel()[free]).max() < 1e-10 * np.abs(added).max()


def test_the_tangent_with_a_fictitious_part_matches_finite_differences():
    rng = np.random.default_rng(11)
    _, model = _models(rng.uniform(0.05, 1.0, 8), 0.05, "neo-hookean-split-sri-inner")
    u = _deformed(model)
    k = tangent_matrix(model, u).toarray()
    assert np.linalg.norm(k - _finite_difference_tangent(model, u)) < 1e-6 * np.linalg.norm(k)


def test_the_solver_energy_has_the_fictitious_forces_as_gradient():
    from biopsynav.fem.loads import Loads, prepare_loads
    from biopsynav.fem.solver import _System

    _, model = _models(np.full(8, 0.2), 0.5)
    system = _System(model, prepare_loads(model, Loads()), 0.0)
    u = model.to_free(_deformed(model))
    d = np.random.default_rng(2).standard_normal(model.n_eq)
    h = 1e-6
    slope = (system.evaluate(u + h * d, 0.0, False)[3]
             - system.evaluate(u - h * d, 0.0, False)[3]) / (2 * h)
    assert slope == pytest.approx(float(system.evaluate(u, 0.0, False)[0] @ d), rel=1e-6)


def test_a_share_outside_zero_to_one_is_refused():
    nodes, hexes = box_mesh((1, 1, 1), (10, 10, 10))
    with pytest.raises(InputError, match="fictitious"):
        FEModel(nodes, hexes, 0.5, E_MPA, NU, nodes[:, 2] < 1e-9, fictitious=1.5)


def test_the_protocol_names_a_fictitious_stiffness_only_when_there_is_one():
    """Data sets made before the key (none then) keep their protocol; a share is recorded,
    so a data set of another share is refused rather than reused."""
    from biopsynav.config import config_from_dict
    from biopsynav.dataset.store import protocol_dict, protocol_fingerprint
    from biopsynav.refine import refined_config

    cfg = config_from_dict({}, "case.toml")
    assert "fictitious_stiffness" not in protocol_dict(cfg, 8, 2)["material"]
    assert "fictitious_stiffness" not in protocol_dict(refined_config(cfg), 8, 2)["material"]
    cfg.refine.fictitious_stiffness = 0.05
    fine = protocol_dict(refined_config(cfg), 8, 2)
    assert fine["material"]["fictitious_stiffness"] == 0.05
    cfg.refine.fictitious_stiffness = 0.0
    none = protocol_dict(refined_config(cfg), 8, 2)
    assert "fictitious_stiffness" not in none["material"]
    assert protocol_fingerprint(none) != protocol_fingerprint(fine)
