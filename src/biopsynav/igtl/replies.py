"""Encode a :class:`~biopsynav.tracker.result.TrackingResult` as the OpenIGTLink reply to a pose.

One reply, sent in two buffers: the status STRING (when due) and the POINT go out as soon as
they are packed, the TRANSFORMs after them (the POINT is what a client waits for first):

* ``POINT`` ``Lesions``: one point per lesion with a finite centre, named ``Lesion<id>``; the
  point's group holds the lesion status, its colour is green when reliable, red otherwise;
* ``TRANSFORM`` ``Lesion<id>ToReference`` per such lesion: identity rotation, translation =
  predicted centre (mm, the frame of the probe pose); sent only for reliable results, so that
  a model attached to it in Slicer never moves to an unreliable position;
* ``STRING`` ``TrackingStatus`` (``"<status>: <reason>"``) when the result is not reliable, and
  once (``"ok"``/``"rest"``) on the first reliable result after an unreliable one.

Every message carries the timestamp of the probe pose it answers.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..tracker.result import RELIABLE, TrackingResult
from .protocol import DEVICE_NAME_BYTES, encode_points, encode_string, encode_transform

log = logging.getLogger(__name__)

POINT_DEVICE = "Lesions"
STATUS_DEVICE = "TrackingStatus"
COMMAND_DEVICE = "biopsynavCommand"
COMMAND_REPLY_DEVICE = "biopsynavReply"
CMD_SET_REST_POSE = "SetRestPose"

RELIABLE_RGBA = [0, 200, 0, 255]
UNRELIABLE_RGBA = [230, 0, 0, 255]
POINT_DIAMETER_MM = 5.0


def lesion_point_name(lesion_id: int) -> str:
    """Name of a lesion in the POINT message."""
    return f"Lesion{lesion_id}"


def lesion_transform_name(lesion_id: int) -> str:
    """Device name of a lesion's TRANSFORM (at most 20 bytes: ids up to 999)."""
    return f"Lesion{lesion_id}ToReference"


def _finite_lesions(result: TrackingResult) -> list[tuple[int, np.ndarray, str]]:
    """(id, centre, status) of the lesions whose centre is three finite numbers."""
    out = []
    for lesion in result.lesions or []:
        try:
            center = np.asarray(lesion.center, dtype=np.float64).reshape(3)
            lesion_id = int(lesion.id)
        except (TypeError, ValueError):
            continue
        if np.all(np.isfinite(center)):
            out.append((lesion_id, center, str(getattr(lesion, "status", ""))))
    return out


def encode_lesions(result: TrackingResult, timestamp: float | None = None,
                   transforms: bool = True) -> bytes:
    """The POINT message and (``transforms``) the per-lesion TRANSFORMs; b"" when no lesion."""
    head = encode_lesion_point(result, timestamp)
    return head + encode_lesion_transforms(result, timestamp) if head and transforms else head


def encode_lesion_point(result: TrackingResult, timestamp: float | None = None) -> bytes:
    """The POINT message of the lesions with a finite centre; b"" when there is none."""
    lesions = _finite_lesions(result)
    if not lesions:
        return b""
    reliable = result.status in RELIABLE
    rgba = [RELIABLE_RGBA if reliable and status in RELIABLE else UNRELIABLE_RGBA
            for _, _, status in lesions]
    return encode_points(POINT_DEVICE, np.array([c for _, c, _ in lesions]),
                         [lesion_point_name(i) for i, _, _ in lesions], rgba=rgba,
                         diameters=[POINT_DIAMETER_MM] * len(lesions),
                         groups=[s[:32] for _, _, s in lesions], timestamp=timestamp)


def encode_lesion_transforms(result: TrackingResult, timestamp: float | None = None) -> bytes:
    """One TRANSFORM ``Lesion<id>ToReference`` per lesion with a finite centre (identity
    rotation, translation = centre in mm); ids too long for a device name are skipped."""
    parts = []
    for lesion_id, center, _ in _finite_lesions(result):
        name = lesion_transform_name(lesion_id)
        if len(name) > DEVICE_NAME_BYTES:
            log.warning("lesion id %d is too long for a TRANSFORM device name; point only",
                        lesion_id)
            continue
        matrix = np.eye(4)
        matrix[:3, 3] = center
        parts.append(encode_transform(name, matrix, timestamp))
    return b"".join(parts)


def status_text(result: TrackingResult) -> str:
    """``"<status>: <reason>"`` (or the bare status without reason)."""
    reason = str(result.reason or "").strip()
    return f"{result.status}: {reason}" if reason else str(result.status)


def encode_status(result: TrackingResult, timestamp: float | None = None) -> bytes:
    """The ``TrackingStatus`` STRING message."""
    return encode_string(STATUS_DEVICE, status_text(result), timestamp)


def error_result(status: str, reason: str) -> TrackingResult:
    """A result with no lesions, for a tracker that failed."""
    return TrackingResult(lesions=[], status=status, reason=reason, latency_ms=math.nan)
