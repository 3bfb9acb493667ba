"""The anatomy of a case as plain arrays: a closed breast surface, its chest wall, its lesions."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fileio import load_npz, save_npz_atomic

#: Arrays added on 2026-11-24 (label maps); left out of the fingerprint while at their defaults.
LATER_KEYS = ("crop_vertices", "chest_curved", "segment_names", "segment_values")
REBUILD = "rebuild the case with `biopsynav init CASE --overwrite` (same inputs)"
ANATOMY_KEYS = ("vertices", "faces", "normals", "fixed_vertices", "chest_point", "chest_normal",
                "lesion_ids", "lesion_centers", "lesion_radii", "lesion_points",
                "lesion_counts", "label_points", "label_values")


@dataclass
class Lesion:
    """A lesion kept as its centre (3,) and surface points (n, 3), mm."""

    id: int
    center: np.ndarray
    radius_mm: float
    points: np.ndarray


@dataclass
class Anatomy:
    """Closed, outward-oriented breast surface and what sits in it (all mm).

    Attributes:
        vertices: (nv, 3) surface vertices.
        faces: (nf, 3) triangles, counter-clockwise seen from outside.
        normals: (nv, 3) outward unit vertex normals.
        fixed_vertices: (nv,) True on the chest wall.
        chest_point, chest_normal: (3,) a point of the chest-wall plane and its unit normal
            pointing out of the breast (posterior).
        lesions: the lesions.
        label_points, label_values: (m, 3) and (m,) tissue-label samples (empty if unlabelled).
        crop_vertices: (nv,) True where a label map's image (or a midline cut) ended the
            breast: never a place to push.
        chest_curved: the chest wall is the interface with a muscle label (fixed_vertices),
            not the plane through ``chest_point``; the plane is then its mean.
        segments: segment name -> label value of a Slicer segmentation (empty otherwise).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    fixed_vertices: np.ndarray
    chest_point: np.ndarray
    chest_normal: np.ndarray
    lesions: list[Lesion] = field(default_factory=list)
    label_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    label_values: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    crop_vertices: np.ndarray | None = None
    chest_curved: bool = False
    segments: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.crop_vertices is None:
            self.crop_vertices = np.zeros(len(self.vertices), dtype=bool)

    @property
    def pushable(self) -> np.ndarray:
        """(nv,) skin vertices a probe may touch: off the chest wall and off crop faces."""
        return ~np.asarray(self.fixed_vertices, bool) & ~np.asarray(self.crop_vertices, bool)

    def nearest_pushable_vertex(self, point: np.ndarray) -> int:
        """Index of the skin vertex a probe may touch (:attr:`pushable`) nearest ``point``
        (3,) mm."""
        dist = np.linalg.norm(self.vertices - np.asarray(point, dtype=np.float64), axis=1)
        dist[~self.pushable] = np.inf
        return int(np.argmin(dist))

    def chest_depth(self, points: np.ndarray) -> np.ndarray:
        """Distance (n,) in mm of ``points`` (n, 3) in front of the chest wall: along the
        plane's normal, and no more than the distance to the nearest chest-wall vertex."""
        from scipy.spatial import cKDTree

        depth = -(np.asarray(points) - self.chest_point) @ self.chest_normal
        if self.chest_curved:
            near, _ = cKDTree(self.vertices[self.fixed_vertices]).query(points)
            depth = np.minimum(np.abs(depth), near)
        return depth

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) minimum and maximum corner of the surface, mm."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def volume_ml(self) -> float:
        """Enclosed volume in millilitres (1 mL = 1000 mm^3)."""
        return surface_volume(self.vertices, self.faces) / 1000.0

    def lesion_points_all(self) -> tuple[np.ndarray, np.ndarray]:
        """All lesion centres and surface points stacked (n, 3), with the lesion index (n,)."""
        pts = [np.vstack([les.center[None], les.points]) for les in self.lesions]
        owner = [np.full(len(p), i) for i, p in enumerate(pts)]
        if not pts:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        return np.vstack(pts), np.concatenate(owner)

    def fingerprint(self) -> str:
        """SHA-256 of the geometry, chest wall, lesions and labels."""
        h = hashlib.sha256()
        skip = () if self._later_keys_used() else LATER_KEYS  # fingerprints as before them
        for key, arr in self._arrays().items():
            if key in skip:
                continue
            a = np.ascontiguousarray(arr)
            h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
        return h.hexdigest()

    def _later_keys_used(self) -> bool:
        return bool(np.any(self.crop_vertices) or self.chest_curved or self.segments)

    def _arrays(self) -> dict[str, np.ndarray]:
        counts = np.array([len(les.points) for les in self.lesions], dtype=np.int64)
        return {
            "vertices": self.vertices, "faces": self.faces, "normals": self.normals,
            "fixed_vertices": self.fixed_vertices, "chest_point": self.chest_point,
            "chest_normal": self.chest_normal,
            "lesion_ids": np.array([les.id for les in self.lesions], dtype=np.int64),
            "lesion_centers": np.array([les.center for les in self.lesions]).reshape(-1, 3),
            "lesion_radii": np.array([les.radius_mm for les in self.lesions], dtype=np.float64),
            "lesion_counts": counts,
            "lesion_points": (np.vstack([les.points for les in self.lesions])
                              if self.lesions else np.zeros((0, 3))),
            "label_points": self.label_points, "label_values": self.label_values,
            "crop_vertices": np.asarray(self.crop_vertices, bool),
            "chest_curved": np.array(bool(self.chest_curved)),
            "segment_names": np.array(list(self.segments), dtype=str),
            "segment_values": np.array(list(self.segments.values()), dtype=np.int64),
        }

    def save(self, path: str | Path) -> Path:
        """Write to ``.npz`` atomically."""
        return save_npz_atomic(path, **self._arrays())

    @classmethod
    def load(cls, path: str | Path) -> Anatomy:
        """Read an anatomy written by :meth:`save`."""
        a = load_npz(path, ANATOMY_KEYS, REBUILD)
        splits = np.cumsum(a["lesion_counts"])[:-1]
        points = np.split(a["lesion_points"], splits) if len(a["lesion_ids"]) else []
        lesions = [Lesion(int(i), c, float(r), p) for i, c, r, p in zip(
            a["lesion_ids"], a["lesion_centers"], a["lesion_radii"], points, strict=True)]
        names = a.get("segment_names", np.zeros(0, str)).tolist()
        return cls(a["vertices"], a["faces"], a["normals"], a["fixed_vertices"],
                   a["chest_point"], a["chest_normal"], lesions, a["label_points"],
                   a["label_values"], a.get("crop_vertices"),
                   bool(a.get("chest_curved", False)),
                   dict(zip(names, a.get("segment_values", np.zeros(0, int)).tolist(),
                            strict=True)))


def surface_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume (mm^3) of a closed triangle surface (positive if outward)."""
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Cross product of each triangle's edges (nf, 3): its outward normal times twice its
    area, mm^2."""
    tri = vertices[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted outward unit vertex normals (nv, 3)."""
    fn = face_cross(vertices, faces)
    vn = np.zeros_like(vertices, dtype=np.float64)
    for c in range(3):
        np.add.at(vn, faces[:, c], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                   chunk: int = 256) -> np.ndarray:
    """Generalised winding number (n,) of points w.r.t. a closed surface (1 inside, 0 outside).

    Van Oosterom-Strackee solid angles, vectorised over faces, chunked over points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = vertices[faces]
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        r = tri[None, :, :, :] - points[s:s + chunk, None, None, :]
        ln = np.linalg.norm(r, axis=3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        la, lb, lc = ln[:, :, 0], ln[:, :, 1], ln[:, :, 2]
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
               + np.einsum("pfi,pfi->pf", b, c) * la + np.einsum("pfi,pfi->pf", c, a) * lb)
        out[s:s + chunk] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * np.pi)
    return out
