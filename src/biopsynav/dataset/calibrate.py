"""A force range that fits the breast at hand: ``[probe] calibrate_force``.

Before the first sample, :func:`calibrate_force` pushes ``[probe] calibration_pushes`` probe
patches of the protocol (centre, angle and tilt drawn as for samples, from their own seeds)
with one total force and measures each probe displacement (mean contact-point displacement,
mm). The force is searched (secant steps on log force against log displacement) until the
:data:`QUANTILE` of those displacements is ``[probe] max_push_mm`` within
:data:`TOLERANCE`; that force becomes the data set's ``f_max_n``. Forces are then drawn
in ``[0, f_max_n]`` as before (training forces up to ``[probe] train_force_scale`` times it),
so the probe displacements spread up to the clinical
depth on a stiff breast and a soft one alike, and few draws go deeper than the limit. A
push whose solve fails counts as deeper than any; a round stops once so many have failed
that its quantile is a failure whatever the rest give (:func:`failures_allowed`), solving
first the pushes that went deepest at the force before. The solves run in local worker
processes (:class:`CalibrationSolves`, as many as generation's), one thread each as a
sample's, so the force found does not depend on their number. The result is recorded in the
data set, and a resumed job reuses it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import BiopsynavError, SolverError

QUANTILE = 0.9
TOLERANCE = 0.05
MAX_ROUNDS = 8
#: Calibration draws use sample indices from here on (never a sample's own).
CALIBRATION_INDEX = 2 ** 40


def calibrate_force(case: Any, workers: int = 1) -> dict:
    """The calibrated ``f_max_n`` (N) of ``case`` and how it was found (plain dict), its FE
    solves spread over ``workers`` local processes (0: one per core).

    With a refined teacher (``[dataset] teacher_refine`` > 1) the search runs on the case
    grid first, where a round costs a fraction of the teacher's, and the teacher's own search
    starts from that force (``case_grid_rounds`` in the record)."""
    from ..fem.teacher import teacher_refinement

    start = time.perf_counter()
    target = float(case.cfg.probe.max_push_mm)
    force, record = float(case.cfg.probe.f_max_n), {}
    with CalibrationSolves(case, workers) as solves:
        if teacher_refinement(case.cfg) > 1:
            coarse = search_force(solves.round_on(CASE_GRID), solves.n_pushes, force, target)
            force, record = best_force(coarse, target)[0], {"case_grid_rounds": _rounded(coarse)}
        history = search_force(solves.round_on(TEACHER), solves.n_pushes, force, target)
    chosen = best_force(history, target)
    return {"f_max_n": round(chosen[0], 6), "quantile_depth_mm": round(chosen[1], 2),
            "quantile": QUANTILE, "target_mm": target, "pushes": solves.n_pushes,
            "rounds": _rounded(history), **record, "solves": solves.count,
            "seconds": round(time.perf_counter() - start, 1)}


def search_force(round_depths: Callable[[float, np.ndarray], np.ndarray], n_pushes: int,
                 force: float, target: float) -> list[tuple[float, float]]:
    """The (force N, quantile depth mm) rounds of the search from ``force`` until the
    :data:`QUANTILE` depth of the ``n_pushes`` pushes is within :data:`TOLERANCE` of
    ``target``, the bracket closes, or :data:`MAX_ROUNDS` pass. ``round_depths(force,
    order)``: each push's probe displacement (mm, inf: failed or left unsolved) at ``force``
    N, solved in ``order`` (:meth:`CalibrationSolves.depths`)."""
    history: list[tuple[float, float]] = []
    depths = np.zeros(n_pushes)
    for _ in range(MAX_ROUNDS):
        # the pushes deepest (or failed) at the last force first: a round that fails ends soon
        depths = round_depths(force, np.argsort(-depths, kind="stable"))
        history.append((force, quantile_depth(depths)))
        if abs(history[-1][1] - target) <= TOLERANCE * target:
            break
        force = next_force(history, target)
        if force is None:
            break
    return history


class CalibrationSolves:
    """The calibration's FE solves in ``workers`` local processes (0: one per core), each
    holding the case's models once (:func:`init_calibration`); ``count``: solves answered."""

    def __init__(self, case: Any, workers: int) -> None:
        from .pool import WorkerProcesses

        self.n_pushes = int(case.cfg.probe.calibration_pushes)
        self.processes = WorkerProcesses(workers, init_calibration, (case,))
        self.count = 0

    def round_on(self, stage: str) -> Callable[[float, np.ndarray], np.ndarray]:
        """:meth:`depths` on the model of ``stage`` (:data:`CASE_GRID` or :data:`TEACHER`)."""
        return lambda force, order: self.depths(stage, force, order)

    def depths(self, stage: str, force_n: float, order: np.ndarray) -> np.ndarray:
        """Probe displacement (mm) of each push at ``force_n`` N total; inf where the solve
        fails. The pushes go to the workers in ``order``, two per worker at a time; once more
        have failed than :func:`failures_allowed`, the rest are not sent (inf too): the
        round's quantile is inf whatever they give. Nothing is ever cancelled: the solves
        still running when a round ends finish unread (on Python 3.11 a future cancelled from
        outside a pool that then breaks is an InvalidStateError traceback in the executor's
        thread, CPython gh-107219)."""
        from concurrent.futures.process import BrokenProcessPool

        depths = np.full(self.n_pushes, np.inf)
        queue = [(rank, int(i)) for rank, i in enumerate(order)]
        try:
            self._collect(stage, float(force_n), queue, depths,
                          failures_allowed(self.n_pushes))
        except BrokenProcessPool:  # a worker died (whether a future names it or not)
            self.processes.check_started()
            raise _worker_died() from None
        return depths

    def _collect(self, stage: str, force_n: float, queue: list, depths: np.ndarray,
                 allowed: int) -> None:
        """Send the ``queue`` of (rank, push index) and write the answers into ``depths``, in
        rank order as they come, until none is left or more than ``allowed`` failed."""
        pending: dict = {}
        failed = 0
        while queue or pending:
            self._send(stage, force_n, queue, pending)
            for future in sorted(self.processes.wait_any(list(pending)), key=pending.get):
                index = pending.pop(future)[1]
                depths[index] = _answer(future)
                self.count += 1
                failed += bool(np.isinf(depths[index]))
                if failed > allowed:
                    return

    def _send(self, stage: str, force_n: float, queue: list, pending: dict) -> None:
        """Move pushes from the front of ``queue`` into ``pending`` (future -> (rank, push
        index)) until each worker has one running and one waiting (no worker idles while the
        main process reads an answer)."""
        while queue and len(pending) < 2 * self.processes.workers:
            rank, index = queue.pop(0)
            future = self.processes.submit(calibration_depth, stage, index, force_n)
            pending[future] = (rank, index)

    def __enter__(self) -> CalibrationSolves:
        return self

    def __exit__(self, *exc: object) -> None:
        self.processes.close()


