"""The OpenIGTLink service end to end: real pyigtl clients, a stand-in PLUS server, faults."""

from __future__ import annotations

import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyigtl
import pytest

from biopsynav.errors import InputError
from biopsynav.igtl.protocol import HEADER_SIZE, encode_string, encode_transform
from biopsynav.igtl.server import IgtlServer, connected_to_itself
from biopsynav.igtl.service import run_service
from biopsynav.tracker.result import INVALID_POSE, OK, REST, TrackingResult
from tests.igtl.rigid import RigidLesionTracker

from .conftest import (
    CENTERS,
    HOST,
    WAIT_S,
    FakePlus,
    RawClient,
    Running,
    free_port,
    quiet_settings,
    translation,
    wait_until,
)


def expect_lesions(client: pyigtl.OpenIGTLinkClient, centers: np.ndarray) -> None:
    """The client receives, within ``WAIT_S``, the POINT and every lesion TRANSFORM at
    ``centers``. Messages of earlier poses that are still queued pass by (pyigtl keeps the
    latest message per device, so the answer to a previous pose may be read first)."""
    point = wait_for_match(client, "Lesions",
                           lambda m: np.allclose(np.array(m.positions), centers, atol=1e-4))
    assert point.names == [f"Lesion{i}" for i in range(1, len(centers) + 1)]
    for i, center in enumerate(centers, start=1):
        tf = wait_for_match(client, f"Lesion{i}ToReference",
                            lambda m, c=center: np.allclose(m.matrix[:3, 3], c, atol=1e-4))
        np.testing.assert_allclose(tf.matrix[:3, :3], np.eye(3))


def wait_for_match(client: pyigtl.OpenIGTLinkClient, device: str, matches):
    """The first message of ``device`` for which ``matches(message)`` holds, within
    ``WAIT_S``; an AssertionError naming the last one seen otherwise."""
    last = None
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        msg = client.wait_for_message(device, timeout=0.05)
        if msg is not None:
            if matches(msg):
                return msg
            last = msg
    seen = "none" if last is None else (getattr(last, "positions", None)
                                        or getattr(last, "matrix", None))
    raise AssertionError(f"no matching {device} within {WAIT_S} s; the last seen: {seen}")


def expect_status(client: pyigtl.OpenIGTLinkClient, prefix: str) -> str:
    """Wait for a TrackingStatus that starts with ``prefix`` (earlier statuses pass by)."""
    seen = []
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        msg = client.wait_for_message("TrackingStatus", timeout=0.05)
        if msg is not None:
            seen.append(msg.string)
            if msg.string.startswith(prefix):
                return msg.string
    raise AssertionError(f"no TrackingStatus {prefix!r}; seen {seen}")


def raw_pose(T: np.ndarray) -> bytes:
    return encode_transform("ProbeToReference", T)


def test_pose_from_tracker_server_reaches_two_clients(tracker, plus):
    run = Running(tracker, tracker_addr=(HOST, plus.port))
    try:
        a, b = run.slicer(), run.slicer()
        plus.accept()
        plus.send_pose(translation(5, 0, 0))  # first contact: becomes the rest pose
        for client in (a, b):
            expect_lesions(client, CENTERS)
        plus.send_pose(translation(5, 2, 3))
        for client in (a, b):
            expect_lesions(client, CENTERS + [0, 2, 3])
        stats = run.server.stats()
        assert stats.tracker_connected and stats.poses_handled == 2
        assert stats.rest_poses_set == 1 and stats.clients == 2
    finally:
        run.stop()


def test_pose_sent_by_a_client_answers_every_client(running):
    sender, other = running.slicer(), running.slicer()
    sender.send_message(pyigtl.TransformMessage(np.eye(4), device_name="ProbeToReference"))
    expect_lesions(other, CENTERS)
    expect_lesions(sender, CENTERS)
    sender.send_message(pyigtl.TransformMessage(translation(0, 0, 4),
                                                device_name="ProbeToReference"))
    expect_lesions(other, CENTERS + [0, 0, 4])


