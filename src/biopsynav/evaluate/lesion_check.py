"""The tracking network against its own FE teacher at every lesion: each lesion's self-check.

The probe is placed over each lesion as Table 2 and the truth place it
(:func:`~biopsynav.evaluate.placement.place_case_probe`) and pushed to ``CHECK_DEPTHS_MM``; the
tracking network and its teacher (the FE engine on the network's teacher grid, Table 2's
``fem``) answer each push. The distance between their lesion centres over the teacher's lesion
displacement is the lesion's *relative miss* at that depth: how much of the lesion's motion
the network has not learnt from its teacher there. Each lesion's *teacher gap* is the teacher
against itself on a grid :data:`TEACHER_CHECK_REFINEMENT` times finer at
:data:`TEACHER_CHECK_DEPTH_MM`: the distance between their lesion centres over the teacher's
lesion displacement, how far the teacher is from converged at that lesion (which the network's
miss against the teacher cannot show). The tracker widens each lesion's error bound by both
(:mod:`biopsynav.tracker.bound`), so that a lesion the network learnt badly, or whose teacher
is off, is not shown with the bound of one learnt well from a converged teacher. No truth takes
part, so every case gets its check.
The depths differ from the truth's 10 / 20 / 30 mm, so that ``benchmarks/error_bound.py``
judges the bound on pushes the check did not make.

Written to ``<tracking model>/lesion_check.json`` (:data:`~biopsynav.layout.LESION_CHECK`)
with the model's checksum: a model trained again makes the check stale, and the tracker then
bounds its lesions without it (:class:`~biopsynav.tracker.bound.LesionCheck`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ..case import Case
from ..fileio import write_json_atomic
from ..inference.model_files import read_meta
from ..layout import LESION_CHECK
from ..tracker.bound import CHECK_FORMAT, LesionCheck
from ..tracker.core import Tracker, fem_engine
from .placement import place_case_probe
from .simulation import evaluation_solver_settings

#: probe displacements (mm) of each lesion's check pushes, between and beyond the truth's
CHECK_DEPTHS_MM = (15.0, 25.0, 35.0)
#: the push (mm) at which each lesion's teacher is compared with itself on a finer grid
TEACHER_CHECK_DEPTH_MM = 15.0
#: how many times finer than the teacher's that grid's cells are
TEACHER_CHECK_REFINEMENT = 1.46


#: The worker process's (case, network tracker, FE tracker, the FE on a finer grid), set up by
#: :func:`init_engines`.
_ENGINES: tuple[Case, Tracker, Tracker, Tracker] | None = None


def run_lesion_check(case: Case, workers: int = 0, log: Callable[[str], None] = print,
                     depths_mm: tuple[float, ...] = CHECK_DEPTHS_MM) -> dict:
    """Every lesion's check (see the module doc) at ``depths_mm`` (increasing) in ``workers``
    local processes (0: one per core; 1: in this process), written to the tracking model's
    folder and returned:
    ``model_checksum``, ``depths_mm``, ``lesions`` ({id: ``miss_mm``, ``teacher_mm``,
    ``relative`` per depth, None where either engine gave no answer, ``status``, and
    ``teacher_gap``, None where the teacher or the finer grid gave none}), ``teacher_check``
    (its depth and refinement) and ``seconds``."""
    import os

    start = time.perf_counter()
    model_dir = case.tracking_model
    meta = read_meta(model_dir)  # checked here: the workers load the model themselves
    indices = list(range(len(case.anatomy.lesions)))
    workers = min(workers or os.cpu_count() or 1, len(indices))
    if workers > 1:
        checks = checks_in_workers(case, indices, workers, depths_mm)
    else:
        settings = evaluation_solver_settings(case)
        engines = (case, Tracker.load(case, engine="net"), fem_engine(case, settings),
                   finer_teacher(case, settings))
        checks = [lesion_pushes(*engines, li, depths_mm) for li in indices]
    result = {"format": CHECK_FORMAT, "model_checksum": LesionCheck.checksum_of(meta),
              "depths_mm": [float(d) for d in depths_mm],
              "lesions": {str(case.anatomy.lesions[li].id): c
                          for li, c in zip(indices, checks, strict=True)},
              "teacher_check": {"depth_mm": TEACHER_CHECK_DEPTH_MM,
                                "refinement": TEACHER_CHECK_REFINEMENT},
              "seconds": time.perf_counter() - start}
    write_json_atomic(model_dir / LESION_CHECK, result)
    log(check_line(result))
    return result


def init_engines(case: Case) -> None:
    """Worker set-up: the network tracker, its FE teacher and the teacher on a finer grid, one
    thread each."""
    global _ENGINES
    settings = dataclasses.replace(evaluation_solver_settings(case), threads=1)
    _ENGINES = (case, Tracker.load(case, engine="net", threads=1), fem_engine(case, settings),
                finer_teacher(case, settings))


def finer_teacher(case: Case, settings) -> Tracker:
    """The FE engine of the tracking model's teacher (its law, contact and solver
    ``settings``) on a grid :data:`TEACHER_CHECK_REFINEMENT` times finer than the teacher's,
    its spring budget scaled as a fine-grid reference's."""
    from ..fem.teacher import teacher_refinement
    from ..refine import tracking_teacher_case
    from ..tracker.core import finer_grid_spring_budget
    from .simulation import reference_case

    refinement = teacher_refinement(tracking_teacher_case(case).cfg) * TEACHER_CHECK_REFINEMENT
    return fem_engine(reference_case(case, refinement),
                      finer_grid_spring_budget(settings, refinement), on_teacher=False)


