"""The contact points of stored samples, redrawn from the data set's protocol.

A sample stores its probe parameters (``vertex``, ``attempt``, ``n_contact``, ...) but not the
skin vertices under the probe. They follow deterministically from the protocol recorded in the
store (probe section and seed) and the case's anatomy, so they are redrawn rather than stored;
the stored centre vertex and contact count guard against a mismatch (another protocol, or a
change to the draw).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..errors import InputError

if TYPE_CHECKING:
    from ..case import Case


def sample_contact_matrices(case: Case, dataset: str | Path,
                            indices: np.ndarray) -> list[sp.csr_matrix]:
    """Trilinear weights ``W_P`` (n_contact, n_nodes) of the contact points of the stored
    samples ``indices`` (into the store's sample axis) of ``dataset`` (a ``dataset.zarr`` or
    its case folder).

    Raises InputError when the store lacks the probe parameters, or when a redrawn push does not
    match the stored one (centre vertex or contact count): the data set was drawn with another
    protocol or code version than this one.
    """
    import zarr

    from ..config import config_from_dict
    from ..grid.embedding import surface_embedding
    from ..probe import eligible_centers, pinned_skin, push_for_sample
    from .store import DATASET_NAME

    path = Path(dataset)
    if path.suffix != ".zarr":
        path = path / DATASET_NAME
    try:
        g = zarr.open_group(str(path), mode="r")
        protocol = dict(g.attrs["protocol"])
        vertex = np.asarray(g["vertex"][:])
        attempt = np.asarray(g["attempt"][:])
        n_contact = np.asarray(g["n_contact"][:])
        probe = config_from_dict({"probe": protocol["probe"]}, str(path)).probe
        seed = int(protocol["dataset"]["seed"])
    except (KeyError, ValueError, OSError, TypeError) as exc:
        raise InputError(f"the data set has no readable probe protocol ({type(exc).__name__}: "
                         f"{exc})", str(path)) from None
    embedding = surface_embedding(case.grid, case.anatomy)
    skin, pinned = embedding.matrix, pinned_skin(case.grid.fixed_nodes, embedding.nodes)
    centers = eligible_centers(case.anatomy, probe.min_chest_distance_mm)
    out = []
    for i in np.asarray(indices, dtype=np.int64).ravel():  # one redraw per requested sample
        push = push_for_sample(case.anatomy, probe, seed, int(i), int(attempt[i]), centers,
                               pinned=pinned)
        if push.vertex != vertex[i] or push.n_contact != n_contact[i]:
            raise InputError(f"sample {i}: the redrawn push (vertex {push.vertex}, "
                             f"{push.n_contact} contact points) is not the stored one (vertex "
                             f"{vertex[i]}, {n_contact[i]}); the data set was drawn with "
                             "another protocol: regenerate it", str(path))
        out.append(sp.csr_matrix(skin[push.contact]))
    return out


__all__ = ["sample_contact_matrices"]
