"""Table 2 by simulation: probe above each lesion, four pushes, against a ground truth.

Ground truth (``[evaluate] reference``, :mod:`biopsynav.evaluate.references`): by default
(``auto``) the stored independent truth where one serves the case
(:mod:`biopsynav.evaluate.stored`), else the FE model of the same anatomy on a grid
``[evaluate] reference_refinement`` times finer (half the cell size by default), driven by
the same prescribed displacement of the same contact points (skin vertices, shared by both
grids), so that the training-resolution FE model shows its discretisation error and the
network shows that plus its learning error; or ``p2``, an independent P2 tetrahedral FE of
the same surface, which shows the formulation's error too.
Methods: ``net`` (the U-Net tracker), ``fem`` (FE tracker at the training resolution) and
``rigid`` (lesions stay where they were at rest). TRE = |predicted - ground-truth centre|."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..case import Case, as_case
from ..fem import SolverSettings
from ..grid.build import build_grid
from ..reference_registry import build_reference, chosen_reference
from ..tracker.core import Tracker, fem_engine, fem_solver_settings
from ..tracker.result import TrackingResult
from .placement import Placement, place_case_probe, push_depths
from .table import AGREEMENT, BIN_NAMES, Record, aggregate, bin_name

METHODS: tuple[str, ...] = ("net", "fem", "rigid")
QUICK_LESIONS = 3
QUICK_REFINEMENT = 1.5
#: prescribed contact displacements are met to this (mm) in the evaluation solves (the case's
#: [solver] value when larger); far below the millimetre TREs that are measured
CONSTRAINT_TOLERANCE_MM = 1e-2
RESIDUAL_TOLERANCE = 1e-6


def evaluation_solver_settings(case: Case) -> SolverSettings:
    """Solver settings of the evaluation solves (reference and ``fem`` method alike): the FE
    engine's (:func:`~biopsynav.tracker.core.fem_solver_settings`) with tolerances loosened
    to ``CONSTRAINT_TOLERANCE_MM`` and ``RESIDUAL_TOLERANCE`` where they are tighter. A
    fine-grid reference drops their spring budget (``GridReference``)."""
    s = fem_solver_settings(case)
    s.constraint_tolerance_mm = max(s.constraint_tolerance_mm, CONSTRAINT_TOLERANCE_MM)
    s.tol_residual = max(s.tol_residual, RESIDUAL_TOLERANCE)
    s.tol_displacement = max(s.tol_displacement, RESIDUAL_TOLERANCE)
    return s


def reference_case(case: Case, refinement: float) -> Case:
    """An in-memory case with the same anatomy and a grid ``refinement`` times finer."""
    section = dataclasses.replace(case.cfg.grid,
                                  cell_size_mm=case.cfg.grid.cell_size_mm / refinement)
    grid = build_grid(case.anatomy, section,
                      chest_tol_mm=case.cfg.anatomy.chest_wall_tolerance_mm)
    return Case(case.dir, case.cfg, case.anatomy, grid)


def select_lesions(n_lesions: int, max_lesions: int) -> list[int]:
    """Indices of the lesions evaluated: all, or ``max_lesions`` spread evenly over the list."""
    if max_lesions <= 0 or max_lesions >= n_lesions:
        return list(range(n_lesions))
    return sorted({int(round(v)) for v in np.linspace(0, n_lesions - 1, max_lesions)})


@dataclass
class Setup:
    """What a Table 2 run uses: lesion indices, refinement, pushes per lesion, deepest push."""

    lesions: list[int]
    refinement: float
    pushes: int
    max_push_mm: float


def setup_for(case: Case, quick: bool) -> Setup:
    """The run's setup from ``[evaluate]``; ``quick`` caps lesions and refinement."""
    ev = case.cfg.evaluate
    max_lesions = ev.max_lesions
    refinement = float(ev.reference_refinement)
    if quick:
        max_lesions = min(max_lesions, QUICK_LESIONS) if max_lesions > 0 else QUICK_LESIONS
        refinement = min(refinement, QUICK_REFINEMENT)
    return Setup(select_lesions(len(case.anatomy.lesions), max_lesions), refinement,
                 ev.deformations_per_lesion, ev.max_push_mm)


