"""Table 2 against a truth computed once and kept (``[evaluate] reference = "stored"``).

An independent P2 truth (:mod:`biopsynav.evaluate.p2`) costs minutes to an hour a lesion on
two cores; ``benchmarks/truth.py CASE --lesions 0 --depths 10 20 30`` computes it once per
anatomy and keeps every lesion's displacement at each depth in a JSON file (``key``: what the
answers depend on; ``lesions``: ``{index: {"displacement": [[dx, dy, dz] | None per depth],
"seconds": ..., "failure": ...}}``, mm). This reference serves those answers: Table 2 then
pushes each lesion to exactly the stored depths (instead of :func:`~.placement.push_depths`'s
levels) and costs what the network and the FE engine cost.

The file is ``[evaluate] truth_file`` (relative to the case folder), or, when that is empty,
the truth shipped with biopsynav whose key matches the case (``biopsynav/data/truths``: the
built-in phantom; the UC Davis breast as one material). A truth serves a case only when the
case's anatomy fingerprint, default tissue's E and nu, probe footprint and contact tolerance
are the ones it was computed with, and the case has one material; otherwise
:meth:`StoredTruth.check` says which differs, before anything runs.
"""

from __future__ import annotations

import json
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .kept import pose_key
from .placement import place_case_probe
from .references import default_tissue_material, other_materials, reference_result

#: the package folder of the shipped truths
SHIPPED = "data/truths"


def shipped_truths() -> list[Path]:
    """The truth files shipped with biopsynav, sorted by name."""
    folder = resources.files("biopsynav").joinpath(SHIPPED)
    return sorted(Path(str(p)) for p in folder.iterdir() if p.name.endswith(".json"))


def read_truth(path: Path) -> dict:
    """The truth file at ``path`` (``key`` and ``lesions``); InputError naming what is wrong."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"cannot read the stored truth {path}: {exc.strerror}",
                         "[evaluate] truth_file") from None
    except ValueError as exc:
        raise InputError(f"the stored truth {path} is not JSON ({exc})",
                         "[evaluate] truth_file") from None
    if not isinstance(data, dict) or not {"key", "lesions"} <= set(data):
        raise InputError(f"the stored truth {path} has no 'key' and 'lesions' (write it with "
                         "benchmarks/truth.py)", "[evaluate] truth_file")
    return data


def case_key(case: Any) -> dict:
    """What a stored truth must share with ``case``: anatomy fingerprint, the default tissue's
    E (MPa) and nu, the probe footprint and contact tolerance (mm)."""
    e_mpa, nu = default_tissue_material(case)
    probe = case.cfg.probe
    return {"anatomy": case.anatomy.fingerprint(), "E_mpa": e_mpa, "nu": nu,
            "footprint": [probe.shape, *probe.footprint_mm],
            "contact_tolerance_mm": probe.contact_tolerance_mm}


def key_differences(truth_key: dict, wanted: dict) -> list[str]:
    """The names of ``wanted``'s entries that ``truth_key`` holds otherwise."""
    return [k for k, v in wanted.items() if truth_key.get(k) != v]


def find_truth(case: Any) -> tuple[Path, dict]:
    """The stored truth file serving ``case`` and its contents; InputError when none does."""
    others = other_materials(case)
    if others:
        raise InputError("a stored truth is of one material, and this case's grid mixes "
                         f"tissues of other materials ({', '.join(others)}); use [evaluate] "
                         "reference = \"fine_grid\"", "[evaluate] reference")
    found, misses = matching_truth(case)
    if found is not None:
        return found
    name = case.cfg.evaluate.truth_file
    where = "[evaluate] truth_file" if name else "the truths shipped with biopsynav"
    raise InputError(f"no stored truth of this case in {where}: {'; '.join(misses)}. Compute "
                     "one with `python benchmarks/truth.py CASE --lesions 0 --depths 10 20 30 "
                     "--reference FILE` and set [evaluate] truth_file, or use [evaluate] "
                     "reference = \"fine_grid\"", "[evaluate] reference")


def matching_truth(case: Any) -> tuple[tuple[Path, dict] | None, list[str]]:
    """The stored truth (file, contents) of ``case``'s anatomy, material and probe among
    ``[evaluate] truth_file`` or the shipped ones (None: none), and each other file's name
    with what differs."""
    wanted = case_key(case)
    name = case.cfg.evaluate.truth_file
    misses = []
    for path in [case.dir / name] if name else shipped_truths():
        data = read_truth(path)
        differs = key_differences(data["key"], wanted)
        if not differs:
            return (path, data), misses
        misses.append(f"{path.name} ({', '.join(differs)} differ)")
    return None, misses


def why_no_truth(case: Any) -> str:
    """Why no stored truth serves ``case``, in a few words; empty when one does."""
    others = other_materials(case)
    if others:
        return f"its grid mixes tissues of other materials ({', '.join(others)})"
    if matching_truth(case)[0] is None:
        return "none is stored of its anatomy, material and probe"
    return ""


