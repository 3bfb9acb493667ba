"""``biopsynav run`` and ``biopsynav demo``: every missing stage of a case, in order.

Stages and their outputs: init (case.toml, anatomy.npz, grid.npz) -> generate (dataset.zarr,
dataset_summary.json) -> train (model/meta.json) -> refine (with ``[refine] samples > 0``:
refine/dataset.zarr, refine/model/meta.json) -> evaluate (eval/table1.json, eval/table2.json)
-> report (report.html, report.md). A stage runs when its output is missing or
older than the output of the stage before it; generation and training resume where they
stopped, so running again after an interruption continues rather than restarts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from .case import Case, build_case
from .config import load_config
from .dataset.pool import check_workers
from .fileio import read_json
from .layout import CasePaths
from .recipes import DEFAULT_RECIPE, merged, recipe_overrides
from .reference_registry import check_reference
from .runtime import estimate_run, remaining_minutes, stage_table

QUICK = {
    "grid": {"cell_size_mm": 12.0},
    "evaluate": {"max_lesions": 3, "reference_refinement": 1.5},
    "dataset": {"n_train": 64, "n_test": 16},
    "probe": {"calibration_pushes": 12},  # a quicker, rougher force range
    "network": {"iterations": 500, "val_interval": 250},  # docs/network.md: physics baseline
    "refine": {"samples": 40, "held_out": 5, "iterations": 500},
}

#: The full demo's Table 2: every lesion against the phantom's independent P2 truth, computed
#: once and shipped (``reference = "stored"``, :mod:`biopsynav.evaluate.stored`), at 10, 20
#: and 30 mm: seconds for the truth instead of the 26 minutes a lesion that the 3.65 mm
#: fine-grid FE took on 2 cores (docs/evaluation.md).
FULL_DEMO = {"evaluate": {"max_lesions": 0, "reference": "stored"}}


def _mtime(path: Path) -> float:
    return path.stat().st_mtime if path.exists() else -1.0


def _stale(output: Path, *inputs: Path) -> bool:
    """True when ``output`` is missing or older than any existing input."""
    return not output.exists() or any(_mtime(output) < _mtime(p) for p in inputs)


def _banner(step: int, total: int, text: str, elapsed_s: float,
            expected_min: float | None = None) -> None:
    """The stage's heading with the whole run's elapsed time (and the expected total and
    what remains of it)."""
    clock = f"run at {elapsed_s / 60:.1f} min"
    if expected_min:
        left = max(expected_min - elapsed_s / 60, 0.0)
        clock += f" of about {expected_min:.0f}, about {left:.0f} to go"
    print(f"\n[{step}/{total}] {text}  ({clock})", flush=True)


def dataset_complete(case: Case) -> bool:
    """True when dataset.zarr holds every requested sample for the current anatomy, grid and
    protocol (then ``generate`` has nothing to do)."""
    from .dataset.store import check_compatible, open_store, protocol_dict
    from .errors import BiopsynavError

    if not case.paths.dataset.exists():
        return False
    try:
        cfg = case.cfg
        store = open_store(case.paths.dataset, mode="r")
        check_compatible(store, case.fingerprint(),
                         protocol_dict(cfg, cfg.dataset.n_train, cfg.dataset.n_test,
                                       case.anatomy))
        return bool(store.done_mask().all())
    except BiopsynavError:  # generate_case then reports what is wrong
        return False


def anatomy_stage(case_dir: Path) -> Case:
    """Stage 1: read case.toml (the only time a run reads it) and build anatomy and grid when
    they are missing or older than it (and no data set was made from them); the loaded case."""
    paths = CasePaths(case_dir)
    cfg = load_config(case_dir)
    if _stale(paths.grid, paths.config) and not paths.dataset.exists():
        case = build_case(case_dir, cfg)
        print("  rebuilt anatomy and grid from case.toml")
        return case
    print("  up to date")
    return Case.load(case_dir, cfg)


def data_stage(case: Case, workers: int) -> dict:
    """Stage 2: complete the training data; its summary."""
    from .dataset.generate import generate_case

    if not dataset_complete(case):
        return generate_case(case, workers=workers)
    print("  up to date")
    return read_json(case.paths.dataset_summary, "run `biopsynav generate CASE` to rewrite it",
                     missing_ok=True) or {}


def training_stage(case: Case) -> None:
    """Stage 3: train (or resume) when the model is missing or older than the data."""
    if _stale(case.paths.model_meta, case.paths.dataset_summary):
        from .network.train import train_case

        train_case(case)
    else:
        print("  up to date")


def refine_stage(case: Case, workers: int) -> dict:
    """Stage 3b (``[refine] samples > 0``, else nothing): the fine teacher's rigid pushes in
    ``CASE_DIR/refine`` (:mod:`biopsynav.refine`), and the case's network trained further on
    them when that model is missing or older than those pushes or than the case's model; the
    fine data's summary ({} when off)."""
    check_workers(workers)
    if not case.cfg.refine.samples:
        print("  off ([refine] samples = 0)")
        return {}
    from .errors import InputError
    from .refine import refine_case

    if not case.paths.model_meta.is_file():
        raise InputError("[refine] trains the case's network further: train it first "
                         "(`biopsynav train CASE`)", str(case.paths.model))
    fine = refine_case(case)
    summary = data_stage(fine, workers)
    if _stale(fine.paths.model_meta, fine.paths.dataset_summary, case.paths.model_meta):
        from .network.train import train_case

        train_case(fine)
    else:
        print("  model up to date")
    return summary


