"""Benchmark of the network stage: default training on the built-in phantom, then Table 1.

Usage: ``python benchmarks/train_and_predict.py [CASE_DIR] [--quick] [--preset NAME]
[--iterations N] [--runtime auto|torchscript|openvino] [--workers N] [--no-train]``.

CASE_DIR (default ``bench-phantom``) is used as it is when it holds a case; otherwise the
built-in phantom case is created there, and its data set generated when missing (800/200
samples; ``--quick``: a coarse grid, 64/16 samples, 300 iterations, 200 timed predictions).
The last line reads ``RESULT mean_e_mm=... std_e_mm=... max_e_mm=... max_disp_mm=...
train_min=... predict_p50_ms=... predict_p99_ms=...``. Targets (2-core CPU, default preset):
mean e <= 0.05 mm, max e <= 0.27 mm with max displacement >= 30 mm, training <= 30 min,
prediction p50 <= 3 ms and p99 <= 6 ms over 1,000 batch-1 predictions.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from resultfile import write_result  # noqa: E402  (benchmarks/, this script's folder)
from speedprobe import speed_probes  # noqa: E402

QUICK = {"grid": {"cell_size_mm": 12.0}, "dataset": {"n_train": 64, "n_test": 16},
         "network": {"iterations": 300, "val_interval": 100}}


def ensure_case(case_dir: Path, quick: bool, workers: int) -> None:
    """Create the phantom case and its data set where they are missing."""
    if not (case_dir / "case.toml").exists():
        from biopsynav.case import make_phantom_case

        print(f"building the phantom case in {case_dir}", flush=True)
        make_phantom_case(case_dir, overrides=QUICK if quick else None)
    if not (case_dir / "dataset.zarr").exists() or quick:
        from biopsynav.dataset.generate import generate_case

        t = time.perf_counter()
        generate_case(case_dir, workers=workers)
        print(f"data set ready in {(time.perf_counter() - t) / 60:.1f} min", flush=True)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case_dir", nargs="?", default="bench-phantom")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--preset", default=None)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--runtime", default=None)
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--no-train", action="store_true",
                    help="evaluate the case's trained model as it is (e.g. the demo case's); "
                         "the training time comes from its meta.json")
    args = ap.parse_args(argv)
    case_dir = Path(args.case_dir)
    ensure_case(case_dir, args.quick, args.workers)

    from biopsynav.config import load_config
    from biopsynav.inference.surrogate import case_fingerprint
    from biopsynav.network.evaluate import evaluate, format_table1
    from biopsynav.network.train import train

    cfg = load_config(case_dir)
    iterations = args.iterations or (300 if args.quick else None)
    if not args.no_train:
        summary = train(case_dir, args.preset, iterations, settings=cfg.network)
        print(f"training: {summary.iterations_done} iterations, "
              f"{summary.train_time_s / 60:.1f} min (this run resumed from "
              f"{summary.resumed_from}), best validation e {summary.best_val_e_mm:.4f} mm at "
              f"{summary.best_iteration}, {summary.n_parameters:,} parameters", flush=True)
    r = evaluate(case_dir / "model", case_dir, case_dir / "eval", case_fingerprint(case_dir),
                 runtime=args.runtime or cfg.network.runtime, threads=cfg.network.threads,
                 n_timing=200 if args.quick else 1000)
    print("Table 1: " + format_table1(r))
    print(f"RESULT mean_e_mm={r['mean_e_mm']:.4f} std_e_mm={r['std_e_mm']:.4f} "
          f"max_e_mm={r['max_e_mm']:.4f} max_disp_mm={r['max_disp_mm']:.2f} "
          f"train_min={r['train_min']:.1f} predict_p50_ms={r['predict_p50_ms']:.2f} "
          f"predict_p99_ms={r['predict_p99_ms']:.2f}", flush=True)
    if not args.quick:
        write_result("train-and-predict", {k: r[k] for k in (
            "mean_e_mm", "std_e_mm", "max_e_mm", "max_disp_mm", "train_min",
            "predict_p50_ms", "predict_p99_ms")}, case=str(case_dir),
            speed_probes=speed_probes())  # after the timings: it would load the machine
    return r


if __name__ == "__main__":
    main()
