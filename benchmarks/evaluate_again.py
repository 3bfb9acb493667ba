"""What evaluating a case again costs once its fine-grid truth is kept (`biopsynav.evaluate.
kept`): a patient's model trained again meets the same truth.

    python benchmarks/evaluate_again.py CASE [--workers 0] [--result-name NAME]

CASE: a trained case whose Table 2 truth is the fine grid (``[evaluate] reference =
"fine_grid"``, the default for a patient; e.g. a ``time_to_model.py --case ucdavis --keep``
folder). Its anatomy, grid, configuration, data set and model are copied into a temporary
folder (no ``eval/``), then ``biopsynav evaluate`` runs there twice: the first solves the
truth and keeps it, the second is what a re-evaluation after training again costs. Printed:
both wall times and whether the second's Table 2 records agree with the first's
(:func:`same_records`). Run it alone.

Writes ``benchmarks/results/evaluate-again-<case>.json``; the last line reads ``RESULT
first_s=... again_s=... same_records=...``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from resultfile import write_result
from speedprobe import speed_probes

#: what a trained case holds beside its evaluation
COPIED = ("case.toml", "anatomy.npz", "grid.npz", "inputs", "dataset.zarr",
          "dataset_summary.json", "model", "cache")


def trained_copy(case_dir: Path, work: Path) -> Path:
    """``case_dir``'s files of :data:`COPIED` (those it has) in ``work/<name>``."""
    out = work / case_dir.name
    out.mkdir(parents=True)
    for name in COPIED:
        src = case_dir / name
        if src.exists():
            (shutil.copytree if src.is_dir() else shutil.copy2)(src, out / name)
    return out


def timed_evaluation(case_dir: Path, workers: int) -> tuple[float, list]:
    """Seconds of ``biopsynav evaluate CASE`` and its Table 2 records."""
    from biopsynav.evaluate import evaluate_case

    start = time.perf_counter()
    evaluate_case(case_dir, workers=workers)
    seconds = time.perf_counter() - start
    return seconds, json.loads((case_dir / "eval" / "table2.json").read_text())["records"]


def same_records(a: list[dict], b: list[dict]) -> bool:
    """Whether two runs' Table 2 records agree: the same lesions, pushes, methods and
    statuses, TREs within 1e-9 mm (the FE method is solved again: round-off), their times
    aside (the network's and the FE method's differ from run to run)."""
    def key(r: dict) -> dict:
        return {k: v for k, v in r.items() if k not in ("time_ms", "tre_mm")}

    def close(x, y) -> bool:
        return (x is None and y is None) or (x is not None and y is not None
                                             and abs(x - y) <= 1e-9)

    return len(a) == len(b) and all(key(r) == key(s) and close(r["tre_mm"], s["tre_mm"])
                                    for r, s in zip(a, b, strict=False))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case", type=Path, help="a trained case whose Table 2 truth is the fine grid")
    p.add_argument("--workers", type=int, default=0, help="evaluate --workers (0: one a core)")
    p.add_argument("--result-name", help="result file name (default evaluate-again-<case>)")
    return p


def main(argv: list[str] | None = None) -> int:
    from biopsynav.config import load_config

    args = parser().parse_args(argv)
    if load_config(args.case).evaluate.reference != "fine_grid":
        sys.exit(f"evaluate_again: {args.case}: its Table 2 truth is not the fine grid")
    probes = speed_probes()
    with tempfile.TemporaryDirectory(prefix="evaluate-again-") as work:
        case_dir = trained_copy(args.case, Path(work))
        first_s, first = timed_evaluation(case_dir, args.workers)
        again_s, again = timed_evaluation(case_dir, args.workers)
    same = same_records(first, again)
    figures = {"first_s": first_s, "again_s": again_s, "same_records": same,
               "records": len(first)}
    write_result(args.result_name or f"evaluate-again-{args.case.name}", figures,
                 speed_probes=probes)
    print(f"evaluate, truth solved: {first_s:.1f} s; again, truth kept: {again_s:.1f} s; "
          f"Table 2 records {'the same' if same else 'DIFFERENT'} ({len(first)})")
    print(f"RESULT first_s={first_s:.1f} again_s={again_s:.1f} same_records={same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
