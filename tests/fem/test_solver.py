"""Solver checks: analytic uniaxial stretch, scikit-fem cross-check, convergence, failures,
prescribed displacements."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import fsolve

from biopsynav.errors import InputError, SolverError
from biopsynav.fem import FEModel, Loads, SolverSettings, solve
from biopsynav.fem import solver as solver_module
from biopsynav.fem.linsolve import available_backends
from biopsynav.fem.solver import solve_once, stiffer_springs
from tests.fem.mesh import box_mesh

from .conftest import E_MPA, NU, distorted_box, lame

TIGHT = SolverSettings(tol_residual=1e-12, tol_displacement=1e-12, single_precision=False,
                       constraint_tolerance_mm=1e-9)
PENALTY_TIGHT = SolverSettings(tol_residual=1e-9, tol_displacement=1e-9, single_precision=False,
                               constraint_tolerance_mm=1e-9)  # penalty round-off floor ~1e-10


def _uniaxial_exact(material: str, p11: float) -> tuple[float, float]:
    """Stretches (axial, lateral) of a block under uniaxial first Piola stress p11 (MPa)."""
    mu, lam = lame()

    def equations(x):
        l1, lt = x
        if material == "svk":
            e1, et = 0.5 * (l1**2 - 1), 0.5 * (lt**2 - 1)
            tr = e1 + 2 * et
            return [l1 * (lam * tr + 2 * mu * e1) - p11, lam * tr + 2 * mu * et]
        log_j = np.log(l1 * lt**2)
        if material.startswith("neo-hookean-split-sri"):  # mu/2 (J^-2/3 I1 - 3) + K/2 (ln J)^2
            j23, i1, k = (l1 * lt**2) ** (-2 / 3), l1**2 + 2 * lt**2, lam + 2 * mu / 3
            return [mu * j23 * (l1 - i1 / (3 * l1)) + k * log_j / l1 - p11,
                    mu * j23 * (lt - i1 / (3 * lt)) + k * log_j / lt]
        return [l1 * (mu * (1 - 1 / l1**2) + lam * log_j / l1**2) - p11,
                mu * (1 - 1 / lt**2) + lam * log_j / lt**2]

    l1, lt = fsolve(equations, [1.0, 1.0], xtol=1e-13)
    return float(l1), float(lt)


def _roller_block(n: int = 2, size: float = 10.0):
    nodes, hexes = box_mesh((n, n, n), (size, size, size))
    fixed = np.zeros((len(nodes), 3), bool)
    for axis in range(3):
        fixed[:, axis] = nodes[:, axis] < 1e-9
    return nodes, hexes, fixed


def _face_forces(nodes: np.ndarray, n: int, size: float, traction: np.ndarray) -> np.ndarray:
    """Consistent nodal forces of a uniform traction (MPa) on the face x = size."""
    h = size / n
    on_face = nodes[:, 0] > size - 1e-9
    inner = lambda c: np.where((c > 1e-9) & (c < size - 1e-9), 1.0, 0.5)  # noqa: E731
    share = inner(nodes[:, 1]) * inner(nodes[:, 2]) * h * h
    forces = np.zeros_like(nodes)
    forces[on_face] = share[on_face, None] * traction
    return forces


@pytest.mark.parametrize("p11_over_e", [0.3, -0.12])
def test_uniaxial_stretch_matches_closed_form(material, p11_over_e):
    n, size = 2, 10.0
    nodes, hexes, fixed = _roller_block(n, size)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, material)
    p11 = p11_over_e * E_MPA
    forces = _face_forces(nodes, n, size, np.array([p11, 0.0, 0.0]))
    u, report = solve(model, Loads(forces=forces), TIGHT)
    l1, lt = _uniaxial_exact(material, p11)
    corner = np.argmax(nodes.sum(axis=1))
    assert abs((1 + u[corner, 0] / size) - l1) < 1e-6 * l1
    assert abs((1 + u[corner, 1] / size) - lt) < 1e-6 * lt
    assert abs(l1 - 1) > 0.08  # a large strain
    assert np.all(u[fixed] == 0.0)


def test_cross_check_against_scikit_fem(material):
    pytest.importorskip("skfem")
    # every cell below is cut (weight < 1), where the inner law is the peer's neo-Hookean
    peer_law = "neo-hookean" if material == "neo-hookean-split-sri-inner" else material
    if peer_law in ("neo-hookean-sri", "neo-hookean-split-sri"):
        pytest.skip("the peer integrates the whole energy at 2x2x2 points (the locking test "
                    "below checks the reduced volumetric rule)")
    from tests.peers.skfem_peer import SkfemModel

    nodes, hexes = box_mesh((4, 3, 3), (40.0, 30.0, 30.0))
    fixed = nodes[:, 2] < 1e-9
    rng = np.random.default_rng(0)
    weight = rng.uniform(0.3, 1.0, len(hexes))
    e_mpa = rng.uniform(3e-3, 8e-3, len(hexes))
    top = np.flatnonzero(nodes[:, 2] > 30 - 1e-9)
    forces = np.zeros_like(nodes)
    forces[top] = np.array([0.3, 0.1, -1.0]) * 0.1 / len(top)
    model = FEModel(nodes, hexes, weight, e_mpa, NU, fixed, material)
    u, _ = solve(model, Loads(forces=forces), TIGHT)
    assert weight.max() < 0.999
    peer = SkfemModel(nodes, hexes, weight, e_mpa, NU, fixed, peer_law)
    x, _ = peer.solve(forces, tol=1e-12)
    u_peer = peer.dofs_to_nodal(x, len(nodes))
    assert np.abs(u).max() > 1.0
    assert np.abs(u - u_peer).max() < 1e-6 * np.abs(u).max()


def _pushed_box(material="neo-hookean", force=0.02):
    nodes, hexes = box_mesh((4, 3, 3), (40.0, 30.0, 30.0))
    fixed = nodes[:, 2] < 1e-9
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, material)
    top = np.flatnonzero(nodes[:, 2] > 30 - 1e-9)
    forces = np.zeros_like(nodes)
    forces[top] = np.array([0.5, 0.0, -1.0]) * force / len(top)
    return model, forces


def test_newton_converges_quadratically():
    model, forces = _pushed_box(force=0.1)
    settings = SolverSettings(tol_residual=1e-13, tol_displacement=1e-13,
                              reuse_factorization=False, single_precision=False)
    _, report = solve(model, Loads(forces=forces), settings)
    rel = [e["residual_rel"] for e in report.log if e["residual_rel"] > 1e-12]
    assert len(rel) >= 3
    tail = list(zip(rel[:-1], rel[1:], strict=True))[-2:]
    for before, after in tail:  # e_{k+1} ~ C e_k^2
        assert after < 10.0 * before**2 or after < 1e-11
    assert report.log[-1]["residual_rel"] <= 1e-13


def test_a_failed_increment_halves_the_step_it_tried(monkeypatch):
    """An easy increment doubles the next, which is clipped at the full load: when that one
    fails, the retry halves the step tried (0.5 -> 0.25, to load 0.75), never the same
    increment again (halving the doubled nominal step gave 0.5 -> load 1.0 once more)."""
    import biopsynav.fem.solver as solver_mod

    model, forces = _pushed_box(force=0.01)
    tried = []
    newton = solver_mod._newton

    def failing_once(system, solver, settings, report, u0, t_prev, t, *a, **k):
        tried.append((t_prev, t))
        if (t_prev, t) == (0.5, 1.0) and tried.count((t_prev, t)) == 1:
            raise solver_mod._IncrementFailed("a failure forced by the test")
        return newton(system, solver, settings, report, u0, t_prev, t, *a, **k)

    monkeypatch.setattr(solver_mod, "_newton", failing_once)
    u, report = solve(model, Loads(forces=forces), SolverSettings(initial_load_step=0.5))
    assert tried[:3] == [(0.0, 0.5), (0.5, 1.0), (0.5, 0.75)], tried
    assert len(set(tried)) == len(tried) and report.increments == len(tried) - 1
    monkeypatch.undo()
    reference, _ = solve(model, Loads(forces=forces), SolverSettings())
    assert np.abs(u - reference).max() < 1e-6 * np.abs(reference).max()


def test_report_and_log_fields():
    model, forces = _pushed_box()
    u, report = solve(model, Loads(forces=forces))
    assert report.iterations == len(report.log) > 0
    assert report.increments >= 1 and report.min_det_F > 0 and report.time_s > 0
    assert report.residual_rel <= 1e-8
    assert report.max_displacement_mm == pytest.approx(np.linalg.norm(u, axis=1).max())
    assert {"residual", "residual_rel", "du", "line_step", "min_det_F", "load"} <= set(
        report.log[0])


def test_repeated_solves_reuse_analysis_and_agree():
    model, forces = _pushed_box()
    u1, _ = solve(model, Loads(forces=forces))
    cached = dict(model.cache)
    u2, _ = solve(model, Loads(forces=forces))
    assert all(model.cache[k] is v for k, v in cached.items())
    assert np.abs(u1 - u2).max() < 1e-8 * np.abs(u1).max()


def test_non_convergence_raises_with_log():
    model, forces = _pushed_box(force=0.5)
    settings = SolverSettings(max_iterations=1, min_load_step=0.25, reuse_factorization=False)
    with pytest.raises(SolverError) as info:
        solve(model, Loads(forces=forces), settings)
    assert info.value.log and "min_load_step" in info.value.what


def test_newton_budget_stops_the_solve_with_its_log():
    model, forces = _pushed_box(force=0.1)
    _, free = solve(model, Loads(forces=forces))
    assert free.iterations > 2
    # the first iteration (from the rest factorisation) cuts |R| by a third only: not converging
    with pytest.raises(SolverError) as info:
        solve(model, Loads(forces=forces), SolverSettings(max_total_iterations=1))
    assert len(info.value.log) == 1 and "max_total_iterations = 1" in info.value.what


def test_a_solve_converging_at_its_budget_is_given_a_few_iterations_more_with_shift():
    model, forces = _pushed_box(force=0.1)
    u_free, free = solve(model, Loads(forces=forces))
    budget = free.iterations - 2  # the last iterations of this solve are reuse steps
    assert budget >= 2 and free.log[budget - 1]["mode"] == "reuse"
    shift = SolverSettings(max_total_iterations=budget, indefinite_tangent="shift")
    u, report = solve(model, Loads(forces=forces), shift)
    assert report.iterations == free.iterations and np.array_equal(u, u_free)
    assert budget + solver_module.GRACE_ITERATIONS >= report.iterations
    with pytest.raises(SolverError):  # ldlt: the budget is the budget
        solve(model, Loads(forces=forces), SolverSettings(max_total_iterations=budget))


def test_budget_grace_ends():
    spent, grace = solver_module._budget_spent, solver_module.GRACE_ITERATIONS
    assert not spent(0, 100, 0)  # no budget
    assert not spent(10, 9, 0) and spent(10, 10, 0)
    assert not spent(10, 10, grace) and spent(10, 10 + grace, grace)


def test_svk_past_its_limit_point_is_reported():
    n, size = 2, 10.0
    nodes, hexes, fixed = _roller_block(n, size)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "svk")
    forces = _face_forces(nodes, n, size, np.array([-1.0 * E_MPA, 0.0, 0.0]))
    with pytest.raises(SolverError) as info:
        solve(model, Loads(forces=forces))
    assert info.value.log
    assert min(e["min_det_F"] for e in info.value.log) > 0  # never an inverted state kept


def test_zero_load_returns_zero():
    model, forces = _pushed_box()
    u, report = solve(model, Loads(forces=0 * forces))
    assert not u.any() and report.iterations == 0


def test_bad_loads_are_input_errors():
    model, forces = _pushed_box()
    with pytest.raises(InputError):
        solve(model, Loads(forces=forces[:-1]))
    bad = forces.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError):
        solve(model, Loads(forces=bad))


def _top_points_matrix(nodes: np.ndarray, points: np.ndarray, cells, size) -> sp.csr_matrix:
    """Trilinear interpolation matrix of points in a regular box mesh."""
    from biopsynav.grid import index
    from biopsynav.grid.embedding import trilinear_weights

    h = np.asarray(size) / np.asarray(cells)
    rel = points / h
    ijk = np.minimum(np.floor(rel).astype(int), np.asarray(cells) - 1)
    weights = trilinear_weights(rel - ijk)
    node_ids = index.hex_connectivity(ijk, tuple(np.asarray(cells) + 1))
    rows = np.repeat(np.arange(len(points)), 8)
    return sp.csr_matrix((weights.ravel(), (rows, node_ids.ravel())),
                         shape=(len(points), len(nodes)))


def test_prescribed_displacements_are_met(material):
    cells, size = (4, 3, 3), (40.0, 30.0, 30.0)
    nodes, hexes = box_mesh(cells, size)
    fixed = nodes[:, 2] < 1e-9
    model = FEModel(nodes, hexes, 0.8, E_MPA, NU, fixed, material)
    points = np.array([[12.0, 14.0, 30.0], [17.5, 11.0, 30.0], [23.0, 16.0, 29.0]])
    w = _top_points_matrix(nodes, points, cells, size)
    target = np.tile([1.0, 0.5, -3.0], (3, 1))
    forces = np.zeros_like(nodes)
    forces[nodes[:, 2] > 29.9] = [0.0, 0.0, 1e-4]
    u, report = solve(model, Loads(forces=forces, prescribed_matrix=w,
                                   prescribed_displacement=target))
    assert np.abs(w @ u - target).max() < 1e-3
    assert report.constraint_error_mm <= 1e-4
    assert np.all(u[fixed] == 0.0)


def test_patch_test_with_prescribed_boundary():
    nodes, hexes = distorted_box(cells=(3, 3, 3), size=30.0)
    boundary = np.any((nodes < 1e-9) | (nodes > 30 - 1e-9), axis=1)
    f_affine = np.array([[1.08, 0.04, 0.0], [0.02, 0.95, 0.03], [0.0, 0.05, 1.04]])
    exact = (nodes - 15.0) @ (f_affine - np.eye(3)).T
    fixed = np.zeros(len(nodes), bool)
    fixed[np.argmin(np.linalg.norm(nodes - 15.0, axis=1))] = False
    anchor = np.flatnonzero(boundary)
    w = sp.csr_matrix((np.ones(len(anchor)), (np.arange(len(anchor)), anchor)),
                      shape=(len(anchor), len(nodes)))
    corner = np.argmin(nodes.sum(axis=1))
    fixed[corner] = True  # keeps the model anchored; its target is moved to zero
    exact -= exact[corner]
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed)
    # the penalty's stiff terms limit the attainable relative residual to about 1e-10
    settings = SolverSettings(tol_residual=1e-9, tol_displacement=1e-9,
                              constraint_tolerance_mm=1e-8)
    u, _ = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=exact[anchor]),
                 settings)
    assert np.abs(u - exact).max() < 1e-6 * np.abs(exact).max()


@pytest.mark.parametrize("backend", available_backends())
def test_every_installed_backend_gives_the_same_answer(backend):
    model, forces = _pushed_box()
    reference, _ = solve(model, Loads(forces=forces), TIGHT)
    settings = SolverSettings(backend=backend, tol_residual=1e-12, tol_displacement=1e-12)
    u, report = solve(model, Loads(forces=forces), settings)
    assert report.backend == backend
    assert np.abs(u - reference).max() < 1e-8 * np.abs(reference).max()


def test_pardiso_s_library_is_searched_for_once(monkeypatch):
    """pypardiso searches for MKL at every construction (about 0.8 s); after the first, the
    project's solvers are handed the library found, and a path the user set is kept."""
    pardiso_wrapper = pytest.importorskip("pypardiso.pardiso_wrapper")
    from biopsynav.fem import linsolve

    linsolve.pypardiso_solver(mtype=2)
    searched = []
    monkeypatch.setattr(pardiso_wrapper, "find_library", lambda n: searched.append(n))
    monkeypatch.setattr(pardiso_wrapper.glob, "glob", lambda *a, **k: searched.append(a))
    model, forces = _pushed_box()
    reference, _ = solve(model, Loads(forces=forces), TIGHT)
    u, report = solve(model, Loads(forces=forces), SolverSettings(backend="pardiso"))
    assert report.backend == "pardiso" and not searched
    assert np.abs(u - reference).max() < 1e-6 * np.abs(reference).max()
    monkeypatch.setenv("PYPARDISO_MKL_RT", "/nowhere/libmkl_rt.so")
    with pytest.raises(InputError, match="nowhere.*PYPARDISO_MKL_RT") as bad:
        linsolve.pypardiso_solver(mtype=2)
    assert bad.value.where == "PYPARDISO_MKL_RT"


