"""Table 2's fine-grid ground truth kept between evaluations.

The fine-grid truth (:class:`~biopsynav.evaluate.references.GridReference`) is most of a
patient's evaluation (minutes), and it depends on neither network: a model trained again
meets the same truth. Each lesion's answers (its contact points at rest and one
:class:`~biopsynav.tracker.result.TrackingResult` per push) are kept in
``CASE/eval/table2_fine_grid_answers.json`` under a key of everything they depend on
(:func:`truth_key`): the anatomy, every setting outside ``[network]``, ``[igtl]`` and
``[case]``, the reference's refinement and solver settings, and the bytes of biopsynav's own
source files, so that a changed case, setting or FE code solves them again rather than
serving another truth. A lesion is served from the file only when every one of its pushes is
there, and kept only when every one was solved (a deeper push continues from the one before:
a lesion's pushes are one solve). A damaged or foreign file is solved again, never trusted.
The file holds the :data:`KEPT_TRUTHS` truths written last, each under its key, so that
``evaluate --quick``'s coarser grid and the full one (or a setting changed and changed back)
do not solve each other's truth again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

#: The configuration's sections that a fine-grid answer does not depend on
UNUSED_SECTIONS = ("network", "igtl", "case")
#: The layout of the kept file: {"format", "truths": {key: {lesion key: answers}}}, the
#: truth written last last
FORMAT = "biopsynav-fine-grid-truth/2"
#: How many truths (keys) the file keeps; writing another drops the one written longest ago
KEPT_TRUTHS = 4


def truth_key(case: Any, refinement: float, settings: Any) -> str:
    """SHA-256 (hex) of what a fine-grid answer of ``case`` depends on: its anatomy, its
    configuration outside :data:`UNUSED_SECTIONS`, the reference's ``refinement`` and solver
    ``settings`` (a :class:`~biopsynav.fem.solver.SolverSettings`), and biopsynav's source."""
    cfg = {k: v for k, v in case.cfg.to_dict().items() if k not in UNUSED_SECTIONS}
    what = {"anatomy": case.anatomy.fingerprint(), "config": cfg,
            "refinement": float(refinement), "settings": dataclasses.asdict(settings),
            "code": source_digest()}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()


def source_digest() -> str:
    """SHA-256 (hex) of every Python file of the biopsynav package, by relative path."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


class KeptTruth:
    """The kept answers of one fine-grid truth (``key``) in the file ``path``."""

    def __init__(self, path: Path, key: str) -> None:
        self.path, self.key = Path(path), key
        self.lesions: dict[str, dict] = kept_truths(self.path).get(key, {})

    def answers(self, rest: np.ndarray, poses: list[np.ndarray]) -> tuple[int, list[Any]] | None:
        """The kept (contact points at rest, one TrackingResult per pose) of a lesion; None
        where one is missing or its entry is malformed (solved again, never trusted)."""
        try:
            kept = self.lesions[pose_key(rest, rest)]
            return int(kept["n_contact"]), [result_from_json(kept["pushes"][pose_key(rest, p)])
                                            for p in poses]
        except (KeyError, TypeError, ValueError, AttributeError):
            return None

    def keep(self, rest: np.ndarray, poses: list[np.ndarray], n_contact: int,
             results: list[Any]) -> None:
        """Add a lesion's solved pushes and write the file (atomically; a folder that cannot
        be written only costs the solves next time)."""
        from ..errors import WriteError
        from ..fileio import write_json_atomic

        pushes = {pose_key(rest, p): result_to_json(r)
                  for p, r in zip(poses, results, strict=True)}
        self.lesions[pose_key(rest, rest)] = {"n_contact": int(n_contact), "pushes": pushes}
        older = [(k, v) for k, v in kept_truths(self.path).items() if k != self.key]
        truths = dict(older[max(0, len(older) - KEPT_TRUTHS + 1):])  # the latest, this last
        truths[self.key] = self.lesions
        try:
            write_json_atomic(self.path, {"format": FORMAT, "truths": truths})
        except WriteError:
            return


def kept_truths(path: Path) -> dict[str, dict]:
    """{key: kept lesions} of ``path``, in the order written (the last written last); {} when
    it is missing, damaged or of another layout. A truth whose entry is not a mapping is left
    out."""
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if not isinstance(stored, dict) or stored.get("format") != FORMAT \
            or not isinstance(stored.get("truths"), dict):
        return {}
    return {k: v for k, v in stored["truths"].items() if isinstance(v, dict)}


def pose_key(rest: np.ndarray, pose: np.ndarray) -> str:
    """A cache key of a push (the P2 reference's, the stored truth's, the kept fine-grid
    truth's): rest pose and pose rounded to 1e-6 mm (and rotation entries)."""
    both = np.round(np.concatenate([rest[:3].ravel(), pose[:3].ravel()]), 6) + 0.0
    return hashlib.sha256(both.tobytes()).hexdigest()[:32]


def result_to_json(result: Any) -> dict:
    """A TrackingResult's status, reason, solve time and lesions as plain JSON."""
    return {"status": result.status, "reason": result.reason,
            "latency_ms": float(result.latency_ms),
            "lesions": [{"id": int(les.id), "center": np.asarray(les.center).tolist(),
                         "displacement": np.asarray(les.displacement).tolist(),
                         "status": les.status} for les in result.lesions]}


def result_from_json(data: dict) -> Any:
    """The TrackingResult of :func:`result_to_json`."""
    from ..tracker.result import LesionResult, TrackingResult

    lesions = [LesionResult(int(les["id"]), np.asarray(les["center"], dtype=np.float64),
                            np.asarray(les["displacement"], dtype=np.float64),
                            str(les["status"])) for les in data["lesions"]]
    return TrackingResult(lesions, str(data["status"]), str(data["reason"]),
                          float(data["latency_ms"]))
