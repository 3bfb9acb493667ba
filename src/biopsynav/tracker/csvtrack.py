"""``biopsynav track``: poses CSV in, lesion positions CSV out.

Input columns ``frame, sequence, m00 ... m23`` (top 3 x 4 of the probe-to-anatomy transform,
mm); the first frame of each sequence is its rest pose. Output columns
``frame, lesion_id, x, y, z, bound_mm, status, reason`` (``bound_mm``: the distance within
which the true position lies at 95 %, :mod:`biopsynav.tracker.bound`; NaN coordinates and
bound when the status is not reliable; ``reason`` says why, empty when reliable).
"""

from __future__ import annotations

import csv
import io
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..case import Case
from ..errors import InputError
from ..fileio import write_text_atomic

MATRIX_COLUMNS = [f"m{r}{c}" for r in range(3) for c in range(4)]


def read_poses(path: str | Path) -> list[tuple[int, str, np.ndarray]]:
    """Rows (frame, sequence, pose (3, 4)) of a poses CSV; errors name the line."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", str(path))
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                         f"{exc.start}); save the CSV as UTF-8", str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", str(path)) from None
    with io.StringIO(text, newline="") as fh:
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


def track_rows(tracker, rows: list[tuple[int, str, np.ndarray]], where: str = "poses"
               ) -> list[tuple]:
    """Track every row; the first row of each sequence sets the rest pose (InputError at
    ``where``, the poses' file, naming the frame, when the tracker refuses it). Returns
    (frame, TrackingResult) per row."""
    out = []
    seen: set[str] = set()
    for frame, sequence, pose in rows:
        if sequence not in seen:
            seen.add(sequence)
            try:
                tracker.set_rest_pose(pose)
            except InputError as exc:
                raise InputError(f"frame {frame}: rest pose of sequence {sequence!r}: "
                                 f"{exc.what}", where) from None
        out.append((frame, tracker.update(pose)))
    return out


def lesions_csv(tracked: list[tuple]) -> str:
    """The output CSV text of :func:`track_rows`' results, one row per lesion and pose."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["frame", "lesion_id", "x", "y", "z", "bound_mm", "status", "reason"])
    for frame, result in tracked:
        for les in result.lesions:
            x, y, z = les.center
            writer.writerow([frame, les.id, f"{x:.4f}", f"{y:.4f}", f"{z:.4f}",
                             f"{les.bound_mm:.3f}", les.status, result.reason])
    return buf.getvalue()


def track_csv(case: Case | str | Path, poses: str | Path, out: str | Path,
              engine: str = "net", log: Callable[[str], None] = print) -> dict[str, int]:
    """Track all poses of ``poses`` with the tracker of ``case`` (loaded, or its folder);
    write ``out``; return the number of poses per status. ``log`` is told what the bounds
    rest on (:attr:`Tracker.bound_basis`)."""
    from ..fileio import check_output_path
    from .core import Tracker

    check_output_path(out, "--out")
    rows = read_poses(poses)
    tracker = Tracker.load(case, engine=engine)
    log(f"95 % bounds: {tracker.bound_basis}")
    tracked = track_rows(tracker, rows, str(poses))
    write_text_atomic(out, lesions_csv(tracked))
    return dict(Counter(result.status for _, result in tracked))


def track_summary(counts: dict[str, int], n_lesions: int, out: str | Path) -> str:
    """What ``biopsynav track`` prints after tracking: the poses per status (``counts``) and
    where the lesions went; for a case without lesions (a healthy breast), that ``out``
    holds the header alone."""
    per_status = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
    done = f"{sum(counts.values())} poses tracked ({per_status})"
    if n_lesions == 0:
        return (f"{done}; the case has no lesions, so {out} holds the header alone (the "
                "tracker still follows the probe: `serve` and the Python API give the skin)")
    return f"{done}; lesion positions and the reason of every unreliable one written to {out}"