def run_simulation(case: Case | str | Path, methods: Sequence[str] = METHODS, quick: bool = False,
                   log: Callable[[str], None] = print, workers: int = 0,
                   keep: bool = True) -> dict:
    """Table 2 by simulation of ``case`` (loaded, or its folder); returns the JSON-ready result.
    A fine-grid ground truth (its lesions kept from an earlier run where ``keep`` and nothing
    it depends on changed, :mod:`biopsynav.evaluate.kept`; the others kept for the next),
    then the ``fem`` method, are solved first in ``workers`` local
    processes (0: one per core; 1: in this process, push by push;
    :mod:`biopsynav.evaluate.parallel`).

    Keys: ``source`` ("simulation"), ``methods``, ``records`` (one per lesion, push and
    method: displacement_mm, bin, tre_mm or None with status and reason, time_ms),
    ``tables`` (per method, see :meth:`Table.to_dict`), ``placements``, ``reference`` (grid
    facts), ``failures`` and ``timing`` (seconds).
    """
    t_start = time.perf_counter()
    case = as_case(case)
    if not case.anatomy.lesions:
        log(f"Table 2: {NO_LESIONS}")
        return no_lesions_result(methods, time.perf_counter() - t_start)
    setup = setup_for(case, quick)
    settings = evaluation_solver_settings(case)
    reference = build_reference(case, setup, settings)
    lesions = _reference_lesions(reference, setup.lesions)
    pushes = (f"{setup.pushes} pushes up to {setup.max_push_mm:g} mm"
              if getattr(reference, "push_depths", None) is None else "its pushes")
    chosen = chosen_reference(case)[1]
    log(f"Table 2: ground truth {reference.describe()}{f' ({chosen})' if chosen else ''}; "
        f"{len(lesions)} lesions x {pushes}")
    plans = [(li, place_case_probe(case, li)) for li in lesions]
    plans = [(li, placement, _depths(reference, li, push_depths(k, setup.pushes,
                                                                setup.max_push_mm)))
             for k, (li, placement) in enumerate(plans)]
    workers = workers or os.cpu_count() or 1
    reference = solved_beforehand(reference, case, setup, settings, plans, workers, log, keep)
    trackers = method_trackers(case, methods, settings,
                               teacher_beforehand(case, methods, settings, plans, workers, log))
    records: list[Record] = []
    placements = []
    for li, placement, depths in plans:
        t_les = time.perf_counter()
        n_contact = _set_rest(placement, reference, trackers)
        placements.append({**placement.to_dict(), "n_contact": n_contact,
                           "push_depths_mm": depths.tolist()})
        for p, depth in enumerate(depths):
            records += push_records(placement, li, p, float(depth), reference, trackers, methods)
        log(f"  lesion {placement.lesion}: {n_contact} contact points, pushes "
            f"{', '.join(f'{d:.1f}' for d in depths)} mm, {time.perf_counter() - t_les:.1f} s")
    lesion_ids = [int(case.anatomy.lesions[i].id) for i in lesions]
    return {
        "source": "simulation",
        "methods": list(methods),
        "bins": list(BIN_NAMES),
        "records": [r.to_dict() for r in records],
        "tables": {m: aggregate(records, m, lesion_ids).to_dict() for m in methods}
        | ({AGREEMENT: aggregate(records, AGREEMENT, lesion_ids).to_dict()}
           if {"net", "fem"} <= set(methods) else {}),
        "placements": placements,
        "reference": reference.facts() | {"description": reference.describe()}
        | ({"chosen": chosen} if chosen else {}),
        "setup": dataclasses.asdict(setup) | {"quick": quick},
        "failures": [r.to_dict() for r in records if r.tre_mm is None],
        "timing": _timing(records, reference.build_s, time.perf_counter() - t_start),
    }


#: Table 2 of a case without lesions (a healthy breast, modelled beside the one that holds
#: the tumour): nothing to push over or to track
NO_LESIONS = ("the case has no lesions, so there is nothing to track: no push solved (Table 1 "
              "judges the network)")


Plans = list[tuple[int, Placement, np.ndarray]]  # (lesion index, placement, depths mm)