def test_a_bad_mkl_path_is_named_when_pypardiso_is_imported():
    """pypardiso makes a solver when it is imported: a wrong ``PYPARDISO_MKL_RT`` fails there,
    in the backend choice, and is still an InputError naming the variable."""
    import subprocess
    import sys

    pytest.importorskip("pypardiso")
    code = ("from biopsynav.errors import InputError\n"
            "from biopsynav.fem.linsolve import available_backends\n"
            "try:\n    available_backends()\n"
            "except InputError as e:\n    print('where', e.where)\n")
    env = {**os.environ, "PYPARDISO_MKL_RT": "/nowhere/libmkl_rt.so"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=120)
    assert done.returncode == 0 and "where PYPARDISO_MKL_RT" in done.stdout, done.stderr


@pytest.mark.parametrize("user_mode", [None, "COMPATIBLE"])
def test_pardiso_s_mkl_is_made_reproducible_unless_the_user_chose(user_mode):
    """Loading Pardiso puts its MKL in conditional numerical reproducibility (MKL_CBWR_AUTO,
    2), so that two threads factor the same matrix to the same bits from run to run; a mode
    the user set in ``MKL_CBWR`` (COMPATIBLE, 3) is left as it is. A fresh process: MKL takes
    the mode only before it first computes."""
    import subprocess
    import sys

    pytest.importorskip("pypardiso")
    code = ("import ctypes\n"
            "from biopsynav.fem import linsolve\n"
            "lib = linsolve._pypardiso().ps.libmkl\n"
            "get = lib.MKL_CBWR_Get\n"
            "get.argtypes, get.restype = [ctypes.c_int], ctypes.c_int\n"
            "mode = get(1)  # MKL_CBWR_BRANCH: the mode loading left\n"
            "print('status', linsolve.reproducible_mkl(lib), 'mode', mode)  # cached\n")
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    if user_mode:
        env["MKL_CBWR"] = user_mode
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=120)
    expected = "status -1 mode 3" if user_mode else "status 0 mode 2"
    assert done.returncode == 0 and expected in done.stdout, done.stdout + done.stderr


