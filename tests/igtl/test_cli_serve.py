"""`biopsynav serve` as a user runs it: what it says at the default level, with --quiet."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from biopsynav.igtl.protocol import encode_transform

from .conftest import HOST, RawClient, free_port

REST = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 76.0], [0, 0, 0, 1]])


def _serve(case: Path, *flags: str) -> tuple[str, int]:
    """Run serve, send two poses (one under a wrong name), read the reply, stop with SIGINT;
    return its stderr and exit status."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "biopsynav.cli", "serve", str(case),
                             "--listen", f"{HOST}:{port}", "--tracker", f"{HOST}:{free_port()}",
                             *flags], stderr=subprocess.PIPE, text=True)
    try:
        client = _connect(port, proc)
        client.send(encode_transform("Tracker", REST) + encode_transform("ProbeToReference",
                                                                          REST))
        assert client.read_until("POINT", "Lesions").body.names
        client.close()
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    return err, proc.returncode


def _connect(port: int, proc: subprocess.Popen) -> RawClient:
    end = time.monotonic() + 120  # loading the tracker
    while True:
        try:
            return RawClient(port)
        except ConnectionRefusedError:
            assert proc.poll() is None and time.monotonic() < end, "serve did not start"
            time.sleep(0.1)


@pytest.mark.slow
def test_serve_tells_the_user_what_happens(trained_case):
    err, code = _serve(trained_case)
    assert code == 0, err
    for line in (f"loading the tracker of {trained_case}", "listening for OpenIGTLink clients "
                 "on 127.0.0.1:", "unavailable (ECONNREFUSED); retrying every <= 2.0 s",
                 "connected (1 clients)",
                 "sends TRANSFORM 'Tracker', ignored: the probe pose is expected as "
                 "'ProbeToReference'", "rest pose taken automatically at first contact",
                 "tracking status: ok", "stopped after"):
        assert line in err, line
    assert "Traceback" not in err


@pytest.mark.slow
def test_serve_quiet_keeps_warnings_only(trained_case):
    err, code = _serve(trained_case, "--quiet")
    assert code == 0, err
    assert "sends TRANSFORM 'Tracker', ignored" in err
    assert "listening for" not in err and "INFO" not in err
