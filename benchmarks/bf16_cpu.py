"""What bf16 buys the training on this CPU: step time and stability, per memory layout.

    python benchmarks/bf16_cpu.py [--steps 40] [--runs 4] [--tag TAG]

* step time: one training step (forward, backward, fused AdamW) of the default U-Net, batch 4,
  on the phantom's node grid (24 x 20 x 13), 2 threads, median of ``--steps`` after 5, in
  fp32 and with ``torch.autocast("cpu", torch.bfloat16)``, channels-last and contiguous; and
  at batch 16 channels-last in both arithmetics;
* stability: ``--runs`` 40-iteration trainings of the test suite's network on its synthetic
  data (``tests/network/synth.py``), each in a fresh process, bf16 in each layout, counting
  the ones whose loss turned NaN (``train`` trains channels-last, ``training_layout``; both
  are forced here for the measurement).

Writes ``benchmarks/results/bf16-cpu-{amx,avx512,emulated}[-TAG].json`` by the CPU's bf16
arithmetic (``biopsynav.threads.cpu_bf16_unit``; ``--tag`` tells CPUs of one kind apart); the
last line reads ``RESULT fp32_cl_ms=...
bf16_cl_ms=... bf16_contig_ms=... nan_cl=k/n nan_contig=k/n``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from resultfile import cpu_flags, write_result

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import sys, torch
sys.path.insert(0, {root!r})
import biopsynav.network.train as T
from tests.network.synth import tiny_settings
layout = torch.contiguous_format if {contiguous} else torch.channels_last_3d
T.training_layout = lambda dev: layout  # measured here in both layouts, whatever the CPU
s = tiny_settings(iterations=40, val_interval=20, precision="bf16", device="cpu")
try:
    T.train({case!r}, settings=s, model_dir={out!r}, progress=False)
    print("finite")
except T.TrainingError:
    print("nan")
"""


def step_ms(layout: str, bf16: bool, steps: int, batch: int = 4) -> float:
    """Median training step (ms) of the default U-Net in ``layout`` ('cl' or 'contig') at
    ``batch``."""
    import torch

    from biopsynav.config import NetworkSection
    from biopsynav.network.unet import UNet3d, section_spec

    torch.set_num_threads(2)
    torch.manual_seed(0)
    fmt = torch.channels_last_3d if layout == "cl" else torch.contiguous_format
    spec = section_spec(NetworkSection())
    net = UNet3d(spec).to(memory_format=fmt)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, fused=True)
    x = torch.randn(batch, spec.feature_channels(), 24, 20, 13).contiguous(memory_format=fmt)
    y = torch.randn(batch, 3, 24, 20, 13)
    times = []
    for i in range(steps + 5):
        t = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred = net(x)
        loss = ((pred.float() - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i >= 5:
            times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


def nan_runs(layout: str, runs: int, tmp: Path) -> int:
    """How many of ``runs`` fresh-process bf16 trainings in ``layout`` ended in a NaN loss."""
    sys.path.insert(0, str(ROOT))
    from tests.network.synth import SHAPE, write_synthetic_dataset

    case = tmp / "synth"
    if not case.exists():
        write_synthetic_dataset(case, shape=SHAPE, n_train=40, n_test=10, seed=1)
    bad = 0
    for i in range(runs):
        code = CHILD.format(root=str(ROOT), contiguous=layout == "contig", case=str(case),
                            out=str(tmp / f"{layout}-{i}"))
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        bad += out.stdout.strip().endswith("nan")
    return bad


def result_name() -> str:
    """The result file's name for this CPU's bf16 arithmetic."""
    from biopsynav.threads import cpu_bf16_unit, cpu_has_amx_bf16

    kind = "amx" if cpu_has_amx_bf16() else "avx512" if cpu_bf16_unit() else "emulated"
    return f"bf16-cpu-{kind}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--runs", type=int, default=4)
    p.add_argument("--tag", default=None, help="appended to the result file's name")
    args = p.parse_args(argv)
    print(f"CPU flags: {' '.join(cpu_flags()) or 'no bf16'}")
    figures = {}
    for layout in ("cl", "contig"):
        for bf16 in (False, True):
            key = f"{'bf16' if bf16 else 'fp32'}_{layout}_ms"
            figures[key] = step_ms(layout, bf16, args.steps)
            print(f"{key}: {figures[key]:.1f}", flush=True)
    for bf16 in (False, True):  # the default batch of 16, channels-last
        key = f"{'bf16' if bf16 else 'fp32'}_cl_b16_ms"
        figures[key] = step_ms("cl", bf16, args.steps, batch=16)
        print(f"{key}: {figures[key]:.1f} ({figures[key] / 16:.2f} per sample)", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for layout in ("cl", "contig"):
            bad = nan_runs(layout, args.runs, Path(tmp))
            figures[f"nan_{layout}"] = f"{bad}/{args.runs}"
            print(f"bf16 {layout}: {bad} of {args.runs} trainings ended in a NaN loss",
                  flush=True)
    write_result(result_name() + (f"-{args.tag}" if args.tag else ""), figures)
    print(f"RESULT fp32_cl_ms={figures['fp32_cl_ms']:.1f} bf16_cl_ms={figures['bf16_cl_ms']:.1f} "
          f"fp32_cl_b16_ms={figures['fp32_cl_b16_ms']:.1f} "
          f"bf16_cl_b16_ms={figures['bf16_cl_b16_ms']:.1f} "
          f"bf16_contig_ms={figures['bf16_contig_ms']:.1f} nan_cl={figures['nan_cl']} "
          f"nan_contig={figures['nan_contig']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
