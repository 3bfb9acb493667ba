"""``biopsynav serve``: the case's tracker behind the OpenIGTLink transport, signals, logging.

Logging goes to stderr through the ``biopsynav.igtl`` loggers: at the default level (INFO) where
the service listens, the tracker connection (connected, lost, reconnected), device names it
ignores (a warning naming the expected one, once each), rest pose set or cleared, status
changes, clients that connect and drop, and a summary of the counters when it stops.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ..config import IgtlSection
from ..errors import BiopsynavError
from .server import Address, IgtlServer
from .session import ServerStats, TrackerLike

if TYPE_CHECKING:
    from ..case import Case

log = logging.getLogger("biopsynav.igtl")

LOG_FORMAT = "%(asctime)s biopsynav serve: %(levelname)s: %(message)s"


def configure_logging(level: int = logging.INFO) -> None:
    """Send the ``biopsynav`` loggers to stderr at ``level`` (once; later calls set the level)."""
    root = logging.getLogger("biopsynav")
    root.setLevel(level)
    if not any(getattr(h, "_biopsynav", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(LOG_FORMAT, "%H:%M:%S"))
        handler._biopsynav = True
        root.addHandler(handler)


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
    server.session.prepare()
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
    stats = server.stats()
    log.info("%s", summary(stats, time.monotonic() - server.started_at))
    return stats


def summary(stats: ServerStats, seconds: float) -> str:
    """The counters of a run in words."""
    return (f"stopped after {seconds:.1f} s: {stats.poses_received} probe poses received, "
            f"{stats.poses_handled} tracked, {stats.poses_coalesced} skipped behind newer ones, "
            f"{stats.poses_not_tracked} reported not tracked; {stats.clients_total} clients "
            f"served ({stats.clients_dropped} dropped, {stats.clients_evicted} evicted); "
            f"tracker server connected {stats.tracker_connects} times, lost "
            f"{stats.tracker_disconnects}; {stats.rest_poses_set} rest poses set, "
            f"{stats.rest_poses_cleared} cleared; {stats.commands} commands; "
            f"{stats.protocol_errors} protocol errors ({stats.messages_dropped} messages "
            f"dropped); {stats.tracker_failures} tracker failures")


#: What ``serve`` says of a case without lesions (a breast modelled before any was marked).
NO_LESIONS = ("the case has no lesions: clients receive the deformed skin (POLYDATA "
              "'BreastSkin') and the tracking status, no lesion positions")


def serve(case: Case | str | Path, tracker_addr: str | Address | None = None,
          listen_addr: str | Address | None = None, device: str | None = None) -> ServerStats:
    """``biopsynav serve``: load the tracker of ``case`` (loaded, or its folder) and run the
    service (addresses and device None: its case.toml)."""
    from ..case import as_case
    from .server import to_address

    case = as_case(case)
    cfg = case.cfg.igtl
    # the addresses are checked before the tracker loads (seconds)
    tracker_addr = to_address(tracker_addr or cfg.tracker, "--tracker")
    listen_addr = to_address(listen_addr or cfg.listen, "--listen")
    log.info("loading the tracker of %s", case.dir)
    if not case.anatomy.lesions:
        log.info(NO_LESIONS)
    return run_service(service_tracker(case, cfg), tracker_addr, listen_addr,
                       device or cfg.probe_device, settings=cfg)


def service_tracker(case: Case | str | Path, cfg: IgtlSection | None = None) -> TrackerLike:
    """The tracker of ``case`` (loaded, or its folder) as the service runs it:
    ``[igtl] inference_threads`` threads (of ``cfg``, else of the case's case.toml)."""
    from ..case import as_case

    try:
        from ..tracker import Tracker
    except ImportError:
        raise BiopsynavError("the tracker (biopsynav.tracker.Tracker) is not available in "
                             "this installation", str(case)) from None
    case = as_case(case)
    cfg = case.cfg.igtl if cfg is None else cfg
    threads = cfg.inference_threads and min(cfg.inference_threads, os.cpu_count() or 1)
    tracker = Tracker.load(case, threads=threads)
    log.info("95 %% bounds: %s", tracker.bound_basis)
    return tracker


__all__ = ["configure_logging", "install_signal_handlers", "run_service", "serve",
           "service_tracker", "summary"]
