"""Table 2's fine-grid ground truth solved in local worker processes, before the methods run.

Each push of the fine-grid reference (:class:`~biopsynav.evaluate.references.GridReference`,
whose ``solves_from_rest`` says so) is solved from rest, so the pushes of every lesion are
independent tasks: they run in
``workers`` spawned processes (:class:`~biopsynav.dataset.pool.WorkerProcesses`), each
holding its own fine-grid FE model and factoring on one thread, the deepest pushes first
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


def solve_push(rest: np.ndarray, pose: np.ndarray) -> tuple[int, Any]:
    """Worker task: the reference's answer to the probe at ``pose`` (4, 4) over the rest pose
    ``rest`` (4, 4); (contact points at rest, the :class:`TrackingResult`)."""
    n_contact = _REFERENCE.set_rest_pose(rest)
    return n_contact, _REFERENCE.update(pose)


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
                     pushes: list[tuple[np.ndarray, np.ndarray]], workers: int
                     ) -> SolvedReference:
    """``reference`` with the answers to ``pushes`` ((rest pose, pushed pose) pairs, (4, 4)
    each) solved in ``workers`` local processes, deepest first; the rest poses answer with
    their contact points too."""
    from concurrent.futures.process import BrokenProcessPool

    from ..dataset.pool import WorkerProcesses
    from ..errors import BiopsynavError

    depth = [float(np.linalg.norm(pose[:3, 3] - rest[:3, 3])) for rest, pose in pushes]
    order = np.argsort(depth)[::-1]
    answers: dict[bytes, tuple[int, Any]] = {}
    with WorkerProcesses(workers, init_reference, (type(reference), case, setup, settings)) \
            as pool:
        futures = {pool.submit(solve_push, *pushes[i]): i for i in order}
        pending = list(futures)
        try:
            while pending:
                for future in pool.wait_any(pending):
                    pending.remove(future)
                    rest, pose = pushes[futures[future]]
                    n_contact, result = future.result()
                    answers[_key(pose)] = (n_contact, result)
                    answers.setdefault(_key(rest), (n_contact, None))
        except BrokenProcessPool:
            pool.check_started()  # a script without the __main__ guard: named as such
            raise BiopsynavError(f"a worker process of Table 2's ground truth died with "
                                 f"{len(pending)} of its {len(pushes)} pushes unsolved (out "
                                 "of memory?); `biopsynav evaluate CASE --workers 1` solves "
                                 "them in this process", "Table 2") from None
    return SolvedReference(reference, answers)