def test_rest_pose_taken_automatically_then_set_by_command(running, tracker):
    client = running.slicer()
    raw = RawClient(running.port)
    raw.send(raw_pose(translation(1, 1, 1)))
    expect_lesions(client, CENTERS)
    assert tracker.has_rest_pose
    raw.send(raw_pose(translation(1, 1, 6)))
    expect_lesions(client, CENTERS + [0, 0, 5])
    raw.send(encode_string("biopsynavCommand", "SetRestPose"))
    assert raw.read_until("STRING", "biopsynavReply").body.string.startswith("SetRestPose: ok")
    raw.send(raw_pose(translation(1, 1, 6)))
    expect_lesions(client, CENTERS)
    raw.send(raw_pose(translation(1, 1, 8)))
    expect_lesions(client, CENTERS + [0, 0, 2])
    raw.send(encode_string("biopsynavCommand", "Bogus"))
    assert "unknown command" in raw.read_until("STRING", "biopsynavReply").body.string
    raw.close()


def test_auto_rest_pose_waits_for_first_contact():
    run = Running(RigidLesionTracker(CENTERS, skin_z=0.0))
    try:
        client = run.slicer()
        for n, z in enumerate((-10.0, -4.0), 1):  # in the air: rest pose re-taken, no contact
            client.send_message(pyigtl.TransformMessage(translation(0, 0, z),
                                                        device_name="ProbeToReference"))
            wait_until(lambda n=n: run.server.stats().poses_handled == n)
        assert "no skin" in expect_status(client, "no_contact: ")  # sent once: on the change
        assert run.server.stats().status_messages == 1
        client.send_message(pyigtl.TransformMessage(np.eye(4), device_name="ProbeToReference"))
        expect_status(client, REST)  # first contact: this is the rest pose
        expect_lesions(client, CENTERS)
        client.send_message(pyigtl.TransformMessage(translation(0, 0, 3),
                                                    device_name="ProbeToReference"))
        expect_lesions(client, CENTERS + [0, 0, 3])
        assert run.server.stats().rest_poses_set == 3
    finally:
        run.stop()


def test_set_rest_pose_without_any_pose_fails_politely(running):
    raw = RawClient(running.port)
    raw.send(encode_string("biopsynavCommand", "SetRestPose"))
    reply = raw.read_until("STRING", "biopsynavReply").body.string
    assert reply.startswith("SetRestPose: failed: no probe pose")
    raw.close()


def test_unreliable_result_sends_status_and_no_transforms(running):
    client = running.slicer()
    raw = RawClient(running.port)
    raw.send(raw_pose(np.eye(4)))
    expect_lesions(client, CENTERS)
    raw.send(raw_pose(translation(0, 0, 25)))  # beyond the 20 mm envelope of the stand-in
    assert "envelope" in expect_status(client, "out_of_envelope: ")
    # the reply to the unreliable pose holds the status and no lesion TRANSFORM
    msgs = []
    while not msgs or msgs[-1].device != "TrackingStatus":
        msgs.append(raw.read())
    raw.send(raw_pose(translation(0, 0, 3)))
    expect_status(client, OK)  # back to reliable: one "ok" status
    expect_lesions(client, CENTERS + [0, 0, 3])
    raw.close()


def test_nan_pose_reports_invalid_pose_and_is_never_the_rest_pose(running, tracker):
    client = running.slicer()
    nan_pose = np.full((4, 4), np.nan)
    client.send_message(pyigtl.TransformMessage(nan_pose, device_name="ProbeToReference"))
    assert "NaN" in expect_status(client, INVALID_POSE)
    assert not tracker.has_rest_pose
    client.send_message(pyigtl.TransformMessage(np.eye(4), device_name="ProbeToReference"))
    expect_status(client, REST)
    expect_lesions(client, CENTERS)
    shear = np.eye(4)
    shear[0, 1] = 0.5
    client.send_message(pyigtl.TransformMessage(shear, device_name="ProbeToReference"))
    assert "orthonormal" in expect_status(client, INVALID_POSE)
    np.testing.assert_array_equal(tracker._rest, np.eye(4))  # never the rest pose


