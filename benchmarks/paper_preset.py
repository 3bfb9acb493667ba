"""Benchmark of the ``paper`` preset (128 channels in the first level, ~90 M parameters) on this
machine, beside the ``default`` preset in the same run.

Usage: ``python benchmarks/paper_preset.py [CASE_DIR] [--steps N] [--predictions N]
[--threads N]``.

A full training of the paper preset does not fit a session on a 2-core CPU, so this script
measures what it would cost, through the code that trains and serves the models:

* one optimizer step (batch 4, AdamW, channels-last on the CPU: ``network.train``'s own step
  on the case's training data), median of ``--steps`` steps after one warm-up step, and the
  training time that projects for the case's ``[network] iterations`` and for the paper's
  100,000 iterations (a projection, not a measurement);
* one prediction (batch 1, the deployed runtime at fp32, ``network.infer``'s runners on the
  model exported as in training), median and 99th percentile of ``--predictions`` calls.

CASE_DIR (default ``bench-phantom``) must hold a case with its data set (see
``benchmarks/train_and_predict.py``). The weights are the initial ones: the times do not depend
on their values. The last line reads ``RESULT paper_params=... paper_step_s=...
paper_train_h=... paper_train_h_100k=... paper_predict_p50_ms=... paper_predict_p99_ms=...
default_step_s=... default_predict_p50_ms=... default_predict_p99_ms=...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

PAPER_ITERATIONS = 100_000  # the paper's training length (section 3)


def load_case_data(case_dir: Path):
    """The case's data set and its normalisation scales, loaded once for every measurement."""
    from biopsynav.network.data import load_dataset, normalisation_stats

    data = load_dataset(case_dir)
    return data, *normalisation_stats(data)


def build_net(preset: str, data, in_scale: np.ndarray, out_scale: np.ndarray):
    """The deployable network of ``preset`` with its initial weights (seed 0)."""
    import torch

    from biopsynav.network.data import quadratic_scale
    from biopsynav.network.export import SurrogateNet
    from biopsynav.network.unet import preset_spec

    torch.manual_seed(0)
    spec = preset_spec(preset)
    quad = quadratic_scale(data, in_scale) if spec.features == "quadratic" else None
    return SurrogateNet(spec, in_scale, out_scale, data.active.numpy(), quad)


def time_steps(case_dir: Path, case_data, preset: str, steps: int, threads: int) -> float:
    """Median seconds of one training step of ``preset`` on the case's data."""
    from biopsynav.config import load_config
    from biopsynav.network.train import TrainingLoop, build_optimizer, resolve_device
    from biopsynav.threads import set_threads

    s = dataclasses.replace(load_config(case_dir).network, preset=preset, threads=threads)
    set_threads(s.threads)
    data = case_data[0]
    net = build_net(preset, *case_data)
    opt = build_optimizer(net.unet.parameters(), s)
    runner = TrainingLoop(net, opt, data, s, resolve_device("cpu"), case_dir, {}, {})
    times = []
    for it in range(steps + 1):
        t = time.perf_counter()
        runner.step(it)
        times.append(time.perf_counter() - t)
    return float(np.median(times[1:]))


def time_predictions(case_data, preset: str, n: int, threads: int) -> tuple[float, float]:
    """Median and 99th percentile (ms) of one batch-1 prediction of ``preset``'s network."""
    from biopsynav.inference.runtimes import OpenVinoRunner, TorchScriptRunner, resolve_runtime
    from biopsynav.network.export import save_onnx, save_torchscript
    from biopsynav.threads import set_threads

    n_threads = set_threads(threads)
    data = case_data[0]
    net = build_net(preset, *case_data).eval()
    x = np.ascontiguousarray(data.inputs[data.test_idx[:1]].numpy())
    with tempfile.TemporaryDirectory() as tmp:
        if resolve_runtime("auto").name == "openvino":
            run = OpenVinoRunner(save_onnx(net, Path(tmp) / "m.onnx", data.node_shape),
                                 n_threads, data.node_shape)
        else:
            run = TorchScriptRunner(save_torchscript(net, Path(tmp) / "m.ts"), n_threads)
        for _ in range(3):
            run(x)
        times = []
        for _ in range(n):
            t = time.perf_counter()
            run(x)
            times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times)), float(np.percentile(times, 99))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case_dir", nargs="?", default="bench-phantom")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--predictions", type=int, default=50)
    ap.add_argument("--threads", type=int, default=0, help="0: the idle cores")
    args = ap.parse_args(argv)
    case_dir = Path(args.case_dir)

    from biopsynav.config import load_config
    from biopsynav.network.unet import count_parameters, preset_spec

    iterations = load_config(case_dir).network.iterations
    out = {"paper_params": count_parameters(preset_spec("paper"))}
    case_data = load_case_data(case_dir)
    for preset in ("paper", "default"):
        step_s = time_steps(case_dir, case_data, preset, args.steps, args.threads)
        n_pred = args.predictions if preset == "paper" else 20 * args.predictions
        p50, p99 = time_predictions(case_data, preset, n_pred, args.threads)
        print(f"{preset:8s} step {step_s:.3f} s -> {iterations} iterations "
              f"{step_s * iterations / 3600:.2f} h, {PAPER_ITERATIONS} iterations "
              f"{step_s * PAPER_ITERATIONS / 3600:.2f} h; prediction p50 {p50:.2f} ms, "
              f"p99 {p99:.2f} ms ({n_pred} calls)", flush=True)
        out[f"{preset}_step_s"] = step_s
        out[f"{preset}_predict_p50_ms"], out[f"{preset}_predict_p99_ms"] = p50, p99
        if preset == "paper":
            out["paper_train_h"] = step_s * iterations / 3600
            out["paper_train_h_100k"] = step_s * PAPER_ITERATIONS / 3600
    keys = ("paper_params", "paper_step_s", "paper_train_h", "paper_train_h_100k",
            "paper_predict_p50_ms", "paper_predict_p99_ms", "default_step_s",
            "default_predict_p50_ms", "default_predict_p99_ms")
    print("RESULT " + " ".join(f"{k}={out[k]:.4g}" for k in keys), flush=True)
    return out


if __name__ == "__main__":
    main()
