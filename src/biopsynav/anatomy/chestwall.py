"""The chest wall: the fixed (Dirichlet) posterior plane of the breast.

``auto`` finds the largest flat face of the surface (faces sharing one normal within 5 degrees
and one plane offset within the tolerance) and requires it to cover at least 5 % of the surface
area; ``x-min`` ... ``z-max`` take the extreme plane along an axis; ``plane:px,py,pz,nx,ny,nz``
gives a point and the normal pointing out of the breast. Surface vertices within the tolerance
of the plane are chest-wall vertices.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .model import face_cross

MIN_FLAT_SHARE = 0.05
FLAT_COS = np.cos(np.deg2rad(5.0))


def chest_wall_plane(vertices: np.ndarray, faces: np.ndarray, spec: str,
                     tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Point (3,) and outward unit normal (3,) of the chest-wall plane for ``spec``."""
    if spec == "auto":
        return _largest_flat_face(vertices, faces, tol)
    if spec.startswith("plane:"):
        vals = np.array([float(v) for v in spec[6:].split(",")])
        return vals[:3], vals[3:] / np.linalg.norm(vals[3:])
    axis = "xyz".index(spec[0])
    normal = np.zeros(3)
    if spec.endswith("min"):
        normal[axis] = -1.0
        point = vertices[np.argmin(vertices[:, axis])]
    else:
        normal[axis] = 1.0
        point = vertices[np.argmax(vertices[:, axis])]
    return point.astype(np.float64), normal


def chest_wall_vertices(vertices: np.ndarray, point: np.ndarray, normal: np.ndarray,
                        tol: float, where: str) -> np.ndarray:
    """Mask (nv,) of vertices on (or behind) the chest-wall plane; error if empty."""
    fixed = (vertices - point) @ normal >= -tol
    if not fixed.any():
        raise InputError("chest wall is empty: no surface vertex lies on the chest-wall plane; "
                         "give --chest-wall plane:px,py,pz,nx,ny,nz", where)
    return fixed


def _largest_flat_face(vertices: np.ndarray, faces: np.ndarray,
                       tol: float) -> tuple[np.ndarray, np.ndarray]:
    tri = vertices[faces]
    cross = face_cross(vertices, faces)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    centroid = tri.mean(axis=1)
    # candidate directions: area-weighted votes of quantised normals
    q = np.round(normal * 8.0).astype(np.int64)
    _, inv, = np.unique(q, axis=0, return_inverse=True)[:2]
    votes = np.bincount(inv.ravel(), weights=area)
    best_area, best = 0.0, None
    for cand in np.argsort(votes)[::-1][:6]:
        members = inv.ravel() == cand
        n0 = (normal[members] * area[members, None]).sum(axis=0)
        n0 /= np.linalg.norm(n0)
        aligned = normal @ n0 > FLAT_COS
        offset = centroid @ n0
        d0 = np.median(offset[aligned])
        flat = aligned & (np.abs(offset - d0) <= tol)
        if area[flat].sum() > best_area:
            best_area, best = area[flat].sum(), flat
    if best is None or best_area < MIN_FLAT_SHARE * area.sum():
        raise InputError("no flat posterior face found for the chest wall; give the muscle "
                         "label of a label map (--chest-labels) or --chest-wall "
                         "plane:px,py,pz,nx,ny,nz or z-min")
    n = (normal[best] * area[best, None]).sum(axis=0)
    n /= np.linalg.norm(n)
    point = (centroid[best] * area[best, None]).sum(axis=0) / area[best].sum()
    return point, n
