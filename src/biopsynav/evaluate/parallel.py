"""Table 2's fine-grid ground truth solved in local worker processes, before the methods run.

The fine-grid reference (:class:`~biopsynav.evaluate.references.GridReference`, whose
``independent_rest_poses`` says so) carries nothing from one rest pose to the next, so each
lesion's pushes are one task: they run in ``workers`` spawned processes
(:class:`~biopsynav.dataset.pool.WorkerProcesses`), each holding its own fine-grid FE model
and factoring on one thread, a lesion's pushes in the order asked (shallow to deep: each
continues from the equilibrium of the one before), the lesions of the deepest pushes first
(they cost the most, so the last tasks are short). A sparse factorisation gains less than
two-fold from a second thread; two solves at once gain two-fold. The answers are then served
to :func:`~biopsynav.evaluate.simulation.run_simulation` in the order it asks for them by
:class:`SolvedReference`, so Table 2's records, timings of the methods and output are those
of a sequential run.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

#: The worker process's fine-grid reference (set up once by :func:`init_reference`).
_REFERENCE: Any = None


def init_reference(kind: type, case: Any, setup: Any, settings: Any) -> None:
    """Worker set-up: a reference of class ``kind`` (the fine grid's) of ``case``, factoring
    on one thread."""
    global _REFERENCE
    _REFERENCE = kind(case, setup, dataclasses.replace(settings, threads=1))


def solve_lesion(rest: np.ndarray, poses: list[np.ndarray]) -> tuple[int, list[Any]]:
    """Worker task: the reference's answers to the probe at each of ``poses`` ((4, 4) each,
    in turn) over the rest pose ``rest`` (4, 4); (contact points at rest, one
    :class:`TrackingResult` per pose)."""
    n_contact = _REFERENCE.set_rest_pose(rest)
    return n_contact, [_REFERENCE.update(pose) for pose in poses]


class SolvedReference:
    """A reference whose answers were solved beforehand: ``set_rest_pose`` and ``update``
    return them (keyed by the poses' bytes), the facts and description are the solving
    reference's."""

    def __init__(self, reference: Any, answers: dict[bytes, tuple[int, Any]]) -> None:
        self.reference = reference
        self.answers = answers
        self.build_s = reference.build_s

    def set_rest_pose(self, pose: np.ndarray) -> int:
        return self.answers[_key(pose)][0]

    def update(self, pose: np.ndarray) -> Any:
        return self.answers[_key(pose)][1]

    def facts(self) -> dict:
        return self.reference.facts()

    def describe(self) -> str:
        return self.reference.describe()


def _key(pose: np.ndarray) -> bytes:
    return np.ascontiguousarray(pose, dtype=np.float64).tobytes()


def solve_in_workers(reference: Any, case: Any, setup: Any, settings: Any,
                     lesions: list[tuple[np.ndarray, list[np.ndarray]]], workers: int
                     ) -> SolvedReference:
    """``reference`` with the answers to each lesion's pushes ((rest pose, [pushed poses])
    pairs, (4, 4) each) solved in ``workers`` local processes, one task per lesion, the
    lesions of the deepest pushes first; the rest poses answer with their contact points."""
    from concurrent.futures.process import BrokenProcessPool

    from ..dataset.pool import WorkerProcesses
    from ..errors import BiopsynavError

    deepest = [max((float(np.linalg.norm(p[:3, 3] - rest[:3, 3])) for p in poses), default=0.0)
               for rest, poses in lesions]
    answers: dict[bytes, tuple[int, Any]] = {}
    with WorkerProcesses(workers, init_reference, (type(reference), case, setup, settings)) \
            as pool:
        futures = {pool.submit(solve_lesion, *lesions[i]): i
                   for i in np.argsort(deepest, kind="stable")[::-1]}
        pending = list(futures)
        try:
            while pending:
                for future in pool.wait_any(pending):
                    pending.remove(future)
                    rest, poses = lesions[futures[future]]
                    n_contact, results = future.result()
                    answers.update({_key(p): (n_contact, r)
                                    for p, r in zip(poses, results, strict=True)})
                    answers.setdefault(_key(rest), (n_contact, None))
        except BrokenProcessPool:
            pool.check_started()  # a script without the __main__ guard: named as such
            raise BiopsynavError(f"a worker process of Table 2's ground truth died with "
                                 f"{len(pending)} of its {len(lesions)} lesions unsolved (out "
                                 "of memory?); `biopsynav evaluate CASE --workers 1` solves "
                                 "them in this process", "Table 2") from None
    return SolvedReference(reference, answers)
