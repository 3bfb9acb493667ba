"""Newton-Raphson with adaptive load increments and a backtracking line search.

The discrete problem: find free displacements ``u`` with

    R(u, t) = f_int(u) - t f + W^T (alpha (W u - t g) + lam) = 0,

``t`` the load factor (0 -> 1), ``f`` nodal forces, ``W u = g`` the prescribed displacements
enforced by a penalty ``alpha`` (relative to the mean diagonal of the reference stiffness)
plus augmented-Lagrangian multiplier updates ``lam`` until the constraint error is below
``constraint_tolerance_mm``. See ``docs/fem.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SolverError
from . import kernels
from .linsolve import FactorizationError, LinearSolver, make_solver
from .loads import Loads, PreparedLoads, prepare_loads
from .model import FEModel

EASY_ITERATIONS = 4  # an increment converging within this many iterations doubles the next
ARMIJO = 1e-4
MAX_BACKTRACKS = 6


@dataclass
class SolverSettings:
    """Newton settings (see ``[solver]`` in case.toml)."""

    tol_residual: float = 1e-8
    tol_displacement: float = 1e-8
    max_iterations: int = 30
    initial_load_step: float = 1.0
    min_load_step: float = 1.0 / 256
    line_search: bool = True
    backend: str = "auto"
    intermediate_tolerance: float = 1e-3
    penalty: float = 1e6
    constraint_tolerance_mm: float = 1e-4

    @classmethod
    def from_config(cls, solver_section) -> SolverSettings:
        """Settings from ``cfg.solver`` (a :class:`biopsynav.config.SolverSection`)."""
        names = cls.__dataclass_fields__
        return cls(**{k: v for k, v in vars(solver_section).items() if k in names})


@dataclass
class SolveReport:
    """What a solve did. ``log``: one dict per Newton iteration (see :func:`solve`)."""

    iterations: int = 0
    increments: int = 0
    residual: float = 0.0
    residual_rel: float = 0.0
    reference_residual: float = 0.0
    time_s: float = 0.0
    min_det_F: float = 1.0
    max_displacement_mm: float = 0.0
    constraint_error_mm: float = 0.0
    backend: str = ""
    log: list[dict] = field(default_factory=list)


class _System:
    """Residual, tangent and potential energy of one model under prepared loads."""

    def __init__(self, model: FEModel, loads: PreparedLoads, penalty: float) -> None:
        self.model = model
        self.loads = loads
        n_el = model.n_elements
        self.fe = np.empty((n_el, 24))
        self.ke = np.empty((n_el, 24, 24))
        self.min_det = np.empty(n_el)
        self.energy = np.empty(n_el)
        self.fint = np.empty(model.n_eq)
        self.alpha = penalty * reference_diagonal_mean(model) if loads.has_constraints else 0.0
        n_pts = loads.w.shape[0] if loads.has_constraints else 0
        self.lam = np.zeros((n_pts, 3))

    def evaluate(self, u: np.ndarray, t: float, tangent: bool):
        """Residual (n_eq,), tangent upper-CSR data (or None), min det F, potential energy."""
        m = self.model
        kernels.element_kernel(m.to_nodes(u), m.hexes, m.elem_set, m.grads, m.jw, m.weight,
                               m.mu, m.lam, m.material_id, tangent, self.fe, self.ke,
                               self.min_det, self.energy)
        min_det = float(self.min_det.min())
        kernels.scatter_vector(self.fe, m.elem_eq, self.fint)
        residual = self.fint - t * self.loads.f
        energy = float(self.energy.sum()) - t * float(self.loads.f @ u)
        data = None
        if tangent:
            data = np.empty(m.nnz)
            kernels.scatter_matrix(self.ke, m.scatter, data)
        if self.loads.has_constraints:
            gap = self.loads.w @ u.reshape(-1, 3) - t * self.loads.g  # (n_pts, 3)
            traction = self.alpha * gap + self.lam
            residual += (self.loads.w.T @ traction).ravel()
            energy += 0.5 * self.alpha * float(np.sum(gap * gap)) + float(np.sum(self.lam * gap))
            if tangent:
                np.add.at(data, self.loads.pen_pos, self.alpha * self.loads.pen_val)
        return residual, data, min_det, energy

    def constraint_error(self, u: np.ndarray) -> float:
        """Largest |W u - g| over the prescribed points, mm (0 without constraints)."""
        if not self.loads.has_constraints:
            return 0.0
        gap = self.loads.w_full @ self.model.to_nodes(u) - self.loads.g
        return float(np.sqrt((gap * gap).sum(axis=1)).max())

    def reference_residual(self, du_full: np.ndarray) -> float:
        """|R0|: the norm of the full external load, where the prescribed displacements count
        by the reactions they need in the linearised problem (``du_full`` = K0^-1 load)."""
        r0 = float(np.dot(self.loads.f, self.loads.f))
        if self.loads.has_constraints:
            gap = self.loads.w @ du_full.reshape(-1, 3) - self.loads.g
            reaction = (self.loads.w.T @ (self.alpha * gap)).ravel()
            r0 += float(np.dot(reaction, reaction))
        return float(np.sqrt(r0))


def reference_diagonal_mean(model: FEModel) -> float:
    """Mean diagonal of the tangent at u = 0 (N/mm), cached on the model."""
    if "k0_diag_mean" not in model.cache:
        n_el = model.n_elements
        fe, ke = np.empty((n_el, 24)), np.empty((n_el, 24, 24))
        kernels.element_kernel(np.zeros((model.n_nodes, 3)), model.hexes, model.elem_set,
                               model.grads, model.jw, model.weight, model.mu, model.lam,
                               model.material_id, True, fe, ke, np.empty(n_el), np.empty(n_el))
        data = np.empty(model.nnz)
        kernels.scatter_matrix(ke, model.scatter, data)
        model.cache["k0_diag_mean"] = float(data[model.diag_pos].mean())
    return model.cache["k0_diag_mean"]


def linear_solver(model: FEModel, backend: str) -> LinearSolver:
    """The model's solver for ``backend``, created (and analysed) once and then reused."""
    key = f"solver:{backend}"
    if key not in model.cache:
        model.cache[key] = make_solver(backend, model.indptr, model.indices)
    return model.cache[key]


