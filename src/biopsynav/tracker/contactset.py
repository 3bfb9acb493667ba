"""The network engine's contact sets: the skin under the face at the rest pose, and that set
grown by the skin the face reaches during a push (``[tracker] contact_follows_pose``).

A :class:`NetContactSet` holds what a prediction needs for one set of contact points, built
once: their trilinear embedding, the network input operator, the contact projection and the
point operators of the lesions and of the skin the face may reach. The rest pose's set is
built at :meth:`~biopsynav.tracker.core.Tracker.set_rest_pose`; a grown set the first time a
push reaches its skin, then looked up.

Skin the face may reach (:func:`reach_candidates`) is chosen at the rest pose: skin vertices
off the chest wall, facing the probe, within :data:`REACH_MM` of a rest contact point, not in
the rest contact and not in a grid cell that shares a node with it (a point held there could
only contradict the rest contact, as in the FE engine). During a push, a candidate that the
prediction puts under the footprint and more than ``PENETRATION_TOL_MM`` behind the face plane
(:func:`behind_face`) is held on the plane: its prescribed displacement is the predicted one
moved along the beam onto the plane (:func:`onto_face`), and the prediction is repeated with
it in the contact set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..contact.lesions import PointOperator
from ..contact.projection import ContactProjection
from ..footprint import Footprint
from ..grid.embedding import Embedding
from ..probe import ContactInputOperator

#: Skin farther than this (mm, at rest) from every rest contact point is never added to the
#: contact set: the deepest training push is 35 mm, and skin beside the face is not held.
REACH_MM = 25.0
#: Grown contact sets kept per rest pose (a push back and forth meets the same ones again).
MAX_GROWN_SETS = 64


@dataclass
class NetContactSet:
    """What the network engine precomputes for one contact set.

    Attributes:
        touched: (t,) sorted skin vertex indices held beyond the rest contact (empty for the
            rest pose's set).
        embedding: the contact points (rest contact first, then ``touched``) in the case grid.
        input_op: the network input as a linear map of their displacements.
        projection: the contact projection (None when predictions are not projected).
        centre_op: the lesion centres' :class:`~biopsynav.contact.lesions.PointOperator`
            (None without a physics baseline or lesions).
        lesion_op: the same at the centres and lesion mesh vertices (built on first use for
            a grown set).
        reach_op: the candidate skin vertices' operator (None when the set does not grow, or
            without a physics baseline).
    """

    touched: np.ndarray
    embedding: Embedding
    input_op: ContactInputOperator
    projection: ContactProjection | None
    centre_op: PointOperator | None
    lesion_op: PointOperator | None
    reach_op: PointOperator | None


def reach_candidates(vertices: np.ndarray, normals: np.ndarray, pushable: np.ndarray,
                     beam: np.ndarray, rest_contact: np.ndarray, pinned: np.ndarray,
                     reach_mm: float = REACH_MM) -> np.ndarray:
    """Indices (m,) of skin vertices (``vertices`` (nv, 3) mm, outward ``normals`` (nv, 3))
    that a push from the rest pose may add to the contact set: ``pushable``, facing the
    probe (normal against ``beam`` (3,)), within ``reach_mm`` of a rest contact vertex
    (``rest_contact`` (n,) indices) and neither in it nor ``pinned`` ((nv,) bool: in a cell
    sharing a node with it)."""
    if not len(rest_contact):
        return np.zeros(0, dtype=np.int64)
    dist, _ = cKDTree(vertices[rest_contact]).query(vertices, distance_upper_bound=reach_mm)
    ok = np.isfinite(dist) & pushable & (normals @ beam < 0.0) & ~pinned
    ok[rest_contact] = False
    return np.flatnonzero(ok)


def behind_face(moved: np.ndarray, pose: np.ndarray, footprint: Footprint,
                tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Which points ``moved`` (m, 3) mm lie under ``footprint`` and more than ``tol_mm``
    behind the face plane at ``pose`` (4, 4); and their depth along the beam (m,) mm
    (negative: behind the face)."""
    local = (moved - pose[:3, 3]) @ pose[:3, :3]
    return (local[:, 2] < -tol_mm) & footprint.inside(local[:, :2]), local[:, 2]


def onto_face(displacement: np.ndarray, depth: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """Displacements (m, 3) mm moved along ``beam`` (3,) by ``-depth`` (m,) mm: onto the
    face plane, the motion across it kept (the skin slides on the face)."""
    return displacement - depth[:, None] * beam[None, :]


def pinned_by_contact(cell_nodes: np.ndarray, contact_nodes: np.ndarray,
                      n_nodes: int) -> np.ndarray:
    """(nv,) bool: vertices whose cell (``cell_nodes`` (nv, 8) flat node indices) shares a
    node with the rest contact's cells (``contact_nodes`` (n, 8))."""
    held = np.zeros(n_nodes, dtype=bool)
    held[np.asarray(contact_nodes).ravel()] = True
    return held[cell_nodes].any(axis=1)
