"""Local worker processes of data generation and force calibration.

:class:`WorkerProcesses` is a ``ProcessPoolExecutor`` of spawned processes with one MKL /
OpenMP thread each (``SINGLE_THREAD_ENV``: a solve gives the same bits whatever the number of
workers), each ending itself when the main process dies, that notices a worker which died
without any future saying so and can be rebuilt after a crash. What a worker holds is set
up once per process by the ``setup`` function it is given (the case's FE model, for
instance); tasks are plain functions of that process's state. Building one starts nothing:
the set-up file and the processes come with the first task.

The set-up and its arguments travel through a file, not through the pipe that starts each
process: CPython's spawn writes a new process's start data to a pipe whose read end it keeps
open until the write ends, so a child that dies before reading data larger than the pipe's
buffer (a script without ``if __name__ == "__main__":``, which the spawned child imports and
runs again) left the main process writing for ever. Each worker leaves a mark once it has
started; a pool that broke before any worker did is named as that mistake
(:meth:`WorkerProcesses.check_started`).
"""

from __future__ import annotations

import os
import pickle
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from ..errors import InputError

#: Environment of a worker process: one MKL/OpenMP thread keeps Pardiso's results
#: bit-identical whatever the number of workers.
SINGLE_THREAD_ENV = {"MKL_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                     "OPENBLAS_NUM_THREADS": "1", "MKL_DYNAMIC": "FALSE"}
#: How often (s) a pool with nothing finished checks that its worker processes live: a
#: worker killed at the wrong moment can leave the executor's own futures pending for ever.
WORKER_WATCH_S = 5.0
#: What a pool that broke before any worker process started says.
NEVER_STARTED = ("the worker processes died while starting, before their set-up: a spawned "
                 "worker imports the main script again, so a script that calls this with "
                 "workers > 0 needs its calls under `if __name__ == \"__main__\":` (Python's "
                 "own message is printed above); or run with workers = 0")
SETUP_FILE = "setup.pickle"  # in a pool's folder: the set-up function and its arguments


def check_workers(workers: int) -> None:
    """InputError naming ``--workers`` unless ``workers`` (local processes; 0: one per core)
    is >= 0: each command that starts processes checks it before any work."""
    if workers < 0:
        raise InputError(f"must be >= 0 (0: one per core), got {workers}", "--workers")


class WorkerProcesses:
    """``workers`` spawned processes (0: one per core), each running ``setup(*setup_args)``
    once after its thread limits and watchdog are in place. Nothing starts until the first
    task: then the folder of the set-up file and the pool (:attr:`pool`)."""

    def __init__(self, workers: int, setup: Callable, setup_args: tuple) -> None:
        self.workers = workers or os.cpu_count() or 1
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        self.env = {**SINGLE_THREAD_ENV, "NUMBA_NUM_THREADS": str(threads)}
        self.setup = (setup, setup_args)
        self.folder: Path | None = None  # the set-up file and start marks, once started
        self._pool: ProcessPoolExecutor | None = None

    @property
    def pool(self) -> ProcessPoolExecutor:
        """The executor; its first use writes the set-up file and starts it."""
        if self._pool is None:
            if self.folder is None:
                self.folder = _setup_folder(self.setup)
            self._pool = self._new_pool()
        return self._pool

    def _new_pool(self) -> ProcessPoolExecutor:
        import multiprocessing

        setup_file = str(self.folder / SETUP_FILE)
        with _env(self.env):  # spawned children inherit it before importing MKL
            return ProcessPoolExecutor(self.workers, multiprocessing.get_context("spawn"),
                                       initializer=start_worker,
                                       initargs=(self.env, os.getpid(), setup_file))

    def check_started(self) -> None:
        """InputError (:data:`NEVER_STARTED`) when no worker process of this pool has ever
        started: a broken pool then has a cause that restarting it will not cure."""
        if self.folder is None or not any(self.folder.glob("started-*")):
            raise InputError(NEVER_STARTED, "worker processes") from None

    def submit(self, task: Callable, *args: Any) -> Future:
        """``task(*args)`` in a worker (processes start lazily, with the workers' env)."""
        with _env(self.env):
            return self.pool.submit(task, *args)

    def wait_any(self, futures: list) -> set:
        """The futures of ``futures`` that finished, once one has; BrokenProcessPool when a
        worker process died and the executor did not say so on any future."""
        while True:
            done = wait(futures, timeout=WORKER_WATCH_S, return_when=FIRST_COMPLETED)[0]
            if done:
                return done
            dead = self._dead_workers()
            if dead:
                raise BrokenProcessPool(f"worker process(es) {dead} died, their tasks pending")

    def _dead_workers(self) -> list[int]:
        """Process ids of this pool's workers that have exited."""
        return [proc.pid for proc in self.processes() if proc.exitcode is not None]

    def processes(self) -> list:
        """The pool's worker processes (none before it started or once the executor has let
        them go)."""
        return list((getattr(self._pool, "_processes", None) or {}).values())

    def restart(self) -> None:
        """Replace a broken pool (a worker died) by a fresh one; InputError when no worker
        had ever started (:meth:`check_started`)."""
        self.check_started()
        self._stop(wait=False)
        self._pool = self._new_pool()

    def _stop(self, wait: bool) -> None:
        """Kill every worker, release the executor's thread that reads their results and shut
        the executor down (nothing to do before it started)."""
        if self._pool is None:
            return
        processes = self.processes()
        for proc in processes:
            if proc.is_alive():
                proc.kill()
        for proc in processes:
            proc.join(WORKER_WATCH_S)
        _release_result_reader(self._pool)
        self._pool.shutdown(wait=wait, cancel_futures=True)
        self._pool = None

    def close(self) -> None:
        """Stop every worker at once: tasks in flight are lost by design, nothing waits on
        them. The set-up folder goes with them."""
        self._stop(wait=True)
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> WorkerProcesses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _setup_folder(setup: tuple[Callable, tuple]) -> Path:
    """A new temporary folder holding ``setup`` (function, arguments) pickled as
    :data:`SETUP_FILE`; nothing is left behind when the pickling fails."""
    folder = Path(tempfile.mkdtemp(prefix="biopsynav-workers-"))
    try:
        with open(folder / SETUP_FILE, "wb") as f:
            pickle.dump(setup, f, protocol=pickle.HIGHEST_PROTOCOL)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder


def _release_result_reader(pool: ProcessPoolExecutor) -> None:
    """Close this process's end for writing of ``pool``'s result pipe, once its workers are
    dead. A worker killed while sending a result (larger than the pipe's buffer) leaves the
    executor's thread reading the rest of that message for ever: this process holds the
    pipe's write end too, so no end of file comes. That thread then never marks the futures
    broken, and the interpreter's exit, which joins it, never ends. Closed, the read ends
    with EOFError, which the executor takes for a broken pool."""
    queue = getattr(pool, "_result_queue", None)
    writer = getattr(queue, "_writer", None)
    if writer is not None:
        writer.close()


def start_worker(env: dict[str, str], parent: int, setup_file: str) -> None:
    """``ProcessPoolExecutor`` initializer: thread limits, a watchdog that ends the process
    when the main process dies (kill -9 leaves no orphan computing), this worker's mark
    (``started-PID`` beside ``setup_file``), then the set-up pickled in ``setup_file``, once.
    ``parent``: the main process id (passed in, so that a main process that died before this
    ran is noticed too)."""
    os.environ.update(env)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True,
                     name="parent-watchdog").start()
    path = Path(setup_file)
    (path.parent / f"started-{os.getpid()}").touch()
    with open(path, "rb") as f:
        setup, setup_args = pickle.load(f)
    setup(*setup_args)


def _exit_with_parent(parent: int, period_s: float = 0.5) -> None:
    """Poll the parent id; once the parent is gone (re-parented), exit at once."""
    while os.getppid() == parent:
        time.sleep(period_s)
    os._exit(1)


class _env:
    """Context manager: set environment variables temporarily (pool processes spawn lazily)."""

    def __init__(self, env: dict[str, str]) -> None:
        self.env = env
        self.saved: dict[str, str | None] = {}

    def __enter__(self) -> None:
        self.saved = {k: os.environ.get(k) for k in self.env}
        os.environ.update(self.env)

    def __exit__(self, *exc: object) -> None:
        for key, value in self.saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
