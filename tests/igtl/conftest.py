"""Fixtures for the OpenIGTLink service tests: real sockets on 127.0.0.1, bounded waits only."""

from __future__ import annotations

import random
import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pyigtl
import pytest

from biopsynav.config import IgtlSection
from biopsynav.igtl.protocol import Message, encode_transform, read_message
from biopsynav.igtl.server import IgtlServer, connected_to_itself
from tests.igtl.rigid import RigidLesionTracker

HOST = "127.0.0.1"
CENTERS = np.array([[10.0, 20.0, 30.0], [-5.0, 0.0, 40.0], [0.0, -15.0, 25.0]])
WAIT_S = 5.0


def wait_until(pred: Callable[[], bool], timeout: float = WAIT_S, what: str = "") -> None:
    """Poll ``pred`` (test side only) until true; fail after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what or pred}")
        time.sleep(0.005)


def translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _ephemeral_low() -> int:
    """Lowest port of the kernel's ephemeral range (where bind(0) and connect() draw theirs)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range", encoding="ascii") as fh:
            return int(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port() -> int:
    """A loopback port free now, for a server a test starts later, drawn below the ephemeral
    range: no other process's bind(0) or outgoing connection can take it in between, and a
    client retrying a connection to it cannot be given it as its own source port."""
    rng = random.Random()
    high = min(_ephemeral_low(), 32768)
    low = 20000 if high > 21000 else 1024
    for _ in range(200):
        port = rng.randrange(low, high)
        with socket.socket() as s:
            try:
                s.bind((HOST, port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free loopback port found below the ephemeral range")


class FakePlus:
    """A minimal OpenIGTLink server standing in for PlusServer: sends pyigtl-packed TRANSFORMs."""

    def __init__(self, port: int = 0) -> None:
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((HOST, port))
        self.listener.listen(4)
        self.listener.settimeout(WAIT_S)
        self.port = self.listener.getsockname()[1]
        self.conn: socket.socket | None = None

    def accept(self) -> None:
        self.conn, _ = self.listener.accept()
        self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send_pose(self, T: np.ndarray, device: str = "ProbeToReference",
                  timestamp: float | None = None) -> None:
        self.conn.sendall(encode_transform(device, T, timestamp))

    def drop_client(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def close(self) -> None:
        self.drop_client()
        self.listener.close()


class RawClient:
    """A blocking-socket client that reads and CRC-checks whole messages."""

    def __init__(self, port: int, rcvbuf: int | None = None) -> None:
        self.sock = socket.socket()
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(WAIT_S)
        self.sock.connect((HOST, port))
        if connected_to_itself(self.sock):  # nobody listens on the port yet
            self.sock.close()
            raise ConnectionRefusedError(f"connected to itself on port {port}")
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read(self) -> Message:
        return read_message(self.sock)

    def read_until(self, msg_type: str, device: str) -> Message:
        for _ in range(1000):
            msg = self.read()
            if msg.type == msg_type and msg.device == device:
                return msg
        raise AssertionError(f"no {msg_type} {device}")

    def closed_by_peer(self, timeout: float = WAIT_S) -> bool:
        """True when the server closes this connection (replies are read and discarded)."""
        self.sock.settimeout(timeout)
        try:
            while self.sock.recv(1 << 16):
                pass
        except TimeoutError:
            return False
        except ConnectionResetError:
            return True
        return True

    def close(self) -> None:
        self.sock.close()


def quiet_settings(**kw) -> IgtlSection:
    """Test settings: fast reconnection, and a probe timeout far beyond any test step (a pause
    of the test would otherwise turn the status it waits for into probe_not_tracked)."""
    return IgtlSection(**{"reconnect_max_s": 0.2, "probe_timeout_s": 600.0, **kw})


class Running:
    """An :class:`IgtlServer` running in a thread, stopped and joined on exit."""

    def __init__(self, tracker, tracker_addr=None, settings: IgtlSection | None = None) -> None:
        self.server = IgtlServer(tracker, (HOST, 0), tracker_addr, "ProbeToReference",
                                 settings or quiet_settings())
        self.port = self.server.start()[1]
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        self.clients: list[pyigtl.OpenIGTLinkClient] = []

    def slicer(self, n_expected: int | None = None) -> pyigtl.OpenIGTLinkClient:
        """A pyigtl client (3D Slicer stand-in), connected before returning."""
        want = n_expected if n_expected is not None else self.server.stats().clients + 1
        client = pyigtl.OpenIGTLinkClient(host=HOST, port=self.port)
        self.clients.append(client)
        wait_until(lambda: self.server.stats().clients >= want, what="client connected")
        return client

    def stop(self) -> None:
        for client in self.clients:
            client.stop()
        self.server.stop()
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "server thread did not stop"


@pytest.fixture
def tracker() -> RigidLesionTracker:
    return RigidLesionTracker(CENTERS, max_push_mm=20.0)


@pytest.fixture
def running(tracker) -> Iterator[Running]:
    run = Running(tracker)
    yield run
    run.stop()


@pytest.fixture
def plus() -> Iterator[FakePlus]:
    fake = FakePlus()
    yield fake
    fake.close()