def test_smallest_det_f_finds_the_inverted_element():
    """A homogeneous stretch gives det F = its volume ratio in every element; moving one node
    through its element's opposite face inverts that element (det F < 0 there), and only the
    elements that share the node change."""
    from biopsynav.fem import smallest_det_f

    n, size = 2, 10.0
    nodes, hexes = box_mesh((n, n, n), (size, size, size))
    model = FEModel(nodes, hexes, np.ones(len(hexes)), E_MPA, NU, nodes[:, 2] < 1e-9)
    stretch = np.diag([1.2, 0.9, 1.0])
    np.testing.assert_allclose(smallest_det_f(model, nodes @ (stretch - np.eye(3)).T),
                               np.linalg.det(stretch), rtol=1e-12)
    corner = int(np.argmin(np.linalg.norm(nodes - size, axis=1)))  # (10, 10, 10): one element
    u = np.zeros_like(nodes)
    u[corner] = [-8.0, -8.0, -8.0]  # past the element's far corner at (5, 5, 5)
    det = smallest_det_f(model, u)
    owner = np.flatnonzero((hexes == corner).any(axis=1))
    assert len(owner) == 1 and det[owner[0]] < 0
    assert np.all(np.delete(det, owner) == 1.0)


def test_stability_check_tells_a_stable_from_an_unstable_state():
    """The eigenvalue check that confirms an instability reported by an indefinite
    factorisation: positive at rest, negative for SVK compressed past its limit point
    (uniaxial stretch 0.3: the SVK stress falls as compression grows)."""
    from biopsynav.fem.loads import prepare_loads
    from biopsynav.fem.solver import _System, lowest_scaled_eigenvalue

    n, size = 2, 10.0
    nodes, hexes, fixed = _roller_block(n, size)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "svk")
    system = _System(model, prepare_loads(model, Loads()), 0.0)
    assert lowest_scaled_eigenvalue(system, np.zeros(model.n_eq)) > 1e-3
    crushed = np.zeros_like(nodes)
    crushed[:, 0] = -0.7 * nodes[:, 0]
    assert lowest_scaled_eigenvalue(system, model.to_free(crushed)) < -1e-3


