"""OpenVINO in bf16 against fp32: the tracker's update time and how far bf16 moves a lesion.

    python benchmarks/inference_bf16.py CASE [CASE ...] [--tag TAG]

For each case folder with a trained tracking model: ``Tracker`` (engine ``net``, 2 threads)
on ``openvino`` (fp32 forced) and on ``openvino-bf16``, the probe placed over the case's first
lesion as in Table 2, pushed from 0 to 30 mm and back to 2 mm along its beam in 600 poses;
each runtime times three passes over them after 50 warm-up updates (median and p99), and the
lesions of the first pass are compared between the two (median, p99 and max distance, mm).
What decides ``[network] runtime = "auto"`` on a CPU with bf16 arithmetic (AMX-BF16 tiles or
AVX-512 BF16; docs/network.md, "Inference runtimes"). Run it alone on the machine.

Writes ``benchmarks/results/inference-bf16[-TAG].json``; the last line reads ``RESULT
CASE:fp32_p50_ms=...,bf16_p50_ms=...,max_mm=... ...``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from resultfile import write_result

RUNTIMES = ("openvino", "openvino-bf16")
POSES_EACH_WAY = 300
PASSES = 3
WARM_UP = 50


def push_poses(case) -> tuple[np.ndarray, list[np.ndarray]]:
    """The rest pose over the first lesion (4, 4) and the push's poses: 0 -> 30 -> 2 mm."""
    from biopsynav.evaluate.placement import place_case_probe

    placement = place_case_probe(case, 0)
    depths = np.concatenate([np.linspace(0.0, 30.0, POSES_EACH_WAY),
                             np.linspace(30.0, 2.0, POSES_EACH_WAY)])
    return placement.pose, [placement.pushed(float(d)) for d in depths]


def timed_updates(case, runtime: str, rest: np.ndarray, poses: list) -> tuple[list, np.ndarray]:
    """Seconds of every update over :data:`PASSES` passes and the lesion centres (n_poses,
    n_lesions, 3) mm of the first pass (NaN where the answer is not reliable)."""
    from biopsynav.inference.surrogate import load_for_case
    from biopsynav.tracker.core import Tracker

    tracker = Tracker(case, "net", surrogate=load_for_case(case, runtime=runtime, threads=2))
    tracker.set_rest_pose(rest)
    for pose in poses[:WARM_UP]:
        tracker.update(pose)
    seconds, centres = [], []
    for k in range(PASSES):
        for pose in poses:
            start = time.perf_counter()
            result = tracker.update(pose)
            seconds.append(time.perf_counter() - start)
            if k == 0:
                centres.append([les.center if result.reliable else np.full(3, np.nan)
                                for les in result.lesions])
    return seconds, np.asarray(centres, dtype=np.float64)


def compare(case_dir: Path) -> dict:
    """Both runtimes' update times (ms) and bf16's lesion distance from fp32's (mm)."""
    from biopsynav.case import Case

    case = Case.load(case_dir)
    rest, poses = push_poses(case)
    out, centres = {"active_cells": int(case.grid.active_cells.sum()),
                    "node_shape": list(case.grid.node_shape)}, {}
    for runtime in RUNTIMES:
        seconds, centres[runtime] = timed_updates(case, runtime, rest, poses)
        ms = 1e3 * np.asarray(seconds)
        out[runtime] = {"update_p50_ms": float(np.median(ms)),
                        "update_p99_ms": float(np.percentile(ms, 99)),
                        "reliable": int(np.isfinite(centres[runtime][:, 0, 0]).sum())}
    apart = np.linalg.norm(centres[RUNTIMES[1]] - centres[RUNTIMES[0]], axis=2)
    apart = apart[np.isfinite(apart)]
    out["lesion_moved_by_bf16_mm"] = {"median": float(np.median(apart)),
                                      "p99": float(np.percentile(apart, 99)),
                                      "max": float(apart.max())}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cases", type=Path, nargs="+")
    p.add_argument("--tag", default=None)
    args = p.parse_args(argv)
    from biopsynav.inference.runtimes import openvino_bf16_available

    if not openvino_bf16_available():
        sys.exit("inference_bf16: this CPU has no bf16 arithmetic, or openvino is missing")
    figures = {}
    for case_dir in args.cases:
        figures[case_dir.name] = f = compare(case_dir)
        print(f"{case_dir.name}: update fp32 {f['openvino']['update_p50_ms']:.2f} / "
              f"{f['openvino']['update_p99_ms']:.2f} ms, bf16 "
              f"{f['openvino-bf16']['update_p50_ms']:.2f} / "
              f"{f['openvino-bf16']['update_p99_ms']:.2f} ms; lesion moved by bf16 at most "
              f"{f['lesion_moved_by_bf16_mm']['max']:.4f} mm", flush=True)
    write_result("inference-bf16" + (f"-{args.tag}" if args.tag else ""), figures)
    print("RESULT " + " ".join(
        f"{k}:fp32_p50_ms={f['openvino']['update_p50_ms']:.2f},"
        f"bf16_p50_ms={f['openvino-bf16']['update_p50_ms']:.2f},"
        f"max_mm={f['lesion_moved_by_bf16_mm']['max']:.4f}" for k, f in figures.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
