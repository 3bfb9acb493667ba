"""Table 2's pushes solved in local worker processes, before the methods run.

Two engines of Table 2 carry nothing from one rest pose to the next: the fine-grid reference
(:class:`~biopsynav.evaluate.references.GridReference`, whose ``independent_rest_poses`` says
so) and the ``fem`` method (the network's FE teacher, which solves every push from rest). Each
lesion's pushes are then one task: they run in ``workers`` spawned processes
(:class:`~biopsynav.dataset.pool.WorkerProcesses`), each holding its own engine (built by a
factory: :func:`grid_reference`, :func:`teacher_engine`) and factoring on one thread, a
lesion's pushes in the order asked (shallow to deep: the reference continues each from the
equilibrium of the one before), the lesions of the deepest pushes first (they cost the most,
so the last tasks are short). A sparse factorisation gains less than two-fold from a second
thread; two solves at once gain two-fold. The answers are then served to
:func:`~biopsynav.evaluate.simulation.run_simulation` in the order it asks for them
(:class:`SolvedAnswers`, :class:`SolvedReference`), so Table 2's records, the methods'
timings (each answer's own solve time) and output are those of a sequential run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

#: The worker process's engine (set up once by :func:`init_engine`).
_ENGINE: Any = None

#: (contact points at the rest pose, answer) of each pose, keyed by the pose's bytes
Answers = dict[bytes, tuple[int, Any]]


def init_engine(factory: Callable[..., Any], args: tuple) -> None:
    """Worker set-up: the engine ``factory(*args)``."""
    global _ENGINE
    _ENGINE = factory(*args)


def grid_reference(kind: type, case: Any, setup: Any, settings: Any) -> Any:
    """A fine-grid reference of class ``kind`` of ``case``, factoring on one thread."""
    return kind(case, setup, dataclasses.replace(settings, threads=1))


def teacher_engine(case: Any, settings: Any) -> Any:
    """Table 2's ``fem`` method of ``case`` (:func:`~biopsynav.tracker.core.fem_engine`, the
    network's FE teacher), factoring on one thread."""
    from ..tracker.core import fem_engine

    return fem_engine(case, dataclasses.replace(settings, threads=1))


def solve_lesion(rest: np.ndarray, poses: list[np.ndarray]) -> tuple[int, list[Any]]:
    """Worker task: :func:`engine_answers` of the worker's engine."""
    return engine_answers(_ENGINE, rest, poses)


def engine_answers(engine: Any, rest: np.ndarray, poses: list[np.ndarray],
                   before_each: Callable[[int], None] | None = None) -> tuple[int, list[Any]]:
    """``engine``'s answers to the probe at each of ``poses`` ((4, 4) each, in turn) over the
    rest pose ``rest`` (4, 4): (contact points at rest, one :class:`TrackingResult` per
    pose); ``before_each(k)`` is called before the k-th pose's solve."""
    n_contact, results = engine.set_rest_pose(rest), []
    for k, pose in enumerate(poses):
        if before_each is not None:
            before_each(k)
        results.append(engine.update(pose))
    return n_contact, results


class SolvedAnswers:
    """An engine whose answers were solved beforehand: ``set_rest_pose`` and ``update``
    return them (keyed by the poses' bytes)."""

    def __init__(self, answers: Answers) -> None:
        self.answers = answers

    def set_rest_pose(self, pose: np.ndarray) -> int:
        return self.answers[pose_bytes(pose)][0]

    def update(self, pose: np.ndarray) -> Any:
        return self.answers[pose_bytes(pose)][1]


class SolvedReference(SolvedAnswers):
    """A reference whose answers were solved beforehand (``kept_lesions`` of its lesions'
    in an earlier evaluation, :mod:`biopsynav.evaluate.kept`); its facts, description and
    build time are the solving reference's, with the kept lesions said."""

    def __init__(self, reference: Any, answers: Answers, kept_lesions: int = 0) -> None:
        super().__init__(answers)
        self.reference = reference
        self.build_s = reference.build_s
        self.kept_lesions = int(kept_lesions)

    def facts(self) -> dict:
        kept = {"kept_lesions": self.kept_lesions} if self.kept_lesions else {}
        return self.reference.facts() | kept

    def describe(self) -> str:
        kept = (f"; {self.kept_lesions} lesions' answers kept from an earlier evaluation"
                if self.kept_lesions else "")
        return self.reference.describe() + kept


def pose_bytes(pose: np.ndarray) -> bytes:
    """A pose (4, 4) as the key of :class:`SolvedAnswers`: its bytes."""
    return np.ascontiguousarray(pose, dtype=np.float64).tobytes()


def lesion_answers(answers: Answers, rest: np.ndarray,
                   poses: list[np.ndarray]) -> tuple[int, list[Any]]:
    """A lesion's (contact points at rest, one answer per pose) from ``answers``."""
    return answers[pose_bytes(rest)][0], [answers[pose_bytes(p)][1] for p in poses]


def lesion_entries(rest: np.ndarray, poses: list[np.ndarray], n_contact: int,
                   results: list[Any]) -> Answers:
    """A lesion's answers as :class:`SolvedAnswers` holds them (:func:`lesion_answers`
    reads them back): each pose's, and the rest pose's contact points."""
    entries = {pose_bytes(p): (n_contact, r) for p, r in zip(poses, results, strict=True)}
    return entries | {pose_bytes(rest): (n_contact, None)}


def solve_in_workers(factory: Callable[..., Any], args: tuple,
                     lesions: list[tuple[np.ndarray, list[np.ndarray]]], workers: int,
                     what: str) -> Answers:
    """The answers of the engine ``factory(*args)`` to each lesion's pushes ((rest pose,
    [pushed poses]) pairs, (4, 4) each) solved in ``workers`` local processes, one task per
    lesion, the lesions of the deepest pushes first; the rest poses answer with their contact
    points. ``what`` names the engine in the error of a worker that died."""
    from concurrent.futures.process import BrokenProcessPool

    from ..dataset.pool import WorkerProcesses
    from ..errors import BiopsynavError

    deepest = [max((float(np.linalg.norm(p[:3, 3] - rest[:3, 3])) for p in poses), default=0.0)
               for rest, poses in lesions]
    answers: Answers = {}
    with WorkerProcesses(workers, init_engine, (factory, args)) as pool:
        futures = {pool.submit(solve_lesion, *lesions[i]): i
                   for i in np.argsort(deepest, kind="stable")[::-1]}
        pending = list(futures)
        try:
            while pending:
                for future in pool.wait_any(pending):
                    pending.remove(future)
                    rest, poses = lesions[futures[future]]
                    answers.update(lesion_entries(rest, poses, *future.result()))
        except BrokenProcessPool:
            pool.check_started()  # a script without the __main__ guard: named as such
            raise BiopsynavError(f"a worker process of {what} died with {len(pending)} of its "
                                 f"{len(lesions)} lesions unsolved (out of memory?); "
                                 "`biopsynav evaluate CASE --workers 1` solves them in this "
                                 "process", "Table 2") from None
    return answers
