"""The OpenIGTLink messages that answer a probe pose (docs/igtl.md: what Slicer makes of them).

* ``POINT`` ``Lesions``: every lesion in a stable slot, always in the same order, named
  ``Lesion<id>``; its group holds the lesion status, its colour is green when reliable and red
  otherwise. An unreliable lesion keeps its slot at its last reliable position (its rest
  position before any), so a client that matches points by index never mixes lesions up.
* ``TRANSFORM`` ``Lesion<id>ToReference`` per lesion (identity rotation, translation = predicted
  centre, mm), for reliable results only: a model under it stays at its last reliable place.
* ``POLYDATA`` ``Lesion<id>``: the lesion's surface mesh where the prediction moved it;
  ``Lesion<id>Bound``: that surface pushed out by the lesion's 95 % bound, the shell the lesion
  lies within at 95 % (with the lesion surfaces, where the bound is known); and
  ``BreastSkin``: the deformed skin, decimated (each at its rate, reliable results only).
* ``STRING`` ``TrackingStatus``: ``"<status>: <reason>"``.

With header version 2 every message carries the metadata ``TrackingStatus`` (the status), the
lesion TRANSFORMs ``TransformStatus`` (``OK``, as PLUS writes it) and the POINT the reason.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..tracker.result import RELIABLE, TrackingResult
from .messages import TriangleMesh
from .protocol import (
    DEVICE_NAME_BYTES,
    Outgoing,
    points_message,
    string_message,
    transform_message,
)

log = logging.getLogger(__name__)

POINT_DEVICE = "Lesions"
STATUS_DEVICE = "TrackingStatus"
SKIN_DEVICE = "BreastSkin"
BOUNDS_DEVICE = "LesionBounds"
RELIABLE_RGBA = [0, 200, 0, 255]
UNRELIABLE_RGBA = [230, 0, 0, 255]
DEFAULT_DIAMETER_MM = 5.0


def lesion_point_name(lesion_id: int) -> str:
    """Name of a lesion in the POINT message, and device name of its POLYDATA model."""
    return f"Lesion{lesion_id}"


def lesion_transform_name(lesion_id: int) -> str:
    """Device name of a lesion's TRANSFORM (at most 20 bytes: ids up to 999)."""
    return f"Lesion{lesion_id}ToReference"


def bound_model_name(lesion_id: int) -> str:
    """Device name of a lesion's 95 % shell (POLYDATA, :func:`bound_model_messages`)."""
    return f"Lesion{lesion_id}Bound"


def _finite_centre(lesion) -> tuple[int, np.ndarray] | None:
    """(id, centre) of a lesion whose centre is three finite numbers, else None."""
    try:
        center = np.asarray(lesion.center, dtype=np.float64).reshape(3)
        lesion_id = int(lesion.id)
    except (TypeError, ValueError):
        return None
    return (lesion_id, center) if np.all(np.isfinite(center)) else None


class LesionSlots:
    """The stable POINT slots: lesion ids in a fixed order with their last reliable centres.

    Slots are the lesions of the tracker's ``lesion_meshes`` (or of the first result that names
    lesions); a lesion first seen later gets a new slot at the end.
    """

    def __init__(self, diameters: dict[int, float] | None = None) -> None:
        self.ids: list[int] = []
        self.last: dict[int, np.ndarray] = {}
        self.diameters = diameters or {}

    def add(self, lesion_id: int, center: np.ndarray) -> None:
        """A slot for ``lesion_id`` with ``center`` as its last known position."""
        if lesion_id not in self.last:
            self.ids.append(lesion_id)
        self.last[lesion_id] = np.asarray(center, dtype=np.float64).reshape(3)

    def rows(self, result: TrackingResult) -> list[tuple[int, np.ndarray, str]]:
        """(id, centre, status) per slot for ``result``: reliable lesions at their prediction
        (remembered), the others at their last reliable centre with their status."""
        reliable = result.status in RELIABLE
        status_of = {}
        for lesion in result.lesions or []:
            status = str(getattr(lesion, "status", "") or result.status)
            found = _finite_centre(lesion)
            if found is None:
                if isinstance(getattr(lesion, "id", None), int):
                    status_of[lesion.id] = status
                continue
            lesion_id, centre = found
            status_of[lesion_id] = status
            if lesion_id not in self.last or (reliable and status in RELIABLE):
                self.add(lesion_id, centre)
        return [(i, self.last[i], status_of.get(i, result.status) if reliable
                 else result.status) for i in self.ids]


