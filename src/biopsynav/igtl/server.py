"""The OpenIGTLink transport: sockets in one ``selectors`` loop, bytes in and out.

Topology (see ``docs/igtl.md``)::

    PlusServer :18944  --TRANSFORM ProbeToReference-->  biopsynav (client connection)
    3D Slicer OpenIGTLinkIF (client) <--POINT, TRANSFORM, POLYDATA, STRING--  biopsynav :18945

One thread, non-blocking sockets with TCP_NODELAY, no polling sleeps: the loop blocks in
``select`` until a socket is ready, a timed event is due (tracker reconnection, a stalled
message, the session's probe timeout), or :meth:`IgtlServer.stop` writes to a wake-up socket.
What to answer is decided by the session (:class:`~.session.IgtlSession`, no sockets): the
transport hands it each read's decoded messages and sends the batches it yields, each as soon as
it is yielded, packed once per header version in use.

Faults cost only the connection (or message) they come from: malformed headers and oversized
bodies drop the connection; a wrong CRC or an undecodable body drops the message; a client whose
unsent replies exceed ``client_backlog_bytes`` (it does not read) is dropped.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import selectors
import socket
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

from ..config import IgtlSection, parse_address
from ..errors import InputError
from .protocol import IgtlProtocolError, Message, MessageReader
from .session import Batch, IgtlSession, Peer, ServerStats, TrackerLike

log = logging.getLogger(__name__)

Address = tuple[str, int]
RECV_BYTES = 1 << 16
ACCEPT_BURST = 16
RECONNECT_MIN_S = 0.05
CONNECT_TIMEOUT_S = 2.0
_CONNECT_PENDING = (errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY, errno.EINTR)


@dataclass(eq=False)
class _Conn:
    """One socket of the loop: a listening client or the tracker-server connection."""

    sock: socket.socket
    name: str
    is_tracker: bool
    reader: MessageReader
    peer: Peer
    out: bytearray = field(default_factory=bytearray)
    connecting: bool = False
    closed: bool = False
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


def connected_to_itself(sock: socket.socket) -> bool:
    """True when ``sock`` reached itself: a connect to a local port that nobody listens on can
    be given that very port as its source port (TCP simultaneous open). Such a connection is
    no tracker server; it is treated as refused."""
    try:
        return sock.getsockname() == sock.getpeername()
    except OSError:  # not connected
        return False


class IgtlServer:
    """The service's transport. No side effects until :meth:`start`; :meth:`run` loops until
    :meth:`stop`. One use: once :meth:`run` has returned, make a new server to serve again.

    ``tracker_addr`` None: no tracker-server connection (poses only from listening clients).
    """

    def __init__(self, tracker: TrackerLike, listen_addr: str | Address = "127.0.0.1:18945",
                 tracker_addr: str | Address | None = "127.0.0.1:18944",
                 probe_device: str = "ProbeToReference",
                 settings: IgtlSection | None = None) -> None:
        self.settings = settings or IgtlSection()
        self.session = IgtlSession(tracker, probe_device, self.settings)
        self.listen_addr = to_address(listen_addr, "--listen")
        self.tracker_addr = to_address(tracker_addr, "--tracker")
        self._stats = self.session.stats
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
        self._stop_requested = False
        self._state_lock = threading.RLock()  # held while the loop changes state; stats() too
        self.address: Address | None = None
        self.started_at = math.nan

    @property
    def tracker(self) -> TrackerLike:
        return self.session.tracker

    @property
    def probe_device(self) -> str:
        return self.session.probe_device

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
        self.started_at = time.monotonic()
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
        self._deliver(self.session.on_timer())

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
        log.debug("OpenIGTLink service stopped: %s", self.stats())

    # ------------------------------------------------------------------------------ the loop
    def _timeout(self) -> float | None:
        """Seconds until the next timed event (reconnect, connect timeout, a stalled partial
        message), None for none."""
        now = time.monotonic()
        deadline = min([*self._stall_deadlines(), self.session.deadline()])
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
            conn = _Conn(sock, name, False, MessageReader(self.settings.max_body_bytes),
                         self.session.add_peer(name))
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
        if err == 0 and connected_to_itself(sock):
            err = errno.ECONNREFUSED
        conn = _Conn(sock, name, True, MessageReader(self.settings.max_body_bytes),
                     self.session.add_peer(name, is_tracker=True))
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
        if not err and connected_to_itself(conn.sock):
            err = errno.ECONNREFUSED
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
        self.session.tracker_up()
        again = " again" if self._stats.tracker_connects > 1 else ""
        log.info("connected%s to %s; waiting for TRANSFORM %r", again, self._tracker_conn.name,
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
                self._deliver(self.session.tracker_down())
        elif conn in self._clients:
            self._clients.remove(conn)
            self.session.remove_peer(conn.peer)

    # ------------------------------------------------------------------------- messages
    def _handle_items(self, conn: _Conn, items: list) -> None:
        """Hand the messages of one read to the session in order; protocol errors cost the
        message (resyncable) or the connection."""
        run: list[Message] = []
        for item in items:
            if not isinstance(item, IgtlProtocolError):
                run.append(item)
                continue
            self._stats.protocol_errors += 1
            self._deliver(self.session.on_messages(conn.peer, run))
            run = []
            if not item.resync:
                self._drop(conn, str(item))
                return
            self._stats.messages_dropped += 1
            log.warning("%s: message dropped: %s", conn.name, item)
        if run and conn.is_tracker:
            self._backoff = RECONNECT_MIN_S  # a valid message: the outage is over
        self._deliver(self.session.on_messages(conn.peer, run))

    def _deliver(self, batches: Iterable[Batch]) -> None:
        """Send each batch as soon as the session yields it: to one peer, or (None) to every
        client, packed once per header version in use."""
        for peer, msgs in batches:
            if not msgs:
                continue
            targets = self._clients if peer is None else [c for c in self._connections()
                                                          if c.peer is peer]
            packed: dict[int, bytes] = {}
            for conn in list(targets):
                version = conn.peer.version
                if version not in packed:
                    packed[version] = b"".join(m.packed(version) for m in msgs)
                self._send(conn, packed[version])


__all__ = ["IgtlServer", "ServerStats", "TrackerLike", "to_address"]
