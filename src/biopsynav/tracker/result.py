"""What a tracker returns for one probe pose (mm, anatomy frame)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

OK = "ok"
REST = "rest"  # rest pose taken; lesions at their pre-operative positions
NO_CONTACT = "no_contact"
OUT_OF_ENVELOPE = "out_of_envelope"
INVALID_POSE = "invalid_pose"
NO_REST_POSE = "no_rest_pose"
SOLVER_FAILED = "solver_failed"  # the FE engine's solve did not converge; not a pose problem
TRACKER_ERROR = "tracker_error"  # the prediction itself failed (a bug or a broken model)
PROBE_NOT_TRACKED = "probe_not_tracked"  # the tracking system lost the probe (or went silent)
RELIABLE = (OK, REST)


@dataclass
class LesionResult:
    """One lesion: ``center`` (3,) predicted position, ``displacement`` (3,) from rest, mm;
    ``bound_mm`` the distance from ``center`` within which the true position lies at 95 %
    (:mod:`biopsynav.tracker.bound`; NaN when the status is not reliable, 0 at rest);
    ``surface`` (k, 3) its surface mesh's vertices where they moved to (the tracker's
    ``lesion_meshes`` give the faces), None when not computed."""

    id: int
    center: np.ndarray
    displacement: np.ndarray
    status: str = OK
    surface: np.ndarray | None = field(default=None, repr=False)
    bound_mm: float = math.nan


@dataclass
class TrackingResult:
    """All lesions for one pose; ``status`` is OK only when the numbers can be trusted.
    ``surface`` (n_vertices, 3) mm: the moved skin; ``grid_displacement`` (n_nodes, 3) mm:
    the case grid's displacement; each None unless asked for (:meth:`Tracker.update`) and
    the pose was solved or predicted (not at rest, not refused)."""

    lesions: list[LesionResult]
    status: str = OK
    reason: str = ""
    latency_ms: float = 0.0
    surface: np.ndarray | None = field(default=None, repr=False)
    grid_displacement: np.ndarray | None = field(default=None, repr=False)

    @property
    def reliable(self) -> bool:
        return self.status in RELIABLE