def solved_beforehand(reference, case: Case, setup: Setup, settings: SolverSettings,
                      plans: Plans, workers: int, log: Callable[[str], None], keep: bool = True):
    """``reference`` with every push of ``plans`` answered beforehand when its rest poses are
    independent (``independent_rest_poses``: the fine grid): the lesions kept from an earlier
    run (``keep``, :mod:`biopsynav.evaluate.kept`), the others solved in ``workers`` local
    processes (:func:`in_workers`) or in this process (:func:`solved_here`) and kept; else
    ``reference`` itself, which then solves as it is asked."""
    from .kept import KeptTruth, truth_key
    from .parallel import SolvedReference, grid_reference, lesion_answers, lesion_entries

    if not getattr(reference, "independent_rest_poses", False):
        return reference
    kept = (KeptTruth(case.paths.table2_fine_grid_cache,
                      truth_key(case, setup.refinement, settings)) if keep else None)
    held = [kept.answers(*lesion_poses(plan)) if kept else None for plan in plans]
    todo = [plan for plan, h in zip(plans, held, strict=True) if h is None]
    if len(todo) < len(plans):
        log(f"  ground truth: {len(plans) - len(todo)} of {len(plans)} lesions kept from an "
            f"earlier evaluation ({kept.path.name})")
    answers = in_workers(grid_reference, (type(reference), case, setup, settings), todo,
                         workers, "ground truth", log)
    if answers is None:
        answers = solved_here(reference, todo, log)
    for plan, h in zip(plans, held, strict=True):
        rest, poses = lesion_poses(plan)
        if h is not None:
            answers.update(lesion_entries(rest, poses, *h))
        elif kept:
            kept.keep(rest, poses, *lesion_answers(answers, rest, poses))
    return SolvedReference(reference, answers, len(plans) - len(todo))


def lesion_poses(plan: tuple) -> tuple[np.ndarray, list[np.ndarray]]:
    """A plan's rest pose (4, 4) and its pushed poses, one per depth."""
    _, placement, depths = plan
    return placement.pose, [placement.pushed(float(d)) for d in depths]


def solved_here(reference, plans: Plans, log: Callable[[str], None]) -> dict:
    """Every push of ``plans`` answered by ``reference`` in this process, each push announced
    before its solve (a deep one can take minutes), as
    :class:`~biopsynav.evaluate.parallel.SolvedAnswers` holds them."""
    from .parallel import engine_answers, lesion_entries

    answers: dict = {}
    for plan in plans:
        rest, poses = lesion_poses(plan)
        solved = engine_answers(reference, rest, poses, push_announcer(plan, log))
        answers.update(lesion_entries(rest, poses, *solved))
    return answers


def push_announcer(plan: tuple, log: Callable[[str], None]) -> Callable[[int], None]:
    """What says, before a plan's k-th push is solved, which it is."""
    _, placement, depths = plan
    return lambda k: log(f"  lesion {placement.lesion}: push {k + 1} of {len(depths)} "
                         f"({depths[k]:.1f} mm) ...")


def in_workers(factory, args: tuple, plans: Plans, workers: int, what: str,
               log: Callable[[str], None]):
    """The answers of the engine ``factory(*args)`` to every push of ``plans``, each lesion's
    pushes in turn in one of ``workers`` local processes
    (:func:`~biopsynav.evaluate.parallel.solve_in_workers`); None (solve them in this
    process) for fewer than two workers or lesions."""
    from .parallel import solve_in_workers

    lesions = [lesion_poses(plan) for plan in plans]
    if workers < 2 or len(lesions) < 2:
        return None
    start = time.perf_counter()
    answers = solve_in_workers(factory, args, lesions, workers, f"Table 2's {what}")
    log(f"  {what}: {sum(len(p) for _, p in lesions)} pushes of {len(lesions)} lesions "
        f"solved in {workers} processes, {time.perf_counter() - start:.1f} s")
    return answers


def no_lesions_result(methods: Sequence[str], seconds: float) -> dict:
    """The Table 2 result of a case without lesions: no records or tables, its ``note``."""
    return {"source": "simulation", "methods": list(methods), "bins": list(BIN_NAMES),
            "records": [], "tables": {}, "placements": [], "reference": {}, "failures": [],
            "note": NO_LESIONS, "timing": {"total_s": seconds}}


def _reference_lesions(reference, lesions: list[int]) -> list[int]:
    """The lesion indices of ``lesions`` that ``reference`` answers (all, unless it names
    those it holds: a stored truth)."""
    held = getattr(reference, "lesion_indices", None)
    if held is None:
        return lesions
    answered = set(held())
    return [li for li in lesions if li in answered]


