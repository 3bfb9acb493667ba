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
* ``elastic``: every contact point is tied to the face by a spring of stiffness
  ``k = beta E A / h`` N/mm (``beta`` = ``[tracker] contact_stiffness``, E the Young's
  modulus of the point's cell in MPa, A the skin area the point stands for in mm^2, h the
  grid's cell size in mm): the discrete form of the penalty ``int beta E / h |u - g|^2 dA``
  over the contact surface. A coarse trilinear cell is not forced to follow every point
  exactly, so it does not drag the tissue beside the face with it; as h shrinks the springs
  stiffen and the points are met (docs/contact.md, "Elastic contact").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class ContactKind:
    """A ``[tracker] fem_contact``: ``rows(cells) -> A`` (n_constraints, n_points) for the
    contact points' flat cell ids ``cells`` (n_points,); ``elastic``: the rows are single
    points tied by springs (``point_stiffness``) instead of met."""

    rows: Callable[[np.ndarray], sp.csr_matrix]
    elastic: bool = False


CONTACT_CONSTRAINTS: dict[str, ContactKind] = {}


def register_contact_constraint(name: str, rows: Callable[[np.ndarray], sp.csr_matrix],
                                elastic: bool = False) -> None:
    """Make ``name`` a ``[tracker] fem_contact``: ``rows(cells) -> A`` (n_constraints,
    n_points) for the contact points' flat cell ids ``cells`` (n_points,); ``elastic``: each
    row is one point, tied to its target by a spring instead of met."""
    CONTACT_CONSTRAINTS[name] = ContactKind(rows, elastic)


def contact_constraint_names() -> tuple[str, ...]:
    """The registered kinds: the allowed ``[tracker] fem_contact`` values."""
    return tuple(CONTACT_CONSTRAINTS)


def constraint_rows(name: str, cells: np.ndarray) -> sp.csr_matrix:
    """Constraint rows ``A`` (n_constraints, n_points) of kind ``name`` for contact points in
    the flat cells ``cells`` (n_points,)."""
    return CONTACT_CONSTRAINTS[name].rows(np.asarray(cells))


def is_elastic(name: str) -> bool:
    """Whether the kind ``name`` ties the points by springs (see ``point_stiffness``)."""
    return CONTACT_CONSTRAINTS[name].elastic


def contact_springs(name: str, beta: float, e_mpa: np.ndarray, grid, cells: np.ndarray,
                    areas: np.ndarray) -> np.ndarray | None:
    """Spring stiffness (n_points,) N/mm of contact points in the flat cells ``cells``
    (n_points,) of ``grid`` standing for skin areas ``areas`` (n_points,) mm^2, for the FE
    model's element moduli ``e_mpa`` (n_elements,) MPa, when the kind ``name`` is elastic;
    None when its points are met."""
    if not is_elastic(name):
        return None
    return grid_springs(beta, e_mpa, grid, cells, areas)


def grid_springs(beta: float, e_mpa: np.ndarray, grid, cells: np.ndarray,
                 areas: np.ndarray) -> np.ndarray:
    """Spring stiffness (n_points,) N/mm of elastic contact for points in the flat cells
    ``cells`` (n_points,) of ``grid`` standing for skin areas ``areas`` (n_points,) mm^2, with
    the element moduli ``e_mpa`` (n_elements,) MPa of that grid's FE model."""
    return point_stiffness(beta, e_mpa[grid.element_of_cells(cells)], areas, grid.spacing)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Skin area (n_vertices,) mm^2 each vertex of a triangle surface stands for: a third of
    the area of every triangle around it."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                               axis=1)
    areas = np.zeros(len(v))
    np.add.at(areas, f.ravel(), np.repeat(tri / 3.0, 3))
    return areas


def point_stiffness(beta: float, e_mpa: np.ndarray, areas: np.ndarray,
                    cell_size_mm: float) -> np.ndarray:
    """Spring stiffness (n_points,) N/mm of elastic contact: ``beta E A / h`` for the Young's
    moduli ``e_mpa`` (n_points,) MPa of the points' cells, their skin areas ``areas``
    (n_points,) mm^2 and the cell size ``h`` mm. Points standing for no area (a vertex of
    no triangle) get a thousandth of the mean, so that every spring holds."""
    k = beta * np.asarray(e_mpa, dtype=np.float64) * np.asarray(areas) / cell_size_mm
    floor = 1e-3 * float(k.mean()) if len(k) else 0.0
    return np.maximum(k, floor) if floor > 0.0 else k


def _every_point(cells: np.ndarray) -> sp.csr_matrix:
    return sp.identity(len(cells), format="csr")


def _cell_average(cells: np.ndarray) -> sp.csr_matrix:
    _, group = np.unique(cells, return_inverse=True)
    counts = np.bincount(group)
    return sp.csr_matrix((1.0 / counts[group], (group, np.arange(len(cells)))),
                         shape=(len(counts), len(cells)))


register_contact_constraint("points", _every_point)
register_contact_constraint("cell_average", _cell_average)
register_contact_constraint("elastic", _every_point, elastic=True)
