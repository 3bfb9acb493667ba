"""An advisory lock on a case folder, held by every command that writes into it.

``CASE_DIR/.biopsynav.lock`` is locked with ``flock`` (released by the kernel when the process
ends, however it ends) and holds one line naming the holder, so a second writer is told which
command runs: ``generate`` (pid 1234, since 2026-11-23T10:00:00). Worker processes forked by the
holder inherit the lock; they never take it themselves.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path

from .errors import CaseBusyError, WriteError
from .layout import LOCK_NAME


@contextlib.contextmanager
def case_lock(case_dir: str | Path, command: str) -> Iterator[None]:
    """Hold the case's write lock for the ``with`` block; CaseBusyError when another process
    holds it, WriteError when the folder cannot hold a lock file (read-only)."""
    path = Path(case_dir) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise WriteError(f"cannot lock the case for writing: {exc.strerror}",
                         str(case_dir)) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CaseBusyError(f"another command is writing to this case: {_holder(fd)}; "
                                "wait for it to end or stop it first", str(case_dir)) from None
        _write_holder(fd, command)
        yield
    finally:
        os.close(fd)  # releases the lock


def _write_holder(fd: int, command: str) -> None:
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S")
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{command} (pid {os.getpid()}, since {stamp})\n".encode(), 0)


def _holder(fd: int) -> str:
    text = os.pread(fd, 512, 0).decode("utf-8", "replace").strip()
    return f"`biopsynav {text}`" if text else "unknown holder"