class BrokenTracker:
    """Raises, then returns garbage, then NaN lesions: the server must survive all of it."""

    has_rest_pose = True

    def __init__(self) -> None:
        self.calls = 0

    def set_rest_pose(self, T):
        raise RuntimeError("cannot")

    def update(self, T):
        self.calls += 1
        if self.calls == 1:
            raise ZeroDivisionError("boom")
        if self.calls == 2:
            return None
        lesion = type("L", (), {"id": 1, "center": [np.nan, 0, 0], "status": OK})()
        return TrackingResult(lesions=[lesion, "junk"], status=OK)


def test_tracker_that_raises_or_returns_garbage_does_not_stop_the_server():
    run = Running(BrokenTracker())
    try:
        client = run.slicer()
        raw = RawClient(run.port)
        raw.send(raw_pose(np.eye(4)))
        assert "boom" in expect_status(client, "tracker_error: ")
        raw.send(raw_pose(np.eye(4)))  # the same status: not sent again before keep-alive
        wait_until(lambda: run.server.stats().tracker_failures == 2)
        raw.send(raw_pose(np.eye(4)))
        expect_status(client, OK)  # recovered; NaN lesion omitted, nothing else sent
        raw.send(encode_string("biopsynavCommand", "SetRestPose"))
        assert "cannot" in raw.read_until("STRING", "biopsynavReply").body.string
        assert run.server.stats().tracker_failures == 2
        raw.close()
    finally:
        run.stop()


def _fault_then_healthy(running, payload: bytes, *, dropped: bool) -> RawClient:
    """Send ``payload`` from a raw client; check the server and a healthy client go on."""
    healthy = running.slicer()
    bad = RawClient(running.port)
    wait_until(lambda: running.server.stats().clients == 2)
    bad.send(payload)
    if dropped:
        assert bad.closed_by_peer(), "faulty client was not dropped"
        wait_until(lambda: running.server.stats().clients == 1)
    healthy.send_message(pyigtl.TransformMessage(np.eye(4), device_name="ProbeToReference"))
    expect_lesions(healthy, CENTERS)
    return bad


def test_client_disconnect_mid_message(running):
    bad = RawClient(running.port)
    bad.send(raw_pose(np.eye(4))[:HEADER_SIZE + 10])
    bad.close()
    wait_until(lambda: running.server.stats().disconnects_mid_message == 1)
    _fault_then_healthy(running, b"", dropped=False).close()
    assert running.server.stats().poses_handled == 1


def test_client_stalled_mid_message_is_dropped_and_a_slow_one_is_not(tracker):
    run = Running(tracker, settings=quiet_settings(stall_timeout_s=1.0))
    try:
        message = raw_pose(translation(0, 0, 1.0))
        slow = RawClient(run.port)
        for start in range(0, len(message), 40):  # a whole message, gaps below the timeout
            slow.send(message[start:start + 40])
            time.sleep(0.1)
        assert slow.read_until("POINT", "Lesions") is not None
        staller = RawClient(run.port)
        staller.send(message[:HEADER_SIZE + 10])
        wait_until(lambda: run.server.stats().stalled == 1, what="stalled client dropped")
        wait_until(lambda: run.server.stats().clients == 1, what="one client left")
        assert run.server.stats().clients_dropped == 1
        slow.send(message)  # the other client is still served
        assert slow.read_until("POINT", "Lesions") is not None
        slow.close()
        staller.close()
    finally:
        run.stop()


def test_malformed_header_drops_that_client_only(running):
    _fault_then_healthy(running, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + b"\0" * 64,
                        dropped=True).close()
    stats = running.server.stats()
    assert stats.protocol_errors == 1 and stats.clients_dropped == 1