def test_rounding_sized_prescribed_displacement_is_no_load():
    """A rest pose recomputed through a matrix inverse prescribes ~1e-13 mm: the solve
    answers zero at once instead of failing its line search on rounding noise."""
    nodes, hexes, fixed = _roller_block(2, 10.0)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "neo-hookean")
    top = np.flatnonzero(nodes[:, 0] > 10.0 - 1e-9)
    w = sp.csr_matrix((np.ones(len(top)), (np.arange(len(top)), top)),
                      shape=(len(top), len(nodes)))
    g = np.full((len(top), 3), 3e-13)
    u, report = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=g))
    assert not np.any(u) and report.iterations == 0


def _sheared_block_tip(material: str, nu: float) -> float:
    """Tip displacement (mm) of a 4 x 4 x 4 block clamped at z = 0 under a shear traction of
    1e-3 E on its top face (about 0.6 % strain)."""
    nodes, hexes = box_mesh((4, 4, 4), (20.0, 20.0, 20.0))
    fixed = nodes[:, 2] < 1e-9
    top = nodes[:, 2] > 20.0 - 1e-9
    forces = np.zeros_like(nodes)
    forces[top, 0] = 1e-3 * E_MPA * 400.0 / top.sum()
    model = FEModel(nodes, hexes, 1.0, E_MPA, nu, fixed, material)
    u, _ = solve(model, Loads(forces=forces), SolverSettings(single_precision=False))
    return float(u[top, 0].mean())