def check_lesion(lesion_index: int, depths_mm: tuple[float, ...]) -> dict:
    """Worker task: the check of lesion ``lesion_index`` on the worker's engines."""
    assert _ENGINES is not None, "init_engines was not run"
    return lesion_pushes(*_ENGINES, lesion_index, depths_mm)


def checks_in_workers(case: Case, indices: list[int], workers: int,
                      depths_mm: tuple[float, ...]) -> list[dict]:
    """:func:`lesion_pushes` of each of ``indices`` in ``workers`` spawned processes."""
    from concurrent.futures.process import BrokenProcessPool

    from ..dataset.pool import WorkerProcesses
    from ..errors import BiopsynavError

    checks: dict[int, dict] = {}
    with WorkerProcesses(workers, init_engines, (case,)) as pool:
        futures = {pool.submit(check_lesion, li, depths_mm): li for li in indices}
        pending = list(futures)
        try:
            while pending:
                for future in pool.wait_any(pending):
                    pending.remove(future)
                    checks[futures[future]] = future.result()
        except BrokenProcessPool:
            pool.check_started()  # a script without the __main__ guard: named as such
            raise BiopsynavError("a worker process of the lesion check died (out of memory?); "
                                 "`biopsynav evaluate CASE --workers 1` checks the lesions in "
                                 "this process", "lesion check") from None
    return [checks[li] for li in indices]


