"""Each lesion's teacher gap on a case, as the lesion self-check measures it, for the bound's fit.

    python benchmarks/teacher_gap.py CASE --name NAME

The teacher gap (``biopsynav.evaluate.lesion_check.teacher_gap``) is the share of a lesion's
motion by which the tracking model's FE teacher, on a grid ``TEACHER_CHECK_REFINEMENT`` times
finer, moves it otherwise when the probe is placed over it as Table 2 places it and pushed
``TEACHER_CHECK_DEPTH_MM``. The check computes it with every model's self-check; this script
computes it on a case without a model (it depends on the anatomy, the grid and the teacher's
law, not on the network), so that ``benchmarks/error_bound.py`` can fit the bound on truth
comparisons made before the gap was part of the check (``bound-rows-*.json``: every network
of one case shares its teacher).

Writes ``benchmarks/results/teacher-gap-NAME.json`` (``lesions``: {id: gap, None where either
grid gave no answer}); the last line reads ``RESULT lesions=N gap_mean=... gap_max=...``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from resultfile import write_result


def lesion_gaps(case_dir: Path) -> dict[str, float | None]:
    """{lesion id: teacher gap} of every lesion of the case in ``case_dir``."""
    from biopsynav.case import Case
    from biopsynav.evaluate.lesion_check import (
        TEACHER_CHECK_DEPTH_MM,
        finer_teacher,
        pushed_lesion,
        teacher_gap,
    )
    from biopsynav.evaluate.placement import place_case_probe
    from biopsynav.evaluate.simulation import evaluation_solver_settings
    from biopsynav.tracker.core import fem_engine

    case = Case.load(case_dir)
    settings = evaluation_solver_settings(case)
    fem, fine = fem_engine(case, settings), finer_teacher(case, settings)
    gaps = {}
    for li, lesion in enumerate(case.anatomy.lesions):
        placement = place_case_probe(case, li)
        teacher = pushed_lesion(fem, placement, li, TEACHER_CHECK_DEPTH_MM)
        gaps[str(lesion.id)] = teacher_gap(fine, placement, li, teacher)
        print(f"lesion {lesion.id}: teacher gap {gaps[str(lesion.id)]}", flush=True)
    return gaps


def main(argv: list[str] | None = None) -> int:
    from biopsynav.evaluate.lesion_check import TEACHER_CHECK_DEPTH_MM, TEACHER_CHECK_REFINEMENT

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case_dir", type=Path)
    p.add_argument("--name", required=True, help="the result file is teacher-gap-NAME.json")
    args = p.parse_args(argv)
    gaps = lesion_gaps(args.case_dir)
    values = np.array([g for g in gaps.values() if g is not None], dtype=np.float64)
    write_result(f"teacher-gap-{args.name}",
                 {"lesions": gaps, "depth_mm": TEACHER_CHECK_DEPTH_MM,
                  "refinement": TEACHER_CHECK_REFINEMENT})
    mean, top = (values.mean(), values.max()) if len(values) else (np.nan, np.nan)
    print(f"RESULT lesions={len(gaps)} gap_mean={mean:.4f} gap_max={top:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