def test_oversized_body_drops_that_client_only(running):
    header = bytearray(raw_pose(np.eye(4))[:HEADER_SIZE])
    header[42:50] = struct.pack(">Q", 10 << 20)
    _fault_then_healthy(running, bytes(header), dropped=True).close()
    assert running.server.stats().clients_dropped == 1


def test_wrong_crc_drops_the_message_not_the_client(running):
    bad_pose = bytearray(raw_pose(translation(0, 0, 9)))
    bad_pose[-1] ^= 0x55
    bad = _fault_then_healthy(running, bytes(bad_pose), dropped=False)
    wait_until(lambda: running.server.stats().messages_dropped == 1)
    bad.send(raw_pose(translation(0, 0, 1)))  # same connection still served
    bad.read_until("POINT", "Lesions")  # the reply to the healthy client's pose
    point = bad.read_until("POINT", "Lesions")
    np.testing.assert_allclose(point.body.positions, CENTERS + [0, 0, 1], atol=1e-4)
    bad.close()
    assert running.server.stats().poses_handled == 2


def test_unknown_type_and_other_devices_are_skipped(running):
    unknown = pyigtl.StringMessage("x" * 300, device_name="Whatever")
    unknown._message_type = "CUSTOM_TYPE"
    other = encode_transform("NeedleToReference", translation(0, 0, 50))
    bad = _fault_then_healthy(running, unknown.pack() + other, dropped=False)
    wait_until(lambda: running.server.stats().messages_skipped == 2)
    bad.close()
    assert running.server.stats().protocol_errors == 0


def test_flood_of_poses_is_coalesced_and_others_keep_being_served(running, tracker):
    observer = RawClient(running.port)
    flooder = RawClient(running.port)
    burst = b"".join(raw_pose(translation(0, 0, 0.001 * i)) for i in range(20000))
    sender = threading.Thread(target=flooder.sock.sendall, args=(burst,))
    sender.start()
    sender.join(WAIT_S * 2)
    def consumed() -> bool:
        stats = running.server.stats()
        return stats.poses_handled + stats.poses_coalesced == 20000

    wait_until(consumed, what="flood consumed")
    stats = running.server.stats()
    assert stats.poses_received == 20000 and stats.poses_coalesced > 10000
    observer.send(raw_pose(translation(0, 0, 2)))
    rest_z = tracker._rest[2, 3]  # the first pose handled, whichever survived coalescing
    for _ in range(stats.poses_handled + 1):  # replies in order; the last answers z = 2
        point = observer.read_until("POINT", "Lesions")
        if np.allclose(point.body.positions, CENTERS + [0, 0, 2 - rest_z], atol=1e-4):
            break
    else:
        raise AssertionError("no reply to the pose sent after the flood")
    flooder.close()
    observer.close()


def test_client_that_does_not_read_is_dropped():
    big = RigidLesionTracker(np.random.default_rng(0).normal(size=(200, 3)) * 20,
                             max_push_mm=1e6)
    run = Running(big, settings=quiet_settings(client_backlog_bytes=256 << 10))
    try:
        reader = RawClient(run.port)
        sleeper = RawClient(run.port, rcvbuf=4096)  # never reads
        wait_until(lambda: run.server.stats().clients == 2)
        for i in range(400):
            reader.send(raw_pose(translation(0, 0, 0.01 * i)))
            reader.read_until("POINT", "Lesions")
            if run.server.stats().clients_dropped:
                break
        assert run.server.stats().clients_dropped == 1
        assert run.server.stats().clients == 1
        reader.send(raw_pose(np.eye(4)))
        assert len(reader.read_until("POINT", "Lesions").body.names) == 200
        reader.close()
        sleeper.close()
    finally:
        run.stop()


