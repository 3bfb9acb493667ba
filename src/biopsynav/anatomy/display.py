"""Meshes for display: a closed triangle mesh per lesion, a decimated skin (mm).

Both are computed once, at rest; what moves is their vertices, read off the predicted
displacement at the same points (the tracker) or a subset of the skin vertices.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import ConvexHull, QhullError

MAX_LESION_VERTICES = 162  # an icosphere of two subdivisions


def _directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread over the sphere (Fibonacci lattice), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def lesion_mesh(points: np.ndarray, max_vertices: int = MAX_LESION_VERTICES
                ) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented triangle mesh (vertices (k, 3), faces (m, 3)) of a lesion's
    surface ``points`` (n, 3) mm: their convex hull, on at most ``max_vertices`` of them (the
    points furthest along evenly spread directions when there are more)."""
    pts = np.unique(np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=0)
    if len(pts) > max_vertices:
        centred = pts - pts.mean(axis=0)
        pts = pts[np.unique(np.argmax(centred @ _directions(max_vertices).T, axis=0))]
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError) as exc:
        raise ValueError(f"lesion points span no volume: {exc}") from None
    used = np.unique(hull.simplices)
    remap = np.full(len(pts), -1)
    remap[used] = np.arange(len(used))
    return pts[used], _outward(pts[used], remap[hull.simplices])


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` of a convex mesh, each wound counter-clockwise seen from outside."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", normal, (a + b + c) / 3 - vertices.mean(axis=0)) < 0
    out = faces.copy()
    out[inward] = out[inward][:, [0, 2, 1]]
    return out


def decimate(vertices: np.ndarray, faces: np.ndarray, max_triangles: int
             ) -> tuple[sp.csr_matrix, np.ndarray]:
    """Quadric decimation of a closed triangle surface to at most ``max_triangles`` faces
    (fast-simplification, through trimesh), which keeps it closed.

    Returns ``weights`` (k, nv) sparse, each decimated vertex as the barycentric combination of
    the original triangle it lies on (nearest point), and ``faces`` (m, 3) indexing the k
    decimated vertices. The deformed decimated surface is ``weights @ deformed_vertices``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) <= max_triangles:
        return sp.identity(len(vertices), format="csr"), faces
    small_vertices, small_faces = quadric_decimated(vertices, faces, max_triangles)
    return on_surface_weights(vertices, faces, small_vertices), small_faces


def quadric_decimated(vertices: np.ndarray, faces: np.ndarray, max_triangles: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The closed triangle surface (vertices (n, 3) mm, faces (m, 3)) as it is with at most
    ``max_triangles`` faces, else decimated to that many (quadric error metric,
    fast-simplification through trimesh; it stays closed), its vertices where the metric
    puts them: (k, 3) mm float64 and (m', 3) int64 when decimated."""
    if len(faces) <= max_triangles:
        return vertices, faces
    import trimesh

    small = trimesh.Trimesh(vertices, faces, process=False).simplify_quadric_decimation(
        face_count=max_triangles)
    return np.asarray(small.vertices, dtype=np.float64), np.asarray(small.faces, dtype=np.int64)


def on_surface_weights(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                       candidates: int = 8) -> sp.csr_matrix:
    """(p, nv) barycentric weights of the nearest point of the surface to each of ``points``
    (p, 3) mm, searched among the ``candidates`` triangles with the nearest centroids."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point, points_to_barycentric

    tri = vertices[faces]
    k = min(candidates, len(faces))
    _, near = cKDTree(tri.mean(axis=1)).query(points, k=k)
    near = near.reshape(len(points), k)
    found = np.stack([closest_point(tri[near[:, j]], points) for j in range(k)], axis=1)
    best = np.argmin(np.linalg.norm(found - points[:, None], axis=2), axis=1)
    rows = np.arange(len(points))
    chosen = near[rows, best]
    bary = points_to_barycentric(tri[chosen], found[rows, best])
    return sp.csr_matrix((bary.ravel(), (np.repeat(rows, 3), faces[chosen].ravel())),
                         shape=(len(points), len(vertices)))
