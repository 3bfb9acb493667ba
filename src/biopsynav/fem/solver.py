"""Newton-Raphson with adaptive load increments and a backtracking line search.

The discrete problem: find free displacements ``u`` with

    R(u, t) = f_int(u) - t f + W^T (alpha (W u - t g) + lam) = 0,

``t`` the load factor (0 -> 1), ``f`` nodal forces, ``W u = g`` the prescribed displacements
enforced by a penalty ``alpha`` (relative to the mean diagonal of the reference stiffness)
plus augmented-Lagrangian multiplier updates ``lam`` until the constraint error is below
``constraint_tolerance_mm``. See ``docs/fem.md``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SolverError
from ..grid.index import HEX_CORNERS
from . import kernels
from .fictitious import fictitious_stiffness
from .linsolve import FactorizationError, LinearSolver, make_solver
from .loads import Loads, PreparedLoads, prepare_loads
from .model import FEModel, upper_rows

EASY_ITERATIONS = 4  # an increment converging within this many iterations doubles the next
REUSE_AFTER = 0.1  # a full Newton iteration cutting |R| by this lets the next reuse its factors
REUSE_CONTRACTION = 0.25  # a reuse iteration must cut |R| by this, else the next is a full one
ARMIJO = 1e-4
MAX_BACKTRACKS = 6
LS_TOLERANCE = 0.25  # accept a step once the energy slope drops to this fraction (Crisfield)
UNSTABLE_EIGENVALUE = 1e-9  # a Jacobi-scaled tangent eigenvalue below minus this: unstable
#: Newton iterations a solve continued from an equilibrium of its loads scaled down may take
#: before it is solved again from rest: a continued solve that converges does so quickly (a
#: 31.4 mm push of UC Davis from its 21.4 mm equilibrium in 22), one that meets a limit
#: point on its path does not (UC Davis as one material: 430 s and no answer, where the
#: same push from rest converged in 26 s; docs/experiments.md)
CONTINUED_BUDGET = 40
EIGEN_SHIFT = -1e-3  # the stability check's shift-invert point, just below zero (scaled)
#: With ``indefinite_tangent = "shift"``: an increment (or a solve at its Newton budget) still
#: converging, its last iteration cutting |R| by REUSE_AFTER or reusing its factors, gets up to
#: this many iterations more (else a solve cut off one or two iterations short of its
#: tolerance starts its last increment again, or goes to the stiffer-spring fallback).
GRACE_ITERATIONS = 6
#: ``indefinite_tangent = "shift"``: the smallest and largest shifts tried, as fractions of
#: each diagonal entry; a solve starts from a tenth of the last shift that factored.
SHIFT_FIRST, SHIFT_LAST = 1e-2, 1e2


#: Elastic contact (``Loads.prescribed_stiffness``) that does not converge is solved again
#: with its springs this many times stiffer, each in turn (inf: the points met). Deep pushes
#: can pass a limit point where a nearly empty cut cell holding contact points turns under
#: soft springs; stiffer springs hold it, at the price of more drag.
SPRING_FALLBACK = (4.0, math.inf)


@dataclass
class SolverSettings:
    """Newton settings (see ``[solver]`` in case.toml). ``max_total_iterations``: give up
    after this many Newton iterations over all increments (0: no limit; data generation sets
    it from ``[dataset] newton_budget``). Elastic contact only: ``first_attempt_budget``, the
    Newton iterations after which the springs as asked give way to their fallbacks (0:
    ``max_total_iterations``), and ``spring_fallback``, the factors of those fallbacks, tried
    in turn (inf: the points met; :data:`SPRING_FALLBACK`); ``elastic_single_precision``,
    whether elastic contact is factored in single precision (faster, but less robust near a
    limit point: springs that converge in double precision may not in single). Data
    generation sets all three. ``indefinite_tangent``: what a Newton iteration does with a
    tangent that is not positive definite: ``shift`` factors ``K + s diag|K|`` with the
    smallest shift ``s`` (1e-2, 1e-1, ...) that makes it so (a descent direction of the
    energy), and lets a solve still converging at its iteration limits finish
    (:data:`GRACE_ITERATIONS`); ``ldlt`` factors the indefinite ``L D L^T`` (a Newton step
    towards any stationary point)."""

    tol_residual: float = 1e-8
    tol_displacement: float = 1e-8
    max_iterations: int = 30
    max_total_iterations: int = 0
    initial_load_step: float = 1.0
    min_load_step: float = 1.0 / 256
    line_search: bool = True
    backend: str = "auto"
    intermediate_tolerance: float = 1e-3
    penalty: float = 1e6
    reuse_factorization: bool = True
    single_precision: bool = True
    threads: int = 0
    constraint_tolerance_mm: float = 1e-4
    first_attempt_budget: int = 0
    spring_fallback: tuple[float, ...] = SPRING_FALLBACK
    elastic_single_precision: bool = False
    indefinite_tangent: str = "ldlt"

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
    #: elastic contact only: how many times stiffer than asked the springs of the answer
    #: are (1: as asked; inf: the points met, see :data:`SPRING_FALLBACK`); None otherwise
    spring_factor: float | None = None
    #: checked only when the last factorisation reported negative pivots (else None)
    lowest_scaled_eigenvalue: float | None = None
    backend: str = ""
    log: list[dict] = field(default_factory=list)
    #: the last converged (load factor, free displacement (n_eq,) mm), or None
    reached: tuple[float, np.ndarray] | None = field(default=None, repr=False)

    def fallback_note(self) -> str:
        """What a user should know of an answer of elastic contact's fallbacks: '' when the
        springs as asked answered (or the solve had no springs), else which fallback did."""
        factor = self.spring_factor
        if factor is None or factor == 1.0:
            return ""
        if math.isinf(factor):
            return ("answered with the contact points met: elastic contact did not converge "
                    "(lesions tend to move too far)")
        return (f"answered with contact springs {factor:g} times stiffer: those asked did not "
                "converge")


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
        self.alpha = _penalty_factor(model, loads, penalty)
        n_pts = loads.w.shape[0] if loads.has_constraints else 0
        self.lam = np.zeros((n_pts, 3))
        self.k0_cacheable = not loads.has_constraints
        self.fictitious = fictitious_stiffness(model)
        self.last_shift = 0.0  # the last diagonal shift that made the tangent definite

    def evaluate(self, u: np.ndarray, t: float, tangent: bool):
        """Residual (n_eq,), tangent upper-CSR data (or None), min det F, potential energy."""
        m = self.model
        u_nodes = m.to_nodes(u)
        kernels.element_kernel(u_nodes, m.hexes, m.elem_set, m.grads, m.jw, m.weight,
                               m.mu, m.lam, m.material_id, tangent, self.fe, self.ke,
                               self.min_det, self.energy)
        min_det = float(self.min_det.min())
        energy = float(self.energy.sum()) - t * float(self.loads.f @ u)
        if self.fictitious is not None:
            fe_f, energy_f = self.fictitious.forces(u_nodes)
            self.fe[self.fictitious.elements] += fe_f
            energy += energy_f
        kernels.scatter_vector(self.fe, m.elem_eq, self.fint)
        residual = self.fint - t * self.loads.f
        data = None
        if tangent:
            data = np.empty(m.nnz)
            kernels.scatter_matrix(self.ke, m.scatter, data)
            if self.fictitious is not None:
                data += self.fictitious.data
        if self.loads.has_constraints:
            gap = self.loads.gap(u_nodes, t)  # (n_pts, 3)
            traction = self.alpha * gap + self.lam
            residual += m.to_free(self.loads.w.T @ traction)
            energy += 0.5 * self.alpha * float(np.sum(gap * gap)) + float(np.sum(self.lam * gap))
            if tangent:
                np.add.at(data, self.loads.pen_pos, self.alpha * self.loads.pen_val)
        return residual, data, min_det, energy

    def constraint_error(self, u: np.ndarray) -> float:
        """Largest |W u - g| over the prescribed points, mm (0 without constraints): with
        elastic contact the largest gap between a point and its target."""
        if not self.loads.has_constraints:
            return 0.0
        gap = self.loads.gap_mm(self.model.to_nodes(u))
        return float(np.sqrt((gap * gap).sum(axis=1)).max())

    def reference_residual(self, du_full: np.ndarray) -> float:
        """|R0|: the norm of the full external load, where the prescribed displacements count
        by the reactions they need in the linearised problem (``du_full`` = K0^-1 load)."""
        r0 = float(np.dot(self.loads.f, self.loads.f))
        if self.loads.has_constraints:
            gap = self.loads.gap(self.model.to_nodes(du_full))
            reaction = self.model.to_free(self.loads.w.T @ (self.alpha * gap))
            r0 += float(np.dot(reaction, reaction))
        return float(np.sqrt(r0))


def _penalty_factor(model: FEModel, loads: PreparedLoads, penalty: float) -> float:
    """The factor of the loads' ``W^T P W``: ``penalty`` times the rest tangent's mean
    diagonal for points that are met, 1 for elastic contact (its springs' stiffness is in
    the rows already), 0 without prescribed points."""
    if not loads.has_constraints:
        return 0.0
    return 1.0 if loads.elastic else penalty * reference_diagonal_mean(model)


def rest_tangent_data(model: FEModel) -> np.ndarray:
    """CSR data (nnz,) of the tangent at u = 0 in the model's pattern, cached on the model."""
    if "k0_data" not in model.cache:
        n_el = model.n_elements
        fe, ke = np.empty((n_el, 24)), np.empty((n_el, 24, 24))
        kernels.element_kernel(np.zeros((model.n_nodes, 3)), model.hexes, model.elem_set,
                               model.grads, model.jw, model.weight, model.mu, model.lam,
                               model.material_id, True, fe, ke, np.empty(n_el), np.empty(n_el))
        data = np.empty(model.nnz)
        kernels.scatter_matrix(ke, model.scatter, data)
        fictitious = fictitious_stiffness(model)
        if fictitious is not None:
            data += fictitious.data
        model.cache["k0_data"] = data
    return model.cache["k0_data"]


