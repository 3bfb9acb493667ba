"""Software versions and the machine the report was made on."""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path

PACKAGES = ("biopsynav", "numpy", "scipy", "torch", "matplotlib", "zarr", "numba")


def package_version(name: str) -> str:
    """Installed version of a distribution, or 'not installed'."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else platform.processor()."""
    info = Path("/proc/cpuinfo")
    if info.is_file():
        for line in info.read_text(errors="replace").splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def memory_gib() -> float | None:
    """Total memory in GiB from /proc/meminfo, None where unavailable."""
    info = Path("/proc/meminfo")
    if info.is_file():
        for line in info.read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 2**20
    return None


def versions_and_machine() -> list[list[str]]:
    """Rows (item, value): python, packages, CPU, cores, memory, OS."""
    rows = [["python", platform.python_version()]]
    rows += [[p, package_version(p)] for p in PACKAGES]
    mem = memory_gib()
    rows += [["CPU", cpu_model()], ["cores (logical)", str(os.cpu_count())],
             ["memory", f"{mem:.1f} GiB" if mem else "unknown"],
             ["OS", platform.platform()]]
    return rows