def test_tracker_server_absent_then_appearing_then_restarting(tracker):
    port = free_port()
    run = Running(tracker, tracker_addr=(HOST, port))
    plus = None
    try:
        client = run.slicer()
        time.sleep(0.3)  # a few refused attempts with backoff
        assert not run.server.stats().tracker_connected
        plus = FakePlus(port)
        plus.accept()
        wait_until(lambda: run.server.stats().tracker_connected)
        plus.send_pose(np.eye(4))
        expect_lesions(client, CENTERS)
        plus.close()  # PLUS goes away and comes back
        wait_until(lambda: run.server.stats().tracker_disconnects == 1)
        expect_status(client, "no_rest_pose: tracker connection lost")
        plus = FakePlus(port)
        plus.accept()
        plus.send_pose(translation(0, 1, 0))  # the new rest pose: the tracker frame may differ
        expect_lesions(client, CENTERS)
        stats = run.server.stats()
        assert (stats.tracker_connects, stats.rest_poses_cleared) == (2, 1)
    finally:
        if plus is not None:
            plus.close()
        run.stop()


def test_rest_pose_kept_across_tracker_restart_when_configured(tracker, plus):
    run = Running(tracker, (HOST, plus.port), quiet_settings(rest_pose_on_reconnect="keep"))
    try:
        client = run.slicer()
        plus.accept()
        plus.send_pose(np.eye(4))
        expect_lesions(client, CENTERS)
        plus.drop_client()
        wait_until(lambda: run.server.stats().tracker_disconnects == 1)
        plus.accept()
        plus.send_pose(translation(0, 1, 0))
        expect_lesions(client, CENTERS + [0, 1, 0])
        assert run.server.stats().rest_poses_cleared == 0
    finally:
        run.stop()


def test_tracker_server_sending_garbage_is_dropped_and_reconnected(tracker, plus):
    run = Running(tracker, tracker_addr=(HOST, plus.port))
    try:
        client = run.slicer()
        plus.accept()
        plus.conn.sendall(b"\x00\x09" + b"garbage" * 20)
        wait_until(lambda: run.server.stats().tracker_disconnects == 1)
        plus.accept()  # the service comes back after its backoff
        plus.send_pose(np.eye(4))
        expect_lesions(client, CENTERS)
        assert run.server.stats().protocol_errors == 1
    finally:
        run.stop()


def test_pyigtl_server_as_plus_stand_in(tracker):
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    plus = pyigtl.OpenIGTLinkServer(port=0, local_server=True)  # installs signal handlers
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    run = Running(tracker, tracker_addr=(HOST, plus.server_address[1]))
    try:
        client = run.slicer()
        wait_until(lambda: run.server.stats().tracker_connected)
        plus.send_message(pyigtl.TransformMessage(translation(3, 0, 0),
                                                  device_name="ProbeToReference"), wait=True)
        expect_lesions(client, CENTERS)
    finally:
        run.stop()
        plus.stop()