def point_message(rows: list[tuple[int, np.ndarray, str]], slots: LesionSlots,
                  result: TrackingResult, timestamp: float | None = None,
                  bounds: str | None = None) -> Outgoing:
    """The ``Lesions`` POINT of ``rows`` from :meth:`LesionSlots.rows`; ``bounds``:
    :func:`bounds_text` of ``result`` when the caller has it already."""
    rgba = [RELIABLE_RGBA if status in RELIABLE else UNRELIABLE_RGBA for _, _, status in rows]
    msg = points_message(POINT_DEVICE, np.array([c for _, c, _ in rows]),
                         [lesion_point_name(i) for i, _, _ in rows], rgba=rgba,
                         diameters=[slots.diameters.get(i, DEFAULT_DIAMETER_MM)
                                    for i, _, _ in rows],
                         groups=[s[:32] for _, _, s in rows], timestamp=timestamp)
    meta = {"TrackingStatus": result.status, "Reason": result.reason[:200]}
    bounds = bounds_text(result) if bounds is None else bounds
    if bounds:
        meta["Bound95"] = bounds[:200]
    return Outgoing(msg, meta)


def transform_messages(result: TrackingResult, timestamp: float | None = None
                       ) -> list[Outgoing]:
    """One TRANSFORM ``Lesion<id>ToReference`` per lesion with a finite centre (identity
    rotation, translation = centre in mm); ids too long for a device name are skipped."""
    out = []
    for lesion in result.lesions or []:
        found = _finite_centre(lesion)
        if found is None:
            continue
        name = lesion_transform_name(found[0])
        if len(name) > DEVICE_NAME_BYTES:
            log.warning("lesion id %d is too long for a TRANSFORM device name; point only",
                        found[0])
            continue
        matrix = np.eye(4)
        matrix[:3, 3] = found[1]
        out.append(Outgoing(transform_message(name, matrix, timestamp),
                            {"TransformStatus": "OK", "TrackingStatus": result.status}))
    return out


def _moved_surfaces(result: TrackingResult, faces: dict[int, np.ndarray]):
    """(lesion, moved surface (k, 3) mm, faces (m, 3)) of each lesion of ``result`` with a
    finite moved surface and known faces."""
    for lesion in result.lesions or []:
        surface, tri = getattr(lesion, "surface", None), faces.get(getattr(lesion, "id", None))
        if surface is not None and tri is not None and np.all(np.isfinite(surface)):
            yield lesion, surface, tri


def lesion_model_messages(result: TrackingResult, faces: dict[int, np.ndarray],
                          timestamp: float | None = None) -> list[Outgoing]:
    """One POLYDATA ``Lesion<id>`` per lesion with a finite moved surface and known faces."""
    return [mesh_message(lesion_point_name(lesion.id), surface, tri, result, timestamp)
            for lesion, surface, tri in _moved_surfaces(result, faces)]


def bound_model_messages(result: TrackingResult, faces: dict[int, np.ndarray],
                         timestamp: float | None = None) -> list[Outgoing]:
    """One POLYDATA ``Lesion<id>Bound`` per lesion with a finite moved surface, known faces and
    a finite 95 % bound (``bound_mm``): the surface pushed out by the bound
    (:func:`offset_surface`). The bound is the lesion centre's, so a lesion moved anywhere
    within it stays inside the shell (for a convex lesion, to the offset's facets); ids too
    long for a device name are skipped."""
    out = []
    for lesion, surface, tri in _moved_surfaces(result, faces):
        bound = float(getattr(lesion, "bound_mm", math.nan))
        name = bound_model_name(lesion.id)
        if math.isfinite(bound) and len(name) <= DEVICE_NAME_BYTES:
            out.append(mesh_message(name, offset_surface(surface, tri, bound), tri, result,
                                    timestamp))
    return out


