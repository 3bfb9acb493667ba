"""A deterministic stand-in tracker for the OpenIGTLink service: NOT a tissue model.

Lesions follow the probe rigidly: ``centre = T @ inv(T_rest) @ centre_rest``. It exists to
exercise and benchmark the network service without a trained model (tests, the round-trip part
of ``benchmarks/tracking_latency.py``, demos); the real tracker is
``biopsynav.tracker.Tracker``. It reports the same statuses as the real one for the cases it can
judge: invalid (NaN or non-rigid) pose, no rest pose, no contact (a rest pose whose origin lies
below ``skin_z``, when given) and a push deeper than ``max_push_mm`` along the rest pose's beam
axis (out of envelope).
"""

from __future__ import annotations

import time

import numpy as np
import trimesh

from biopsynav.tracker.core import as_pose, pose_problem
from biopsynav.tracker.result import (
    INVALID_POSE,
    NO_CONTACT,
    NO_REST_POSE,
    OK,
    OUT_OF_ENVELOPE,
    REST,
    LesionResult,
    TrackingResult,
)


class RigidLesionTracker:
    """Lesions at ``centers`` (N, 3) mm in the rest pose, moved rigidly by the probe motion.

    Each lesion is a sphere of ``radius_mm`` (a 42-vertex mesh, ``lesion_meshes``); ``skin``
    (vertices, faces), when given, is a surface moved the same way (``skin_mesh``).
    """

    def __init__(self, centers: np.ndarray, ids: list[int] | None = None,
                 max_push_mm: float = 40.0, rigid_tolerance: float = 1e-3,
                 skin_z: float | None = None, radius_mm: float = 5.0,
                 skin: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        self.ids = list(ids) if ids is not None else list(range(1, len(self.centers) + 1))
        self.max_push_mm = max_push_mm
        self.rigid_tolerance = rigid_tolerance
        self.skin_z = skin_z
        sphere = trimesh.creation.icosphere(subdivisions=1, radius=radius_mm)
        self.lesion_meshes = {i: (np.asarray(sphere.vertices) + c, np.asarray(sphere.faces))
                              for i, c in zip(self.ids, self.centers, strict=True)}
        if skin is not None:
            self.skin_mesh = (np.asarray(skin[0], dtype=np.float64), np.asarray(skin[1]))
        self._rest: np.ndarray | None = None
        self._rest_inv: np.ndarray | None = None

    @property
    def has_rest_pose(self) -> bool:
        return self._rest is not None

    def clear_rest_pose(self) -> None:
        """Forget the rest pose."""
        self._rest = self._rest_inv = None

    def set_rest_pose(self, T: np.ndarray) -> None:
        """Take ``T`` as the rest pose; ValueError for an unusable pose."""
        problem = pose_problem(T, self.rigid_tolerance)
        if problem:
            raise ValueError(problem)
        self._rest = as_pose(T).copy()
        self._rest_inv = np.linalg.inv(self._rest)

    def update(self, T: np.ndarray, with_surface: bool = False,
               lesion_surfaces: bool = True) -> TrackingResult:
        """Lesion centres for pose ``T``; a status instead of numbers when the pose is unusable."""
        t0 = time.perf_counter()
        problem = pose_problem(T, self.rigid_tolerance)
        if problem:
            return self._empty(INVALID_POSE, problem, t0)
        if self._rest is None:
            return self._empty(NO_REST_POSE, "no rest pose set", t0)
        if self.skin_z is not None and self._rest[2, 3] < self.skin_z:
            return self._empty(NO_CONTACT, "no skin under the probe face at the rest pose", t0)
        T = as_pose(T)
        motion = T @ self._rest_inv
        push = float(np.dot(T[:3, 3] - self._rest[:3, 3], self._rest[:3, 2]))
        if push > self.max_push_mm:
            return self._empty(OUT_OF_ENVELOPE, f"probe pushed {push:.1f} mm, beyond the "
                               f"{self.max_push_mm:.1f} mm envelope", t0)
        move = _rigid(motion)
        moved = move(self.centers)
        status = REST if np.allclose(motion, np.eye(4), atol=1e-9) else OK
        lesions = [LesionResult(i, c, c - c0, status, move(self.lesion_meshes[i][0]))
                   for i, c, c0 in zip(self.ids, moved, self.centers, strict=True)]
        result = TrackingResult(lesions, status, "", (time.perf_counter() - t0) * 1e3)
        if with_surface and hasattr(self, "skin_mesh"):
            result.surface = move(self.skin_mesh[0])
        return result

    def _empty(self, status: str, reason: str, t0: float) -> TrackingResult:
        return TrackingResult([], status, reason, (time.perf_counter() - t0) * 1e3)


def _rigid(motion: np.ndarray):
    """The function moving (n, 3) points by the 4 x 4 ``motion``."""
    return lambda p: p @ motion[:3, :3].T + motion[:3, 3]