@pytest.mark.parametrize("reduced", ["neo-hookean-sri", "neo-hookean-split-sri",
                                     "neo-hookean-split-sri-inner"])
def test_reduced_volumetric_integration_does_not_lock(reduced):
    """Nearly incompressible (nu 0.45 -> 0.4999): the sheared block barely stiffens with the
    volumetric term at the cell centre (-2 %), while full 2x2x2 integration locks (its lambda
    term stiffens the isochoric shear mode: -46 %)."""
    sri = _sheared_block_tip(reduced, 0.4999) / _sheared_block_tip(reduced, 0.45)
    full = _sheared_block_tip("neo-hookean", 0.4999) / _sheared_block_tip("neo-hookean", 0.45)
    assert sri > 0.95
    assert full < 0.6


def test_normal_only_prescribed_points_slide_freely():
    """Frictionless compression: the top face of a rollered block pushed 10 % down along z
    only (``prescribed_normals``) contracts in z and expands freely in x and y, as the closed
    form of uniaxial stress says (neo-Hookean); with the whole vector prescribed it cannot."""
    size = 10.0
    nodes, hexes, fixed = _roller_block(2, size)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "neo-hookean")
    top = np.flatnonzero(nodes[:, 2] > size - 1e-9)
    w = sp.csr_matrix((np.ones(len(top)), (np.arange(len(top)), top)),
                      shape=(len(top), len(nodes)))
    g = np.tile([0.0, 0.0, -1.0], (len(top), 1))
    normals = np.tile([0.0, 0.0, 1.0], (len(top), 1))
    u, _ = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=g,
                              prescribed_normals=normals), PENALTY_TIGHT)
    mu, lam = lame()

    def lateral(lt):
        return mu * (1 - 1 / lt**2) + lam * np.log(0.9 * lt**2) / lt**2

    (lt,) = fsolve(lateral, [1.0], xtol=1e-13)
    corner = np.argmax(nodes.sum(axis=1))
    np.testing.assert_allclose(u[top, 2], -1.0, atol=1e-8)
    np.testing.assert_allclose(u[corner, :2], (lt - 1.0) * size, rtol=1e-6)
    assert lt > 1.01
    stuck, _ = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=g),
                     PENALTY_TIGHT)
    np.testing.assert_allclose(stuck[top, :2], 0.0, atol=1e-8)


def test_prescribed_normals_are_checked():
    nodes, hexes, fixed = _roller_block(2, 10.0)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "neo-hookean")
    w = sp.csr_matrix((np.ones(1), ([0], [len(nodes) - 1])), shape=(1, len(nodes)))
    with pytest.raises(InputError, match="unit vectors"):
        solve(model, Loads(prescribed_matrix=w, prescribed_displacement=np.ones((1, 3)),
                           prescribed_normals=np.array([[0.0, 0.0, 2.0]])))


def _top_springs(nodes: np.ndarray, size: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The top face's nodes (z = size) and the reference area (mm^2) each stands for."""
    top = np.flatnonzero(nodes[:, 2] > size - 1e-9)
    h = size / n
    inner = lambda c: np.where((c > 1e-9) & (c < size - 1e-9), 1.0, 0.5)  # noqa: E731
    return top, inner(nodes[top, 0]) * inner(nodes[top, 1]) * h * h


def test_elastic_contact_matches_the_closed_form_of_a_block_on_springs():
    """A rollered block whose top face is tied by springs of stiffness ``K`` per unit area
    (normal only) to a plate moved down by 1.5 mm: the springs carry the nominal stress
    ``P33 = K (g - delta)``, and the block takes the uniaxial stretch of that stress
    (neo-Hookean closed form) with a gap between face and plate."""
    n, size, stiffness, g = 2, 10.0, 0.002, -1.5  # K in N/mm^3 (MPa/mm)
    nodes, hexes, fixed = _roller_block(n, size)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "neo-hookean")
    top, area = _top_springs(nodes, size, n)
    w = sp.csr_matrix((np.ones(len(top)), (np.arange(len(top)), top)),
                      shape=(len(top), len(nodes)))
    u, report = solve(model, Loads(
        prescribed_matrix=w, prescribed_displacement=np.tile([0.0, 0.0, g], (len(top), 1)),
        prescribed_normals=np.tile([0.0, 0.0, 1.0], (len(top), 1)),
        prescribed_stiffness=stiffness * area), PENALTY_TIGHT)
    (delta,) = fsolve(lambda d: (_uniaxial_exact("neo-hookean", stiffness * (g - d[0]))[0]
                                 - 1.0) * size - d[0], [g / 2], xtol=1e-13)
    np.testing.assert_allclose(u[top, 2], delta, rtol=1e-7)
    assert g < delta < 0.5 * g  # a real gap: the springs carry the load, not a constraint
    assert report.spring_factor == 1.0
    assert report.constraint_error_mm == pytest.approx(delta - g, rel=1e-6)


