"""The OpenIGTLink service: probe pose in, lesion positions out, in one ``selectors`` loop.

Topology (see ``docs/igtl.md``)::

    PlusServer :18944  --TRANSFORM ProbeToReference-->  biopsynav (client connection)
    3D Slicer OpenIGTLinkIF (client) <--POINT, TRANSFORM, STRING--  biopsynav :18945 (server)

One thread, non-blocking sockets with TCP_NODELAY, no polling sleeps: the loop blocks in
``select`` until a socket is ready, the next tracker reconnection is due, or :meth:`stop` writes
to a wake-up socket. Every probe pose (from the tracker server or from any listening client) goes
to ``tracker.update``; the reply (see :mod:`.replies`) is packed once and written to every
listening client in two sends: status and POINT first, then the lesion TRANSFORMs. When more
than ``max_poses_per_read`` poses arrive in one read only the newest ones are tracked (the
others count as ``poses_coalesced``), so a backlog (a stall, a flood) never delays the newest
pose by more than that many updates.

Faults are logged and cost only the connection (or message) they come from: malformed headers
and oversized bodies drop the connection; a wrong CRC or an undecodable body drops the message;
unknown types are skipped; a client whose unsent replies exceed ``client_backlog_bytes`` (it does
not read) is dropped; whatever ``tracker.update`` raises or returns becomes a ``tracker_error``
status.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import selectors
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import IgtlSection, parse_address
from ..errors import BiopsynavError, InputError
from ..tracker.result import NO_CONTACT, RELIABLE, TRACKER_ERROR, TrackingResult
from .protocol import IgtlProtocolError, Message, MessageReader, encode_string
from .replies import (
    CMD_SET_REST_POSE,
    COMMAND_DEVICE,
    COMMAND_REPLY_DEVICE,
    encode_lesion_point,
    encode_lesion_transforms,
    encode_status,
    error_result,
)

log = logging.getLogger(__name__)

Address = tuple[str, int]
RECV_BYTES = 1 << 16
ACCEPT_BURST = 16
RECONNECT_MIN_S = 0.05
CONNECT_TIMEOUT_S = 2.0
_CONNECT_PENDING = (errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY, errno.EINTR)


@runtime_checkable
class TrackerLike(Protocol):
    """What the service needs from a tracker (``biopsynav.tracker.Tracker`` provides it)."""

    @property
    def has_rest_pose(self) -> bool: ...

    def set_rest_pose(self, T: np.ndarray) -> None: ...

    def update(self, T: np.ndarray) -> TrackingResult: ...


@dataclass
class ServerStats:
    """Counters of one service run (a snapshot from :meth:`IgtlServer.stats`)."""

    poses_received: int = 0
    poses_handled: int = 0
    poses_coalesced: int = 0
    replies_sent: int = 0
    rest_poses_set: int = 0
    tracker_failures: int = 0
    clients: int = 0
    clients_total: int = 0
    clients_dropped: int = 0
    clients_evicted: int = 0
    disconnects_mid_message: int = 0
    protocol_errors: int = 0
    messages_dropped: int = 0
    messages_skipped: int = 0
    commands: int = 0
    tracker_connected: bool = False
    tracker_connects: int = 0
    tracker_disconnects: int = 0
    last_update_ms: float = math.nan
    stalled: int = 0


@dataclass(eq=False)
class _Conn:
    """One socket of the loop: a listening client or the tracker-server connection."""

    sock: socket.socket
    name: str
    is_tracker: bool
    reader: MessageReader
    out: bytearray = field(default_factory=bytearray)
    connecting: bool = False
    closed: bool = False
    seen_skipped: set = field(default_factory=set)
    partial_since: float = math.inf  # monotonic time of the first byte of an incomplete message
    last_active: float = field(default_factory=time.monotonic)  # last whole message or reply


def to_address(value: str | Address | None, where: str) -> Address | None:
    """``"HOST:PORT"`` or ``(host, port)`` to a tuple; None stays None."""
    if value is None or isinstance(value, tuple):
        return value
    return parse_address(value, where)


def _is_loopback(host: str) -> bool:
    return host in ("localhost", "::1") or host.startswith("127.")


def _nodelay(sock: socket.socket) -> None:
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class IgtlServer:
    """The service. No side effects until :meth:`start`; :meth:`run` loops until :meth:`stop`.

    One use: once :meth:`run` has returned, make a new server to serve again.

    ``tracker_addr`` None: no tracker-server connection (poses only from listening clients).
    """

    def __init__(self, tracker: TrackerLike, listen_addr: str | Address = "127.0.0.1:18945",
                 tracker_addr: str | Address | None = "127.0.0.1:18944",
                 probe_device: str = "ProbeToReference",
                 settings: IgtlSection | None = None) -> None:
        self.tracker = tracker
        self.listen_addr = to_address(listen_addr, "--listen")
        self.tracker_addr = to_address(tracker_addr, "--tracker")
        self.probe_device = probe_device
        self.settings = settings or IgtlSection()
        self._stats = ServerStats()
        self._sel: selectors.BaseSelector | None = None
        self._listener: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._clients: list[_Conn] = []
        self._tracker_conn: _Conn | None = None
        self._next_attempt = 0.0
        self._connect_deadline = math.inf
        self._backoff = RECONNECT_MIN_S
        self._tracker_warned = False
        self._latest_pose: np.ndarray | None = None
        self._last_reliable = True
        self._provisional_rest = False
        self._stop_requested = False
        self._state_lock = threading.RLock()  # held while the loop changes state; stats() too
        self.address: Address | None = None

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> Address:
        """Bind and listen; return the bound (host, port) (port 0 picks a free one)."""
        if self._sel is not None:
            return self.address
        host, port = self.listen_addr
        if not _is_loopback(host):
            log.warning("listening on %s:%d, reachable from other machines", host, port)
        family, _, _, _, sockaddr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                       flags=socket.AI_PASSIVE)[0]
        listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            _nodelay(listener)
            listener.bind(sockaddr)
            listener.listen(64)
            listener.setblocking(False)
        except OSError as exc:
            listener.close()
            raise InputError(f"cannot listen: {exc}", f"--listen {host}:{port}") from None
        self._listener = listener
        self.address = listener.getsockname()[:2]
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(listener, selectors.EVENT_READ, "listener")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        log.info("listening for OpenIGTLink clients on %s:%d", *self.address)
        return self.address

    def stop(self) -> None:
        """Ask the loop to end; safe from other threads and from signal handlers."""
        self._stop_requested = True
        wake = self._wake_w
        if wake is not None:
            try:
                wake.send(b"x")
            except OSError:
                pass

    def run(self) -> None:
        """Serve until :meth:`stop`; closes every socket on the way out."""
        self.start()
        try:
            while not self._stop_requested:
                events = self._sel.select(self._timeout())
                with self._state_lock:
                    self._handle_events(events)
        finally:
            with self._state_lock:
                self._close_all()

    def _handle_events(self, events: list) -> None:
        """One turn of the loop after ``select``: reconnect, dispatch, timeouts."""
        self._maybe_connect_tracker()
        for key, mask in events:
            self._dispatch(key, mask)
        self._check_connect_timeout()
        self._check_stalled()

    def serve_forever(self) -> None:
        """Alias of :meth:`run`."""
        self.run()

    def stats(self) -> ServerStats:
        """A consistent snapshot of the counters (safe from other threads: taken between two
        turns of the loop, never in the middle of one)."""
        with self._state_lock:
            snap = dataclasses.replace(self._stats)
            snap.clients = len(self._clients)
            snap.tracker_connected = (self._tracker_conn is not None
                                      and not self._tracker_conn.connecting)
        return snap

    def _close_all(self) -> None:
        self._stop_requested = True
        for conn in list(self._clients):
            self._close(conn, "server stopping", logging.DEBUG)
        if self._tracker_conn is not None:
            self._close(self._tracker_conn, "server stopping", logging.DEBUG)
        for sock in (self._listener, self._wake_r, self._wake_w):
            if sock is not None:
                sock.close()
        self._wake_w = None
        if self._sel is not None:
            self._sel.close()
        log.info("OpenIGTLink service stopped: %s", self.stats())

    # ------------------------------------------------------------------------------ the loop
    def _timeout(self) -> float | None:
        """Seconds until the next timed event (reconnect, connect timeout, a stalled partial
        message), None for none."""
        now = time.monotonic()
        deadline = min(self._stall_deadlines(), default=math.inf)
        if self.tracker_addr is not None:
            if self._tracker_conn is None:
                deadline = min(deadline, self._next_attempt)
            elif self._tracker_conn.connecting:
                deadline = min(deadline, self._connect_deadline)
        return None if deadline == math.inf else max(0.0, deadline - now)

    def _connections(self) -> list[_Conn]:
        return self._clients + ([self._tracker_conn] if self._tracker_conn is not None else [])

    def _stall_deadlines(self) -> list[float]:
        return [c.partial_since + self.settings.stall_timeout_s for c in self._connections()
                if c.partial_since < math.inf]

    def _check_stalled(self) -> None:
        """Drop connections whose message did not arrive whole in ``stall_timeout_s``."""
        now = time.monotonic()
        for conn in self._connections():
            if conn.partial_since + self.settings.stall_timeout_s <= now:
                self._stats.stalled += 1
                self._drop(conn, f"stalled in the middle of a message ({conn.reader.pending} "
                                 f"bytes of it received in {now - conn.partial_since:.1f} s)")

    def _dispatch(self, key: selectors.SelectorKey, mask: int) -> None:
        if key.data == "listener":
            self._accept()
        elif key.data == "wake":
            self._drain_wake()
        else:
            conn: _Conn = key.data
            try:
                if mask & selectors.EVENT_WRITE and not conn.closed:
                    self._on_writable(conn)
                if mask & selectors.EVENT_READ and not conn.closed:
                    self._on_readable(conn)
            except Exception as exc:  # never let one connection stop the service
                log.exception("unexpected error on %s", conn.name)
                self._drop(conn, f"internal error: {exc!r}")

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass

    def _accept(self) -> None:
        for _ in range(ACCEPT_BURST):
            try:
                sock, peer = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("accept failed: %s", exc)
                return
            name = f"client {peer[0]}:{peer[1]}"
            if len(self._clients) >= self.settings.max_clients:
                self._evict_idlest(name)
            sock.setblocking(False)
            _nodelay(sock)
            conn = _Conn(sock, name, False, MessageReader(self.settings.max_body_bytes))
            self._clients.append(conn)
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self._stats.clients_total += 1
            log.info("%s connected (%d clients)", name, len(self._clients))

    def _evict_idlest(self, newcomer: str) -> None:
        """Make room for ``newcomer``: close the client idle longest (oldest ``last_active``)."""
        idlest = min(self._clients, key=lambda c: c.last_active)
        idle_s = time.monotonic() - idlest.last_active
        self._stats.clients_evicted += 1
        self._close(idlest, f"evicted after {idle_s:.1f} s idle: all "
                            f"{self.settings.max_clients} client slots were taken and "
                            f"{newcomer} arrived", logging.WARNING)

    # ------------------------------------------------------------------- tracker connection
    def _maybe_connect_tracker(self) -> None:
        if (self.tracker_addr is None or self._tracker_conn is not None
                or time.monotonic() < self._next_attempt):
            return
        host, port = self.tracker_addr
        name = f"tracker server {host}:{port}"
        try:
            family, _, _, _, sockaddr = socket.getaddrinfo(host, port,
                                                           type=socket.SOCK_STREAM)[0]
            sock = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:
            self._tracker_unavailable(f"cannot resolve: {exc}")
            return
        sock.setblocking(False)
        _nodelay(sock)
        err = sock.connect_ex(sockaddr)
        conn = _Conn(sock, name, True, MessageReader(self.settings.max_body_bytes))
        self._tracker_conn = conn
        if err == 0:
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self._tracker_connected()
        elif err in _CONNECT_PENDING:
            conn.connecting = True
            self._connect_deadline = time.monotonic() + CONNECT_TIMEOUT_S
            self._sel.register(sock, selectors.EVENT_WRITE, conn)
        else:
            self._tracker_conn = None
            sock.close()
            self._tracker_unavailable(errno.errorcode.get(err, str(err)))

    def _finish_connect(self, conn: _Conn) -> None:
        err = conn.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            self._close(conn, "", logging.DEBUG)
            self._tracker_unavailable(errno.errorcode.get(err, str(err)))
            return
        conn.connecting = False
        self._sel.modify(conn.sock, selectors.EVENT_READ, conn)
        self._tracker_connected()

    def _check_connect_timeout(self) -> None:
        conn = self._tracker_conn
        if conn is not None and conn.connecting and time.monotonic() >= self._connect_deadline:
            self._close(conn, "", logging.DEBUG)
            self._tracker_unavailable(f"no answer within {CONNECT_TIMEOUT_S:.0f} s")

    def _tracker_connected(self) -> None:
        self._stats.tracker_connects += 1
        self._tracker_warned = False
        log.info("connected to %s; waiting for TRANSFORM %r", self._tracker_conn.name,
                 self.probe_device)

    def _tracker_unavailable(self, reason: str) -> None:
        """Schedule the next attempt with exponential backoff; warn once per outage."""
        host, port = self.tracker_addr
        level = logging.DEBUG if self._tracker_warned else logging.WARNING
        log.log(level, "tracker server %s:%d unavailable (%s); retrying every <= %.1f s",
                host, port, reason, self.settings.reconnect_max_s)
        self._tracker_warned = True
        self._next_attempt = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2, self.settings.reconnect_max_s)

    # ------------------------------------------------------------------------------- I/O
    def _on_writable(self, conn: _Conn) -> None:
        if conn.connecting:
            self._finish_connect(conn)
            return
        try:
            sent = conn.sock.send(conn.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(conn, f"send failed: {exc}")
            return
        del conn.out[:sent]
        if not conn.out:
            conn.last_active = time.monotonic()
            self._sel.modify(conn.sock, selectors.EVENT_READ, conn)

    def _on_readable(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(conn, f"receive failed: {exc}")
            return
        if not data:
            self._on_eof(conn)
            return
        was_partial = conn.reader.pending > 0
        items = conn.reader.feed(data)
        now = time.monotonic()
        if items:
            conn.last_active = now
        if not conn.reader.pending:
            conn.partial_since = math.inf
        elif items or not was_partial:  # a new message began in this read
            conn.partial_since = now
        self._handle_items(conn, items)

    def _on_eof(self, conn: _Conn) -> None:
        pending = conn.reader.pending
        if pending:
            self._stats.disconnects_mid_message += 1
            self._close(conn, f"disconnected in the middle of a message ({pending} bytes "
                              "of it received)", logging.WARNING)
        else:
            self._close(conn, "disconnected", logging.INFO)

    def _send(self, conn: _Conn, data: bytes) -> None:
        """Queue ``data`` for ``conn``: one ``send`` now, the rest when writable."""
        if conn.closed or not data:
            return
        limit = self.settings.client_backlog_bytes
        if conn.out:
            if len(conn.out) + len(data) > limit:
                self._drop(conn, f"not reading: {len(conn.out)} bytes of replies unsent")
                return
            conn.out += data
            return
        try:
            sent = conn.sock.send(data)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as exc:
            self._drop(conn, f"send failed: {exc}")
            return
        if sent == len(data):
            conn.last_active = time.monotonic()
        if sent < len(data):
            if len(data) - sent > limit:
                self._drop(conn, f"not reading: {len(data) - sent} bytes of replies unsent")
                return
            conn.out += data[sent:]
            self._sel.modify(conn.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, conn)

    def _drop(self, conn: _Conn, reason: str) -> None:
        """Close a connection because of a fault."""
        if conn.closed:
            return
        self._close(conn, f"dropped: {reason}", logging.WARNING)
        if not conn.is_tracker:
            self._stats.clients_dropped += 1

    def _close(self, conn: _Conn, reason: str, level: int) -> None:
        if conn.closed:
            return
        conn.closed = True
        try:
            self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        conn.sock.close()
        if reason:
            log.log(level, "%s %s", conn.name, reason)
        if conn.is_tracker:
            was_connected = not conn.connecting
            self._tracker_conn = None
            if was_connected and not self._stop_requested:
                self._stats.tracker_disconnects += 1
                self._tracker_unavailable("connection lost")
        elif conn in self._clients:
            self._clients.remove(conn)

    # ------------------------------------------------------------------------- messages
    def _handle_items(self, conn: _Conn, items: list) -> None:
        """Act on the messages of one read in order; poses are handled in runs (see below)."""
        poses: list[Message] = []
        for item in items:
            if isinstance(item, IgtlProtocolError):
                self._stats.protocol_errors += 1
                if not item.resync:
                    self._handle_poses(poses)
                    self._drop(conn, str(item))
                    return
                self._stats.messages_dropped += 1
                log.warning("%s: message dropped: %s", conn.name, item)
                continue
            if conn.is_tracker:
                self._backoff = RECONNECT_MIN_S  # a valid message: the outage is over
            if item.type == "TRANSFORM" and item.device == self.probe_device:
                self._stats.poses_received += 1
                poses.append(item)
            elif item.type == "STRING" and item.device == COMMAND_DEVICE:
                self._handle_poses(poses)
                poses = []
                self._command(conn, item.body.string)
            else:
                self._skip(conn, item)
        self._handle_poses(poses)

    def _handle_poses(self, poses: list[Message]) -> None:
        """Handle the newest ``max_poses_per_read`` of a run of poses; skip (coalesce) older."""
        keep = self.settings.max_poses_per_read
        self._stats.poses_coalesced += max(0, len(poses) - keep)
        for msg in poses[-keep:]:
            self._latest_pose = np.array(msg.body.matrix, dtype=np.float64)
            self._handle_pose(self._latest_pose, msg.header.timestamp)

    def _skip(self, conn: _Conn, item: Message) -> None:
        self._stats.messages_skipped += 1
        key = (item.type, item.device)
        if key not in conn.seen_skipped and len(conn.seen_skipped) < 64:
            conn.seen_skipped.add(key)
            known = "" if item.body is not None else " (unknown type)"
            log.info("%s: skipping %s %r%s", conn.name, item.type, item.device, known)

    def _command(self, conn: _Conn, text: str) -> None:
        self._stats.commands += 1
        command = text.strip()
        if command != CMD_SET_REST_POSE:
            reply = f"error: unknown command {command[:64]!r}; known: {CMD_SET_REST_POSE}"
        elif self._latest_pose is None:
            reply = f"{CMD_SET_REST_POSE}: failed: no probe pose received yet"
        else:
            try:
                self.tracker.set_rest_pose(self._latest_pose.copy())
                self._stats.rest_poses_set += 1
                self._provisional_rest = False
                reply = f"{CMD_SET_REST_POSE}: ok"
            except Exception as exc:
                reply = f"{CMD_SET_REST_POSE}: failed: {exc}"
        log.info("%s: command %r -> %s", conn.name, command[:64], reply)
        if not conn.is_tracker:
            self._send(conn, encode_string(COMMAND_REPLY_DEVICE, reply))

    def _handle_pose(self, T: np.ndarray, timestamp: float) -> None:
        """Auto rest pose, ``tracker.update``, reply to every client."""
        self._stats.poses_handled += 1
        self._auto_rest_pose(T)
        result = self._safe_update(T)
        if self._provisional_rest and result.status != NO_CONTACT:
            self._provisional_rest = False
            log.info("rest pose taken automatically at first contact (%s)", result.status)
        for payload in self._reply_parts(result, timestamp):
            for conn in list(self._clients):
                self._send(conn, payload)
        self._stats.replies_sent += len(self._clients)

    def _auto_rest_pose(self, T: np.ndarray) -> None:
        """Rest pose at first contact when none was set.

        The first finite pose is taken; while the tracker answers ``no_contact`` to that rest
        pose (the probe is not on the skin yet) it is re-taken at every pose.
        """
        try:
            if not np.all(np.isfinite(T)):
                return
            if self.tracker.has_rest_pose and not self._provisional_rest:
                return
            self.tracker.set_rest_pose(T.copy())
        except Exception as exc:
            log.warning("automatic rest pose not taken: %s", exc)
            return
        self._stats.rest_poses_set += 1
        self._provisional_rest = True

    def _safe_update(self, T: np.ndarray) -> TrackingResult:
        t0 = time.perf_counter()
        try:
            result = self.tracker.update(T.copy())
            if not isinstance(getattr(result, "status", None), str):
                raise TypeError(f"update returned {type(result).__name__}, not a "
                                "TrackingResult")
        except Exception as exc:
            self._stats.tracker_failures += 1
            log.error("tracker.update failed: %r", exc)
            result = error_result(TRACKER_ERROR, f"tracker failed: {exc}")
        self._stats.last_update_ms = (time.perf_counter() - t0) * 1e3
        return result

    def _reply_parts(self, result: TrackingResult, timestamp: float) -> Iterator[bytes]:
        """The reply in the order it is sent: the status STRING (when due) with the POINT, then,
        if reliable, the lesion TRANSFORMs, packed only after the POINT went out."""
        reliable = result.status in RELIABLE
        head = []
        if not reliable or not self._last_reliable:
            head.append(encode_status(result, timestamp))
        self._last_reliable = reliable
        try:
            head.append(encode_lesion_point(result, timestamp))
            yield b"".join(head)
            if reliable:
                yield encode_lesion_transforms(result, timestamp)
        except Exception as exc:
            self._stats.tracker_failures += 1
            log.error("cannot encode the tracking result: %r", exc)
            self._last_reliable = False
            yield encode_status(error_result(TRACKER_ERROR, f"unusable result: {exc}"),
                                timestamp)


# --------------------------------------------------------------------------- entry points
def install_signal_handlers(server: IgtlServer) -> Callable[[], None]:
    """SIGINT/SIGTERM stop ``server`` (main thread only); returns a function that restores."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, lambda signum, frame: server.stop())

    def restore() -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)

    return restore