def reference_diagonal_mean(model: FEModel) -> float:
    """Mean diagonal of the tangent at u = 0 (N/mm)."""
    return float(rest_tangent_data(model)[model.diag_pos].mean())


def linear_solver(model: FEModel, settings: SolverSettings, single: bool) -> LinearSolver:
    """The model's solver for these settings, created (and analysed) once and then reused."""
    key = f"solver:{settings.backend}:{settings.threads}:{single}"
    if key not in model.cache:
        model.cache[key] = make_solver(settings.backend, model.indptr, model.indices,
                                       settings.threads, single)
    return model.cache[key]


def reference_solver(model: FEModel, settings: SolverSettings) -> LinearSolver:
    """A solver holding the factorisation of the tangent at u = 0 (no penalty), cached on
    the model: the first Newton iteration of every force-loaded solve starts from it."""
    key = f"k0:{settings.backend}:{settings.threads}:{settings.single_precision}"
    if key not in model.cache:
        solver = make_solver(settings.backend, model.indptr, model.indices, settings.threads,
                             settings.single_precision)
        solver.factor(rest_tangent_data(model).copy())
        model.cache[key] = solver
    return model.cache[key]


class _BudgetExhausted(Exception):
    """The solve used ``max_total_iterations`` Newton iterations without converging."""


