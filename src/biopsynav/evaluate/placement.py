"""Where the probe goes for Table 2 by simulation, and how deep it pushes.

Placement of the probe above lesion ``c`` (all mm, anatomy frame):

1. the skin point ``p``: the surface vertex nearest to ``c`` of those a training push may
   centre on (:func:`biopsynav.probe.eligible_centers`: off the chest wall and crop faces, at
   least ``[probe] min_chest_distance_mm`` in front of the wall). A lesion lying against the
   chest wall near the back of the breast (exam 02 left of the MRI collection, docs/anatomy.md)
   has its nearest pushable skin vertex 1 mm from held ones: a probe there pushes along the
   wall and barely loads the lesion, and no training push was ever centred there;
2. the beam axis ``z``: the unit vector from ``p`` to ``c``, so the lesion centre lies on the
   probe axis, under the face centre, at the depth ``|c - p|`` (the nearest-point direction
   is the inward skin normal on a smooth surface; where it deviates from it by more than
   ``MAX_AXIS_TILT_DEG`` the inward normal is used instead, and the lesion then lies in the
   image plane but off the axis);
3. the long side ``x``: parallel to the chest wall, ``x = n_chest x z`` normalised (the 50 mm
   side then never reaches down to the fixed chest wall, which would crush the tissue
   between them); where ``z`` is nearly normal to the chest wall (lesions under the nipple)
   the world axis least aligned with ``z``, projected normal to ``z``. Either way ``x`` is
   normal to ``z`` and the x-z image plane holds ``c``; ``y = z x x``;
4. the rest pose: the probe face centre at ``p`` (the face touches the skin there).

Pushes translate the probe from the rest pose along its own axis ``z`` by depths of increasing
extent. With ``n`` pushes per lesion there are ``n + 1`` depth levels evenly spread from
``max_push_mm * 10/32`` to ``max_push_mm * 30/32`` (10, 15, 20, 25, 30 mm with the defaults: the
centres of the paper's bins D10 ... D30); the k-th evaluated lesion skips level ``k mod (n+1)``
(one empty cell per row, as in the paper's Table 2) and every depth gets a small
deterministic per-lesion offset (within +-1.5 mm, kept inside its bin) so that rows differ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..anatomy.model import Anatomy
from ..config import ProbeSection
from ..probe import eligible_centers

if TYPE_CHECKING:
    from ..case import Case

MAX_AXIS_TILT_DEG = 30.0
LEVEL_JITTER_MM = 1.5
MIN_CHEST_CROSS = 0.3  # |n_chest x z| below this: z is too close to the chest normal
MIN_CHEST_DISTANCE_MM = ProbeSection().min_chest_distance_mm


@dataclass
class Placement:
    """Probe placement above one lesion: rest ``pose`` (4, 4), skin ``vertex`` index, lesion
    ``depth_mm`` below the face and its in-plane offset ``lateral_mm`` (along probe x)."""

    lesion: int
    vertex: int
    pose: np.ndarray
    depth_mm: float
    lateral_mm: float

    def pushed(self, depth_mm: float) -> np.ndarray:
        """The pose (4, 4) translated by ``depth_mm`` along the probe axis from rest."""
        pose = self.pose.copy()
        pose[:3, 3] += depth_mm * pose[:3, 2]
        return pose

    def to_dict(self) -> dict:
        return {"lesion": self.lesion, "vertex": self.vertex, "pose": self.pose.tolist(),
                "depth_mm": self.depth_mm, "lateral_mm": self.lateral_mm}


def beam_frame(z: np.ndarray, chest_normal: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) with columns x, y, z for beam axis ``z`` (3,): x = chest_normal x z
    (parallel to the chest wall), or, where z is within ~17 degrees of the chest normal, the
    world axis least aligned with z projected normal to z; y = z cross x."""
    z = np.asarray(z, dtype=np.float64) / np.linalg.norm(z)
    x = np.cross(np.asarray(chest_normal, dtype=np.float64), z)
    if np.linalg.norm(x) < MIN_CHEST_CROSS:
        e = np.eye(3)[int(np.argmin(np.abs(z)))]
        x = e - (e @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def skin_point(anatomy: Anatomy, point: np.ndarray, min_chest_distance_mm: float) -> int:
    """Index of the skin vertex nearest ``point`` (3,) mm among those a training push may centre
    on, at least ``min_chest_distance_mm`` in front of the chest wall (step 1 of the module
    doc)."""
    centres = eligible_centers(anatomy, min_chest_distance_mm)
    dist = np.linalg.norm(anatomy.vertices[centres] - np.asarray(point, np.float64), axis=1)
    return int(centres[np.argmin(dist)])


def place_probe(anatomy: Anatomy, lesion_index: int,
                min_chest_distance_mm: float = MIN_CHEST_DISTANCE_MM) -> Placement:
    """Rest pose of the probe above lesion ``lesion_index`` (see module doc), its skin point at
    least ``min_chest_distance_mm`` in front of the chest wall (a case's own is ``[probe]
    min_chest_distance_mm``; :func:`place_case_probe` reads it)."""
    les = anatomy.lesions[lesion_index]
    c = np.asarray(les.center, dtype=np.float64)
    v = skin_point(anatomy, c, min_chest_distance_mm)
    p = anatomy.vertices[v]
    z = (c - p) / max(float(np.linalg.norm(c - p)), 1e-12)
    inward = -anatomy.normals[v]
    if np.degrees(np.arccos(np.clip(z @ inward, -1.0, 1.0))) > MAX_AXIS_TILT_DEG:
        z = inward / np.linalg.norm(inward)
    pose = np.eye(4)
    pose[:3, :3] = beam_frame(z, anatomy.chest_normal)
    pose[:3, 3] = p
    local = (c - p) @ pose[:3, :3]
    return Placement(int(les.id), v, pose, float(local[2]), float(local[0]))


def place_case_probe(case: Case, lesion_index: int) -> Placement:
    """:func:`place_probe` on a loaded case's anatomy with its ``[probe]
    min_chest_distance_mm``."""
    return place_probe(case.anatomy, lesion_index, case.cfg.probe.min_chest_distance_mm)


def push_depths(k: int, n_pushes: int, max_push_mm: float) -> np.ndarray:
    """Increasing push depths (n_pushes,) mm for the k-th evaluated lesion (see module doc)."""
    levels = np.linspace(max_push_mm * 10.0 / 32.0, max_push_mm * 30.0 / 32.0, n_pushes + 1)
    keep = np.delete(np.arange(n_pushes + 1), k % (n_pushes + 1))
    step = levels[1] - levels[0] if n_pushes else 0.0
    jitter = min(LEVEL_JITTER_MM, 0.3 * step) * np.sin(1.0 + 2.399 * k)  # golden-angle spread
    return np.sort(levels[keep] + jitter)
