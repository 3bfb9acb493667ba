"""Surface checks and repairs: closed, outward, manifold vertices, plausible units."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import InputError
from .model import surface_volume


def boundary_loop_count(faces: np.ndarray) -> int:
    """Number of holes: connected loops of edges used by exactly one face."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    open_edges = uniq[counts == 1]
    if len(open_edges) == 0:
        return 0
    verts, inv = np.unique(open_edges, return_inverse=True)
    inv = inv.reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])),
                          shape=(len(verts), len(verts)))
    return int(connected_components(graph, directed=False)[0])


def close_surface(vertices: np.ndarray, faces: np.ndarray, where: str,
                  repairs: list[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge duplicate vertices, drop degenerate faces, fill small holes; error if still open.
    Each repair that changed the surface is said in one line appended to ``repairs``."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    holes_before = boundary_loop_count(np.asarray(mesh.faces))
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    holes = boundary_loop_count(np.asarray(mesh.faces))
    if holes:
        raise InputError(f"surface is not closed: {holes} hole(s) remain after repair", where)
    if holes_before and repairs is not None:
        repairs.append(f"the surface was open ({holes_before} hole(s)) and was closed by "
                       "filling them: check that the filled faces belong to the breast")
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if surface_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


def split_pinch_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray,
                                                                           np.ndarray, int]:
    """Duplicate non-manifold ("pinch") vertices so that each fan of faces has its own vertex.

    Corners (face, vertex) of one vertex are linked when their faces share an edge through it;
    each connected group of corners becomes one vertex. Returns vertices, faces, split count.
    """
    nf = len(faces)
    corner_vertex = faces.ravel()
    corner_id = np.arange(3 * nf).reshape(nf, 3)
    # each directed face edge (a, b): corners of a and b in this face
    a_loc, b_loc = np.array([0, 1, 2]), np.array([1, 2, 0])
    ea, eb = faces[:, a_loc].ravel(), faces[:, b_loc].ravel()
    ca, cb = corner_id[:, a_loc].ravel(), corner_id[:, b_loc].ravel()
    key = np.minimum(ea, eb) * (len(vertices) + 1) + np.maximum(ea, eb)
    order = np.argsort(key, kind="stable")
    key_s = key[order]
    starts = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
    group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(key_s)]))
    first = order[starts][group]  # the first half-edge of each edge group
    # link corner of vertex v in one face to the corner of v in the other face
    lo = ea[first] == ea[order]
    rows = np.concatenate([ca[order], cb[order]])
    cols = np.concatenate([np.where(lo, ca[first], cb[first]), np.where(lo, cb[first],
                                                                         ca[first])])
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * nf, 3 * nf))
    _, comp = connected_components(graph, directed=False)
    uniq_comp, first_corner = np.unique(comp, return_index=True)
    new_vertex_of_comp = np.empty(comp.max() + 1, dtype=np.int64)
    owner = corner_vertex[first_corner]
    new_vertex_of_comp[uniq_comp] = np.arange(len(uniq_comp))
    new_faces = new_vertex_of_comp[comp].reshape(nf, 3)
    n_split = len(uniq_comp) - len(np.unique(owner))
    new_vertices = vertices[owner]
    return new_vertices, new_faces, int(n_split)


def check_units(vertices: np.ndarray, where: str) -> None:
    """Reject a bounding box under 10 mm or over 1 m (wrong units, likely m or um)."""
    extent = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    if not np.isfinite(vertices).all():
        raise InputError("surface has NaN or infinite coordinates", where)
    if extent < 10.0:
        raise InputError(f"bounding box is only {extent:.3g} mm across: units look wrong "
                         "(biopsynav expects mm; was it saved in m or cm?)", where)
    if extent > 1000.0:
        raise InputError(f"bounding box is {extent:.4g} mm across (over 1 m): units look wrong "
                         "(biopsynav expects mm; was it saved in um?)", where)
