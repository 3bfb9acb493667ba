"""Table 2 from user data: tracked probe poses plus lesion positions measured in images.

Inputs (the paper's phantom experiment, section 3.2):

* a poses CSV as for ``biopsynav track`` (``frame, sequence, m00 ... m23``; the first frame
  of each sequence is its rest pose, the probe just touching the skin);
* a measured positions CSV ``frame, lesion_id, x, y, z`` (mm, anatomy frame), e.g. lesion
  centres picked in the ultrasound images of those frames.

Where a lesion is measured in the rest frame of a sequence, that position is its landmark
(as in the paper): methods predict ``landmark + predicted displacement`` and the rigid model
predicts the landmark; otherwise the pre-operative centre of the case takes its place. Rest
frames themselves are not scored. The probe displacement of a frame is the distance of its
probe position from the rest pose's; it picks the bin D10 ... D30.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..case import Case, as_case
from ..errors import InputError
from ..tracker.csvtrack import read_poses
from .simulation import METHODS, evaluation_solver_settings, method_trackers
from .table import BIN_NAMES, Record, aggregate, bin_name

MEASURED_COLUMNS = ("frame", "lesion_id", "x", "y", "z")


def read_measured(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """Measured positions {(frame, lesion_id): (3,) mm}; errors name the file and line."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", str(path))
    out: dict[tuple[int, int], np.ndarray] = {}
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        cols = {c.strip() for c in reader.fieldnames or [] if c}
        missing = [c for c in MEASURED_COLUMNS if c not in cols]
        if missing:
            raise InputError(f"line 1: measured positions CSV lacks the columns "
                             f"{', '.join(missing)}", str(path))
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
            try:
                key = (int(row["frame"]), int(row["lesion_id"]))
                xyz = np.array([float(row[c]) for c in "xyz"])
            except ValueError:
                raise InputError(f"line {line}: frame and lesion_id must be integers and x, y, "
                                 "z numbers (mm)", str(path)) from None
            if not np.isfinite(xyz).all():
                raise InputError(f"line {line}: x, y, z must be finite", str(path))
            if key in out:
                raise InputError(f"line {line}: lesion {key[1]} of frame {key[0]} is given "
                                 "twice", str(path))
            out[key] = xyz
    if not out:
        raise InputError("measured positions CSV has no rows", str(path))
    return out


def _check_consistency(rows: list, measured: dict, lesion_ids: list[int], poses_path: Path,
                       measured_path: Path) -> None:
    frames = [f for f, _, _ in rows]
    seen: set[int] = set()
    for line, f in enumerate(frames, start=2):
        if f in seen:
            raise InputError(f"line {line}: frame {f} appears twice", str(poses_path))
        seen.add(f)
    for line, (f, lid) in enumerate(measured, start=2):
        if f not in seen:
            raise InputError(f"line {line}: frame {f} is not in the poses CSV {poses_path.name}",
                             str(measured_path))
        if lid not in lesion_ids:
            raise InputError(f"line {line}: lesion {lid} is not a lesion of this case (ids "
                             f"{', '.join(map(str, lesion_ids))})", str(measured_path))


def evaluate_measured(case: Case | str | Path, poses_csv: str | Path, measured_csv: str | Path,
                      methods: Sequence[str] = METHODS,
                      log: Callable[[str], None] = print) -> dict:
    """Table 2 (methods against measured positions) from a poses and a positions CSV.

    Returns the same structure as :func:`biopsynav.evaluate.simulation.run_simulation` with
    ``source`` "measured"; records carry ``frame`` and ``sequence``.
    """
    t_start = time.perf_counter()
    poses_csv, measured_csv = Path(poses_csv), Path(measured_csv)
    rows = read_poses(poses_csv)
    measured = read_measured(measured_csv)
    case = as_case(case)
    lesion_ids = [int(les.id) for les in case.anatomy.lesions]
    _check_consistency(rows, measured, lesion_ids, poses_csv, measured_csv)
    index_of = {lid: i for i, lid in enumerate(lesion_ids)}
    trackers = method_trackers(case, methods, evaluation_solver_settings(case))
    records: list[Record] = []
    rest: dict[str, tuple[np.ndarray, int]] = {}
    for frame, sequence, pose in rows:
        if sequence not in rest:
            rest[sequence] = (pose[:3, 3].copy(), frame)
            for name, tr in trackers.items():
                try:
                    tr.set_rest_pose(pose)
                except InputError as exc:
                    raise InputError(f"frame {frame}: rest pose of sequence {sequence!r} "
                                     f"({name}): {exc.what}", str(poses_csv)) from None
            continue
        targets = [lid for (f, lid) in measured if f == frame]
        if not targets:
            continue
        rest_t, rest_frame = rest[sequence]
        displacement = float(np.linalg.norm(pose[:3, 3] - rest_t))
        results = {name: tr.update(pose) for name, tr in trackers.items()}
        push = sum(1 for f, s, _ in rows if s == sequence and f < frame)
        for lid in targets:
            anchor = measured.get((rest_frame, lid), case.anatomy.lesions[index_of[lid]].center)
            base = {"lesion": lid, "push": push, "displacement_mm": displacement,
                    "bin": bin_name(displacement), "frame": frame, "sequence": sequence}
            truth = measured[(frame, lid)]
            for m in methods:
                records.append(_record(base, m, results.get(m), index_of[lid], anchor, truth))
    if not records:
        raise InputError("no measured position belongs to a pushed (non-rest) frame",
                         str(measured_csv))
    rows_ids = sorted({r.lesion for r in records})
    log(f"Table 2 from measured data: {len(records) // len(methods)} lesion positions in "
        f"{len(rest)} sequences")
    return {
        "source": "measured",
        "inputs": {"poses": str(poses_csv), "measured": str(measured_csv)},
        "methods": list(methods),
        "bins": list(BIN_NAMES),
        "records": [r.to_dict() for r in records],
        "tables": {m: aggregate(records, m, rows_ids).to_dict() for m in methods},
        "failures": [r.to_dict() for r in records if r.tre_mm is None],
        "timing": {"total_s": time.perf_counter() - t_start},
    }


def _record(base: dict, method: str, result, lesion_index: int, anchor: np.ndarray,
            truth: np.ndarray) -> Record:
    if method == "rigid":
        return Record(**base, method=method, tre_mm=float(np.linalg.norm(anchor - truth)),
                      time_ms=0.0)
    if not result.reliable:
        return Record(**base, method=method, tre_mm=None, status=result.status,
                      reason=result.reason, time_ms=result.latency_ms)
    lesion = result.lesions[lesion_index]
    predicted = anchor + lesion.displacement
    return Record(**base, method=method, tre_mm=float(np.linalg.norm(predicted - truth)),
                  time_ms=result.latency_ms, bound_mm=float(lesion.bound_mm))
