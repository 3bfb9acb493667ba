"""``biopsynav run`` and ``biopsynav demo``: every missing stage of a case, in order.

Stages and their outputs: init (case.toml, anatomy.npz, grid.npz) -> generate (dataset.zarr,
dataset_summary.json) -> train (model/meta.json) -> evaluate (eval/table1.json,
eval/table2.json) -> report (report.html, report.md). A stage runs when its output is missing or
older than the output of the stage before it; generation and training resume where they
stopped, so running again after an interruption continues rather than restarts.
"""

from __future__ import annotations

import time
from pathlib import Path

from .config import load_config
from .fileio import read_json

QUICK = {
    "grid": {"cell_size_mm": 12.0},
    "evaluate": {"max_lesions": 3, "reference_refinement": 1.5},
    "dataset": {"n_train": 64, "n_test": 16},
    "network": {"iterations": 500, "val_interval": 250},  # docs/network.md: physics baseline
}

#: The full demo evaluates Table 2 on 3 of the 10 lesions: each lesion costs 3-9 minutes of
#: fine-grid FE reference solves on 2 cores (BENCHMARKS.md); set [evaluate] max_lesions = 0
#: in demo-case/case.toml and run `biopsynav evaluate demo-case` for all of them.
FULL_DEMO = {"evaluate": {"max_lesions": 3}}


def _mtime(path: Path) -> float:
    return path.stat().st_mtime if path.exists() else -1.0


def _stale(output: Path, *inputs: Path) -> bool:
    """True when ``output`` is missing or older than any existing input."""
    return not output.exists() or any(_mtime(output) < _mtime(p) for p in inputs)


def _banner(step: int, total: int, text: str) -> None:
    print(f"\n[{step}/{total}] {text}", flush=True)


def dataset_complete(case_dir: Path) -> bool:
    """True when dataset.zarr holds every requested sample for the current anatomy, grid and
    protocol (then ``generate`` has nothing to do)."""
    from .case import Case
    from .dataset.store import check_compatible, dataset_path, open_store, protocol_dict
    from .errors import BiopsynavError

    if not dataset_path(case_dir).exists():
        return False
    try:
        case = Case.load(case_dir)
        cfg = case.cfg
        store = open_store(dataset_path(case_dir), mode="r")
        check_compatible(store, case.fingerprint(),
                         protocol_dict(cfg, cfg.dataset.n_train, cfg.dataset.n_test))
        return bool(store.done_mask().all())
    except BiopsynavError:  # generate_case then reports what is wrong
        return False


def run_case(case_dir: str | Path, workers: int = 0, quick: bool = False) -> dict:
    """Run every stage of ``case_dir`` whose outputs are missing or out of date."""
    from .case import Case, build_case

    case_dir = Path(case_dir)
    cfg = load_config(case_dir)
    timings: dict[str, float] = {}
    grid_file, toml = case_dir / "grid.npz", case_dir / "case.toml"

    _banner(1, 5, "anatomy and grid")
    t = time.perf_counter()
    if _stale(grid_file, toml) and not (case_dir / "dataset.zarr").exists():
        build_case(case_dir, cfg)
        print("  rebuilt anatomy and grid from case.toml")
    else:
        print("  up to date")
    timings["grid_s"] = time.perf_counter() - t

    _banner(2, 5, "training data (FE simulations)")
    from .dataset.generate import generate_case

    t = time.perf_counter()
    summary_file = case_dir / "dataset_summary.json"
    if dataset_complete(case_dir):
        print("  up to date")
        data_summary = read_json(summary_file, "run `biopsynav generate CASE` to rewrite it",
                                 missing_ok=True) or {}
    else:
        data_summary = generate_case(case_dir, workers=workers)
    timings["generate_s"] = time.perf_counter() - t

    _banner(3, 5, "network training")
    meta = case_dir / "model" / "meta.json"
    t = time.perf_counter()
    if _stale(meta, summary_file):
        from .network.train import train_case

        train_case(case_dir)
    else:
        print("  up to date")
    timings["train_s"] = time.perf_counter() - t

    _banner(4, 5, "evaluation (Table 1 and Table 2)")
    table2 = case_dir / "eval" / "table2.json"
    t = time.perf_counter()
    if _stale(table2, meta):
        from .evaluate import evaluate_case

        evaluate_case(case_dir, quick=quick)
    else:
        print("  up to date")
    timings["evaluate_s"] = time.perf_counter() - t

    _banner(5, 5, "report")
    from .report import write_report

    t = time.perf_counter()
    paths = write_report(case_dir)
    timings["report_s"] = time.perf_counter() - t
    Case.load(case_dir)  # the finished case must load cleanly
    return {"report": [str(p) for p in paths], "timings_s": timings, "dataset": data_summary}


def run_demo(case_dir: str | Path = "demo-case", quick: bool = False, workers: int = 0) -> dict:
    """Build the built-in phantom case (if absent) and run the whole pipeline on it."""
    from .case import make_phantom_case

    case_dir = Path(case_dir)
    start = time.perf_counter()
    if not (case_dir / "case.toml").exists():
        print(f"building the built-in phantom case in {case_dir}"
              + (" (quick: reduced sizes)" if quick else ""))
        make_phantom_case(case_dir, overrides=QUICK if quick else FULL_DEMO)
    result = run_case(case_dir, workers=workers, quick=quick)
    minutes = (time.perf_counter() - start) / 60
    print(f"\nbiopsynav demo finished in {minutes:.1f} min. Report: {result['report'][0]}")
    return result

