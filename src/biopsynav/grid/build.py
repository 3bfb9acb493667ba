"""Build the immersed grid: extent, padding, volume fractions, labels, active and fixed nodes.

Volume fractions come from an exact inside test on a regular lattice of ``n^3`` sub-cell sample
points per cell: every lattice column along z is intersected with the surface triangles (a
vectorised scan conversion), and the parity of crossings below a sample says inside or outside.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..anatomy.model import Anatomy
from ..config import GridSection
from ..errors import InputError
from . import index
from .model import Grid

# tiny irrational offsets keep lattice columns off mesh vertices and edges
_COLUMN_JITTER = np.array([np.sqrt(2.0) * 1e-7, np.sqrt(3.0) * 1e-7])


def build_grid(anatomy: Anatomy, settings: GridSection, max_fixed_share: float = 1.0,
               chest_tol_mm: float = 1.0) -> Grid:
    """The immersed grid of ``anatomy`` with cells of ``settings.cell_size_mm``: the anatomy's
    box plus ``settings.margin_cells`` (the network takes any node counts). Nodes within
    ``chest_tol_mm`` of a curved chest wall, or behind it, are fixed. InputError when the chest
    wall fixes more than ``max_fixed_share`` of the active nodes."""
    h = float(settings.cell_size_mm)
    origin, node_shape = _grid_frame(anatomy, h, settings.margin_cells)
    cshape = index.cell_shape(node_shape)
    if int(np.prod(cshape)) > 5_000_000:
        raise InputError(f"grid of {cshape} cells is too large; increase [grid] cell_size_mm")
    inside, lattice = inside_lattice(anatomy.vertices, anatomy.faces, origin, h, cshape,
                                     settings.samples_per_axis)
    n = settings.samples_per_axis
    fraction = inside.reshape(cshape[0], n, cshape[1], n, cshape[2], n).mean(axis=(1, 3, 5))
    touched = _cells_touched(anatomy, origin, h, cshape)
    active = (fraction > settings.fraction_threshold) | touched
    status = np.where(fraction >= 1.0, 2, np.where((fraction > 0) | touched, 1, 0))
    values, share = _grid_label_shares(anatomy, inside, lattice, cshape, n, active)
    active_nodes = _nodes_of_cells(active, node_shape)
    coords = index.node_coordinates(origin, h, node_shape).reshape((*node_shape, 3))
    if anatomy.chest_curved:
        fixed = active_nodes & behind_curved_wall(anatomy, coords, chest_tol_mm)
    else:
        behind = (coords - anatomy.chest_point) @ anatomy.chest_normal >= -1e-6 * h
        fixed = active_nodes & (behind | _wall_layer(anatomy, node_shape))
    if not fixed.any():
        raise InputError("no grid node lies on the chest wall; check [anatomy] chest_wall")
    check_fixed_share(int(fixed.sum()), int(active_nodes.sum()), max_fixed_share)
    return Grid(origin=origin, spacing=h, fraction=fraction.astype(np.float32),
                label_values=values, label_share=share, active_cells=active,
                active_nodes=active_nodes, fixed_nodes=fixed, status=status.astype(np.int8))


def check_fixed_share(n_fixed: int, n_active: int, max_share: float) -> None:
    """Refuse a chest wall that fixes more than ``max_share`` of the active nodes."""
    if n_fixed > max_share * n_active:
        raise InputError(f"the chest wall fixes {n_fixed} of {n_active} grid nodes "
                         f"({100.0 * n_fixed / n_active:.0f} %, more than [anatomy] "
                         f"max_fixed_share = {100.0 * max_share:.0f} %): a chest wall holds the "
                         "breast's base only; is its normal reversed? ([anatomy] chest_wall)")


def _grid_frame(anatomy: Anatomy, h: float,
                margin: int) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Origin and node shape: the box around the anatomy plus ``margin`` cells.

    When the chest wall is perpendicular to an axis, a node plane is put on it and no margin is
    added behind it, so that fixed nodes sit exactly on the chest wall.
    """
    lo, hi = anatomy.bounds
    origin = np.empty(3)
    shape = []
    walls = _wall_axes(anatomy)
    for ax in range(3):
        n_ax = anatomy.chest_normal[ax]
        cells = int(np.ceil((hi[ax] - lo[ax]) / h - 1e-9))
        if ax in walls:
            wall = float(anatomy.chest_point[ax])
            nodes = cells + margin + 1
            start = wall if n_ax < 0 else wall - (nodes - 1) * h
        else:
            nodes = cells + 2 * margin + 1
            centre = 0.5 * (lo[ax] + hi[ax])
            start = centre - 0.5 * (nodes - 1) * h
        origin[ax] = start
        shape.append(nodes)
    return origin, tuple(shape)  # type: ignore[return-value]


def _wall_axes(anatomy: Anatomy) -> list[int]:
    """Axes the chest wall is perpendicular to (|normal| > 0.999 along it): the grid puts a
    node plane on the wall there, the first (normal < 0) or the last."""
    return [ax for ax in range(3) if abs(anatomy.chest_normal[ax]) > 0.999]


def _wall_layer(anatomy: Anatomy, node_shape: tuple[int, int, int]) -> np.ndarray:
    """Nodes (node_shape) of the node plane that :func:`_grid_frame` put on a chest wall
    perpendicular to an axis (:func:`_wall_axes`). A fitted wall is rarely exactly
    perpendicular: tilted by 0.06 degrees (the UC Davis breast), the plane test alone left
    half of that layer free, and the breast hinged on the other half."""
    layer = np.zeros(node_shape, dtype=bool)
    for ax in _wall_axes(anatomy):
        index = [slice(None)] * 3
        index[ax] = 0 if anatomy.chest_normal[ax] < 0 else node_shape[ax] - 1
        layer[tuple(index)] = True
    return layer