def _watch(stop_event: threading.Event, server: IgtlServer) -> None:
    stop_event.wait()
    server.stop()


def run_service(tracker: TrackerLike, tracker_addr: str | Address | None,
                listen_addr: str | Address, probe_device: str = "ProbeToReference",
                stop_event: threading.Event | None = None, *,
                settings: IgtlSection | None = None, handle_signals: bool = True,
                on_started: Callable[[IgtlServer], None] | None = None) -> ServerStats:
    """Run the service until SIGINT/SIGTERM (main thread) or ``stop_event``; return the stats.

    ``stop_event`` is set on return. ``on_started(server)`` is called once listening (the
    bound address is ``server.address``).
    """
    server = IgtlServer(tracker, listen_addr, tracker_addr, probe_device, settings)
    server.start()
    restore = install_signal_handlers(server) if handle_signals else (lambda: None)
    if stop_event is not None:
        threading.Thread(target=_watch, args=(stop_event, server), daemon=True,
                         name="igtl-stop-watch").start()
    try:
        if on_started is not None:
            on_started(server)
        server.run()
    finally:
        restore()
        if stop_event is not None:
            stop_event.set()
    return server.stats()


def serve(case_dir: str | Path, tracker_addr: str | Address | None = None,
          listen_addr: str | Address | None = None, device: str | None = None) -> ServerStats:
    """``biopsynav serve``: load the case's tracker and run the service (None: case.toml)."""
    from ..config import load_config

    cfg = load_config(case_dir).igtl
    return run_service(service_tracker(case_dir), tracker_addr or cfg.tracker,
                       listen_addr or cfg.listen, device or cfg.probe_device, settings=cfg)


def service_tracker(case_dir: str | Path) -> TrackerLike:
    """The case's tracker as the service runs it: ``[igtl] inference_threads`` network
    threads."""
    from ..config import load_config

    try:
        from ..tracker import Tracker
    except ImportError:
        raise BiopsynavError("the tracker (biopsynav.tracker.Tracker) is not available in "
                             "this installation", str(case_dir)) from None
    return Tracker.load(case_dir, threads=load_config(case_dir).igtl.inference_threads)


__all__ = ["IgtlServer", "ServerStats", "TrackerLike", "install_signal_handlers", "run_service",
           "serve", "service_tracker", "to_address"]