def _answer(future: Any) -> float:
    """A calibration solve's depth (mm); a worker's error as one line (its death,
    BrokenProcessPool, is said by the round)."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return future.result()
    except (BiopsynavError, BrokenProcessPool):
        raise
    except Exception as exc:  # noqa: BLE001 - a worker's error, said in one line
        raise BiopsynavError(f"force calibration: a solve failed in its worker: "
                             f"{type(exc).__name__}: {exc}", "generate") from None


def _worker_died() -> BiopsynavError:
    return BiopsynavError("force calibration: a worker process died (killed by the system, "
                          "for instance out of memory); run again", "generate")


#: The models a calibration solves on: the case grid's (a refined teacher's first search)
#: and the teacher's.
CASE_GRID, TEACHER = "case_grid", "teacher"
#: A calibration worker's case and, per stage, its (model, settings, push contacts).
_WORKER: dict[str, Any] = {}


def init_calibration(case: Any) -> None:
    """Set-up of a calibration worker process: its case (the models are built on first use)."""
    _WORKER.clear()
    _WORKER["case"] = case


def calibration_depth(stage: str, index: int, force_n: float) -> float:
    """Task of a calibration worker: the probe displacement (mm) of push ``index`` at
    ``force_n`` N total on the model of ``stage``; inf when the solve fails."""
    from ..fem import Loads, solve
    from ..probe import nodal_forces
    from .worker import probe_displacement

    model, settings, contacts = _stage_context(stage)
    contact, direction = contacts[index]
    try:
        u, _ = solve(model, Loads(forces=nodal_forces(contact, force_n * direction)), settings)
    except SolverError:
        return math.inf
    return probe_displacement(contact @ u)


def _stage_context(stage: str) -> tuple[Any, Any, list]:
    """This worker's (model, solver settings, push contacts) of ``stage``, built once."""
    if stage not in _WORKER:
        from ..fem import FEModel
        from ..fem.teacher import build_teacher
        from ..grid.embedding import surface_embedding
        from .worker import sample_solver_settings

        case = _WORKER["case"]
        if stage == CASE_GRID:
            model = FEModel.from_case(case)
            skin = surface_embedding(case.grid, case.anatomy).matrix
        else:
            teacher = build_teacher(case)
            model, skin = teacher.model, teacher.skin.matrix
        _WORKER[stage] = (model, sample_solver_settings(case),
                          push_contacts(skin, calibration_pushes(case)))
    return _WORKER[stage]


