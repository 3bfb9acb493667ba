"""Settings that make a whole `run` of a test case take seconds, and a benchmark script run as
a user runs it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from biopsynav.config import CaseConfig

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def small_run_settings(cfg: CaseConfig) -> None:
    """Set ``cfg`` (in place) to a few training iterations on one thread, 10 timed
    predictions and one Table 2 push over one lesion on a grid no finer than the case's (the
    fine grid, not the stored truth that ``auto`` chooses for the phantom: three pushes)."""
    cfg.network.iterations, cfg.network.val_interval = 6, 3
    cfg.network.warmup_iterations, cfg.network.threads = 2, 1
    cfg.evaluate.timed_predictions = 10
    cfg.evaluate.max_lesions, cfg.evaluate.deformations_per_lesion = 1, 1
    cfg.evaluate.reference, cfg.evaluate.reference_refinement = "fine_grid", 1.0


def run_benchmark(script: str, args: list[str], cwd: Path) -> tuple[str, dict[str, str]]:
    """Run ``benchmarks/<script>`` with ``args`` in the folder ``cwd``, which must succeed:
    its standard output and the values of its last line (``RESULT key=value ...``)."""
    proc = subprocess.run([sys.executable, str(BENCHMARKS / script), *args],
                          capture_output=True, text=True, timeout=600, cwd=cwd)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("RESULT "), last
    return proc.stdout, dict(item.split("=") for item in last.split()[1:])
