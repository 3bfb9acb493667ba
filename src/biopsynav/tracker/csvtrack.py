"""``biopsynav track``: poses CSV in, lesion positions CSV out.

Input columns ``frame, sequence, m00 ... m23`` (top 3 x 4 of the probe-to-anatomy transform,
mm); the first frame of each sequence is its rest pose. Output columns
``frame, lesion_id, x, y, z, status`` (NaN coordinates when the status is not reliable).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fileio import write_text_atomic

MATRIX_COLUMNS = [f"m{r}{c}" for r in range(3) for c in range(4)]


def read_poses(path: str | Path) -> list[tuple[int, str, np.ndarray]]:
    """Rows (frame, sequence, pose (3, 4)) of a poses CSV; errors name the line."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", str(path))
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        cols = {c.strip() for c in reader.fieldnames or []}
        missing = [c for c in ["frame", "sequence", *MATRIX_COLUMNS] if c not in cols]
        if missing:
            raise InputError(f"poses CSV lacks the columns {', '.join(missing)}", str(path))
        rows = []
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
            try:
                frame = int(row["frame"])
                pose = np.array([float(row[c]) for c in MATRIX_COLUMNS]).reshape(3, 4)
            except ValueError:
                raise InputError(f"line {line}: frame must be an integer and m00..m23 numbers",
                                 str(path)) from None
            rows.append((frame, row["sequence"], pose))
    if not rows:
        raise InputError("poses CSV has no rows", str(path))
    return rows


def track_rows(tracker, rows: list[tuple[int, str, np.ndarray]]) -> list[tuple]:
    """Track every row; the first row of each sequence sets the rest pose."""
    out = []
    seen: set[str] = set()
    for frame, sequence, pose in rows:
        if sequence not in seen:
            seen.add(sequence)
            try:
                tracker.set_rest_pose(pose)
            except InputError as exc:
                raise InputError(f"frame {frame}: rest pose of sequence {sequence!r}: "
                                 f"{exc.what}", "poses") from None
        result = tracker.update(pose)
        for les in result.lesions:
            out.append((frame, les.id, *les.center, les.status))
    return out


def track_csv(case_dir: str | Path, poses: str | Path, out: str | Path,
              engine: str = "net") -> int:
    """Track all poses of ``poses`` with the case's tracker; write ``out``; return pose count."""
    from .core import Tracker

    rows = read_poses(poses)
    tracker = Tracker.load(case_dir, engine=engine)
    lines = track_rows(tracker, rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["frame", "lesion_id", "x", "y", "z", "status"])
    for frame, lid, x, y, z, status in lines:
        writer.writerow([frame, lid, f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", status])
    write_text_atomic(out, buf.getvalue())
    return len(rows)