def push_contacts(skin: Any, pushes: list) -> list:
    """Per push, its contact points' rows of the skin embedding ``skin`` (CSR (n_skin,
    n_nodes)) and its unit force direction (3,): what :func:`calibration_depth` solves."""
    return [(skin[p.contact], p.direction) for p in pushes]


def calibration_pushes(case: Any) -> list:
    """The calibration's probe pushes (their force magnitudes unused)."""
    from ..probe import eligible_centers, push_for_draw

    cfg = case.cfg
    centers = eligible_centers(case.anatomy, cfg.probe.min_chest_distance_mm)
    return [push_for_draw(case.anatomy, cfg.probe, cfg.dataset.seed, CALIBRATION_INDEX + i,
                          0, centers, rigid=False) for i in range(cfg.probe.calibration_pushes)]


def quantile_depth(depths: np.ndarray) -> float:
    """The :data:`QUANTILE` of the pushes' probe displacements (mm; inf when too many
    failed)."""
    return float(np.quantile(depths, QUANTILE, method="inverted_cdf"))


def failures_allowed(n_pushes: int) -> int:
    """How many of ``n_pushes`` solves may fail before the :data:`QUANTILE` depth is inf
    (it is the ``ceil(QUANTILE n)``-th smallest depth)."""
    return n_pushes - math.ceil(QUANTILE * n_pushes - 1e-9)


def next_force(history: list[tuple[float, float]], target: float) -> float | None:
    """The next force (N) to try, or None when the bracket is closed.

    A secant step in log-log through the two nearest points (a proportional step from one),
    kept inside the bracket of forces known to fall short of ``target`` and known to go
    beyond it or fail (infinite depth): a step out of the bracket bisects it (geometric
    mean). None when the bracket is narrower than :data:`TOLERANCE`.
    """
    short = [f for f, d in history if d < target]
    beyond = [f for f, d in history if d >= target]
    lo, hi = (max(short) if short else 0.0), (min(beyond) if beyond else math.inf)
    if lo > 0 and hi < math.inf and hi / lo < 1.0 + TOLERANCE:
        return None
    force, depth = history[-1]
    if math.isfinite(depth):
        proposal = force * (target / max(depth, 1e-6)) ** (1.0 / _slope(history))
        if lo < proposal < hi:
            return proposal
    if lo > 0 and hi < math.inf:
        return math.sqrt(lo * hi)
    return 0.5 * hi if lo == 0 else 2.0 * lo


def _slope(history: list[tuple[float, float]]) -> float:
    """d log depth / d log force through the two latest finite points (1 without them),
    clipped to [0.3, 3]."""
    finite = [(f, d) for f, d in history if math.isfinite(d) and d > 0]
    if len(finite) < 2 or finite[-1][0] == finite[-2][0]:
        return 1.0
    (f0, d0), (f1, d1) = finite[-2], finite[-1]
    return min(max(math.log(d1 / d0) / math.log(f1 / f0), 0.3), 3.0)


def best_force(history: list[tuple[float, float]], target: float) -> tuple[float, float]:
    """The (force, quantile depth) tried that comes nearest ``target`` without failing: the
    one within :data:`TOLERANCE`, else the strongest whose depth fell short."""
    within = [(f, d) for f, d in history if abs(d - target) <= TOLERANCE * target]
    if within:
        return within[-1]
    short = [(f, d) for f, d in history if d < target]
    if not short:
        raise BiopsynavError(f"force calibration: every force tried pushed deeper than "
                             f"{target:g} mm or failed (force, depth: {_rounded(history)}); "
                             "set [probe] calibrate_force = false and choose f_max_n",
                             "generate")
    return max(short)


def _rounded(history: list[tuple[float, float]]) -> list[list[float]]:
    return [[round(f, 4), round(d, 2) if math.isfinite(d) else None] for f, d in history]
