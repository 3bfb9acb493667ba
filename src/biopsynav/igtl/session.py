"""The OpenIGTLink session: decoded messages in, messages to send out; no sockets, no threads.

:class:`IgtlSession` holds everything the service decides: which TRANSFORM is the probe, the
rest-pose policy, the commands, the tracking status and when to send it, the per-client header
version, and the models. The transport (:mod:`.server`) only moves bytes: it hands every
decoded message to :meth:`IgtlSession.on_messages` and sends the batches it yields, each as soon
as it is yielded (the lesion POINT leaves before the TRANSFORMs and models are packed).

A batch is ``(peer, [Outgoing, ...])``: ``peer`` None means every listening client.

Policies (docs/igtl.md):

* probe pose: a TRANSFORM named ``probe_device``; with header version 2, metadata
  ``TransformStatus`` (PLUS) other than ``OK`` means the tracking system lost the probe: status
  ``probe_not_tracked``, no numbers. No pose for ``[igtl] probe_timeout_s`` does the same.
* rest pose: taken automatically at first contact when none is set; ``SetRestPose`` /
  ``ClearRestPose`` commands; a lost tracker-server connection clears it
  (``[igtl] rest_pose_on_reconnect = "clear"``).
* ``TrackingStatus`` is sent when the status changes, and again every
  ``[igtl] status_keepalive_s`` while it stays.
* replies in header version 1 until a client sends version 2 (``[igtl] reply_header_version``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from ..anatomy.display import decimate
from ..config import IgtlSection
from ..tracker.result import (
    NO_CONTACT,
    NO_REST_POSE,
    PROBE_NOT_TRACKED,
    RELIABLE,
    TRACKER_ERROR,
    TrackingResult,
)
from . import commands
from .protocol import Message, Outgoing
from .replies import (
    SKIN_DEVICE,
    bound_model_messages,
    bounds_messages,
    bounds_text,
    error_result,
    lesion_model_messages,
    mesh_message,
    point_message,
    rest_slots,
    status_message,
    transform_messages,
)

log = logging.getLogger("biopsynav.igtl")

TRANSFORM_STATUS_KEYS = ("TransformStatus", "Status")
VALID_TRANSFORM_STATUS = ("OK", "VALID")


@runtime_checkable
class TrackerLike(Protocol):
    """What the service needs from a tracker (``biopsynav.tracker.Tracker`` provides it;
    ``clear_rest_pose``, ``lesion_meshes`` and ``skin_mesh`` are used when present)."""

    @property
    def has_rest_pose(self) -> bool: ...

    def set_rest_pose(self, T: np.ndarray) -> None: ...

    def update(self, T: np.ndarray) -> TrackingResult: ...


@dataclass
class ServerStats:
    """Counters of one service run (a snapshot from ``IgtlServer.stats()``)."""

    poses_received: int = 0
    poses_handled: int = 0
    poses_coalesced: int = 0
    poses_not_tracked: int = 0
    replies_sent: int = 0
    status_messages: int = 0
    models_sent: int = 0
    rest_poses_set: int = 0
    rest_poses_cleared: int = 0
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
class Peer:
    """One connection as the session sees it: a listening client or the tracker server."""

    name: str
    is_tracker: bool = False
    version: int = 1  # header version of what is sent to it
    auto_version: bool = True
    skipped: set = field(default_factory=set)  # (type, device) already reported


Batch = tuple[Peer | None, list[Outgoing]]


def transform_status(msg: Message) -> str:
    """The tracking system's status of a TRANSFORM ("" when it has none or it is valid)."""
    metadata = getattr(msg.body, "metadata", None) or {}
    for key in TRANSFORM_STATUS_KEYS:
        value = str(metadata.get(key, "")).strip()
        if value and value.upper() not in VALID_TRANSFORM_STATUS:
            return f"{key}={value}"
    return ""