def test_stiffer_springs_close_the_gap_towards_the_met_points():
    """Elastic contact tends to the points met as its springs stiffen: the gap falls about
    in proportion, and the field approaches the constrained solve's."""
    cells, size = (4, 3, 3), (40.0, 30.0, 30.0)
    nodes, hexes = box_mesh(cells, size)
    model = FEModel(nodes, hexes, 0.8, E_MPA, NU, nodes[:, 2] < 1e-9, "neo-hookean")
    points = np.array([[12.0, 14.0, 30.0], [17.5, 11.0, 30.0], [23.0, 16.0, 29.0]])
    w = _top_points_matrix(nodes, points, cells, size)
    target = np.tile([1.0, 0.5, -3.0], (3, 1))
    met, _ = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=target),
                   PENALTY_TIGHT)
    gaps, misfits = [], []
    for k in (0.1, 1.0, 10.0, 100.0):
        u, report = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=target,
                                       prescribed_stiffness=np.full(3, k)), PENALTY_TIGHT)
        gaps.append(report.constraint_error_mm)
        misfits.append(np.abs(u - met).max())
    assert np.all(np.array(gaps[:-1]) > 4 * np.array(gaps[1:]))  # 1/k once the gap is small
    assert np.all(np.diff(misfits) < 0) and misfits[-1] < 0.01


def _block_on_one_spring() -> tuple[FEModel, Loads]:
    """A 4 x 3 x 3 block fixed at its base, one top point on a spring pulled down by 2 mm."""
    cells, size = (4, 3, 3), (40.0, 30.0, 30.0)
    nodes, hexes = box_mesh(cells, size)
    model = FEModel(nodes, hexes, 0.8, E_MPA, NU, nodes[:, 2] < 1e-9, "neo-hookean")
    w = _top_points_matrix(nodes, np.array([[12.0, 14.0, 30.0]]), cells, size)
    return model, Loads(prescribed_matrix=w,
                        prescribed_displacement=np.array([[0.0, 0.0, -2.0]]),
                        prescribed_stiffness=np.array([0.05]))


def test_elastic_contact_gives_the_springs_as_asked_their_own_budget(monkeypatch):
    """The springs as asked get at most ``first_attempt_budget`` Newton iterations (a solve
    past their limit point wanders until its budget is spent); the fallbacks get the whole
    ``max_total_iterations``."""
    import biopsynav.fem.solver as solver_mod

    model, loads = _block_on_one_spring()
    real, budgets = solver_mod.solve_once, []

    def first_fails(model, loads, settings=None, resume_from=None):
        budgets.append(settings.max_total_iterations)
        if len(budgets) == 1:
            raise SolverError("made to fail", "test")
        return real(model, loads, settings, resume_from)

    monkeypatch.setattr(solver_mod, "solve_once", first_fails)
    for first_budget, total, first in ((0, 0, 0), (40, 0, 40), (40, 400, 40), (40, 20, 20),
                                       (0, 300, 300)):
        budgets.clear()
        solve(model, loads, SolverSettings(max_total_iterations=total,
                                           first_attempt_budget=first_budget))
        assert budgets == [first, total]


def test_a_fallback_starts_where_the_springs_before_it_stopped(monkeypatch):
    """The stiffer springs start from the last load factor the springs as asked converged
    at (their state the first guess), and reach the answer they reach from rest."""
    import biopsynav.fem.solver as solver_mod

    model, loads = _block_on_one_spring()
    half = dataclasses.replace(loads, prescribed_displacement=0.5 * loads.prescribed_displacement)
    u_half, _ = solve_once(model, half)
    reached = (0.5, model.to_free(u_half))
    real, starts = solver_mod.solve_once, []

    def first_stops_halfway(model, loads, settings=None, resume_from=None):
        starts.append(resume_from)
        if len(starts) == 1:
            raise SolverError("made to fail", "test", reached=reached)
        return real(model, loads, settings, resume_from)

    monkeypatch.setattr(solver_mod, "solve_once", first_stops_halfway)
    u, report = solve(model, loads, SolverSettings(spring_fallback=(4.0,)))
    assert starts[0] is None and starts[1] is reached
    assert report.spring_factor == 4.0
    assert report.log[0]["load"] == 1.0 and report.log[0]["step"] == 0.5  # from 0.5, not rest
    monkeypatch.undo()
    cold, cold_report = solve_once(model, stiffer_springs(loads, 4.0))
    np.testing.assert_allclose(u, cold, atol=1e-6)
    assert report.residual_rel < 1e-8
    assert report.reference_residual == pytest.approx(cold_report.reference_residual)


def test_a_failed_solve_says_how_far_it_converged():
    """A solve stopped by its budget carries the last converged load factor and state."""
    model, loads = _block_on_one_spring()
    deep = dataclasses.replace(loads, prescribed_displacement=20 * loads.prescribed_displacement,
                               prescribed_stiffness=None)
    with pytest.raises(SolverError) as caught:
        solve_once(model, deep, SolverSettings(max_total_iterations=6, initial_load_step=0.25))
    load, state = caught.value.reached
    assert 0.0 < load < 1.0 and state.shape == (model.n_eq,) and np.abs(state).max() > 0.0