class _IncrementFailed(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def solve(model: FEModel, loads: Loads,
          settings: SolverSettings | None = None) -> tuple[np.ndarray, SolveReport]:
    """Static equilibrium of ``model`` under ``loads``.

    Returns the displacement (n_nodes, 3) in mm (zero on fixed and unused nodes) and a
    :class:`SolveReport`. Each ``report.log`` entry holds: increment, load (target load
    factor), step (load increment), iteration, residual |R| (N), residual_rel |R|/|R0|,
    du |du| (mm), line_step, min_det_F, mode (linear-solver mode).

    Raises:
        SolverError: no convergence down to ``min_load_step`` or inverted elements, with the
            Newton log attached.
    """
    settings = settings or SolverSettings()
    start = time.perf_counter()
    prepared = prepare_loads(model, loads)
    report = SolveReport(backend="none")
    if prepared.is_zero:
        report.time_s = time.perf_counter() - start
        return np.zeros((model.n_nodes, 3)), report
    system = _System(model, prepared, settings.penalty)
    solver = linear_solver(model, settings.backend)
    report.backend = solver.name
    u = _continuation(system, solver, settings, report)
    u = _enforce_constraints(system, solver, settings, report, u)
    _final_checks(system, settings, report, u)
    report.time_s = time.perf_counter() - start
    return model.to_nodes(u), report


def _continuation(system: _System, solver: LinearSolver, settings: SolverSettings,
                  report: SolveReport) -> np.ndarray:
    """Adaptive load stepping from t = 0 to t = 1; returns the converged free displacement."""
    u = np.zeros(system.model.n_eq)
    t, dt = 0.0, settings.initial_load_step
    last_reason = ""
    while t < 1.0:
        target = 1.0 if t + dt >= 1.0 - 1e-12 else t + dt
        try:
            u, n_it = _newton(system, solver, settings, report, u, t, target)
        except _IncrementFailed as exc:
            last_reason = exc.reason
            dt *= 0.5
            if dt < settings.min_load_step:
                raise SolverError(
                    f"no convergence: the load increment fell below min_load_step "
                    f"({settings.min_load_step:g}) at load factor {t:.4f}; last failure: "
                    f"{last_reason}", "fem.solve", log=report.log) from None
            continue
        report.increments += 1
        t, dt = target, (2.0 * dt if n_it <= EASY_ITERATIONS else dt)
    return u


def _newton(system: _System, solver: LinearSolver, settings: SolverSettings,
            report: SolveReport, u0: np.ndarray, t_prev: float, t: float,
            final: bool | None = None) -> tuple[np.ndarray, int]:
    """Newton iterations at load factor ``t`` from ``u0``; raises _IncrementFailed."""
    final = t >= 1.0 if final is None else final
    tol_r = settings.tol_residual if final else max(settings.tol_residual,
                                                    settings.intermediate_tolerance)
    tol_d = settings.tol_displacement if final else max(settings.tol_displacement,
                                                        settings.intermediate_tolerance)
    u = u0.copy()
    r, data, _, energy = system.evaluate(u, t, tangent=True)
    for it in range(1, settings.max_iterations + 1):
        try:
            solver.factor(data)
            du = -solver.solve(r)
        except FactorizationError as exc:
            raise _IncrementFailed(str(exc)) from None
        if not np.all(np.isfinite(du)):
            raise _IncrementFailed("the linear solve returned NaN")
        if report.reference_residual == 0.0:
            report.reference_residual = system.reference_residual(du / (t - t_prev))
        u, r, data, energy, step, min_det = _line_search(system, settings, u, du, r, energy, t)
        r_norm, du_norm = float(np.linalg.norm(r)), step * float(np.linalg.norm(du))
        r0 = report.reference_residual
        report.iterations += 1
        report.log.append({"increment": report.increments + 1, "load": t, "step": t - t_prev,
                           "iteration": it, "residual": r_norm, "residual_rel": r_norm / r0,
                           "du": du_norm, "line_step": step, "min_det_F": min_det,
                           "mode": solver.last_mode})
        if r_norm <= tol_r * r0 and du_norm <= tol_d * max(float(np.linalg.norm(u)), 1e-300):
            return u, it
    raise _IncrementFailed(f"{settings.max_iterations} Newton iterations without convergence "
                           f"(|R|/|R0| = {report.log[-1]['residual_rel']:.3g})")


def _line_search(system: _System, settings: SolverSettings, u: np.ndarray, du: np.ndarray,
                 r: np.ndarray, energy: float, t: float):
    """Backtrack along du until the state is uninverted and the residual norm or the potential
    energy decreases (Armijo); returns the new state and the accepted step length."""
    r_norm = float(np.linalg.norm(r))
    slope = float(r @ du)  # directional derivative of the potential energy
    step = 1.0
    worst_det = np.inf
    for _ in range(MAX_BACKTRACKS + 1):
        trial = u + step * du
        r_t, data_t, det_t, energy_t = system.evaluate(trial, t, tangent=True)
        worst_det = min(worst_det, det_t)
        finite = np.isfinite(energy_t) and np.all(np.isfinite(r_t))
        if det_t > 0.0 and finite:
            if not settings.line_search:
                return trial, r_t, data_t, energy_t, step, det_t
            decrease = float(np.linalg.norm(r_t)) <= (1.0 - ARMIJO * step) * r_norm
            descent = slope < 0.0 and energy_t <= energy + ARMIJO * step * slope
            if decrease or descent:
                return trial, r_t, data_t, energy_t, step, det_t
        elif not settings.line_search and det_t <= 0.0:
            break
        step *= 0.5
    if worst_det <= 0.0:
        raise _IncrementFailed(f"inverted elements (min det F = {worst_det:.3g}) along the "
                               "Newton direction")
    raise _IncrementFailed("the line search found no decrease of residual or energy")


def _enforce_constraints(system: _System, solver: LinearSolver, settings: SolverSettings,
                         report: SolveReport, u: np.ndarray) -> np.ndarray:
    """Augmented-Lagrangian updates until the prescribed points are within tolerance."""
    for _ in range(10):
        error = system.constraint_error(u)
        report.constraint_error_mm = error
        if error <= settings.constraint_tolerance_mm:
            return u
        gap = system.loads.w @ u.reshape(-1, 3) - system.loads.g
        system.lam += system.alpha * gap
        try:
            u, _ = _newton(system, solver, settings, report, u, 0.0, 1.0, final=True)
        except _IncrementFailed as exc:
            raise SolverError(f"no convergence while enforcing prescribed displacements: "
                              f"{exc.reason}", "fem.solve", log=report.log) from None
    raise SolverError(f"prescribed displacements not met: error {error:.3g} mm > "
                      f"{settings.constraint_tolerance_mm:g} mm", "fem.solve", log=report.log)


def _final_checks(system: _System, settings: SolverSettings, report: SolveReport,
                  u: np.ndarray) -> None:
    r, _, min_det, _ = system.evaluate(u, 1.0, tangent=False)
    report.min_det_F = min_det
    report.residual = float(np.linalg.norm(r))
    report.residual_rel = report.residual / report.reference_residual
    report.max_displacement_mm = float(np.linalg.norm(u.reshape(-1, 3), axis=1).max())
    if min_det <= 0.0 or not np.all(np.isfinite(u)):
        raise SolverError(f"the converged state has inverted elements (min det F = "
                          f"{min_det:.3g})", "fem.solve", log=report.log)