class StoredTruth:
    """A Table 2 reference that answers the pushes of a stored truth file (module doc)."""

    def __init__(self, case: Any, setup: Any, settings: Any) -> None:
        t0 = time.perf_counter()
        self.path, data = find_truth(case)
        self.truth_key = data["key"]
        self.depths_mm = [float(d) for d in self.truth_key.get("depths_mm", [])]
        self.stored = data["lesions"]
        self.anatomy, self.probe = case.anatomy, case.cfg.probe
        self.ids = [les.id for les in case.anatomy.lesions]
        self.centres = np.array([les.center for les in case.anatomy.lesions]).reshape(-1, 3)
        self.answers: dict[str, tuple[int, Any, str, float]] = {}
        self.lesions = sorted(li for li in map(int, self.stored) if li < len(self.ids))
        for li in self.lesions:
            self._index_lesion(case, li)
        self._rest: np.ndarray | None = None
        self.build_s = time.perf_counter() - t0

    check = staticmethod(find_truth)

    def _index_lesion(self, case: Any, li: int) -> None:
        """Every stored push of lesion index ``li`` by its pose key."""
        entry = self.stored[str(li)]
        placement = place_case_probe(case, li)
        seconds = float(entry.get("seconds", np.nan)) / max(len(self.depths_mm), 1)
        for depth, disp in zip(self.depths_mm, entry["displacement"], strict=True):
            why = "" if disp is not None else f"no stored answer: {entry.get('failure') or '?'}"
            key = pose_key(placement.pose, placement.pushed(depth))
            self.answers[key] = (li, disp, why, seconds * 1e3)

    def lesion_indices(self) -> list[int]:
        """The lesion indices the truth answers."""
        return self.lesions

    def push_depths(self, lesion_index: int) -> np.ndarray | None:
        """The depths (mm) Table 2 pushes lesion ``lesion_index`` to: the stored ones, or None
        when the truth holds nothing of that lesion."""
        return np.array(self.depths_mm) if lesion_index in self.lesions else None

    def set_rest_pose(self, pose: np.ndarray) -> int:
        from ..tracker.core import as_pose, contact_indices

        self._rest = as_pose(pose)
        probe = self.probe
        return len(contact_indices(self.anatomy, self._rest, probe.footprint,
                                   probe.contact_tolerance_mm))

    def update(self, pose: np.ndarray) -> Any:
        from ..tracker import result as st
        from ..tracker.core import as_pose

        start = time.perf_counter()
        found = self.answers.get(pose_key(self._rest, as_pose(pose)))
        if found is None:
            return reference_result(self.ids, self.centres, None, st.SOLVER_FAILED,
                                    "the stored truth holds no push at this pose", start)
        li, disp, why, solve_ms = found
        if disp is None:
            return reference_result(self.ids, self.centres, None, st.SOLVER_FAILED, why, start)
        moved = np.full_like(self.centres, np.nan)  # only the lesion under the probe is stored
        moved[li] = disp
        res = reference_result(self.ids, self.centres, moved, st.OK, "", start)
        res.latency_ms = solve_ms  # the solve's when the truth was computed
        return res

    def facts(self) -> dict:
        return {"kind": "stored", "file": self.path.name, "key": self.truth_key,
                "lesions": len(self.lesions), "depths_mm": self.depths_mm,
                "computed_s": {k: v.get("seconds") for k, v in self.stored.items()}}

    def describe(self) -> str:
        k = self.truth_key
        hours = sum(float(v.get("seconds") or 0.0) for v in self.stored.values()) / 3600
        return (f"independent P2 tetrahedral FE computed once and stored ({self.path.name}: "
                f"{len(self.lesions)} lesions at "
                f"{', '.join(f'{d:g}' for d in self.depths_mm)} mm, {k.get('tet_size_mm', '?')}"
                f" mm tetrahedra, {k.get('tet_fine_mm', '?')} mm under the probe, homogeneous "
                f"{float(k['E_mpa']) * 1e3:g} kPa, nu {float(k['nu']):g}; {hours:.1f} h of "
                "solves on 2 cores when computed)")


def choose_reference(case: Any) -> tuple[str, str]:
    """``[evaluate] reference = "auto"``: ``stored`` where a stored independent truth serves
    ``case``, else ``fine_grid``; and why, in words."""
    why = why_no_truth(case)
    if why:
        return "fine_grid", f"chosen: no stored independent truth serves this case: {why}"
    return "stored", "chosen: a stored independent truth serves this case"


def auto_reference(case: Any, setup: Any, settings: Any) -> Any:
    """The reference :func:`choose_reference` chooses for ``case``, built."""
    from ..reference_registry import reference_builder

    return reference_builder(choose_reference(case)[0])(case, setup, settings)


auto_reference.choose = choose_reference  # type: ignore[attr-defined]