def _depths(reference, lesion_index: int, default: np.ndarray) -> np.ndarray:
    """The push depths (mm) of a lesion: the reference's own (a stored truth's) or
    ``default``."""
    own = getattr(reference, "push_depths", None)
    depths = None if own is None else own(lesion_index)
    return default if depths is None else depths


def teacher_beforehand(case: Case, methods: Sequence[str], settings: SolverSettings,
                       plans: Plans, workers: int, log: Callable[[str], None]):
    """The ``fem`` method's answers to every push of ``plans``, solved in ``workers`` local
    processes (:func:`in_workers`); None where it is not asked or is solved here."""
    from .parallel import teacher_engine

    if "fem" not in methods:
        return None
    return in_workers(teacher_engine, (case, settings), plans, workers, "FE teacher", log)


def method_trackers(case: Case, methods: Sequence[str], settings: SolverSettings,
                    fem_answers=None) -> dict:
    """The engines of ``methods``: the network tracker and the FE teacher (on the network's
    teacher grid; served from ``fem_answers``, :func:`teacher_beforehand`, where given)."""
    from .parallel import SolvedAnswers

    trackers: dict = {}
    if "net" in methods:
        trackers["net"] = Tracker.load(case, engine="net")
    if "fem" in methods:
        trackers["fem"] = (fem_engine(case, settings) if fem_answers is None
                           else SolvedAnswers(fem_answers))
    return trackers


def _set_rest(placement: Placement, reference, trackers: dict) -> int:
    n = reference.set_rest_pose(placement.pose)
    for tr in trackers.values():
        tr.set_rest_pose(placement.pose)
    return n


def push_records(placement: Placement, lesion_index: int, push: int, depth_mm: float,
                 reference, trackers: dict,
                 methods: Sequence[str]) -> list[Record]:
    """Records of every method for one push of ``depth_mm`` (probe displacement) mm."""
    pose = placement.pushed(depth_mm)
    displacement = float(np.linalg.norm(pose[:3, 3] - placement.pose[:3, 3]))
    base = {"lesion": placement.lesion, "push": push, "displacement_mm": displacement,
            "bin": bin_name(displacement)}
    truth = reference.update(pose)
    if not truth.reliable:
        reason = f"ground truth: {truth.status}: {truth.reason}"
        return [Record(**base, method=m, tre_mm=None, status="no_reference", reason=reason)
                for m in methods]
    true_centre = truth.lesions[lesion_index].center
    rest_centre = true_centre - truth.lesions[lesion_index].displacement
    out, results = [], {}
    for m in methods:
        if m == "rigid":
            out.append(Record(**base, method=m, tre_mm=float(np.linalg.norm(true_centre
                                                                             - rest_centre)),
                              time_ms=0.0))
        else:
            results[m] = trackers[m].update(pose)
            out.append(method_record(base, m, results[m], lesion_index, true_centre))
    out.append(Record(**base, method="reference", tre_mm=0.0, reason=truth.reason,
                      time_ms=truth.latency_ms))
    net, fem = results.get("net"), results.get("fem")
    if net is not None and fem is not None and net.reliable and fem.reliable:
        gap = net.lesions[lesion_index].center - fem.lesions[lesion_index].center
        out.append(Record(**base, method=AGREEMENT, tre_mm=float(np.linalg.norm(gap))))
    return out


def method_record(base: dict, method: str, result: TrackingResult, lesion_index: int,
                  true_centre: np.ndarray) -> Record:
    """The record of one tracker result against the ground-truth centre (3,) mm."""
    if not result.reliable:
        return Record(**base, method=method, tre_mm=None, status=result.status,
                      reason=result.reason, time_ms=result.latency_ms)
    lesion = result.lesions[lesion_index]
    tre = float(np.linalg.norm(lesion.center - true_centre))
    return Record(**base, method=method, tre_mm=tre, reason=result.reason,
                  time_ms=result.latency_ms, bound_mm=float(lesion.bound_mm))


def _timing(records: list[Record], ref_build_s: float, total_s: float) -> dict:
    per_method: dict[str, list[float]] = {}
    for r in records:
        if r.time_ms is not None and r.tre_mm is not None:
            per_method.setdefault(r.method, []).append(r.time_ms)
    return {"total_s": total_s, "reference_build_s": ref_build_s,
            "mean_ms": {m: float(np.mean(v)) for m, v in per_method.items()},
            "n_solves": {m: len(v) for m, v in per_method.items()}}
