"""The immersed grid as plain arrays (see :mod:`biopsynav.grid.index` for the index convention)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..anatomy.model import REBUILD
from ..fileio import load_npz, save_npz_atomic
from . import index


@dataclass
class Grid:
    """A regular hexahedral grid around the anatomy.

    Attributes (mm; node arrays are (nx, ny, nz), cell arrays (nx-1, ny-1, nz-1)):
        origin: (3,) position of node (0, 0, 0).
        spacing: cell edge length.
        fraction: tissue volume fraction of each cell in [0, 1].
        label_values: (k,) the tissue-label values of the anatomy (any integers; empty when
            unlabelled).
        label_share: (nx-1, ny-1, nz-1, k) share of each cell's tissue carrying each label
            value (rows sum to 1 in labelled cells; all zero: the default tissue).
        active_cells: cells that carry finite elements.
        active_nodes: nodes of active cells.
        fixed_nodes: active nodes on or behind the chest wall (Dirichlet u = 0).
        status: per cell 0 outside, 1 boundary, 2 inside.
    """

    origin: np.ndarray
    spacing: float
    fraction: np.ndarray
    label_values: np.ndarray
    label_share: np.ndarray
    active_cells: np.ndarray
    active_nodes: np.ndarray
    fixed_nodes: np.ndarray
    status: np.ndarray

    @property
    def node_shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.active_nodes.shape)  # type: ignore[return-value]

    @property
    def cell_shape(self) -> tuple[int, int, int]:
        return index.cell_shape(self.node_shape)

    @property
    def n_nodes(self) -> int:
        return int(np.prod(self.node_shape))

    def node_coords(self) -> np.ndarray:
        """Positions (n_nodes, 3) of every node in flat order, mm."""
        return index.node_coordinates(self.origin, self.spacing, self.node_shape)

    def active_cell_ijk(self) -> np.ndarray:
        """Integer coordinates (n_active, 3) of active cells in flat order."""
        return np.argwhere(self.active_cells)

    def active_hexes(self) -> np.ndarray:
        """Flat node indices (n_active, 8) of the active cells, VTK hexahedron order."""
        return index.hex_connectivity(self.active_cell_ijk(), self.node_shape)

    def active_fraction(self) -> np.ndarray:
        """Volume fraction (n_active,) of the active cells."""
        return self.fraction[self.active_cells]

    def element_of_cells(self, cells: np.ndarray) -> np.ndarray:
        """Element index (n,) of the active flat cell ids ``cells`` (n,): their rank among
        the active cells in flat order, the FE model's element order."""
        rank = np.cumsum(self.active_cells.ravel()) - 1
        return rank[np.asarray(cells, dtype=np.int64)]

    def active_label_share(self) -> np.ndarray:
        """Label shares (n_active, k) of the active cells, columns as ``label_values``."""
        return self.label_share[self.active_cells]

    def fingerprint(self) -> str:
        """SHA-256 of every array and the geometry: changes whenever the grid changes."""
        h = hashlib.sha256()
        for f in fields(self):
            name, value = f.name, np.ascontiguousarray(getattr(self, f.name))
            if name.startswith("label_") and len(self.label_values) == 0:
                if name == "label_share":
                    continue
                name, value = "label", np.full(self.cell_shape, -1, np.int32)  # as before shares
            h.update(name.encode())
            h.update(str(value.dtype).encode() + str(value.shape).encode())
            h.update(value.tobytes())
        return h.hexdigest()

    def save(self, path: str | Path) -> Path:
        """Write the grid to an ``.npz`` atomically."""
        return save_npz_atomic(path, **{f.name: np.asarray(getattr(self, f.name))
                                        for f in fields(self)})

    @classmethod
    def load(cls, path: str | Path) -> Grid:
        """Read a grid written by :meth:`save`."""
        data = _from_majority_labels(load_npz(path, [f.name for f in fields(cls)
                                                     if not f.name.startswith("label_")],
                                              REBUILD))
        kwargs = {f.name: data[f.name] for f in fields(cls)}
        kwargs["spacing"] = float(kwargs["spacing"])
        return cls(**kwargs)


def _from_majority_labels(data: dict) -> dict:
    """Grids written before label shares held one label per cell (-1: none): read that as a
    share of 1."""
    if "label_share" in data:
        return data
    label = data.pop("label", np.full(data["fraction"].shape, -1, np.int32))
    values = np.unique(label[label >= 0]).astype(np.int64)
    data["label_values"] = values
    data["label_share"] = (label[..., None] == values).astype(np.float32)
    return data
