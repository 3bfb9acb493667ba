"""Probe face shapes: one registry (``register_footprint``), used by data generation, the
tracker and ``simulate`` alike.

A :class:`Footprint` is the probe face in its own frame: x along the long side, y along the
short side (the tracker's probe frame, docs/igtl.md), in mm. Skin points count as under the
face when their (x, y) lie inside the shape and they are within a depth tolerance of the face
plane. ``[probe] shape`` names the shape, ``[probe] footprint_mm`` its size (long, short).

Registered: ``rectangle`` (a linear array, 50 x 10 mm by default: the paper's) and ``ellipse``
(the ellipse inscribed in that rectangle: a round or rounded face).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Footprint:
    """A probe face: ``size_mm`` (long, short) and ``inside(xy) -> bool (n,)`` for points
    ``xy`` (n, 2) mm in the face frame. Every shape lies within its bounding rectangle."""

    name: str
    size_mm: tuple[float, float]
    inside: Callable[[np.ndarray], np.ndarray]

    @property
    def half_mm(self) -> np.ndarray:
        """Half-sizes (2,) of the bounding rectangle, mm."""
        return 0.5 * np.asarray(self.size_mm, dtype=np.float64)

    def covers(self, local: np.ndarray, depth_tol: float) -> np.ndarray:
        """Which points ``local`` (n, 3) mm in the probe frame (z along the beam) lie under
        the face: inside the shape and within ``depth_tol`` of the face plane."""
        local = np.asarray(local, dtype=np.float64)
        return (np.abs(local[:, 2]) <= depth_tol) & self.inside(local[:, :2])


FOOTPRINTS: dict[str, Callable[[tuple[float, float]], Footprint]] = {}


def register_footprint(name: str, make: Callable[[tuple[float, float]], Footprint]) -> None:
    """Make ``name`` a ``[probe] shape``: ``make(size_mm) -> Footprint``."""
    FOOTPRINTS[name] = make


def footprint_names() -> tuple[str, ...]:
    """The registered shapes: the allowed ``[probe] shape`` values."""
    return tuple(FOOTPRINTS)


def make_footprint(name: str, size_mm) -> Footprint:
    """The footprint called ``name`` of ``size_mm`` (long, short) mm."""
    return FOOTPRINTS[name]((float(size_mm[0]), float(size_mm[1])))


def _rectangle(size: tuple[float, float]) -> Footprint:
    half = 0.5 * np.asarray(size)
    return Footprint("rectangle", size, lambda xy: np.all(np.abs(xy) <= half, axis=1))


def _ellipse(size: tuple[float, float]) -> Footprint:
    half = 0.5 * np.asarray(size)
    return Footprint("ellipse", size, lambda xy: np.sum((xy / half) ** 2, axis=1) <= 1.0)


register_footprint("rectangle", _rectangle)
register_footprint("ellipse", _ellipse)


def as_footprint(value) -> Footprint:
    """A :class:`Footprint` as is; (long, short) sizes in mm as a rectangle."""
    return value if isinstance(value, Footprint) else make_footprint("rectangle", value)
