"""One result file per benchmark run, ``benchmarks/results/<name>.json``: the date, the
command that produced it, the machine it ran on and its figures. README.md and BENCHMARKS.md
show figures from these files only (``benchmarks/figures.py``; ``tests/test_figures.py``
fails when a shown figure differs from its file)."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def cpu_flags() -> list[str]:
    """The CPU's bf16 and AMX flags (what the training arithmetic could use)."""
    from biopsynav.threads import cpu_flags as all_flags

    return sorted(f for f in all_flags() if "bf16" in f or f.startswith("amx"))


def machine() -> dict:
    """The machine a figure was measured on."""
    import numpy

    from biopsynav.report.machine import cpu_model

    info = {"cpu": cpu_model(), "cores": os.cpu_count(), "cpu_flags": cpu_flags(),
            "python": platform.python_version(), "numpy": numpy.__version__}
    try:
        import torch

        info["torch"] = torch.__version__
    except ImportError:
        pass
    return info


def write_result(name: str, figures: dict, **extra) -> Path:
    """Write ``benchmarks/results/<name>.json`` atomically: today's date (UTC), the command
    line of this process, the machine, ``figures`` and any ``extra`` keys; its path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    data = {"name": name, "date": time.strftime("%Y-%m-%d", time.gmtime()),
            "command": "python " + " ".join(shlex.quote(a) for a in sys.argv),
            "machine": machine(), "figures": figures, **extra}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1, default=float) + "\n")
    os.replace(tmp, path)
    print(f"result file: {path.relative_to(RESULTS.parent.parent)}", flush=True)
    return path


def result_line(figures: dict, keys: tuple[str, ...], digits: int = 4) -> str:
    """A benchmark's last line: ``RESULT key=value ...`` of ``figures``' ``keys`` (floats to
    ``digits`` decimals)."""
    return "RESULT " + " ".join(f"{k}={figures[k]:.{digits}f}" for k in keys)
