"""The local worker processes of data generation and calibration (dataset.pool)."""

from __future__ import annotations

import gc
import os
import signal
import struct

import pytest


def _nothing() -> None:
    """A worker's set-up that holds nothing."""


def _pid() -> int:
    return os.getpid()


def _die_while_sending_a_result() -> None:
    """Write the start of a result message of 1 MB to the executor's result pipe, then die:
    what a worker killed while sending a large result leaves behind."""
    from multiprocessing.queues import SimpleQueue

    queue = next(o for o in gc.get_objects() if isinstance(o, SimpleQueue))
    os.write(queue._writer.fileno(), struct.pack("!i", 1 << 20) + b"\0" * 1024)
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_killed_while_sending_its_result_leaves_nothing_waiting(monkeypatch):
    """The executor's thread reading results is left mid-message (its future pending for
    ever, and the interpreter's exit joining that thread for ever, which hung `generate` after
    a killed worker). The wait notices the dead worker, and the restart releases that thread:
    it ends, and the new pool answers."""
    from concurrent.futures.process import BrokenProcessPool

    from biopsynav.dataset import pool

    monkeypatch.setattr(pool, "WORKER_WATCH_S", 0.2)
    processes = pool.WorkerProcesses(1, _nothing, ())
    try:
        first = processes.submit(_pid).result(timeout=120)
        dying = processes.submit(_die_while_sending_a_result)
        with pytest.raises(BrokenProcessPool, match=str(first)):
            processes.wait_any([dying])  # the executor says nothing: the wait notices
        reader = processes.pool._executor_manager_thread
        assert reader.is_alive() and not dying.done()  # stuck in the middle of the message
        processes.restart()
        reader.join(30)
        assert not reader.is_alive(), "the old pool's result reader still waits"
        assert processes.submit(_pid).result(timeout=120) != first
    finally:
        processes.close()
