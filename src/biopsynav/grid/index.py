"""The one index convention of biopsynav grids; every conversion lives here.

* Axes: array axis 0 is x, axis 1 is y, axis 2 is z (mm, anatomy/world frame). Never zyx.
* Nodes versus cells: a grid of ``shape = (nx, ny, nz)`` nodes has ``(nx-1, ny-1, nz-1)``
  cells. Node ``(i, j, k)`` sits at ``origin + spacing * (i, j, k)``; cell ``(i, j, k)`` spans
  nodes ``(i..i+1, j..j+1, k..k+1)``.
* Flattening: C order, so z is fastest: ``flat = (i * ny + j) * nz + k``. Per-node vector fields
  are ``(n_nodes, 3)`` arrays in that flat order, with columns x, y, z.
* Network tensors are ``(channels, nx, ny, nz)`` (batch first when batched); a node field
  ``(n_nodes, 3)`` becomes a tensor by :func:`field_to_tensor` and back by :func:`tensor_to_field`.
* Local node order of a hexahedron (the VTK_HEXAHEDRON order): corner offsets
  :data:`HEX_CORNERS`, ``(0,0,0), (1,0,0), (1,1,0), (0,1,0), (0,0,1), (1,0,1), (1,1,1), (0,1,1)``.
* Image volumes from SimpleITK arrive as ``(z, y, x)``; :func:`image_array_to_xyz` is the only
  place that swaps them.
"""

from __future__ import annotations

import numpy as np

HEX_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.int64,
)


def flat_index(ijk: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Flat C-order index of integer coordinates ``ijk`` (..., 3) in an array of ``shape``."""
    ijk = np.asarray(ijk, dtype=np.int64)
    return (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]


def unflat_index(flat: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Integer coordinates (..., 3) of flat C-order indices."""
    return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), shape), axis=-1)


def cell_shape(node_shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """Cell counts per axis of a grid with ``node_shape`` nodes."""
    return tuple(int(n) - 1 for n in node_shape)  # type: ignore[return-value]


def hex_connectivity(cell_ijk: np.ndarray, node_shape: tuple[int, int, int]) -> np.ndarray:
    """Flat node indices (n_cells, 8) of cells given by integer coordinates (n_cells, 3)."""
    corners = np.asarray(cell_ijk, dtype=np.int64)[:, None, :] + HEX_CORNERS[None, :, :]
    return flat_index(corners, node_shape)


def node_coordinates(origin: np.ndarray, spacing: float,
                     node_shape: tuple[int, int, int]) -> np.ndarray:
    """Positions (n_nodes, 3) in mm of all nodes, in flat order."""
    ijk = unflat_index(np.arange(int(np.prod(node_shape))), node_shape)
    return np.asarray(origin, dtype=np.float64) + spacing * ijk


def field_to_tensor(field: np.ndarray, node_shape: tuple[int, int, int]) -> np.ndarray:
    """Node field (n_nodes, C) -> tensor layout (C, nx, ny, nz)."""
    field = np.asarray(field)
    return np.ascontiguousarray(field.T.reshape((field.shape[1], *node_shape)))


def tensor_to_field(tensor: np.ndarray) -> np.ndarray:
    """Tensor layout (C, nx, ny, nz) -> node field (n_nodes, C)."""
    tensor = np.asarray(tensor)
    return np.ascontiguousarray(tensor.reshape(tensor.shape[0], -1).T)


def image_array_to_xyz(array_zyx: np.ndarray) -> np.ndarray:
    """A SimpleITK ``GetArrayFromImage`` array (z, y, x) -> (x, y, z)."""
    return np.ascontiguousarray(np.transpose(array_zyx, (2, 1, 0)))