def inside_lattice(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, h: float,
                   cshape: tuple[int, int, int], n: int) -> tuple[np.ndarray, tuple]:
    """Inside test (Mx, My, Mz) bool on the lattice of n^3 sample points per cell."""
    step = h / n
    axes = tuple(origin[ax] + (np.arange(cshape[ax] * n) + 0.5) * step for ax in range(3))
    xs, ys, zs = axes
    xq = xs + _COLUMN_JITTER[0] * h
    yq = ys + _COLUMN_JITTER[1] * h
    col, zc = _column_crossings(vertices, faces, xq, yq)
    counts = np.zeros((len(xs) * len(ys), len(zs) + 1), dtype=np.int32)
    np.add.at(counts, (col, np.searchsorted(zs, zc)), 1)
    parity = np.cumsum(counts, axis=1)[:, :-1] % 2 == 1
    return parity.reshape(len(xs), len(ys), len(zs)), axes


def _column_crossings(vertices: np.ndarray, faces: np.ndarray, xs: np.ndarray,
                      ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat column ids and z of every crossing of lattice columns (x_i, y_j) with triangles."""
    tri = vertices[faces]
    ix0 = np.searchsorted(xs, tri[:, :, 0].min(axis=1))
    ix1 = np.searchsorted(xs, tri[:, :, 0].max(axis=1))
    iy0 = np.searchsorted(ys, tri[:, :, 1].min(axis=1))
    iy1 = np.searchsorted(ys, tri[:, :, 1].max(axis=1))
    nx_, ny_ = ix1 - ix0, iy1 - iy0
    per = nx_ * ny_
    t = np.repeat(np.arange(len(tri)), per)
    local = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
    ix = ix0[t] + local // np.maximum(ny_[t], 1)
    iy = iy0[t] + local % np.maximum(ny_[t], 1)
    px, py = xs[ix], ys[iy]
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    w1 = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1]))
    w2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1]))
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = w1 / d, w2 / d
        hit = (d != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
        z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
    return (ix * len(ys) + iy)[hit], z[hit]


def _cells_touched(anatomy: Anatomy, origin: np.ndarray, h: float,
                   cshape: tuple[int, int, int]) -> np.ndarray:
    """Cells (cshape) holding a surface vertex or a lesion point."""
    lesion_pts, _ = anatomy.lesion_points_all()
    pts = np.vstack([anatomy.vertices, lesion_pts])
    ijk = np.clip(np.floor((pts - origin) / h).astype(np.int64), 0, np.array(cshape) - 1)
    touched = np.zeros(cshape, dtype=bool)
    touched[tuple(ijk.T)] = True
    return touched


def behind_curved_wall(anatomy: Anatomy, coords: np.ndarray, tol: float) -> np.ndarray:
    """Nodes (coords.shape[:-1]) on or behind a curved chest wall: their nearest surface
    vertex is a chest-wall vertex and they lie on its outer side (along its normal) or within
    ``tol`` mm inside."""
    flat = coords.reshape(-1, 3)
    _, nearest = cKDTree(anatomy.vertices).query(flat, workers=-1)
    outward = np.einsum("ij,ij->i", flat - anatomy.vertices[nearest], anatomy.normals[nearest])
    return (anatomy.fixed_vertices[nearest] & (outward >= -tol)).reshape(coords.shape[:-1])


def _grid_label_shares(anatomy: Anatomy, inside: np.ndarray, lattice: tuple, cshape, n: int,
                       active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label values (k,) and the share (cshape + (k,)) of each cell's inside samples that has
    each value (nearest label sample); an active cell with no inside sample takes the label
    nearest its centre. Without labels: (0,) and (cshape + (0,))."""
    values = np.unique(anatomy.label_values).astype(np.int64)
    if len(values) == 0:
        return values, np.zeros((*cshape, 0), np.float32)
    tree = cKDTree(anatomy.label_points)
    ii, jj, kk = np.nonzero(inside)
    _, nearest = tree.query(np.stack([lattice[0][ii], lattice[1][jj], lattice[2][kk]], axis=1),
                            workers=-1)
    column = np.searchsorted(values, anatomy.label_values[nearest])
    cell = index.flat_index(np.stack([ii // n, jj // n, kk // n], axis=1), cshape)
    votes = np.zeros((int(np.prod(cshape)), len(values)), np.float64)
    np.add.at(votes, (cell, column), 1.0)
    total = votes.sum(axis=1, keepdims=True)
    share = np.divide(votes, total, out=np.zeros_like(votes), where=total > 0)
    empty = active.ravel() & (total[:, 0] == 0)
    if empty.any():
        h = (lattice[0][1] - lattice[0][0]) * n
        origin = np.array([lattice[a][0] for a in range(3)]) - 0.5 * h / n
        centres = origin + (index.unflat_index(np.flatnonzero(empty), cshape) + 0.5) * h
        _, near = tree.query(centres)
        share[np.flatnonzero(empty), np.searchsorted(values, anatomy.label_values[near])] = 1.0
    return values, share.reshape((*cshape, len(values))).astype(np.float32)


def _nodes_of_cells(cells: np.ndarray, node_shape: tuple[int, int, int]) -> np.ndarray:
    nodes = np.zeros(node_shape, dtype=bool)
    for dx, dy, dz in index.HEX_CORNERS:
        nodes[dx:dx + cells.shape[0], dy:dy + cells.shape[1], dz:dz + cells.shape[2]] |= cells
    return nodes