class _IncrementFailed(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class _NoDecrease(_IncrementFailed):
    """The line search found no step along a descent direction that lowers the energy."""


def solve(model: FEModel, loads: Loads, settings: SolverSettings | None = None,
          start: tuple[float, np.ndarray] | None = None) -> tuple[np.ndarray, SolveReport]:
    """Solve ``loads`` on ``model`` (see :func:`solve_once`); elastic contact that fails
    (within ``settings.first_attempt_budget`` iterations, where set) is solved again with
    stiffer springs (``settings.spring_fallback``, each with ``max_total_iterations``), and
    the report's ``spring_factor`` says which answered. Each stiffer-spring attempt starts
    from the furthest load factor an attempt before it converged at (its state the first
    guess), not from rest. ``start`` (load factor in (0, 1), free displacement (n_eq,) mm):
    an equilibrium of these loads scaled by that factor, where the (first) attempt's load
    stepping begins (``solve_once``'s ``resume_from``), within :data:`CONTINUED_BUDGET`
    Newton iterations; when that attempt fails, the whole solve is done again from rest (the
    path from a continued state can end at a limit point that a solve from rest steps over
    onto another branch). Raises the first SolverError when none does."""
    settings = settings or SolverSettings()
    if start is not None:
        try:
            return solve_once(model, loads, continued_settings(settings), start)
        except SolverError:
            return solve(model, loads, settings)
    if loads.prescribed_stiffness is None:
        return solve_once(model, loads, settings)
    try:
        return solve_once(model, loads, first_attempt_settings(settings))
    except SolverError as first:
        reached = first.reached
        for factor in settings.spring_fallback:
            start = reached if math.isfinite(factor) else None  # points met: from rest
            try:
                u, report = solve_once(model, stiffer_springs(loads, factor), settings, start)
            except SolverError as exc:
                reached = _further(reached, exc.reached)
                continue
            report.spring_factor = factor
            return u, report
        raise first from None


def _further(a: tuple | None, b: tuple | None) -> tuple | None:
    """Of two reached states (load factor, free displacement), the one at the larger load."""
    if a is None or b is None:
        return a if b is None else b
    return a if a[0] >= b[0] else b


def continued_settings(settings: SolverSettings) -> SolverSettings:
    """``settings`` with the Newton budget of a solve continued from an equilibrium of the
    same loads scaled down: at most :data:`CONTINUED_BUDGET` iterations."""
    return _within_budgets(settings, CONTINUED_BUDGET)


def first_attempt_settings(settings: SolverSettings) -> SolverSettings:
    """``settings`` with the Newton budget of elastic contact's first attempt: the smaller
    of ``first_attempt_budget`` and ``max_total_iterations`` where they are set (> 0)."""
    return _within_budgets(settings, settings.first_attempt_budget)


def _within_budgets(settings: SolverSettings, budget: int) -> SolverSettings:
    """``settings`` whose ``max_total_iterations`` is the smaller of it and ``budget``, of
    those set (> 0; 0 where neither is: no budget)."""
    budgets = [b for b in (budget, settings.max_total_iterations) if b > 0]
    return dataclasses.replace(settings, max_total_iterations=min(budgets, default=0))


def stiffer_springs(loads: Loads, factor: float) -> Loads:
    """``loads`` with its springs ``factor`` times stiffer (inf: the points met)."""
    stiffness = None if math.isinf(factor) else factor * np.asarray(loads.prescribed_stiffness)
    return dataclasses.replace(loads, prescribed_stiffness=stiffness)


def solve_once(model: FEModel, loads: Loads, settings: SolverSettings | None = None,
               resume_from: tuple[float, np.ndarray] | None = None
               ) -> tuple[np.ndarray, SolveReport]:
    """Static equilibrium of ``model`` under ``loads``.

    ``resume_from`` (load factor in (0, 1), free displacement (n_eq,) mm), where given: the load
    stepping begins there instead of at rest, the state the first Newton guess (elastic
    contact's fallbacks start from what the springs before them reached; a state of other
    loads is a guess, never an answer).

    Returns the displacement (n_nodes, 3) in mm (zero on fixed and unused nodes) and a
    :class:`SolveReport`. Each ``report.log`` entry holds: increment, load (target load
    factor), step (load increment), iteration, residual |R| (N), residual_rel |R|/|R0|,
    du |du| (mm), line_step, min_det_F, mode (linear-solver mode).

    Raises:
        SolverError: no convergence down to ``min_load_step``, inverted elements, or more
            than ``settings.max_total_iterations`` Newton iterations in all (when > 0), with
            the Newton log and the last converged state (``reached``) attached.
    """
    settings = settings or SolverSettings()
    start = time.perf_counter()
    model.check_anchored()
    prepared = prepare_loads(model, loads)
    report = SolveReport(backend="none", spring_factor=1.0 if prepared.elastic else None)
    if prepared.is_zero:
        report.time_s = time.perf_counter() - start
        return np.zeros((model.n_nodes, 3)), report
    system = _System(model, prepared, settings.penalty)
    # single precision without prescribed points (the penalty's stiff terms need double
    # precision), and for elastic contact only where asked: near a limit point its
    # single-precision factors mislead Newton (docs/contact.md, "Elastic contact")
    single = ((settings.single_precision and not prepared.has_constraints)
              or (prepared.elastic and settings.elastic_single_precision))
    solver = linear_solver(model, settings, single)
    report.backend = solver.name
    if resume_from is not None and 0.0 < resume_from[0] < 1.0:
        report.reference_residual = _rest_reference_residual(system, solver)
    else:
        resume_from = None
    try:
        u = _continuation(system, solver, settings, report, resume_from)
        u = _enforce_constraints(system, solver, settings, report, u)
    except _BudgetExhausted:
        raise SolverError(f"no convergence within max_total_iterations = "
                          f"{settings.max_total_iterations} Newton iterations (|R|/|R0| = "
                          f"{report.log[-1]['residual_rel']:.3g} at load factor "
                          f"{report.log[-1]['load']:.4f})", "fem.solve", log=report.log,
                          reached=report.reached) from None
    except SolverError as exc:
        exc.reached = report.reached
        raise
    _final_checks(system, settings, report, u)
    report.time_s = time.perf_counter() - start
    return model.to_nodes(u), report


def _rest_reference_residual(system: _System, solver: LinearSolver) -> float:
    """|R0| of ``system`` (see :meth:`_System.reference_residual`), from one linear solve
    at rest: what the first Newton iteration of a solve from rest computes on the way."""
    r, data, _, _ = system.evaluate(np.zeros(system.model.n_eq), 1.0, tangent=True)
    _factor(solver, data)
    return system.reference_residual(_solve(solver, r))


def _continuation(system: _System, solver: LinearSolver, settings: SolverSettings,
                  report: SolveReport, resume_from: tuple[float, np.ndarray] | None = None
                  ) -> np.ndarray:
    """Adaptive load stepping to t = 1 from rest, or from ``resume_from`` (load factor, free
    displacement); returns the converged free displacement and keeps the last converged
    state in ``report.reached``."""
    u = np.zeros(system.model.n_eq)
    u_back, t_back = u, 0.0  # the converged state before u, for the secant predictor
    t, dt = 0.0, settings.initial_load_step
    if resume_from is not None:  # the secant predictor then extrapolates from rest through it
        t, u = float(resume_from[0]), np.array(resume_from[1], dtype=float)
    last_reason = ""
    while t < 1.0:
        target = 1.0 if t + dt >= 1.0 - 1e-12 else t + dt
        guess = u + (target - t) / (t - t_back) * (u - u_back) if t > 0.0 else u
        try:
            u_new, n_it = _newton(system, solver, settings, report, guess, t, target, base=u)
        except _IncrementFailed as exc:
            last_reason = exc.reason
            dt = 0.5 * (target - t)  # the step tried, not the nominal one: clipped at t = 1,
            # halving a doubled dt would try the same target again
            if dt < settings.min_load_step:
                raise SolverError(
                    f"no convergence: the load increment fell below min_load_step "
                    f"({settings.min_load_step:g}) at load factor {t:.4f}; last failure: "
                    f"{last_reason}", "fem.solve", log=report.log) from None
            continue
        report.increments += 1
        u_back, t_back, u = u, t, u_new
        t, dt = target, (2.0 * dt if n_it <= EASY_ITERATIONS else dt)
        report.reached = (t, u)
    return u


def _newton(system: _System, solver: LinearSolver, settings: SolverSettings,
            report: SolveReport, u0: np.ndarray, t_prev: float, t: float,
            final: bool | None = None, base: np.ndarray | None = None
            ) -> tuple[np.ndarray, int]:
    """Newton iterations at load factor ``t`` from the guess ``u0`` (``base``, the last
    converged state, when the guess inverts an element); raises _IncrementFailed.

    A full iteration factors the tangent at the current state (at rest, the model's cached
    reference factorisation) and line-searches. Once a full iteration has cut |R| by
    ``REUSE_AFTER`` (the quadratic regime), further iterations reuse that factorisation
    (modified Newton: one solve and one force evaluation each) as long as each cuts |R| by
    ``REUSE_CONTRACTION``; otherwise the next iteration is a full one again."""
    final = t >= 1.0 if final is None else final
    tol_r = settings.tol_residual if final else max(settings.tol_residual,
                                                    settings.intermediate_tolerance)
    tol_d = settings.tol_displacement if final else max(settings.tol_displacement,
                                                        settings.intermediate_tolerance)
    u = u0.copy()
    at_rest = system.k0_cacheable and not np.any(u)
    r, data, det, energy = system.evaluate(u, t, tangent=not at_rest)
    if (det <= 0.0 or not np.isfinite(energy)) and base is not None:
        u = base.copy()
        r, data, det, energy = system.evaluate(u, t, tangent=True)
    active, reuse, min_det, it, converging = solver, False, det, 0, False
    grace = _grace(settings)
    while it < settings.max_iterations or (converging and it < settings.max_iterations + grace):
        it += 1
        r_before = float(np.linalg.norm(r))
        state = _reuse_step(system, active, u, r, t) if reuse else None
        if state is not None:
            u, r, energy, min_det, du_norm = state
            step, mode, data = 1.0, "reuse", None
        else:
            if at_rest and it == 1:
                active, mode = reference_solver(system.model, settings), "k0-cached"
            else:
                if data is None:
                    r, data, _, energy = system.evaluate(u, t, tangent=True)
                active = solver
                mode = _factor_tangent(system, active, settings, data)
            du = _solve(active, r)
            if report.reference_residual == 0.0:
                report.reference_residual = system.reference_residual(du / (t - t_prev))
            try:
                u, r, energy, step, min_det = _line_search(system, settings, u, du, r,
                                                           energy, t)
                data = None  # the new state's tangent: evaluated when the next step factors
            except _NoDecrease:
                # at the residual's round-off floor (docs/fem.md, "Newton strategy")?
                rel = r_before / report.reference_residual
                if rel > math.sqrt(tol_r):
                    raise
                if not _small_step(float(np.linalg.norm(du)), u, tol_d):
                    raise _stalled(rel, tol_r) from None
                _log_iteration(report, (t, t_prev, it), r_before,
                               (float(np.linalg.norm(du)), 0.0, min_det, "floor"))
                return u, it
            du_norm = step * float(np.linalg.norm(du))
        r_norm = float(np.linalg.norm(r))
        reuse = settings.reuse_factorization and r_norm <= (
            REUSE_CONTRACTION if mode == "reuse" else REUSE_AFTER) * r_before
        converging = mode == "reuse" or r_norm <= REUSE_AFTER * r_before
        _log_iteration(report, (t, t_prev, it), r_norm, (du_norm, step, min_det, mode))
        if r_norm <= tol_r * report.reference_residual and _small_step(du_norm, u, tol_d):
            return u, it
        if _budget_spent(settings.max_total_iterations, report.iterations,
                         grace if converging else 0):
            raise _BudgetExhausted
    raise _IncrementFailed(f"{it} Newton iterations without convergence "
                           f"(|R|/|R0| = {report.log[-1]['residual_rel']:.3g})")


def _grace(settings: SolverSettings) -> int:
    """The iterations a still-converging increment or solve gets past its limits."""
    return GRACE_ITERATIONS if settings.indefinite_tangent == "shift" else 0


def _budget_spent(budget: int, iterations: int, grace: int) -> bool:
    """Whether a solve with the Newton ``budget`` (0: none) stops after ``iterations``: at
    the budget plus ``grace`` (the iterations more a still-converging solve gets, else 0)."""
    return 0 < budget and iterations >= budget + grace


def _small_step(du_norm: float, u: np.ndarray, tol_d: float) -> bool:
    """Whether a correction of norm ``du_norm`` (mm) is within ``tol_d`` of ``|u|``."""
    return du_norm <= tol_d * max(float(np.linalg.norm(u)), 1e-300)


def _stalled(residual_rel: float, tol_r: float) -> _IncrementFailed:
    """An increment whose line search found no lower energy with the residual already near
    its round-off floor, above the tolerance ``tol_r``."""
    return _IncrementFailed(
        f"the residual stalled at {residual_rel:.3g} of |R0|, near its round-off floor and "
        f"above the tolerance {tol_r:g} (looser [solver] tol_residual / tol_displacement "
        "converge)")


def _log_iteration(report: SolveReport, where: tuple[float, float, int], r_norm: float,
                   step: tuple[float, float, float, str]) -> None:
    """Count one Newton iteration and log it (``where``: load factor, previous load factor,
    iteration; ``step``: |du| mm, line step, min det F, linear-solver mode or ``floor``)."""
    (t, t_prev, it), (du_norm, line_step, min_det, mode) = where, step
    report.iterations += 1
    report.log.append({"increment": report.increments + 1, "load": t, "step": t - t_prev,
                       "iteration": it, "residual": r_norm,
                       "residual_rel": r_norm / report.reference_residual, "du": du_norm,
                       "line_step": line_step, "min_det_F": min_det, "mode": mode})


def _factor(solver: LinearSolver, data: np.ndarray) -> None:
    try:
        solver.factor(data)
    except FactorizationError as exc:
        raise _IncrementFailed(str(exc)) from None


def _factor_tangent(system: _System, solver: LinearSolver, settings: SolverSettings,
                    data: np.ndarray) -> str:
    """Factor the tangent ``data`` for a Newton step; returns the mode logged: the backend's
    (``spd``, ``indefinite(k neg)``, ...) or ``shifted(s)`` (``settings.indefinite_tangent``
    is ``shift`` and the tangent is not positive definite: ``K + s diag|K|`` factored, with
    the smallest tried shift ``s`` that is; the backend's own indefinite factorisation when
    none up to SHIFT_LAST is)."""
    if settings.indefinite_tangent == "ldlt" or not solver.tests_definiteness:
        _factor(solver, data)
        return solver.last_mode
    try:
        solver.factor(data, definite=True)
        return solver.last_mode
    except FactorizationError:
        pass
    diagonal = system.model.diag_pos
    scale = np.abs(data[diagonal])
    shift = max(SHIFT_FIRST, 0.1 * system.last_shift)
    while shift <= SHIFT_LAST:
        shifted = data.copy()
        shifted[diagonal] += shift * scale
        try:
            solver.factor(shifted, definite=True)
        except FactorizationError:
            shift *= 10.0
            continue
        system.last_shift = shift
        return f"shifted({shift:g})"
    _factor(solver, data)
    return solver.last_mode


def _solve(solver: LinearSolver, r: np.ndarray) -> np.ndarray:
    try:
        du = -solver.solve(r)
    except FactorizationError as exc:
        raise _IncrementFailed(str(exc)) from None
    if not np.all(np.isfinite(du)):
        raise _IncrementFailed("the linear solve returned NaN")
    return du


def _reuse_step(system: _System, solver: LinearSolver, u: np.ndarray, r: np.ndarray, t: float):
    """A modified-Newton step with the last factorisation; None unless it keeps every
    element uninverted and cuts |R| by REUSE_CONTRACTION."""
    du = _solve(solver, r)
    trial = u + du
    r_t, _, det_t, energy_t = system.evaluate(trial, t, tangent=False)
    if det_t <= 0.0 or not np.isfinite(energy_t):
        return None
    if float(np.linalg.norm(r_t)) > REUSE_CONTRACTION * float(np.linalg.norm(r)):
        return None
    return trial, r_t, energy_t, det_t, float(np.linalg.norm(du))


def _line_search(system: _System, settings: SolverSettings, u: np.ndarray, du: np.ndarray,
                 r: np.ndarray, energy: float, t: float):
    """Step length along ``du``: the full Newton step when it keeps every element uninverted
    and the energy's slope ``g(s) = R(u + s du) . du`` drops to half its initial size or
    stays negative; else a safeguarded secant search on ``g`` (Crisfield), bisecting away
    from inverted states. Without ``settings.line_search`` only inversion shortens the step.
    Returns (u, R, energy, step, min det F) of the accepted state; trials evaluate no
    tangent: the caller evaluates the accepted state's only when the next iteration factors
    one (not for a modified Newton iteration, nor at convergence)."""
    g0 = float(r @ du)
    if g0 >= 0.0:  # not a descent direction (indefinite tangent): backtrack on |R|
        return _backtrack_residual(system, u, du, r, t)
    lo, hi = (0.0, g0), None
    step = 1.0
    best = None
    worst_det = np.inf
    for k in range(MAX_BACKTRACKS + 1):
        trial = u + step * du
        r_t, _, det_t, energy_t = system.evaluate(trial, t, tangent=False)
        worst_det = min(worst_det, det_t)
        if det_t <= 0.0 or not (np.isfinite(energy_t) and np.all(np.isfinite(r_t))):
            hi = None
            step = 0.5 * (lo[0] + step)
            continue
        g = float(r_t @ du)
        lower = energy_t <= energy + 1e-12 * abs(energy)
        if lower and (best is None or abs(g) < abs(best[0])):
            best = (g, step, trial, r_t, energy_t, det_t)
        if not settings.line_search or (lower and (abs(g) <= LS_TOLERANCE * abs(g0)
                                                   or (k == 0 and g < 0.0))):
            break
        if g < 0.0:
            lo = (step, g)
        else:
            hi = (step, g)
        if hi is None:
            step = 0.5 * (lo[0] + step)
            continue
        secant = lo[0] - lo[1] * (hi[0] - lo[0]) / (hi[1] - lo[1])
        width = hi[0] - lo[0]
        step = min(max(secant, lo[0] + 0.1 * width), hi[0] - 0.1 * width)
    if best is None:
        if worst_det <= 0.0:
            raise _IncrementFailed(f"inverted elements (min det F = {worst_det:.3g}) along "
                                   "the Newton direction")
        raise _NoDecrease("the line search found no decrease of the energy")
    _, step, trial, r_t, energy_t, det_t = best
    return trial, r_t, energy_t, step, det_t


def _backtrack_residual(system: _System, u: np.ndarray, du: np.ndarray, r: np.ndarray,
                        t: float):
    """Halve the step until the residual norm decreases on an uninverted state: (u, R,
    energy, step, min det F) of it, as :func:`_line_search` (no tangent evaluated)."""
    r_norm = float(np.linalg.norm(r))
    step, worst_det = 1.0, np.inf
    for _ in range(MAX_BACKTRACKS + 1):
        trial = u + step * du
        r_t, _, det_t, energy_t = system.evaluate(trial, t, tangent=False)
        worst_det = min(worst_det, det_t)
        if det_t > 0.0 and np.isfinite(energy_t) and \
                float(np.linalg.norm(r_t)) <= (1.0 - ARMIJO * step) * r_norm:
            return trial, r_t, energy_t, step, det_t
        step *= 0.5
    if worst_det <= 0.0:
        raise _IncrementFailed(f"inverted elements (min det F = {worst_det:.3g}) along the "
                               "Newton direction")
    raise _IncrementFailed("no decrease of the residual along a non-descent direction")


def _enforce_constraints(system: _System, solver: LinearSolver, settings: SolverSettings,
                         report: SolveReport, u: np.ndarray) -> np.ndarray:
    """Augmented-Lagrangian updates until the prescribed points are within tolerance (none
    for elastic contact, whose gap is part of the answer)."""
    for _ in range(10):
        error = system.constraint_error(u)
        report.constraint_error_mm = error
        if error <= settings.constraint_tolerance_mm or system.loads.elastic:
            return u
        system.lam += system.alpha * system.loads.gap(system.model.to_nodes(u))
        try:
            u, _ = _newton(system, solver, settings, report, u, 0.0, 1.0, final=True)
        except _IncrementFailed as exc:
            raise SolverError(f"no convergence while enforcing prescribed displacements: "
                              f"{exc.reason}", "fem.solve", log=report.log) from None
    raise SolverError(f"prescribed displacements not met after 10 augmented-Lagrangian "
                      f"updates: error {error:.3g} mm > {settings.constraint_tolerance_mm:g} mm "
                      "([solver] constraint_tolerance_mm; the default, 0.01 mm, is far below "
                      "the discretisation error)", "fem.solve", log=report.log)


def _final_checks(system: _System, settings: SolverSettings, report: SolveReport,
                  u: np.ndarray) -> None:
    r, _, min_det, _ = system.evaluate(u, 1.0, tangent=False)
    report.min_det_F = min_det
    report.residual = float(np.linalg.norm(r))
    report.residual_rel = report.residual / report.reference_residual
    report.max_displacement_mm = float(np.linalg.norm(system.model.to_nodes(u), axis=1).max())
    if min_det <= 0.0 or not np.all(np.isfinite(u)):
        raise SolverError(f"the converged state has inverted elements (min det F = "
                          f"{min_det:.3g})", "fem.solve", log=report.log)
    last = report.log[-1]["increment"] if report.log else 0
    modes = [e["mode"] for e in report.log if e["increment"] == last and e["mode"] != "reuse"]
    if modes and modes[-1].startswith(("indefinite", "shifted")):
        lowest = lowest_scaled_eigenvalue(system, u, settings)
        report.lowest_scaled_eigenvalue = lowest
        if lowest < -UNSTABLE_EIGENVALUE:
            raise SolverError(f"the solve converged to an unstable equilibrium (tangent "
                              f"{modes[-1]}, lowest Jacobi-scaled eigenvalue {lowest:.3g}): "
                              "the load is past the structure's stability limit", "fem.solve",
                              log=report.log)


def lowest_scaled_eigenvalue(system: _System, u: np.ndarray,
                             settings: SolverSettings | None = None) -> float:
    """The lowest eigenvalue of the Jacobi-scaled tangent ``D^-1/2 K D^-1/2`` at ``u`` (free
    equations, penalty included), by shift-invert Lanczos just below zero, the shifted matrix
    factored by ``settings``' backend (Pardiso where installed; the upper triangle, the
    model's pattern).

    Scaling keeps the inertia (Sylvester) and makes the answer independent of units and of the
    tiny stiffness of nodes in thinly cut cells. Used to confirm an instability when the
    factorisation reports negative pivots: on tangents conditioned as the penalty and thin
    cut cells make them (1e9 and beyond), a symmetric-indefinite factorisation with pivot
    perturbation can report a negative pivot of a positive definite matrix."""
    from scipy.sparse.linalg import LinearOperator, eigsh

    from .linsolve import full_matrix

    settings = settings or SolverSettings()
    m = system.model
    _, data, _, _ = system.evaluate(u, 1.0, tangent=True)
    scale = 1.0 / np.sqrt(np.abs(data[m.diag_pos]))
    scaled = data * scale[upper_rows(m)] * scale[m.indices]
    shifted = scaled.copy()
    shifted[m.diag_pos] -= EIGEN_SHIFT
    solver = make_solver(settings.backend, m.indptr, m.indices, settings.threads)
    try:
        solver.factor(shifted)
    except FactorizationError:  # singular: an eigenvalue at the shift itself
        return EIGEN_SHIFT
    n = m.n_eq
    inverse = LinearOperator((n, n), matvec=lambda x: solver.solve(np.ravel(x)), dtype=float)
    vals = eigsh(full_matrix(m.indptr, m.indices, scaled), k=1, sigma=EIGEN_SHIFT, which="LM",
                 OPinv=inverse, return_eigenvectors=False)
    return float(vals[0])


def internal_forces(model: FEModel, u: np.ndarray) -> np.ndarray:
    """Internal nodal forces (n_nodes, 3) N at displacement ``u`` (n_nodes, 3) mm, on every
    node (on fixed nodes they are the support reactions)."""
    n_el = model.n_elements
    fe = np.empty((n_el, 24))
    u = np.ascontiguousarray(u, dtype=np.float64)
    kernels.element_kernel(u, model.hexes, model.elem_set, model.grads, model.jw, model.weight,
                           model.mu, model.lam, model.material_id, False, fe,
                           np.empty((1, 24, 24)), np.empty(n_el), np.empty(n_el))
    fictitious = fictitious_stiffness(model)
    if fictitious is not None:
        fe[fictitious.elements] += fictitious.forces(u)[0]
    out = np.zeros((model.n_nodes, 3))
    np.add.at(out, model.hexes, fe.reshape(n_el, 8, 3))
    return out


def smallest_det_f(model: FEModel, u: np.ndarray) -> np.ndarray:
    """Smallest ``det F`` (n_el,) over each element's Gauss points at displacement ``u``
    (n_nodes, 3) mm: at or below 0 the element is inverted there (its energy undefined)."""
    n_el = model.n_elements
    min_det = np.empty(n_el)
    kernels.element_kernel(np.ascontiguousarray(u, dtype=np.float64), model.hexes,
                           model.elem_set, model.grads, model.jw, model.weight, model.mu,
                           model.lam, model.material_id, False, np.empty((n_el, 24)),
                           np.empty((1, 24, 24)), min_det, np.empty(n_el))
    return min_det


#: The 12 edges of a hexahedron, as pairs of its corners (VTK order).
HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64)