class IgtlSession:
    """The service's decisions for one run (see the module docstring)."""

    def __init__(self, tracker: TrackerLike, probe_device: str = "ProbeToReference",
                 settings: IgtlSection | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.tracker = tracker
        self.probe_device = probe_device
        self.settings = settings or IgtlSection()
        self.clock = clock
        self.stats = ServerStats()
        self.clients: list[Peer] = []
        self.tracker_connected = False
        self.slots = rest_slots(tracker)
        self._lesion_faces = {i: f for i, (_, f) in
                              (getattr(tracker, "lesion_meshes", None) or {}).items()}
        self._skin: tuple[np.ndarray, np.ndarray] | None = None
        self._latest_pose: np.ndarray | None = None
        self._last_pose_at = math.nan
        self._provisional_rest = False
        self._status = ""
        self._status_sent_at = -math.inf
        self._next_model = {"lesions": -math.inf, "skin": -math.inf}
        self._warned_devices: set[str] = set()

    def prepare(self) -> None:
        """Compute before the first pose what a reply would otherwise compute on the hot path:
        the decimated skin model, when one is sent (its first decimation, imports included,
        takes a few hundred milliseconds: at 100 Hz that many poses would queue), and the
        tracker's own skin embedding (``prepare_surface``, when it has one)."""
        if self._skin is None and self.settings.skin_model_rate_hz > 0 and \
                getattr(self.tracker, "skin_mesh", None) is not None:
            self._skin = decimate(*self.tracker.skin_mesh, self.settings.skin_model_triangles)
            prepare_surface = getattr(self.tracker, "prepare_surface", None)
            if prepare_surface is not None:
                prepare_surface()

    # --------------------------------------------------------------------------- peers
    def add_peer(self, name: str, is_tracker: bool = False) -> Peer:
        """A new connection; clients receive every broadcast batch."""
        fixed = self.settings.reply_header_version
        peer = Peer(name, is_tracker, 1 if fixed == "auto" else int(fixed), fixed == "auto")
        if not is_tracker:
            self.clients.append(peer)
        return peer

    def remove_peer(self, peer: Peer) -> None:
        if peer in self.clients:
            self.clients.remove(peer)

    def tracker_up(self) -> None:
        self.tracker_connected = True

    def tracker_down(self) -> Iterator[Batch]:
        """The tracker-server connection was lost: apply the rest-pose policy."""
        self.tracker_connected = False
        if self.settings.rest_pose_on_reconnect != "clear" or not self.tracker.has_rest_pose:
            return
        clear = getattr(self.tracker, "clear_rest_pose", None)
        if clear is None:
            return
        clear()
        self.stats.rest_poses_cleared += 1
        self._provisional_rest = False
        log.info("rest pose cleared: the tracker connection was lost; it is taken again at "
                 "the next contact")
        yield from self._status_batch(error_result(
            NO_REST_POSE, "tracker connection lost: rest pose cleared, taken again at the "
            "next contact"), None, force=True)

    # ------------------------------------------------------------------------ messages
    def on_messages(self, peer: Peer, messages: list[Message]) -> Iterator[Batch]:
        """Act on the messages of one read in order; runs of probe poses are coalesced to
        their newest ``max_poses_per_read``."""
        poses: list[Message] = []
        for msg in messages:
            self._note_version(peer, msg)
            if msg.type == "TRANSFORM" and msg.device == self.probe_device:
                self.stats.poses_received += 1
                poses.append(msg)
            elif commands.is_command(msg):
                yield from self._poses(poses)
                poses = []
                yield from self._command(peer, msg)
            else:
                self._skip(peer, msg)
        yield from self._poses(poses)

    def _note_version(self, peer: Peer, msg: Message) -> None:
        if peer.auto_version and msg.header.version > peer.version:
            peer.version = msg.header.version
            if not peer.is_tracker:
                log.info("%s speaks OpenIGTLink header version %d: replies in version %d, "
                         "with status metadata", peer.name, peer.version, peer.version)

    def _skip(self, peer: Peer, msg: Message) -> None:
        self.stats.messages_skipped += 1
        key = (msg.type, msg.device)
        if key in peer.skipped or len(peer.skipped) >= 64:
            return
        peer.skipped.add(key)
        if msg.type == "TRANSFORM" and msg.device not in self._warned_devices:
            self._warned_devices.add(msg.device)
            log.warning("%s sends TRANSFORM %r, ignored: the probe pose is expected as %r "
                        "(--device or [igtl] probe_device)", peer.name, msg.device,
                        self.probe_device)
            return
        known = "" if msg.body is not None else " (unknown type)"
        log.info("%s: skipping %s %r%s", peer.name, msg.type, msg.device, known)

    def _poses(self, poses: list[Message]) -> Iterator[Batch]:
        keep = self.settings.max_poses_per_read
        self.stats.poses_coalesced += max(0, len(poses) - keep)
        for msg in poses[-keep:]:
            yield from self.on_pose(np.array(msg.body.matrix, dtype=np.float64),
                                    msg.header.timestamp, transform_status(msg))

    # ---------------------------------------------------------------------------- poses
    def on_pose(self, T: np.ndarray, timestamp: float, not_tracked: str = "") -> Iterator[Batch]:
        """Track one probe pose and yield its reply; ``not_tracked`` (the tracking system's
        status, e.g. ``TransformStatus=INVALID``) answers ``probe_not_tracked`` instead."""
        now = self.clock()
        self._last_pose_at = now
        if not_tracked:
            self.stats.poses_not_tracked += 1
            yield from self._status_batch(error_result(
                PROBE_NOT_TRACKED, f"the tracking system reports {not_tracked}"), timestamp)
            return
        self.stats.poses_handled += 1
        self._latest_pose = T
        self._auto_rest_pose(T)
        models = self._models_due(now)
        result = self._safe_update(T, models)
        if self._provisional_rest and result.status != NO_CONTACT:
            self._provisional_rest = False
            log.info("rest pose taken automatically at first contact (%s)", result.status)
        yield from self._reply(result, models, timestamp, now)

    def _models_due(self, now: float) -> dict[str, bool]:
        """Which models this pose sends (``lesions``, ``skin``): none without a client, a
        lesion mesh or a skin, else each at its rate."""
        if not self.clients:
            return {}
        due = {}
        if self._lesion_faces and self._due("lesions", self.settings.lesion_model_rate_hz, now):
            due["lesion_surfaces"] = True
        if getattr(self.tracker, "skin_mesh", None) is not None and \
                self._due("skin", self.settings.skin_model_rate_hz, now):
            due["with_surface"] = True
        return due

    def _reply(self, result: TrackingResult, models: dict[str, bool], timestamp: float,
               now: float) -> Iterator[Batch]:
        """Status (when due) and POINT, then for reliable results the TRANSFORMs and the
        models that are due."""
        try:
            head = self._status_due(result, timestamp, now)
            rows = self.slots.rows(result)
            bounds = bounds_text(result)  # the POINT's metadata and the LesionBounds STRING
            if rows:
                head.append(point_message(rows, self.slots, result, timestamp, bounds))
            self.stats.replies_sent += len(self.clients)
            yield None, head
            if result.status in RELIABLE:
                yield None, (transform_messages(result, timestamp)
                             + bounds_messages(result, timestamp, bounds))
                yield from self._models(result, models, timestamp)
        except Exception as exc:
            self.stats.tracker_failures += 1
            log.error("cannot encode the tracking result: %r", exc)
            yield from self._status_batch(error_result(TRACKER_ERROR,
                                                       f"unusable result: {exc}"), timestamp)

    def _status_due(self, result: TrackingResult, timestamp: float, now: float
                    ) -> list[Outgoing]:
        """[the TrackingStatus STRING] when the status changed or the keep-alive is due."""
        if result.status == self._status and now - self._status_sent_at < \
                self.settings.status_keepalive_s:
            return []
        if result.status != self._status:
            log.info("tracking status: %s", status_message(result).msg.string)
        self._status, self._status_sent_at = result.status, now
        self.stats.status_messages += 1
        return [status_message(result, timestamp)]

    def _status_batch(self, result: TrackingResult, timestamp: float | None,
                      force: bool = False) -> Iterator[Batch]:
        if force:
            self._status = ""
        msgs = self._status_due(result, timestamp, self.clock())
        if msgs:
            yield None, msgs

    def _models(self, result: TrackingResult, models: dict[str, bool],
                timestamp: float) -> Iterator[Batch]:
        """The lesion (with their 95 % shells) and skin POLYDATA that were due (computed by the
        same update)."""
        if models.get("lesion_surfaces"):
            msgs = (lesion_model_messages(result, self._lesion_faces, timestamp)
                    + bound_model_messages(result, self._lesion_faces, timestamp))
            self.stats.models_sent += len(msgs)
            yield None, msgs
        if models.get("with_surface") and result.surface is not None:
            if self._skin is None:
                self._skin = decimate(*self.tracker.skin_mesh,
                                      self.settings.skin_model_triangles)
            weights, faces = self._skin
            self.stats.models_sent += 1
            yield None, [mesh_message(SKIN_DEVICE, weights @ result.surface, faces, result,
                                      timestamp)]

    def _due(self, what: str, rate_hz: float, now: float) -> bool:
        due = self._next_model[what]
        if rate_hz <= 0 or now < due:
            return False
        period = 1.0 / rate_hz
        self._next_model[what] = due + period if due + period > now else now + period
        return True

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
        self.stats.rest_poses_set += 1
        self._provisional_rest = True

    def _safe_update(self, T: np.ndarray, models: dict[str, bool]) -> TrackingResult:
        """``tracker.update`` (asked for the models that are due); a failure becomes a
        ``tracker_error`` result."""
        t0 = time.perf_counter()
        try:
            result = self.tracker.update(T.copy(), **models)
            if not isinstance(getattr(result, "status", None), str):
                raise TypeError(f"update returned {type(result).__name__}, not a "
                                "TrackingResult")
        except Exception as exc:
            self.stats.tracker_failures += 1
            log.error("tracker.update failed: %r", exc)
            result = error_result(TRACKER_ERROR, f"tracker failed: {exc}")
        self.stats.last_update_ms = (time.perf_counter() - t0) * 1e3
        return result

    # ---------------------------------------------------------------------------- timer
    def deadline(self) -> float:
        """Clock time of the next timed event (the probe timeout), ``inf`` for none."""
        if math.isnan(self._last_pose_at) or self._status == PROBE_NOT_TRACKED:
            return math.inf
        return self._last_pose_at + self.settings.probe_timeout_s

    def on_timer(self) -> Iterator[Batch]:
        """Timed events that are due: the probe timeout."""
        now = self.clock()
        if now < self.deadline():
            return
        silent = now - self._last_pose_at
        log.warning("no probe pose for %.1f s: probe not tracked", silent)
        yield from self._status_batch(error_result(
            PROBE_NOT_TRACKED, f"no probe pose for {silent:.1f} s"), None, force=True)

    # ------------------------------------------------------------------------- commands
    def _command(self, peer: Peer, msg: Message) -> Iterator[Batch]:
        self.stats.commands += 1
        command = commands.parse(msg)
        ok, text = commands.run(command.name, self)
        log.info("%s: command %s -> %s", peer.name, command.name[:64] or "(empty)",
                 "ok" if ok else f"failed: {text}")
        if not peer.is_tracker:
            yield peer, [commands.reply(command, ok, text)]

    def set_rest_pose(self) -> tuple[bool, str]:
        """``SetRestPose``: the latest probe pose becomes the rest pose."""
        if self._latest_pose is None:
            return False, "no probe pose received yet"
        try:
            self.tracker.set_rest_pose(self._latest_pose.copy())
        except Exception as exc:
            return False, str(exc)
        self.stats.rest_poses_set += 1
        self._provisional_rest = False
        log.info("rest pose set by command")
        return True, "rest pose set at the latest probe pose"

    def clear_rest_pose(self) -> tuple[bool, str]:
        """``ClearRestPose``: forget the rest pose; the next contact sets it again."""
        clear = getattr(self.tracker, "clear_rest_pose", None)
        if clear is None:
            return False, "this tracker cannot clear its rest pose"
        clear()
        self.stats.rest_poses_cleared += 1
        self._provisional_rest = False
        log.info("rest pose cleared by command")
        return True, "rest pose cleared; taken again at the next contact"

    def status_summary(self) -> tuple[bool, str]:
        """``GetStatus``: the tracking status, rest pose, tracker connection, counters."""
        rest = "set" if self.tracker.has_rest_pose else "not set"
        link = "connected" if self.tracker_connected else "not connected"
        return True, (f"status {self._status or 'none yet'}; rest pose {rest}; tracker server "
                      f"{link}; {self.stats.poses_handled} poses tracked; "
                      f"{len(self.clients)} clients")