def test_run_service_stops_on_event_and_on_sigint(tracker):
    started = threading.Event()
    stop = threading.Event()
    holder = {}

    def on_started(server):
        holder["server"] = server
        started.set()

    thread = threading.Thread(target=lambda: holder.setdefault("stats", run_service(
        tracker, None, (HOST, 0), stop_event=stop, on_started=on_started)))
    thread.start()
    assert started.wait(WAIT_S)
    raw = RawClient(holder["server"].address[1])
    raw.send(raw_pose(np.eye(4)))
    raw.read_until("POINT", "Lesions")
    stop.set()
    thread.join(WAIT_S)
    assert not thread.is_alive() and holder["stats"].poses_handled == 1
    raw.close()

    # SIGINT in a process of its own: sent to the pytest-xdist worker itself, the worker once
    # died during this step (2026-11-28, "worker 'gw1' crashed", no reason left behind); a
    # child's failure fails this test with its output instead of ending the run
    proc = subprocess.run([sys.executable, "-c", SIGINT_SCRIPT], capture_output=True, text=True,
                          timeout=120, cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert proc.stdout.split()[-1] == "handled=0,restored=True"


#: The main thread runs the service; once it listens (its handlers installed) the process
#: sends itself SIGINT, which stops it and leaves the previous handler in place.
SIGINT_SCRIPT = """
import os, signal
from biopsynav.igtl.service import run_service
from tests.igtl.conftest import CENTERS, HOST
from tests.igtl.rigid import RigidLesionTracker

before = signal.getsignal(signal.SIGINT)
stats = run_service(RigidLesionTracker(CENTERS, max_push_mm=20.0), None, (HOST, 0),
                    on_started=lambda server: os.kill(os.getpid(), signal.SIGINT))
print(f"handled={stats.poses_handled},restored={signal.getsignal(signal.SIGINT) is before}")
"""


def test_constructor_has_no_side_effects_and_listens_on_loopback(tracker):
    port = free_port()
    server = IgtlServer(tracker, f"{HOST}:{port}", None)
    with socket.socket() as probe:
        assert probe.connect_ex((HOST, port)) != 0  # nothing bound yet
    assert IgtlServer(tracker).listen_addr == ("127.0.0.1", 18945)
    del server


def test_bad_listen_address_is_an_input_error(tracker):
    from biopsynav.errors import InputError

    with pytest.raises(InputError):
        IgtlServer(tracker, "nonsense", None)


def test_idle_connections_never_lock_a_real_client_out(tracker):
    run = Running(tracker, settings=quiet_settings(max_clients=32))
    idle = []
    try:
        for _ in range(40):  # more than max_clients idle connections, none sends or reads
            idle.append(RawClient(run.port))
        wait_until(lambda: run.server.stats().clients_total == 40, what="40 accepted")
        assert run.server.stats().clients == 32
        assert run.server.stats().clients_evicted == 8
        real = RawClient(run.port)  # a well-behaved client still gets in and is served
        wait_until(lambda: run.server.stats().clients_total == 41, what="real client accepted")
        real.send(raw_pose(translation(0, 0, 1.0)))
        assert real.read_until("POINT", "Lesions") is not None
        assert run.server.stats().clients == 32
        # the evicted are the oldest idle ones, not the client that just got its reply
        assert not real.closed_by_peer(timeout=0.2)
        real.close()
    finally:
        for conn in idle:
            conn.close()
        run.stop()


def test_trickling_client_is_dropped_after_stall_timeout_from_its_first_byte(tracker):
    run = Running(tracker, settings=quiet_settings(stall_timeout_s=0.5))
    try:
        message = raw_pose(translation(0, 0, 1.0))
        trickler = RawClient(run.port)
        start = time.monotonic()
        for i in range(len(message)):  # one byte every 50 ms: each resets no timer
            if run.server.stats().stalled:
                break
            trickler.send(message[i:i + 1])
            time.sleep(0.05)
        wait_until(lambda: run.server.stats().stalled == 1, what="trickler dropped")
        assert time.monotonic() - start < 0.5 + WAIT_S
        assert trickler.closed_by_peer()
        assert run.server.stats().poses_received == 0
    finally:
        run.stop()


def test_ipv6_listen_address(tracker):
    from biopsynav.config import parse_address

    assert parse_address("[::1]:18945") == ("::1", 18945)
    with pytest.raises(InputError, match="brackets"):
        parse_address("::1:18945", "--listen")
    if not socket.has_ipv6:
        pytest.skip("no IPv6 in this Python")
    server = IgtlServer(tracker, ("::1", 0), None)
    try:
        try:
            host, port = server.start()
        except InputError as exc:  # a machine without IPv6 loopback: one clear line
            assert "--listen" in str(exc)
            pytest.skip(f"no IPv6 loopback here: {exc}")
        assert host == "::1" and port > 0
    finally:
        server._close_all()


def test_a_connection_to_itself_is_told_from_a_tracker_server():
    """A connect to a loopback port nobody listens on can reach itself (TCP simultaneous open
    when the kernel picks that port as the source): made here on purpose by binding first."""
    with socket.socket() as own:
        own.bind((HOST, 0))
        own.connect(own.getsockname())
        assert connected_to_itself(own)
    plus = FakePlus()
    try:
        with socket.create_connection((HOST, plus.port)) as sock:
            assert not connected_to_itself(sock)
    finally:
        plus.close()
    with socket.socket() as unconnected:
        assert not connected_to_itself(unconnected)
