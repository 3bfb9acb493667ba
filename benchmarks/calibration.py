"""Time of the force calibration (``[probe] calibrate_force``) on one and on two worker
processes.

Runs :func:`biopsynav.dataset.calibrate.calibrate_force` on CASE (default: the built-in
phantom, built in a temporary folder) twice in one process: with its solves in one worker
process (the speed of the serial calibration before 2026-11-29, which solved in
the main process), then spread over two (``--workers``). Both must find the same force and the
same rounds, to the bit; the script prints both times, the FE solves each made and the
rounds (``--reverse`` times the two workers first, to see any effect of the order).
``--every-push`` solves every push of every round (the rule before 2026-11-29:
no early end of a failing round) in both runs.

Last line: ``RESULT one_worker_s=<..> workers_s=<..> workers=<n> solves=<one>/<n>
same_rounds=<..>``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path


def timed(case, workers: int) -> dict:
    """``calibrate_force(case, workers)``: its record and wall time."""
    from biopsynav.dataset import calibrate

    start = time.perf_counter()
    found = calibrate.calibrate_force(case, workers)
    return {"seconds": round(time.perf_counter() - start, 1), "found": found}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", nargs="?", type=Path, help="case folder (default: phantom)")
    parser.add_argument("--pushes", type=int, help="override [probe] calibration_pushes")
    parser.add_argument("--workers", type=int, default=2, help="the parallel run's workers")
    parser.add_argument("--reverse", action="store_true", help="time the parallel run first")
    parser.add_argument("--every-push", action="store_true",
                        help="no early end of a failing round (the rule before)")
    args = parser.parse_args()

    from biopsynav.case import Case, make_phantom_case
    from biopsynav.dataset import calibrate
    from biopsynav.fem import compile_kernels

    tmp = None
    if args.case is None:
        tmp = Path(tempfile.mkdtemp(prefix="biopsynav-bench-"))
        make_phantom_case(tmp / "phantom")
    if args.every_push:
        calibrate.failures_allowed = lambda n: n
    try:
        case = Case.load(args.case or tmp / "phantom")
        if args.pushes:
            case.cfg.probe.calibration_pushes = args.pushes
        compile_kernels()
        order = (args.workers, 1) if args.reverse else (1, args.workers)
        runs = {workers: timed(case, workers) for workers in order}
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    one, many = runs[1], runs[args.workers]
    same = one["found"]["rounds"] == many["found"]["rounds"]
    for workers, run in runs.items():
        print(f"{workers} worker(s): {run['seconds']} s, {run['found']['solves']} FE solves, "
              f"rounds (force N, quantile depth mm) {json.dumps(run['found']['rounds'])}")
    print(f"RESULT one_worker_s={one['seconds']} workers_s={many['seconds']} "
          f"workers={args.workers} solves={one['found']['solves']}/{many['found']['solves']} "
          f"same_rounds={same}")


if __name__ == "__main__":
    main()
