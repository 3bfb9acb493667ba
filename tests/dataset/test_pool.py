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


def test_a_script_without_the_main_guard_gets_an_error_not_a_hang(base_case, tmp_path):
    """A script that calls generate_case with workers at its top level: each spawned worker
    imports it again and dies while starting. The main process once waited for ever writing
    the case to a dead worker's start pipe; now it stops within seconds naming the guard."""
    import shutil
    import subprocess
    import sys

    case = tmp_path / "case"
    shutil.copytree(base_case, case)
    script = tmp_path / "no_guard.py"
    script.write_text("from biopsynav.dataset.generate import generate_case\n"
                      f"generate_case({str(case)!r}, workers=2, progress=False)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert done.returncode != 0
    assert 'needs its calls under `if __name__ == "__main__":`' in done.stderr
    assert "During handling" not in done.stderr.split("InputError")[-1]


def test_a_closed_pool_leaves_no_files(tmp_path):
    """Building the pool starts nothing and writes nothing; its first task writes the set-up
    file and the workers' start marks in a folder that close() removes."""
    from biopsynav.dataset import pool

    processes = pool.WorkerProcesses(1, _nothing, ())
    assert processes.folder is None and processes.processes() == []
    try:
        assert processes.submit(_pid).result(timeout=120) > 0
        folder = processes.folder
        assert (folder / pool.SETUP_FILE).is_file()
        assert len(list(folder.glob("started-*"))) == 1
        processes.check_started()  # a worker started: nothing to say
    finally:
        processes.close()
    assert not folder.exists()


def test_a_pool_closed_before_any_task_is_a_no_op():
    from biopsynav.dataset import pool

    processes = pool.WorkerProcesses(2, _nothing, ())
    processes.close()
    assert processes.folder is None and processes.processes() == []
