"""The tracking network against its own FE teacher at every lesion: each lesion's self-check.

The probe is placed over each lesion as Table 2 and the truth place it
(:func:`~biopsynav.evaluate.placement.place_case_probe`) and pushed to ``CHECK_DEPTHS_MM``; the
tracking network and its teacher (the FE engine on the network's teacher grid, Table 2's
``fem``) answer each push. The distance between their lesion centres over the teacher's lesion
displacement is the lesion's *relative miss* at that depth: how much of the lesion's motion
the network has not learnt from its teacher there. The tracker widens each lesion's error
bound by it (:mod:`biopsynav.tracker.bound`), so that a lesion the network learnt badly is not
shown with the bound of one it learnt well. No truth takes part, so every case gets its check.
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


#: The worker process's (case, network tracker, FE tracker), set up by :func:`init_engines`.
_ENGINES: tuple[Case, Tracker, Tracker] | None = None


def run_lesion_check(case: Case, workers: int = 0, log: Callable[[str], None] = print,
                     depths_mm: tuple[float, ...] = CHECK_DEPTHS_MM) -> dict:
    """Every lesion's check (see the module doc) at ``depths_mm`` (increasing) in ``workers``
    local processes (0: one per core; 1: in this process), written to the tracking model's
    folder and returned:
    ``model_checksum``, ``depths_mm``, ``lesions`` ({id: ``miss_mm``, ``teacher_mm``,
    ``relative`` per depth, None where either engine gave no answer, and ``status``}) and
    ``seconds``."""
    import os

    start = time.perf_counter()
    model_dir = case.tracking_model
    meta = read_meta(model_dir)  # checked here: the workers load the model themselves
    indices = list(range(len(case.anatomy.lesions)))
    workers = min(workers or os.cpu_count() or 1, len(indices))
    if workers > 1:
        checks = checks_in_workers(case, indices, workers, depths_mm)
    else:
        engines = (case, Tracker.load(case, engine="net"),
                   fem_engine(case, evaluation_solver_settings(case)))
        checks = [lesion_pushes(*engines, li, depths_mm) for li in indices]
    result = {"format": CHECK_FORMAT, "model_checksum": LesionCheck.checksum_of(meta),
              "depths_mm": [float(d) for d in depths_mm],
              "lesions": {str(case.anatomy.lesions[li].id): c
                          for li, c in zip(indices, checks, strict=True)},
              "seconds": time.perf_counter() - start}
    write_json_atomic(model_dir / LESION_CHECK, result)
    log(check_line(result))
    return result


def init_engines(case: Case) -> None:
    """Worker set-up: the network tracker and its FE teacher, one thread each."""
    global _ENGINES
    settings = dataclasses.replace(evaluation_solver_settings(case), threads=1)
    _ENGINES = (case, Tracker.load(case, engine="net", threads=1), fem_engine(case, settings))


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


def lesion_pushes(case: Case, net: Tracker, fem: Tracker, lesion_index: int,
                  depths_mm: tuple[float, ...]) -> dict:
    """The check of one lesion: both engines at each of ``depths_mm`` over it."""
    placement = place_case_probe(case, lesion_index)
    for tracker in (net, fem):
        tracker.set_rest_pose(placement.pose)
    out: dict[str, list] = {"miss_mm": [], "teacher_mm": [], "relative": [], "status": []}
    for depth in depths_mm:
        pose = placement.pushed(depth)
        answers = net.update(pose), fem.update(pose)
        unanswered = [f"{name}: {a.status}" for name, a in zip(("net", "fem"), answers,
                                                                strict=True) if not a.reliable]
        miss, moved = (None, None) if unanswered else pair_distance(answers, lesion_index)
        out["miss_mm"].append(miss)
        out["teacher_mm"].append(moved)
        out["relative"].append(None if miss is None else miss / max(moved, 1e-9))
        out["status"].append("; ".join(unanswered) or "ok")
    return out


def pair_distance(answers, lesion_index: int) -> tuple[float, float]:
    """(distance between the network's and the teacher's lesion centres, the teacher's lesion
    displacement), mm."""
    net, fem = (a.lesions[lesion_index] for a in answers)
    return (float(np.linalg.norm(net.center - fem.center)),
            float(np.linalg.norm(fem.displacement)))


def check_line(result: dict) -> str:
    """One line: the largest relative miss of each lesion, and the time taken."""
    worst = {i: max((r for r in v["relative"] if r is not None), default=None)
             for i, v in result["lesions"].items()}
    parts = [f"{i} {'-' if w is None else f'{100 * w:.0f} %'}" for i, w in worst.items()]
    depths = ", ".join(f"{d:g}" for d in result["depths_mm"])
    return (f"lesion check (the network against its teacher at {depths} mm; the largest "
            "share of each lesion's motion missed): " + ", ".join(parts)
            + f"; {result['seconds']:.0f} s")
