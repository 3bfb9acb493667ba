"""What a worker does: build the FE model of a case once, then compute samples on request.

Runs in local worker processes (set up by :func:`init_process`, task
:func:`process_sample`) and in Dask workers (task :func:`dask_sample`, the context cached per
worker thread). Workers never touch the store: they return plain arrays and the main process
writes them.

Kept free of heavy imports at module level so that a spawned process can set its thread
limits before numba and MKL load.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Why a draw was not kept (``kind`` of its failure record): its solve did not converge, it
#: pushed deeper than ``[probe] max_push_mm``, or its solution stretches a cell edge beyond
#: ``[dataset] max_edge_stretch``.
NOT_CONVERGED, TOO_DEEP, IMPLAUSIBLE = "not_converged", "too_deep", "implausible"

@dataclass
class WorkerSpec:
    """Everything a worker needs, picklable: the loaded case and the protocol key."""

    case: Any  # biopsynav.case.Case
    key: str  # fingerprint + protocol fingerprint: identifies the cached context


class SampleContext:
    """Per-worker precomputation: the teacher FE model, solver settings, skin embeddings,
    eligible centres, and the contact compliance of the elastic contact input (``Z`` of the
    candidate dofs).

    Attributes:
        teacher: the :class:`~biopsynav.fem.teacher.Teacher` (its model's linear-solver
            analysis is cached on it): the case grid's FE model, or a finer grid's.
        model: the teacher's :class:`biopsynav.fem.FEModel`.
        skin: CSR (n_vertices, n_nodes) trilinear embedding of every skin vertex in the case
            grid (the network input; the teacher's own when it solves on the case grid).
        case_skin: that :class:`~biopsynav.grid.embedding.Embedding` itself (the loads of
            an extrapolating teacher's case-grid solve).
        pinned: (n_vertices,) skin a rigid push may not hold (:func:`biopsynav.probe.pinned_skin`).
        centers: (k,) skin vertices that may centre a push.
        skin_areas: (n_vertices,) mm^2, the skin area each vertex stands for (the springs of
            elastic contact).
        case_e_mpa: (n_active_cells,) MPa, the case grid's element moduli (the springs of the
            input of elastic rigid pushes).
    """

    def __init__(self, case: Any) -> None:
        from ..contact.constraints import vertex_areas
        from ..contact.springs import case_young_moduli
        from ..fem.teacher import build_teacher
        from ..grid.embedding import surface_embedding
        from ..probe import eligible_centers, pinned_skin

        self.case = case
        self.teacher = build_teacher(case)
        self.model = self.teacher.model
        self.settings = sample_solver_settings(case)
        skin = (self.teacher.skin if self.teacher.transfer is None
                else surface_embedding(case.grid, case.anatomy))
        self.skin, self.case_skin = skin.matrix, skin
        self.pinned = pinned_skin(case.grid.fixed_nodes, skin.nodes)
        self.centers = eligible_centers(case.anatomy, case.cfg.probe.min_chest_distance_mm)
        self.skin_areas = vertex_areas(case.anatomy.vertices, case.anatomy.faces)
        self.case_e_mpa = case_young_moduli(case)
        self.node_shape = case.grid.node_shape
        self.active = np.asarray(case.grid.active_nodes, dtype=bool).ravel()
        self.contact_input = case.cfg.dataset.contact_input
        self.compliance = None
        if self.contact_input == "elastic":
            from ..contact.greens import ContactCompliance

            self.compliance = ContactCompliance.from_case(case)
        self.converged = converged_teacher(case)


def converged_teacher(case: Any) -> Any:
    """The solver of ``[dataset] teacher`` when it is not the grid FE
    (:mod:`biopsynav.teacher_registry`), else None."""
    from ..teacher_registry import builder_or_none

    builder = builder_or_none(case.cfg.dataset.teacher)
    return None if builder is None else builder(case)


def sample_solver_settings(case: Any) -> Any:
    """The solver settings of data generation's solves (a sample's, a force calibration's):
    ``[solver]`` on one thread (parallel over solves; one thread keeps the bits the same
    whatever the worker count) with the Newton budget ``[dataset] newton_budget``."""
    from ..fem import SolverSettings

    settings = SolverSettings.from_config(case.cfg.solver)
    settings.threads = 1
    settings.max_total_iterations = int(case.cfg.dataset.newton_budget)
    return settings


#: Same-place redraws of a too-deep training push (``[probe] too_deep_redraw``) before the
#: attempt is given up as too deep (the next attempt draws a new place).
MAX_SAME_PLACE_REDRAWS = 8


def compute_sample(ctx: SampleContext, index: int, attempt: int) -> dict:
    """Draw, solve and package sample ``index`` (draw ``attempt``), a too-deep training push
    redrawn at the same place (``[probe] too_deep_redraw = "same-place"``) within the same call.

    Returns a dict with ``index``, ``attempt``, ``redraw`` (same-place redraws before it),
    ``ok``, ``too_deep_before`` (the results of those redraws' too-deep draws); when ok:
    ``inputs`` (4, nx, ny, nz) float32, ``targets`` (3, nx, ny, nz) float32 and the
    per-sample metadata; when the draw was not kept: ``kind`` (:data:`NOT_CONVERGED`,
    :data:`TOO_DEEP` or :data:`IMPLAUSIBLE`), ``error`` (message) and ``diagnostics`` (last
    Newton iterations; empty for a push that was solved).
    """
    from ..probe import push_for_sample, weaker_push

    cfg = ctx.case.cfg
    training = index < cfg.dataset.n_train
    push = push_for_sample(ctx.case.anatomy, cfg.probe, cfg.dataset.seed, index, attempt,
                           ctx.centers, pinned=ctx.pinned, training=training)
    result, before = solve_draw(ctx, push, index, 0), []
    while redraws_here(ctx, result, training) and len(before) < MAX_SAME_PLACE_REDRAWS:
        before.append(result)
        push = weaker_push(push, cfg.probe, cfg.dataset.seed, index, len(before))
        result = solve_draw(ctx, push, index, len(before))
    result["too_deep_before"] = before
    return result


def redraws_here(ctx: SampleContext, result: dict, training: bool) -> bool:
    """Whether ``result`` is a too-deep training force patch that ``[probe] too_deep_redraw``
    redraws at the same place."""
    return (training and not result["ok"] and result["kind"] == TOO_DEEP
            and result["force_n"] > 0.0 and ctx.case.cfg.probe.too_deep_redraw == "same-place")


def solve_draw(ctx: SampleContext, push: Any, index: int, redraw: int) -> dict:
    """Solve and package one draw ``push`` of sample ``index`` (``redraw``: its same-place
    redraws before it); the dict of :func:`compute_sample` without ``too_deep_before``."""
    from ..errors import SolverError

    contact, loaded = ctx.skin[push.contact], ctx.teacher.skin.matrix[push.contact]
    start = time.perf_counter()
    result: dict[str, Any] = {"index": int(index), "attempt": int(push.attempt),
                              "redraw": int(redraw), **push_metadata(push)}
    if ctx.converged is not None:
        return converged_draw(ctx, push, result, start)
    try:  # an extrapolating teacher's case grid first: it costs a fraction of the fine solve
        u_case = case_grid_solution(ctx, push)
        rejected = case_grid_rejection(ctx, u_case)
        if rejected is not None:
            return rejected_result(result, rejected,
                                   probe_displacement(face_motion(ctx, push, contact @ u_case)), 0,
                                   start)
        u, report = teacher_solution(ctx, push, loaded)
    except SolverError as exc:
        return not_converged(result, exc, start, push)
    contact_u = np.asarray(loaded @ u)
    probe_disp = probe_displacement(face_motion(ctx, push, contact_u))
    rejected = solved_rejection(ctx, push, probe_disp, u)
    if rejected is None:
        # a rigid push's contact points move by the push itself, which the case grid can hold
        # (docs/experiments.md, "A finer teacher"); a force patch's differ point by point
        u = ctx.teacher.case_field(u, (contact, contact_u) if push.rigid else None, u_case,
                                   ctx.case.cfg.dataset.max_edge_stretch)
        rejected = extrapolation_rejection(ctx, u, u_case)
    if rejected is not None:
        return rejected_result(result, rejected, probe_disp, report.iterations, start)
    # the input from the stored field at the contact points (a refined teacher's field as
    # fitted to the case grid; on the case grid, contact_u itself), so that training
    # rebuilds it from the target
    return kept_result(ctx, push, result, u, probe_disp, report.iterations,
                       report.residual_rel, start)


def converged_draw(ctx: SampleContext, push: Any, result: dict, start: float) -> dict:
    """``result`` (the draw's record, started at ``start``, ``time.perf_counter`` s) with
    ``push`` answered by the teacher of ``[dataset] teacher`` (:attr:`SampleContext.
    converged`), its field on the case grid: kept unless it is not answered (recorded as
    :data:`NOT_CONVERGED`) or stretches a case-grid cell beyond ``[dataset]
    max_edge_stretch``. Its Newton iterations are not counted (``newton_iters`` and
    ``residual`` 0)."""
    from ..errors import SolverError

    contact = ctx.skin[push.contact]
    try:
        field = ctx.converged.solve(push)
    except SolverError as exc:
        return not_converged(result, exc, start, push)
    probe_disp = probe_displacement(face_motion(ctx, push, contact @ field))
    why = implausible(ctx.model, field, ctx.case.cfg.dataset.max_edge_stretch)
    if why:
        return rejected_result(result, (IMPLAUSIBLE, why), probe_disp, 0, start)
    return kept_result(ctx, push, result, field, probe_disp, 0, 0.0, start)


def kept_result(ctx: SampleContext, push: Any, result: dict, u: np.ndarray,
                probe_disp: float, iterations: int, residual: float, start: float) -> dict:
    """``result`` of a kept draw: the network input built from the case-grid field ``u``
    (n_nodes, 3) mm at the contact points, the target ``u``, and the per-sample record."""
    from ..grid.index import field_to_tensor
    from ..probe import contact_input

    contact = ctx.skin[push.contact]
    node_disp = np.linalg.norm(u, axis=1)
    result.update(
        ok=True,
        inputs=field_to_tensor(contact_input(contact, face_motion(ctx, push, contact @ u),
                                             ctx.contact_input, ctx.compliance,
                                             input_springs(ctx, push)),
                               ctx.node_shape).astype(np.float32),
        targets=field_to_tensor(u, ctx.node_shape).astype(np.float32),
        max_disp_mm=float(node_disp.max()),
        mean_disp_mm=float(node_disp[ctx.active].mean()),
        probe_disp_mm=probe_disp,
        newton_iters=int(iterations),
        residual=float(residual),
        solve_s=float(time.perf_counter() - start),
    )
    return result


def teacher_solution(ctx: SampleContext, push: Any, loaded: Any) -> tuple[np.ndarray, Any]:
    """``push`` solved on the teacher's grid: (n_model_nodes, 3) mm and the solve report;
    ``loaded``: the contact points' embedding in that grid (CSR (n, n_model_nodes)) that a
    force patch loads; raises SolverError."""
    from ..fem import Loads, solve
    from ..probe import nodal_forces

    if push.rigid:
        return solve(ctx.model, rigid_push_loads(ctx, push), rigid_push_settings(ctx))
    return solve(ctx.model, Loads(forces=nodal_forces(loaded, push.force)), ctx.settings)


def rejected_result(result: dict, rejected: tuple[str, str], probe_disp: float,
                    iterations: int, start: float) -> dict:
    """``result`` marked as a draw that was solved and not kept: ``rejected`` (kind,
    message), its probe displacement mm, the teacher's Newton iterations (0 when only the
    case grid solved it), started at ``start`` (``time.perf_counter`` s)."""
    result.update(ok=False, kind=rejected[0], error=rejected[1], probe_disp_mm=probe_disp,
                  solve_s=time.perf_counter() - start, diagnostics=[],
                  newton_iters=int(iterations))
    return result


#: A rigid push's Newton budget, in multiples of ``[dataset] newton_budget``: held contact
#: points add augmented-Lagrangian updates, and a displacement-controlled push has no limit
#: load whose neighbourhood the budget is meant to cut short.
RIGID_BUDGET_FACTOR = 4


def rigid_push_loads(ctx: SampleContext, push: Any, skin: Any = None) -> Any:
    """The loads of a rigid push on the teacher's grid (or on the grid of the embedding
    ``skin``): the contact points moved by ``push.displacement`` through the constraints of
    ``[tracker] fem_contact`` (as the FE tracker holds them)."""
    from ..contact.constraints import constraint_rows, contact_springs
    from ..fem import Loads

    on_case_grid = skin is not None
    skin = ctx.teacher.skin if skin is None else skin
    model, grid = ((ctx.teacher.coarse, ctx.case.grid) if on_case_grid
                   else (ctx.model, ctx.teacher.grid))
    tracker = ctx.case.cfg.tracker
    cells = skin.cells[push.contact]
    rows = constraint_rows(tracker.fem_contact, cells)
    springs = contact_springs(tracker.fem_contact, tracker.contact_stiffness, model.E_mpa,
                              grid, cells, ctx.skin_areas[push.contact])
    target = np.broadcast_to(push.displacement, (len(push.contact), 3))
    return Loads(prescribed_matrix=rows @ skin.matrix[push.contact],
                 prescribed_displacement=rows @ target, prescribed_stiffness=springs)


def not_converged(result: dict, exc: Any, start: float, push: Any) -> dict:
    """``result`` marked as a draw whose solve raised the SolverError ``exc`` (started at
    ``start``, ``time.perf_counter`` s), with the last Newton iterations and, for a rigid
    ``push``, its depth (``push_mm``: what sets a rigid push's cost)."""
    result.update(ok=False, kind=NOT_CONVERGED, error=exc.what,
                  solve_s=time.perf_counter() - start, diagnostics=exc.log[-5:],
                  newton_iters=len(exc.log))
    if push.rigid:
        result["push_mm"] = float(push.push_mm)
    return result


def case_grid_solution(ctx: SampleContext, push: Any) -> np.ndarray | None:
    """The push solved on the case grid (n_nodes, 3) mm when the teacher extrapolates
    (``[dataset] teacher_extrapolation``), else None; raises SolverError (its reason
    prefixed "case grid: ")."""
    from ..errors import SolverError
    from ..fem import Loads, solve
    from ..probe import nodal_forces

    coarse = ctx.teacher.coarse
    if coarse is None:
        return None
    try:
        if push.rigid:
            u, _ = solve(coarse, rigid_push_loads(ctx, push, ctx.case_skin),
                         rigid_push_settings(ctx))
        else:
            loads = Loads(forces=nodal_forces(ctx.skin[push.contact], push.force))
            u, _ = solve(coarse, loads, ctx.settings)
    except SolverError as exc:
        raise SolverError(f"case grid: {exc.what}", exc.where, log=exc.log) from None
    return u


def case_grid_rejection(ctx: SampleContext, u_case: np.ndarray | None
                        ) -> tuple[str, str] | None:
    """Why a draw is not kept on its case-grid solution ``u_case`` (n_nodes, 3) mm alone
    (:data:`IMPLAUSIBLE`, message), or None (also when ``u_case`` is None: no
    extrapolation): it stretches a cell beyond ``[dataset] max_edge_stretch`` (a flung lone
    node, as the case-grid teacher checks)."""
    if u_case is None:
        return None
    why = implausible(ctx.teacher.coarse, u_case, ctx.case.cfg.dataset.max_edge_stretch)
    return (IMPLAUSIBLE, f"case grid: {why}") if why else None


def face_motion(ctx: SampleContext, push: Any, contact_u: np.ndarray) -> np.ndarray:
    """What the tracker will see of a push's contact points (n, 3) mm: with elastic contact
    the rigid face's own motion (its springs leave the points lagging it, and the tracker
    knows only the face), else their displacement in the solved field, ``contact_u``."""
    from ..contact.constraints import is_elastic

    if push.rigid and is_elastic(ctx.case.cfg.tracker.fem_contact):
        return np.broadcast_to(push.displacement, np.shape(contact_u)).copy()
    return np.asarray(contact_u)


def input_springs(ctx: SampleContext, push: Any) -> np.ndarray | None:
    """The springs (n,) N/mm of a rigid push's contact points on the case grid with elastic
    contact (the input is the linear field of that contact), else None."""
    from ..contact.constraints import contact_springs

    tracker = ctx.case.cfg.tracker
    if not push.rigid:
        return None
    return contact_springs(tracker.fem_contact, tracker.contact_stiffness, ctx.case_e_mpa,
                           ctx.case.grid, ctx.case_skin.cells[push.contact],
                           ctx.skin_areas[push.contact])


def probe_displacement(contact_u: np.ndarray) -> float:
    """The probe displacement (mm): the mean norm of the contact points' displacements
    ``contact_u`` (n, 3) mm."""
    return float(np.linalg.norm(contact_u, axis=1).mean())


def extrapolation_rejection(ctx: SampleContext, u: np.ndarray, u_case: np.ndarray | None
                            ) -> tuple[str, str] | None:
    """Why an extrapolated sample is not kept (:data:`IMPLAUSIBLE`, message), or None (also
    when ``u_case`` is None: no extrapolation): the extrapolated field ``u`` (n_nodes, 3) mm
    still stretches a cell it was extrapolated in (at least half full) beyond ``[dataset]
    max_edge_stretch`` after :meth:`~biopsynav.fem.teacher.Teacher.extrapolate` gave the
    cells over it the fitted field. Nearly empty cells keep the fitted fine field's nodes
    beside extrapolated ones, and cells under the probe's edges may come out inverted: both
    are kept; the refined model's Table 1 counts inverted targets."""
    if u_case is None:
        return None
    teacher, stretch = ctx.teacher, ctx.case.cfg.dataset.max_edge_stretch
    why = implausible(teacher.coarse, u, stretch, teacher.extrapolated_cells)
    return (IMPLAUSIBLE, f"extrapolated field: {why}") if why else None


def rigid_push_settings(ctx: SampleContext) -> Any:
    """The worker's solver settings with the Newton budget of a rigid push. With elastic
    contact the springs as asked get the plain ``[dataset] newton_budget``: a draw that needs
    more is past their limit point, and the FE engine's fallbacks to stiffer springs
    (:data:`biopsynav.fem.solver.SPRING_FALLBACK`) get the whole budget; all are factored in
    single precision (with ``[solver] single_precision``). Never the points met: that teacher
    drags the tissue (docs/experiments.md, "`[refine]` on the case grid with elastic contact"), so
    a draw that no springs answer is recorded as failed and redrawn."""
    from ..fem.solver import SPRING_FALLBACK

    budget = ctx.settings.max_total_iterations
    return dataclasses.replace(ctx.settings, max_total_iterations=RIGID_BUDGET_FACTOR * budget,
                               first_attempt_budget=budget,
                               spring_fallback=tuple(f for f in SPRING_FALLBACK
                                                     if math.isfinite(f)),
                               elastic_single_precision=ctx.settings.single_precision)


def too_deep(probe_disp_mm: float, max_push_mm: float) -> bool:
    """Whether a solved push (mean contact-point displacement norm, mm) goes beyond the
    data set's deepest push ``[probe] max_push_mm`` (0: no limit)."""
    return max_push_mm > 0 and probe_disp_mm > max_push_mm


def solved_rejection(ctx: SampleContext, push: Any, probe_disp: float, u: np.ndarray
                     ) -> tuple[str, str] | None:
    """Why a converged push is not kept, as (:data:`TOO_DEEP` or :data:`IMPLAUSIBLE`,
    message), or None: ``probe_disp`` mm, ``u`` (n_model_nodes, 3) mm on the teacher's grid."""
    cfg = ctx.case.cfg
    if not push.rigid and too_deep(probe_disp, cfg.probe.max_push_mm):
        return TOO_DEEP, (f"probe displacement {probe_disp:.1f} mm is beyond [probe] "
                          f"max_push_mm = {cfg.probe.max_push_mm:g} mm")
    why = implausible(ctx.model, u, cfg.dataset.max_edge_stretch)
    return (IMPLAUSIBLE, why) if why else None


def implausible(model: Any, u: np.ndarray, max_stretch: float,
                elements: np.ndarray | None = None) -> str:
    """Why the solution ``u`` (n_nodes, 3) mm of ``model`` is not kept, or "": a cell edge
    (of the cells selected by ``elements``, (n_el,) bool; all by default) stretched more than
    ``max_stretch`` times its rest length (0: no check)."""
    from ..fem import largest_edge_stretch

    stretch = largest_edge_stretch(model, u, elements) if max_stretch > 0 else 0.0
    if stretch <= max_stretch:
        return ""
    return (f"the solve converged to a state no tissue reaches: a cell edge stretched "
            f"{stretch:.1f} times its rest length, more than [dataset] max_edge_stretch = "
            f"{max_stretch:g} (the lone node of a nearly empty cell flung by the push?)")


def push_metadata(push: Any) -> dict:
    """The per-sample probe parameters of a :class:`biopsynav.probe.ProbePush`."""
    return {"center": push.center, "vertex": int(push.vertex), "long_axis": push.long_axis,
            "direction": push.direction, "force_n": float(push.force_n),
            "tilt_deg": float(push.tilt_deg), "n_contact": push.n_contact}


# ----- local worker processes ---------------------------------------------------------------

_PROCESS_CONTEXT: SampleContext | None = None


def init_process(spec: WorkerSpec) -> None:
    """Set-up of a local worker process (:class:`~biopsynav.dataset.pool.WorkerProcesses`,
    after its thread limits and watchdog): the case's context, once."""
    global _PROCESS_CONTEXT
    _PROCESS_CONTEXT = SampleContext(spec.case)


def process_sample(index: int, attempt: int) -> dict:
    """Task of a local worker process (uses the context of :func:`init_process`)."""
    if _PROCESS_CONTEXT is None:  # pragma: no cover - initializer always ran
        raise RuntimeError("worker process has no case context")
    return compute_sample(_PROCESS_CONTEXT, index, attempt)


# ----- Dask workers -------------------------------------------------------------------------

_THREAD_CONTEXTS: dict[tuple[str, int], SampleContext] = {}
_THREAD_LOCK = threading.Lock()


def dask_sample(spec: WorkerSpec, index: int, attempt: int) -> dict:
    """Task of a Dask worker: the context is built once per worker thread (an FE model holds
    a stateful factorisation, so threads do not share one)."""
    key = (spec.key, threading.get_ident())
    ctx = _THREAD_CONTEXTS.get(key)
    if ctx is None:
        ctx = SampleContext(spec.case)
        with _THREAD_LOCK:
            _THREAD_CONTEXTS[key] = ctx
    return compute_sample(ctx, index, attempt)
