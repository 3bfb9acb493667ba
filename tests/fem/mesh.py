"""Structured boxes of hexahedra in the grid index convention (tests, benchmarks)."""

from __future__ import annotations

import numpy as np

from biopsynav.grid import index


def box_mesh(cells: tuple[int, int, int], size_mm: tuple[float, float, float],
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
             ) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n_nodes, 3) mm and hexes (n_el, 8) of a box split into ``cells`` hexahedra.

    Node and cell order follow :mod:`biopsynav.grid.index` (C order, z fastest; VTK corners).
    """
    cells = tuple(int(c) for c in cells)
    node_shape = tuple(c + 1 for c in cells)
    ijk = index.unflat_index(np.arange(int(np.prod(node_shape))), node_shape)
    nodes = np.asarray(origin, dtype=np.float64) + ijk * (np.asarray(size_mm) / np.asarray(cells))
    cell_ijk = index.unflat_index(np.arange(int(np.prod(cells))), cells)
    return nodes, index.hex_connectivity(cell_ijk, node_shape)
