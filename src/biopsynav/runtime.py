"""How long ``run`` will take on this machine, and the run's stage table.

Each stage's expected time is a measured reference run's time scaled to the case and to this
machine today:

* **FE stages** (``generate``, the rigid pushes of ``[refine]``, Table 2's references) scale
  with the number of samples and with the active cells (solves cost about ``cells^1.3``);
* **training stages** scale with iterations and with the grid's nodes (the U-Net sees the whole
  grid);
* every stage scales with this machine's speed today: a 3-step probe of the case's U-Net
  training step (about 2 s) against the same probe on the reference machine, so that a slow
  day of a shared VM lengthens the estimate.

The references (:data:`REFERENCE`) are the stage times of one ``biopsynav run`` with every
default on the 2-core machine, alone, 2026-12-02 (docs/pipeline.md). An estimate is a
forecast: the run's stage table says what each stage took.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

#: The reference run: stage -> (minutes, work units); units are samples x cells^1.3 for FE
#: stages and iterations x grid nodes for training stages (see :func:`stage_work`).
REFERENCE = {"probe_s": 0.0, "active_cells": 0, "grid_nodes": 0, "minutes": {}}
FE_EXPONENT = 1.3
PROBE_STEPS = 3


@dataclass
class Estimate:
    """Expected minutes per stage (stage name -> minutes) and the machine's speed factor
    (1: as fast as the reference machine; 2: half as fast)."""

    minutes: dict[str, float]
    slowness: float

    @property
    def total(self) -> float:
        return float(sum(self.minutes.values()))

    def line(self) -> str:
        parts = ", ".join(f"{k} {v:.0f}" for k, v in self.minutes.items() if v >= 0.5)
        return (f"expected on this machine today: about {self.total:.0f} min ({parts} min; "
                f"speed probe {self.slowness:.2f}x the reference machine's time)")


def stage_work(case) -> dict[str, float]:
    """Work units of each stage of ``case`` (see :data:`REFERENCE`)."""
    cfg, grid = case.cfg, case.grid
    cells = float(grid.active_cells.sum()) ** FE_EXPONENT
    nodes = float(np.prod(grid.node_shape))
    samples = cfg.dataset.n_train + cfg.dataset.n_test
    work = {"generate": samples * cells, "train": cfg.network.iterations * nodes}
    if cfg.refine.samples:
        work["refine pushes"] = cfg.refine.samples * cells * cfg.refine.teacher_refine ** 3
        work["refine training"] = cfg.refine.iterations * nodes
    return work


def probe_seconds(case) -> float:
    """Seconds per step of the case's U-Net training (forward, backward, Adam) at its batch
    size on random inputs, the median of :data:`PROBE_STEPS` after one warm-up."""
    import torch

    from .network.unet import UNet3d, preset_spec

    s = case.cfg.network
    spec = preset_spec(s.preset, levels=s.levels, base_channels=s.base_channels, norm=s.norm,
                       activation=s.activation, features=s.features)
    net = UNet3d(spec).to(memory_format=torch.channels_last_3d)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    x = torch.randn(s.batch_size, spec.feature_channels(), *case.grid.node_shape)
    x = x.contiguous(memory_format=torch.channels_last_3d)
    times = []
    for _ in range(PROBE_STEPS + 1):
        start = time.perf_counter()
        loss = net(x).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - start)
    return float(np.median(times[1:]))


def estimate_run(case, probe_s: float | None = None) -> Estimate:
    """Expected minutes of each stage of ``case`` on this machine (``probe_s``: the training
    step probe's seconds, measured when None)."""
    ref = REFERENCE
    probe_s = probe_seconds(case) if probe_s is None else probe_s
    ref_nodes = float(ref["grid_nodes"])
    slowness = probe_s / ref["probe_s"] * ref_nodes / float(np.prod(case.grid.node_shape))
    ref_work = {"generate": ref["minutes"]["generate"][1],
                "train": ref["minutes"]["train"][1],
                "refine pushes": ref["minutes"]["refine pushes"][1],
                "refine training": ref["minutes"]["refine training"][1]}
    minutes = {stage: ref["minutes"][stage][0] * w / ref_work[stage] * slowness
               for stage, w in stage_work(case).items()}
    minutes["evaluate and report"] = ref["minutes"]["evaluate and report"][0] * slowness
    return Estimate(minutes, slowness)


def stage_table(timings_s: dict[str, float]) -> str:
    """The run's stage times as a table (minutes), the whole run last."""
    width = max(len(k) for k in timings_s) + 2
    lines = [f"{'stage':<{width}}minutes"]
    lines += [f"{k:<{width}}{v / 60:7.1f}" for k, v in timings_s.items()]
    lines.append(f"{'whole run':<{width}}{sum(timings_s.values()) / 60:7.1f}")
    return "\n".join(lines)
