"""Meshes for display: a closed triangle mesh per lesion, a decimated skin (mm).

Both are computed once, at rest; what moves is their vertices, read off the predicted
displacement at the same points (the tracker) or a subset of the skin vertices.
"""

from __future__ import annotations

import numpy as np
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
             ) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering of a triangle surface to at most ``max_triangles`` faces.

    Returns ``keep`` (k,) indices of the kept vertices (one per occupied cube of a grid, the
    vertex nearest the cube's mean) and ``faces`` (m, 3) indexing ``keep``; faces that collapse
    are dropped, and the cube grows by 20 % until the count fits. The deformed decimated
    surface is ``deformed_vertices[keep]`` with the same faces.
    """
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) <= max_triangles:
        return np.arange(len(vertices)), faces
    extent = np.ptp(vertices, axis=0).max()
    cube = extent * np.sqrt(2.0 / max_triangles)
    while True:
        keep, new_faces = _cluster(vertices, faces, cube)
        if len(new_faces) <= max_triangles:
            return keep, new_faces
        cube *= 1.2


def _cluster(vertices: np.ndarray, faces: np.ndarray, cube: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """One clustering pass with cubes of edge ``cube`` mm."""
    cell = np.floor((vertices - vertices.min(axis=0)) / cube).astype(np.int64)
    _, label = np.unique(cell, axis=0, return_inverse=True)
    label = label.ravel()
    n = label.max() + 1
    mean = np.zeros((n, 3))
    np.add.at(mean, label, vertices)
    mean /= np.bincount(label, minlength=n)[:, None]
    dist = np.linalg.norm(vertices - mean[label], axis=1)
    order = np.lexsort((dist, label))
    first = order[np.r_[True, label[order][1:] != label[order][:-1]]]  # nearest per cluster
    keep = first[np.argsort(label[first])]
    new = label[faces]
    ok = (new[:, 0] != new[:, 1]) & (new[:, 1] != new[:, 2]) & (new[:, 0] != new[:, 2])
    new = new[ok]
    _, unique_rows = np.unique(np.sort(new, axis=1), axis=0, return_index=True)
    return keep, new[np.sort(unique_rows)]