def test_elastic_contact_in_single_precision_converges_to_the_double_answer():
    """Elastic contact factored in single precision where asked (data generation's first
    attempt): Newton's residual in double precision brings it to the same answer."""
    cells, size = (4, 3, 3), (40.0, 30.0, 30.0)
    nodes, hexes = box_mesh(cells, size)
    model = FEModel(nodes, hexes, 0.8, E_MPA, NU, nodes[:, 2] < 1e-9, "neo-hookean")
    points = np.array([[12.0, 14.0, 30.0], [17.5, 11.0, 30.0], [23.0, 16.0, 29.0]])
    loads = Loads(prescribed_matrix=_top_points_matrix(nodes, points, cells, size),
                  prescribed_displacement=np.tile([1.0, 0.5, -6.0], (3, 1)),
                  prescribed_stiffness=np.full(3, 0.5))
    answers = []
    for single in (True, False):
        u, report = solve(model, loads, SolverSettings(elastic_single_precision=single))
        answers.append(u)
        assert report.spring_factor == 1.0
    np.testing.assert_allclose(answers[0], answers[1], atol=1e-6)
    assert np.abs(answers[0]).max() > 1.0


def test_elastic_contact_falls_back_to_stiffer_springs(monkeypatch):
    """An elastic solve that fails is solved again with stiffer springs, then with the points
    met; the report says which answered, and when none does the first error is raised."""
    import biopsynav.fem.solver as solver_mod

    model, loads = _block_on_one_spring()
    real, tried = solver_mod.solve_once, []

    def failing_below(limit):
        def solve_once(model, loads, settings=None, resume_from=None):
            k = loads.prescribed_stiffness
            tried.append(None if k is None else float(k[0]))
            if k is not None and k[0] < limit:
                raise SolverError("made to fail", "test")
            return real(model, loads, settings, resume_from)
        return solve_once

    monkeypatch.setattr(solver_mod, "solve_once", failing_below(0.1))
    _, report = solve(model, loads)
    assert tried == [0.05, 0.2] and report.spring_factor == 4.0
    tried.clear()
    monkeypatch.setattr(solver_mod, "solve_once", failing_below(np.inf))
    _, report = solve(model, loads)
    assert tried == [0.05, 0.2, None] and report.spring_factor == np.inf
    assert report.constraint_error_mm < 1e-2
    assert report.fallback_note().startswith("answered with the contact points met")
    monkeypatch.setattr(solver_mod, "solve_once", lambda *a, **k: (_ for _ in ()).throw(
        SolverError("always", "test")))
    with pytest.raises(SolverError, match="always"):
        solve(model, loads)


def test_bad_spring_stiffness_is_an_input_error():
    nodes, hexes, fixed = _roller_block(2, 10.0)
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, fixed, "neo-hookean")
    w = sp.csr_matrix((np.ones(1), ([0], [len(nodes) - 1])), shape=(1, len(nodes)))
    for bad in (np.array([0.0]), np.array([np.nan]), np.ones(2)):
        with pytest.raises(InputError, match="prescribed stiffness"):
            solve(model, Loads(prescribed_matrix=w, prescribed_displacement=np.ones((1, 3)),
                               prescribed_stiffness=bad))


def test_solve_leaves_the_callers_matrix_as_it_was():
    """A prescribed-point matrix holding explicit zeros (a point on a cell face has zero
    weights) is pruned inside the solve on a copy: the caller's matrix keeps its arrays.
    Pruning it in place once left the caller's indptr pointing past its data, and a later
    column slice of it corrupted the heap."""
    cells, size = (4, 3, 3), (40.0, 30.0, 30.0)
    nodes, hexes = box_mesh(cells, size)
    model = FEModel(nodes, hexes, 0.8, E_MPA, NU, nodes[:, 2] < 1e-9, "neo-hookean")
    w = _top_points_matrix(nodes, np.array([[10.0, 10.0, 30.0], [17.5, 11.0, 30.0]]), cells,
                           size)
    assert np.any(w.data == 0.0)  # the first point sits on a node: seven zero weights
    before = (w.data.copy(), w.indices.copy(), w.indptr.copy())
    for stiffness in (None, np.array([0.05, 0.05])):
        solve(model, Loads(prescribed_matrix=w, prescribed_displacement=np.tile(
            [0.0, 0.0, -1.0], (2, 1)), prescribed_stiffness=stiffness))
        for a, b in zip((w.data, w.indices, w.indptr), before, strict=True):
            np.testing.assert_array_equal(a, b)


def _tiny_spring_push(law: str, folder) -> tuple[FEModel, Loads]:
    """A 1e-3 mm push of the 15 mm phantom through springs, with the material law ``law``:
    Newton stops near 1e-10 of |R0| there with both laws (the energy's round-off; the
    decoupled law's forces level off there too)."""
    from biopsynav.case import make_phantom_case
    from biopsynav.grid.embedding import Embedding
    from biopsynav.probe import eligible_centers, push_for_sample

    case = make_phantom_case(folder / "case", cell_size_mm=15.0)
    case.cfg.material.model = law
    probe = case.cfg.probe
    push = push_for_sample(case.anatomy, probe, 7, 0, 0,
                           eligible_centers(case.anatomy, probe.min_chest_distance_mm))
    w = Embedding.build(case.grid, case.anatomy.vertices).matrix[push.contact]
    springs = np.linspace(0.01, 0.03, w.shape[0])  # N/mm
    g = np.tile([0.0, 0.0, -1e-3], (w.shape[0], 1))
    return FEModel.from_case(case), Loads(prescribed_matrix=w, prescribed_displacement=g,
                                          prescribed_stiffness=springs)


