"""CPU thread settings and features, in one place: how many threads, one thread for small
solves, and whether the CPU has AMX-BF16 tiles (bf16 training and inference).

PyTorch's intra-op threads (training, TorchScript), OpenVINO's (``threads`` of its runner) and
NumPy/SciPy's BLAS threads are all set from here.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch


def auto_threads(sample_s: float = 0.2, tries: int = 3) -> int:
    """Cores not busy with other processes, at least 1.

    Two PyTorch (OpenMP) threads collapse when another process holds a core: measured here, a
    training step took 380 ms with 2 threads against 99 ms with 1 thread on a loaded 2-core
    machine (64 ms with 2 threads when idle), so ``threads = 0`` takes only the idle cores.
    Busy cores are measured from the CPU time the system spent outside idle and I/O wait over
    ``sample_s`` seconds (``/proc/stat``), less this process's own (``/proc/self/stat``), not
    from the load average: on the development VM a kernel thread keeps the load average at 1
    while both cores are idle. A window that finds a busy core is followed by up to
    ``tries - 1`` more and the least busy counts, so that a process ending at that moment
    (the workers of a data generation that has just finished) does not halve the threads of
    a training that follows it. Elsewhere the 1-minute load average is used.
    """
    cores = os.cpu_count() or 1
    busy = _busy_cores(sample_s)
    if busy is None:
        try:
            busy = os.getloadavg()[0]
        except OSError:
            return cores
    for _ in range(tries - 1):
        if busy < 0.5:
            break
        again = _busy_cores(sample_s)
        if again is None:
            break
        busy = min(busy, again)
    return max(1, min(cores, int(cores - busy + 0.5)))


def _busy_cores(sample_s: float) -> float | None:
    """Cores' worth of CPU time that other processes spent over ``sample_s`` seconds (Linux:
    the system's non-idle time less this process's), else None."""
    split = _cpu_split(sample_s)
    return None if split is None else max(0.0, split[0] - split[1])


def _cpu_split(sample_s: float) -> tuple[float, float] | None:
    """(all, own): cores' worth of the system's non-idle CPU time and of this process's over
    one window of ``sample_s`` seconds (Linux ``/proc``), else None."""
    first, own_first = _system_ticks(), _own_ticks()
    if first is None:
        return None
    time.sleep(sample_s)
    second, own_second = _system_ticks(), _own_ticks()
    if second is None or second[0] <= first[0]:
        return None
    total, idle = second[0] - first[0], second[1] - first[1]
    cores = os.cpu_count() or 1
    own = 0 if own_first is None or own_second is None else own_second - own_first
    return cores * (total - idle) / total, cores * min(own, total) / total


def _system_ticks() -> tuple[int, int] | None:
    """(all, idle + I/O wait) clock ticks of every core since boot (``/proc/stat``)."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return sum(fields[:8]), fields[3] + (fields[4] if len(fields) > 4 else 0)


def _own_ticks() -> int | None:
    """User + system clock ticks of this process, every thread (``/proc/self/stat``)."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, ValueError, IndexError):
        return None


def set_threads(threads: int) -> int:
    """Use ``threads`` intra-op CPU threads (0: :func:`auto_threads`); returns the count."""
    n = threads if threads > 0 else auto_threads()
    set_torch_threads(n)
    return n


def set_torch_threads(n: int) -> None:
    """``torch.set_num_threads(n)`` that a later numba kernel cannot undo.

    numba's OpenMP thread pool, launched by the process's first parallel kernel (the FE
    assembly), sets the OpenMP thread count that PyTorch reads to numba's own (every core):
    a training set to one thread beside a busy core then ran on two, many times slower
    (docs/network.md, "Training"). The pool is started first, so the count set here stays.
    """
    launch_numba_pool()
    torch.set_num_threads(n)


@functools.cache
def launch_numba_pool() -> None:
    """Start numba's thread pool now (once per process), so that its start cannot change
    the OpenMP thread count set after it."""
    import numba

    numba.get_num_threads()


@contextmanager
def one_thread() -> Iterator[None]:
    """Run the enclosed NumPy/SciPy BLAS, OpenMP and PyTorch work on one thread, then restore
    the thread counts. For many small (hundreds of rows) dense products and solves in turn:
    there, extra threads only wait on each other, and PyTorch's spinning OpenMP workers
    starve BLAS's. Measured for the per-sample projections of the phantom, 2-core VM, beside a
    running training: 0.15 s against 0.01 s per sample (docs/experiments.md)."""
    from threadpoolctl import threadpool_limits

    torch_threads = torch.get_num_threads()
    # the pools' state is saved before torch's change (torch.set_num_threads also sets the MKL
    # pool) and restored after torch's restore, so each pool ends as it was on entry
    launch_numba_pool()  # a pool started in the block would set the count restored below
    with threadpool_limits(limits=1):
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(torch_threads)


@functools.cache
def cpu_flags() -> frozenset[str]:
    """The CPU's flags (``/proc/cpuinfo``'s first ``flags`` line; empty where it is absent)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    return next((frozenset(ln.split(":", 1)[1].split()) for ln in text.splitlines()
                 if ln.startswith("flags")), frozenset())


def cpu_has_amx_bf16() -> bool:
    """Whether this CPU has AMX-BF16 tile instructions (``amx_bf16`` in ``/proc/cpuinfo``;
    False where that file is absent): oneDNN's and OpenVINO's bf16 convolutions then run on
    the tiles."""
    return "amx_bf16" in cpu_flags()


def cpu_bf16_unit() -> str | None:
    """The CPU's bf16 arithmetic that oneDNN trains with: ``"AMX-BF16 tiles"``, else
    ``"AVX-512 BF16"`` (``avx512_bf16``: bf16 dot products, fp32 sums), else None."""
    if cpu_has_amx_bf16():
        return "AMX-BF16 tiles"
    return "AVX-512 BF16" if "avx512_bf16" in cpu_flags() else None