def lesion_pushes(case: Case, net: Tracker, fem: Tracker, fine: Tracker, lesion_index: int,
                  depths_mm: tuple[float, ...]) -> dict:
    """The check of one lesion: the network and the teacher at each of ``depths_mm`` over it,
    then its teacher gap (:func:`teacher_gap`, ``fine`` the teacher on the finer grid; the
    teacher's own push at :data:`TEACHER_CHECK_DEPTH_MM` is the check's where it made one)."""
    placement = place_case_probe(case, lesion_index)
    for tracker in (net, fem):
        tracker.set_rest_pose(placement.pose)
    out: dict[str, list] = {"miss_mm": [], "teacher_mm": [], "relative": [], "status": []}
    taught: dict[float, np.ndarray | None] = {}  # depth -> the teacher's lesion displacement
    for depth in depths_mm:
        pose = placement.pushed(depth)
        answers = net.update(pose), fem.update(pose)
        taught[depth] = lesion_displacement(answers[1], lesion_index)
        unanswered = [f"{name}: {a.status}" for name, a in zip(("net", "fem"), answers,
                                                                strict=True) if not a.reliable]
        miss, moved = (None, None) if unanswered else pair_distance(answers, lesion_index)
        out["miss_mm"].append(miss)
        out["teacher_mm"].append(moved)
        out["relative"].append(None if miss is None else miss / max(moved, 1e-9))
        out["status"].append("; ".join(unanswered) or "ok")
    at = TEACHER_CHECK_DEPTH_MM
    teacher = taught[at] if at in taught else pushed_lesion(fem, placement, lesion_index, at)
    return {**out, "teacher_gap": teacher_gap(fine, placement, lesion_index, teacher)}


def teacher_gap(fine: Tracker, placement, lesion_index: int,
                teacher: np.ndarray | None) -> float | None:
    """The share of the lesion's motion by which the teacher on the finer grid moves it
    otherwise at :data:`TEACHER_CHECK_DEPTH_MM` over it: |u_teacher - u_finer| / |u_teacher|,
    ``teacher`` (3,) mm the teacher's lesion displacement there
    (:func:`pushed_lesion`); None where either gave no reliable answer."""
    if teacher is None:
        return None
    finer = pushed_lesion(fine, placement, lesion_index, TEACHER_CHECK_DEPTH_MM)
    if finer is None:
        return None
    return float(np.linalg.norm(teacher - finer) / max(float(np.linalg.norm(teacher)), 1e-9))


def pushed_lesion(tracker: Tracker, placement, lesion_index: int,
                  depth_mm: float) -> np.ndarray | None:
    """The lesion's displacement (3,) mm when ``tracker``, set to the placement's rest pose,
    answers its push of ``depth_mm``; None where the answer is not reliable."""
    tracker.set_rest_pose(placement.pose)
    return lesion_displacement(tracker.update(placement.pushed(depth_mm)), lesion_index)


def lesion_displacement(answer, lesion_index: int) -> np.ndarray | None:
    """A copy of the lesion's displacement (3,) mm in a tracker's ``answer``, None where the
    answer is not reliable."""
    return (np.array(answer.lesions[lesion_index].displacement, dtype=np.float64)
            if answer.reliable else None)


def pair_distance(answers, lesion_index: int) -> tuple[float, float]:
    """(distance between the network's and the teacher's lesion centres, the teacher's lesion
    displacement), mm."""
    net, fem = (a.lesions[lesion_index] for a in answers)
    return (float(np.linalg.norm(net.center - fem.center)),
            float(np.linalg.norm(fem.displacement)))


def check_line(result: dict) -> str:
    """One line: the largest relative miss of each lesion, its teacher gap, the time taken."""
    worst = {i: max((r for r in v["relative"] if r is not None), default=None)
             for i, v in result["lesions"].items()}
    parts = [f"{i} {share_words(w)}" for i, w in worst.items()]
    depths = ", ".join(f"{d:g}" for d in result["depths_mm"])
    gaps = [f"{i} {share_words(v.get('teacher_gap'))}" for i, v in result["lesions"].items()]
    return (f"lesion check (the network against its teacher at {depths} mm; the largest "
            "share of each lesion's motion missed): " + ", ".join(parts)
            + f"; the teacher against a grid {TEACHER_CHECK_REFINEMENT:g} times finer at "
            f"{TEACHER_CHECK_DEPTH_MM:g} mm: " + ", ".join(gaps)
            + f"; {result['seconds']:.0f} s")


def share_words(share: float | None) -> str:
    """A share as a whole percentage, ``-`` for None."""
    return "-" if share is None else f"{100 * share:.0f} %"