@pytest.mark.parametrize("law", ["neo-hookean", "neo-hookean-split-sri-inner"])
def test_a_residual_at_its_round_off_floor_is_converged_not_a_failure(law, tmp_path):
    """Where the energy cannot be lowered along a Newton correction already within the
    displacement tolerance, the state is accepted (mode 'floor'). Before, the increment was
    halved down to min_load_step and 4x stiffer springs answered, 30 % off this push's
    linear field."""
    model, loads = _tiny_spring_push(law, tmp_path)
    u, report = solve(model, loads, SolverSettings(tol_residual=1e-10, tol_displacement=1e-10,
                                                   single_precision=False))
    assert report.spring_factor == 1.0 and report.increments == 1
    ref, _ = solve(model, loads, SolverSettings(tol_residual=1e-8, tol_displacement=1e-8,
                                                single_precision=False))
    assert np.abs(u - ref).max() < 1e-6 * np.abs(ref).max()
    assert report.log[-1]["residual_rel"] < 1e-5


def test_a_tolerance_below_the_round_off_floor_fails_saying_so(tmp_path):
    model, loads = _tiny_spring_push("neo-hookean-split-sri-inner", tmp_path)
    with pytest.raises(SolverError, match="round-off floor"):
        solve(model, loads, SolverSettings(tol_residual=1e-13, tol_displacement=1e-13,
                                           single_precision=False))


def _indented_block():
    """A neo-Hookean 40 mm cube held at its base, the middle of its top face pulled 20 mm
    down and 6 mm sideways by springs: Newton's first steps meet tangents that are not
    positive definite, its answer is stable."""
    nodes, hexes = box_mesh((4, 4, 4), (40.0, 40.0, 40.0))
    model = FEModel(nodes, hexes, 1.0, E_MPA, NU, nodes[:, 2] < 1e-9, "neo-hookean")
    top = np.flatnonzero((nodes[:, 2] > 40 - 1e-9) & (np.abs(nodes[:, 0] - 20) <= 10)
                         & (np.abs(nodes[:, 1] - 20) <= 10))
    w = sp.csr_matrix((np.ones(len(top)), (np.arange(len(top)), top)),
                      shape=(len(top), len(nodes)))
    g = np.tile([6.0, 0.0, -20.0], (len(top), 1))
    return model, Loads(prescribed_matrix=w, prescribed_displacement=g,
                        prescribed_stiffness=np.full(len(top), 10 * E_MPA))


def test_a_tangent_not_positive_definite_is_shifted_to_the_same_answer():
    model, loads = _indented_block()
    u, report = solve(model, loads, SolverSettings(indefinite_tangent="shift"))
    modes = {e["mode"].split("(")[0] for e in report.log}
    assert "shifted" in modes and "indefinite" not in modes and report.spring_factor == 1.0
    u_ldlt, ldlt = solve(model, loads)
    assert "indefinite" in {e["mode"].split("(")[0] for e in ldlt.log}
    assert np.abs(u - u_ldlt).max() < 1e-6 * np.abs(u).max()


def test_the_protocol_names_the_indefinite_tangent_only_when_it_is_shift():
    """Data sets solved before ``[solver] indefinite_tangent`` existed (LDL^T then, the
    default) keep their fingerprint; ``shift`` makes other answers and another one."""
    from biopsynav.config import config_from_dict
    from biopsynav.dataset.store import protocol_dict, protocol_fingerprint

    cfg = config_from_dict({}, "case.toml")
    assert cfg.solver.indefinite_tangent == "ldlt"
    ldlt = protocol_dict(cfg, 8, 2)
    assert "indefinite_tangent" not in ldlt["solver"]
    cfg.solver.indefinite_tangent = "shift"
    shift = protocol_dict(cfg, 8, 2)
    assert shift["solver"]["indefinite_tangent"] == "shift"
    assert protocol_fingerprint(ldlt) != protocol_fingerprint(shift)


def test_a_continued_solve_that_fails_is_solved_again_from_rest(monkeypatch):
    """``solve(start=...)``: the continued attempt has at most CONTINUED_BUDGET iterations;
    when it fails, the solve starts again from rest with the caller's settings (a limit point
    on the continued path must not cost the whole budget and every fallback)."""
    calls = []
    answer = (np.zeros((1, 3)), solver_module.SolveReport())

    def fake_solve_once(model, loads, settings, resume_from=None):
        calls.append((resume_from is not None, settings.max_total_iterations))
        if resume_from is not None:
            raise SolverError("no convergence on the continued path", "fem.solve")
        return answer

    monkeypatch.setattr(solver_module, "solve_once", fake_solve_once)
    settings = SolverSettings(max_total_iterations=500)
    loads = Loads(prescribed_matrix=sp.csr_matrix((3, 3)), prescribed_displacement=np.zeros((1, 3)))
    assert solve(None, loads, settings, start=(0.5, np.zeros(3))) is answer
    assert calls == [(True, solver_module.CONTINUED_BUDGET), (False, 500)]
