"""How the probe's contact points constrain the FE model: one registry
(``register_contact_constraint``), read by ``[tracker] fem_contact``.

The FE engine (``Tracker(engine="fem")``, Table 2's FE method and its ground truth) prescribes
the displacement of the contact points, skin points embedded in grid cells with trilinear
weights ``W`` (n_points, n_nodes). A constraint kind turns the points into constraint rows
``A`` (n_constraints, n_points); the solve then enforces ``A W u = A g``.

Registered:

* ``points``: every contact point is met (``A = I``). In a cell holding several points this
  fixes the whole trilinear cell to the probe's motion, nodes beyond the probe's edge
  included: on coarse grids the probe acts as if it were up to a cell wider on every side.
* ``cell_average``: the mean displacement of the contact points of each cell is met (one
  constraint per cell, the multipliers piecewise constant per cell: a mortar-type coupling).
  The cell may deform under the probe's edge; as the cells shrink both kinds reach the same
  limit (docs/fem.md, benchmarks/convergence.py).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

CONTACT_CONSTRAINTS: dict[str, Callable[[np.ndarray], sp.csr_matrix]] = {}


def register_contact_constraint(name: str, rows: Callable[[np.ndarray], sp.csr_matrix]) -> None:
    """Make ``name`` a ``[tracker] fem_contact``: ``rows(cells) -> A`` (n_constraints,
    n_points) for the contact points' flat cell ids ``cells`` (n_points,)."""
    CONTACT_CONSTRAINTS[name] = rows


def contact_constraint_names() -> tuple[str, ...]:
    """The registered kinds: the allowed ``[tracker] fem_contact`` values."""
    return tuple(CONTACT_CONSTRAINTS)


def constraint_rows(name: str, cells: np.ndarray) -> sp.csr_matrix:
    """Constraint rows ``A`` (n_constraints, n_points) of kind ``name`` for contact points in
    the flat cells ``cells`` (n_points,)."""
    return CONTACT_CONSTRAINTS[name](np.asarray(cells))


def _every_point(cells: np.ndarray) -> sp.csr_matrix:
    return sp.identity(len(cells), format="csr")


def _cell_average(cells: np.ndarray) -> sp.csr_matrix:
    _, group = np.unique(cells, return_inverse=True)
    counts = np.bincount(group)
    return sp.csr_matrix((1.0 / counts[group], (group, np.arange(len(cells)))),
                         shape=(len(counts), len(cells)))


register_contact_constraint("points", _every_point)
register_contact_constraint("cell_average", _cell_average)
