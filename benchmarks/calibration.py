"""Time of the force calibration (``[probe] calibrate_force``) with and without its early end
of a failing round.

Runs :func:`biopsynav.dataset.calibrate.calibrate_force` on CASE (default: the built-in
phantom, built in a temporary folder) twice in one process: first with every push of every
round solved (the rule before the forty-eighth session, ``failures_allowed`` set to the push
count), then with today's rule (a round stops once more pushes failed than its quantile
survives; the pushes deepest at the last force solved first). Both must find the same force
and the same rounds; the script prints both times, the FE solves each made and the rounds
(``--early-first`` runs today's rule first, to see any effect of the order).

Last line: ``RESULT every_push_s=<..> early_end_s=<..> solves=<every>/<early> same_rounds=<..>``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path


def timed(case, solve_every_push: bool) -> dict:
    """``calibrate_force(case)`` with or without the early end; its record and wall time."""
    from biopsynav import fem
    from biopsynav.dataset import calibrate

    rule, solve, solves = calibrate.failures_allowed, fem.solve, []
    if solve_every_push:
        calibrate.failures_allowed = lambda n: n

    def counted(*args, **kwargs):
        solves.append(1)
        return solve(*args, **kwargs)

    fem.solve = counted  # calibration_depths imports it from biopsynav.fem at each call
    try:
        start = time.perf_counter()
        found = calibrate.calibrate_force(case)
        return {"seconds": round(time.perf_counter() - start, 1), "solves": len(solves),
                "found": found}
    finally:
        calibrate.failures_allowed, fem.solve = rule, solve


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", nargs="?", type=Path, help="case folder (default: phantom)")
    parser.add_argument("--pushes", type=int, help="override [probe] calibration_pushes")
    parser.add_argument("--early-first", action="store_true", help="time today's rule first")
    args = parser.parse_args()

    from biopsynav.case import Case, make_phantom_case
    from biopsynav.fem import compile_kernels

    tmp = None
    if args.case is None:
        tmp = Path(tempfile.mkdtemp(prefix="biopsynav-bench-"))
        make_phantom_case(tmp / "phantom")
    try:
        case = Case.load(args.case or tmp / "phantom")
        if args.pushes:
            case.cfg.probe.calibration_pushes = args.pushes
        compile_kernels()
        if args.early_first:
            after = timed(case, False)
            before = timed(case, True)
        else:
            before, after = timed(case, True), timed(case, False)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    same = before["found"]["rounds"] == after["found"]["rounds"]
    for name, run in (("every push solved", before), ("early end", after)):
        print(f"{name}: {run['seconds']} s, {run['solves']} FE solves, rounds (force N, "
              f"quantile depth mm) {json.dumps(run['found']['rounds'])}")
    print(f"RESULT every_push_s={before['seconds']} early_end_s={after['seconds']} "
          f"solves={before['solves']}/{after['solves']} same_rounds={same}")


if __name__ == "__main__":
    main()
