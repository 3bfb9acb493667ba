"""Data-generation throughput on the built-in phantom at the default resolution.

Builds the phantom case (default grid, ~2,200 active cells) in a temporary folder, generates
the same ``--samples`` samples (indices 0..n-1 of seed 0) with 1 and with 2 local workers,
and prints samples per minute. The rate is the steady one, from the first to the last sample
written (file times of the ``done`` chunks): the start-up before the first sample (the force
calibration, about 1.5 min of it on the phantom, then the pool's spawn, imports and first
factorisation) is reported apart and added once to the projection for 1,000 samples.
``--recipe pushes`` measures the rigid pushes of that recipe instead of force patches
(``generate-pushes.json``).

Last line: ``RESULT per_min_1w=<..> per_min_2w=<..> minutes_1000=<..>``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from biopsynav.recipes import RECIPES, recipe_overrides
from resultfile import write_result  # noqa: E402  (benchmarks/, this script's folder)


def timed_run(case_dir: Path, workers: int, n_samples: int) -> dict:
    """Generate ``n_samples`` into ``case_dir``; returns rate, start-up and the summary."""
    from biopsynav.dataset.generate import generate_case

    n_test = max(1, n_samples // 5)
    start = time.time()
    summary = generate_case(case_dir, workers=workers, overwrite=True,
                            n_train=n_samples - n_test, n_test=n_test, progress=False)
    wall = time.time() - start
    stamps = np.sort([p.stat().st_mtime for p in (case_dir / "dataset.zarr" / "done" / "c")
                      .iterdir()])
    steady = (len(stamps) - 1) / max(stamps[-1] - stamps[0], 1e-9) * 60.0
    return {"workers": workers, "wall_s": round(wall, 1),
            "startup_s": round(float(stamps[0] - start), 1),
            "per_min_steady": round(float(steady), 1),
            "per_min_wall": round(n_samples / wall * 60.0, 1), "summary": summary}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=30, help="samples per run")
    parser.add_argument("--keep", type=Path, help="keep the case folder here")
    parser.add_argument("--recipe", choices=sorted(RECIPES), help="a recipe of `init "
                        "--recipe` (e.g. pushes: rigid pushes; default: the configuration's "
                        "defaults, force patches)")
    args = parser.parse_args()

    from biopsynav.case import make_phantom_case

    overrides = None if args.recipe is None else recipe_overrides(args.recipe)

    tmp = Path(tempfile.mkdtemp(prefix="biopsynav-bench-"))
    try:
        case = make_phantom_case(tmp / "phantom", overrides=overrides)
        print(f"phantom: {int(case.grid.active_cells.sum())} active cells, nodes "
              f"{case.grid.node_shape}, f_max_n {case.cfg.probe.f_max_n} N, "
              f"E {case.cfg.material.tissues['phantom']['E_mpa'] * 1e3:g} kPa", flush=True)
        runs = {}
        for workers in (1, 2):
            runs[workers] = run = timed_run(case.dir, workers, args.samples)
            s = run["summary"]
            print(f"{workers} worker(s): {args.samples} samples in {run['wall_s']} s "
                  f"(start-up {run['startup_s']} s), steady {run['per_min_steady']}/min, "
                  f"overall {run['per_min_wall']}/min; mean solve {s['mean_solve_s']} s, "
                  f"failures {s['failures']}, max probe disp {s['max_probe_disp_mm']} mm, "
                  f"max nodal disp {s['max_disp_mm']} mm", flush=True)
        print(json.dumps({w: {k: v for k, v in r.items() if k != "summary"}
                          for w, r in runs.items()}))
        two = runs[2]
        minutes_1000 = (two["startup_s"] + 1000 / two["per_min_steady"] * 60.0) / 60.0
        if args.keep:
            shutil.copytree(case.dir, args.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"RESULT per_min_1w={runs[1]['per_min_steady']:.1f} "
          f"per_min_2w={runs[2]['per_min_steady']:.1f} minutes_1000={minutes_1000:.1f}")
    name = "generate" if args.recipe is None else f"generate-{args.recipe}"
    write_result(name, {"per_min_1w": runs[1]["per_min_steady"],
                        "per_min_2w": runs[2]["per_min_steady"], "minutes_1000": minutes_1000})


if __name__ == "__main__":
    main()
