"""Does the FE engine answer? Rigid-probe pushes over every lesion, up to the clinical 35 mm.

    python benchmarks/fe_pushes.py CASE [--depths 8.75 17.5 26.25 35] [--json out.json]

The probe is placed over each lesion of the case as in Table 2
(:func:`biopsynav.evaluate.placement.place_probe`) and pushed along its beam by each depth,
through ``Tracker(engine="fem")`` with the case's own materials and ``[solver]`` settings
(what ``biopsynav track --engine fem`` does); the rest pose itself is asked first. Printed per
push: status, reason, wall time, Newton iterations and load increments of the solve. The last
line reads ``RESULT`` with the number of pushes answered ``ok`` out of all (and how many of
them elastic contact answered only with stiffer springs), the rest poses that
answered at once, and the median and largest solve time.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from biopsynav.case import Case  # noqa: E402
from biopsynav.evaluate.placement import place_case_probe  # noqa: E402
from biopsynav.tracker import Tracker  # noqa: E402

CLINICAL_DEPTHS = (8.75, 17.5, 26.25, 35.0)


def push_row(tracker: Tracker, pose: np.ndarray) -> dict:
    """Status, reason, wall time (s) and solve effort of one pose."""
    t0 = time.perf_counter()
    res = tracker.update(pose)
    row = {"status": res.status, "reason": res.reason, "seconds": time.perf_counter() - t0}
    solve = tracker.last_solve
    if solve is not None:
        row.update(iterations=solve.iterations, increments=solve.increments,
                   spring_factor=solve.spring_factor)
    return row


def springs_note(row: dict) -> str:
    """'springs x4  ' when elastic contact answered with stiffer springs than asked
    (:data:`biopsynav.fem.solver.SPRING_FALLBACK`), else ''."""
    factor = row.get("spring_factor")
    return "" if factor in (None, 1.0) else f"springs x{factor:g}  "


def run(case: Case, depths: list[float]) -> list[dict]:
    """One row per lesion and depth (depth 0: the rest pose)."""
    tracker = Tracker.load(case, engine="fem")
    rows = []
    for li, les in enumerate(case.anatomy.lesions):
        placement = place_case_probe(case, li)
        n_contact = tracker.set_rest_pose(placement.pose)
        for depth in [0.0, *depths]:
            row = {"lesion": int(les.id), "depth_mm": depth, "lesion_depth_mm":
                   placement.depth_mm, "contact_points": n_contact,
                   **push_row(tracker, placement.pushed(depth))}
            rows.append(row)
            print(f"lesion {row['lesion']:>3} ({placement.depth_mm:4.1f} mm deep)  push "
                  f"{depth:5.2f} mm  {row['status']:<14} {row['seconds']:6.2f} s  "
                  f"{row.get('iterations', 0):3d} it  {row.get('increments', 0):2d} inc  "
                  f"{springs_note(row)}{row['reason']}", flush=True)
    return rows


def summary(rows: list[dict]) -> str:
    pushes = [r for r in rows if r["depth_mm"] > 0]
    rests = [r for r in rows if r["depth_mm"] == 0]
    ok = [r for r in pushes if r["status"] == "ok"]
    times = [r["seconds"] for r in ok] or [float("nan")]
    at_once = sum(r["status"] == "ok" and r["seconds"] < 0.05 for r in rests)
    stiffer = sum(springs_note(r) != "" for r in ok)
    return (f"RESULT pushes ok {len(ok)}/{len(pushes)} ({stiffer} with stiffer springs); rest "
            f"poses answered at once {at_once}/{len(rests)}; solve time median "
            f"{np.median(times):.2f} s, largest {max(times):.2f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case_dir", type=Path)
    ap.add_argument("--depths", type=float, nargs="+", default=list(CLINICAL_DEPTHS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    case = Case.load(args.case_dir)
    rows = run(case, args.depths)
    line = summary(rows)
    print(line)
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows, "result": line}, indent=1))


if __name__ == "__main__":
    main()