def evaluation_stage(case: Case, quick: bool, workers: int) -> None:
    """Stage 4: Table 1, each lesion's self-check and Table 2 when they are missing or older
    than the model (the tracking model: ``refine/model`` with ``[refine] samples > 0``); the
    self-check, the FE teacher and a fine-grid ground truth solved in ``workers`` local
    processes."""
    if _stale(case.paths.table2(), case.paths.model_meta, *_refined_meta(case)):
        from .evaluate import evaluate_case

        evaluate_case(case, quick=quick, workers=workers)
    else:
        print("  up to date")


def _refined_meta(case: Case) -> tuple[Path, ...]:
    """``(refine/model/meta.json,)`` with ``[refine] samples > 0``, else none: a refined
    model left from before does not make the evaluation stale."""
    return (CasePaths(case.paths.refine).model_meta,) if case.cfg.refine.samples else ()


def run_case(case_dir: str | Path, workers: int = 0, quick: bool = False) -> dict:
    """Run every stage of ``case_dir`` whose outputs are missing or out of date: the folder is
    read once into a :class:`~biopsynav.case.Case` that every stage is handed."""
    from .report import write_report

    check_workers(workers)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    estimate = None  # made before the long stages of a new case; read by timed()

    def timed(step: int, text: str, key: str, stage: Callable, *args):
        elapsed = time.perf_counter() - start
        expected = (None if estimate is None
                    else elapsed / 60 + remaining_minutes(estimate, timings))
        _banner(step, 6, text, elapsed, expected)
        t = time.perf_counter()
        out = stage(*args)
        timings[key] = time.perf_counter() - t
        return out

    case = timed(1, "anatomy and grid", "anatomy and grid", anatomy_stage, Path(case_dir))
    check_reference(case)  # a truth that cannot serve this case: said now, not after training
    if not dataset_complete(case):  # a new case: say what the whole will take first
        estimate = estimate_run(case, workers=workers)
        print(f"  {estimate.line()}", flush=True)
    data_summary = timed(2, "training data (FE simulations)", "training data", data_stage,
                         case, workers)
    timed(3, "network training", "network training", training_stage, case)
    timed(4, "training further on rigid pushes ([refine])", "refine", refine_stage, case,
          workers)
    timed(5, "evaluation (Table 1, lesion self-check, Table 2)", "evaluation",
          evaluation_stage, case, quick, workers)
    paths = timed(6, "report", "report", write_report, case)
    print(f"\n{stage_table(timings)}", flush=True)
    return {"report": [str(p) for p in paths], "timings_s": timings, "dataset": data_summary,
            "expected_min": None if estimate is None else estimate.total}


def demo_overrides(recipe: str, quick: bool) -> dict:
    """The demo case's case.toml values: ``recipe``'s, then the full demo's (or ``quick``'s
    reduced sizes; a recipe without ``[refine]`` keeps it off)."""
    chosen = recipe_overrides(recipe)
    values = merged(chosen, QUICK if quick else FULL_DEMO)
    if chosen.get("refine", {}).get("samples") == 0:
        values["refine"] = {"samples": 0}
    return values


def run_demo(case_dir: str | Path = "demo-case", quick: bool = False, workers: int = 0,
             recipe: str = DEFAULT_RECIPE) -> dict:
    """Build the built-in phantom case (if absent; its training data of ``recipe``,
    :mod:`biopsynav.recipes`) and run the whole pipeline on it."""
    from .case import make_phantom_case

    check_workers(workers)
    case_dir = Path(case_dir)
    start = time.perf_counter()
    if not CasePaths(case_dir).config.exists():
        print(f"building the built-in phantom case in {case_dir}"
              + (" (quick: reduced sizes)" if quick else ""))
        make_phantom_case(case_dir, overrides=demo_overrides(recipe, quick))
    result = run_case(case_dir, workers=workers, quick=quick)
    minutes = (time.perf_counter() - start) / 60
    print(f"\nbiopsynav demo finished in {minutes:.1f} min. Report: {result['report'][0]}")
    return result