def largest_edge_stretch(model: FEModel, u: np.ndarray,
                         elements: np.ndarray | None = None) -> float:
    """The largest ratio of deformed to rest length over every edge of every element (or of
    the elements selected by ``elements``, (n_el,) bool) at displacement ``u`` (n_nodes, 3) mm
    (1 at rest)."""
    stretches = edge_stretches(model, u)
    stretches = stretches if elements is None else stretches[elements]
    return float(stretches.max()) if len(stretches) else 1.0


def edge_stretches(model: FEModel, u: np.ndarray) -> np.ndarray:
    """(n_el,) the largest ratio of deformed to rest length over each element's 12 edges at
    displacement ``u`` (n_nodes, 3) mm (1 at rest)."""
    a, b = model.hexes[:, HEX_EDGES[:, 0]], model.hexes[:, HEX_EDGES[:, 1]]
    rest = np.linalg.norm(model.nodes[b] - model.nodes[a], axis=2)
    x = model.nodes + u
    return (np.linalg.norm(x[b] - x[a], axis=2) / rest).max(axis=1)


def tangent_matrix(model: FEModel, u: np.ndarray):
    """The full symmetric tangent (n_eq, n_eq) N/mm (CSR) at displacement ``u`` (n_nodes, 3)."""
    from .linsolve import full_matrix

    system = _System(model, prepare_loads(model, Loads()), 0.0)
    _, data, _, _ = system.evaluate(model.to_free(u), 0.0, tangent=True)
    return full_matrix(model.indptr, model.indices, data)


def compile_kernels() -> None:
    """Compile the numba kernels, or load them from numba's on-disk cache, by one solve on a
    one-cell model (a 1 mm cube on a fixed base, pressed by 0.1 mN). A process that starts
    several others at once (a test run on several workers) calls it first: they then load the
    kernels instead of each compiling its own at the same time."""
    nodes = HEX_CORNERS.astype(np.float64)
    forces = np.zeros((8, 3))
    forces[nodes[:, 2] == 1.0, 2] = -1e-4 / 4
    model = FEModel(nodes, np.arange(8)[None, :], 1.0, 0.005, 0.45, nodes[:, 2] == 0.0)
    solve(model, Loads(forces=forces))