def offset_surface(vertices: np.ndarray, faces: np.ndarray, distance_mm: float) -> np.ndarray:
    """(k, 3) mm: the closed triangle surface ``vertices`` (k, 3) mm, ``faces`` (m, 3), each
    vertex moved outwards by ``distance_mm`` along its area-weighted normal (outwards: the side
    the faces' winding encloses, whichever way they wind)."""
    v, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
    tri = v[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length: 2 x area
    corners, spread = faces.ravel(), np.repeat(face_normals, 3, axis=0)
    normals = np.stack([np.bincount(corners, spread[:, k], minlength=len(v))
                        for k in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    enclosed = float(np.einsum("ij,ij->", tri[:, 0], face_normals))  # 6 x signed volume
    return v + (distance_mm if enclosed >= 0 else -distance_mm) * normals


def mesh_message(device: str, vertices: np.ndarray, faces: np.ndarray, result: TrackingResult,
                 timestamp: float | None = None) -> Outgoing:
    """A POLYDATA triangle mesh (vertices (k, 3) mm, faces (m, 3))."""
    return Outgoing(TriangleMesh(vertices, faces, timestamp=timestamp, device_name=device),
                    {"TrackingStatus": result.status})


def status_text(result: TrackingResult) -> str:
    """``"<status>: <reason>"`` (or the bare status without reason)."""
    reason = str(result.reason or "").strip()
    return f"{result.status}: {reason}" if reason else str(result.status)


def bounds_text(result: TrackingResult) -> str:
    """``"Lesion1 0.4 mm, Lesion2 1.1 mm"``: each lesion's 95 % bound (the distance from its
    point within which the true position lies at 95 %) for a reliable result, '' otherwise."""
    if result.status not in RELIABLE:
        return ""
    parts = [f"{lesion_point_name(les.id)} {les.bound_mm:.1f} mm" for les in result.lesions
             if math.isfinite(getattr(les, "bound_mm", math.nan))]
    return ", ".join(parts)


def bounds_messages(result: TrackingResult, timestamp: float | None = None,
                    text: str | None = None) -> list[Outgoing]:
    """[the ``LesionBounds`` STRING] of a reliable result with bounds ([] otherwise): a text
    node in Slicer beside ``TrackingStatus``, updated with every answer. ``text``:
    :func:`bounds_text` of ``result`` when the caller has it already."""
    text = bounds_text(result) if text is None else text
    if not text:
        return []
    return [Outgoing(string_message(BOUNDS_DEVICE, "95 % within: " + text, timestamp),
                     {"TrackingStatus": result.status})]



def status_message(result: TrackingResult, timestamp: float | None = None) -> Outgoing:
    """The ``TrackingStatus`` STRING."""
    return Outgoing(string_message(STATUS_DEVICE, status_text(result), timestamp),
                    {"TrackingStatus": result.status})


def error_result(status: str, reason: str) -> TrackingResult:
    """A result with no lesions, for a tracker that failed (or a probe not tracked)."""
    return TrackingResult(lesions=[], status=status, reason=reason, latency_ms=math.nan)


def rest_slots(tracker) -> LesionSlots:
    """Slots of the tracker's lesions at their rest centres (the mesh vertex mean), with their
    diameters, when it has ``lesion_meshes``; empty slots otherwise."""
    meshes = getattr(tracker, "lesion_meshes", None) or {}
    slots = LesionSlots()
    for lesion_id, (vertices, _) in meshes.items():
        centre = vertices.mean(axis=0)
        slots.add(int(lesion_id), centre)
        slots.diameters[int(lesion_id)] = float(2 * np.linalg.norm(vertices - centre,
                                                                   axis=1).mean())
    return slots


__all__ = ["LesionSlots", "bound_model_messages", "bound_model_name", "error_result",
           "lesion_model_messages", "mesh_message", "offset_surface",
           "point_message", "rest_slots", "status_message", "status_text", "transform_messages",
           "bounds_messages", "bounds_text", "BOUNDS_DEVICE"]
