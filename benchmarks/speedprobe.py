"""The day's speed of a shared VM, recorded beside a benchmark's figures so that a slow day
can be told from a slower program: :func:`speed_probes`."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np


def speed_probes() -> dict:
    """The day's speed: a U-Net training step (batch 4, fp32) on the phantom's grid and a matmul
    (seconds)."""
    import torch

    from biopsynav.case import make_phantom_case
    from biopsynav.runtime import probe_seconds

    with tempfile.TemporaryDirectory() as tmp:
        case = make_phantom_case(Path(tmp) / "ph")
        step = float(np.median([probe_seconds(case, as_reference=True) for _ in range(3)]))
    a = torch.randn(1024, 1024)
    times = []
    for _ in range(6):
        t = time.perf_counter()
        a @ a
        times.append(time.perf_counter() - t)
    return {"unet_step_s": step, "matmul_1024_s": float(np.median(times[1:]))}


def slowness(data: dict) -> float | None:
    """How many times slower than the reference machine (``biopsynav.runtime.REFERENCE``) the
    day of the result ``data`` was, by its U-Net probe; None when it holds no probe."""
    from biopsynav.runtime import REFERENCE

    probes = data.get("speed_probes")
    return None if not probes else probes["unet_step_s"] / REFERENCE["probe_s"]
