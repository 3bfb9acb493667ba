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
    """A probe face: ``size_mm`` (long, short), ``inside(xy) -> bool (n,)`` for points
    ``xy`` (n, 2) mm in the face frame and, where the shape provides it, ``nearest(xy) ->
    (n, 2)`` mm, the nearest point of the filled shape (``xy`` itself inside; the P2
    reference's rounded probe body needs it). Every shape lies within its bounding
    rectangle."""

    name: str
    size_mm: tuple[float, float]
    inside: Callable[[np.ndarray], np.ndarray]
    nearest: Callable[[np.ndarray], np.ndarray] | None = None

    @property
    def half_mm(self) -> np.ndarray:
        """Half-sizes (2,) of the bounding rectangle, mm."""
        return 0.5 * np.asarray(self.size_mm, dtype=np.float64)

    def rounded_core(self, radius_mm: float) -> Footprint:
        """This shape shrunk by ``radius_mm`` on every side: the flat part of a face whose
        edges are rounded by that radius. ValueError unless 0 < radius < half the short
        side, or when the shape gives no ``nearest`` point (a rounded body needs it)."""
        size = np.asarray(self.size_mm, dtype=np.float64)
        if not 0.0 < radius_mm < 0.5 * size.min():
            raise ValueError(f"a probe edge radius of {radius_mm:g} mm does not fit a "
                             f"{size[0]:g} x {size[1]:g} mm face "
                             f"(0 < radius < {0.5 * size.min():g})")
        if self.nearest is None:
            raise ValueError(f"the probe shape {self.name!r} gives no nearest point: it "
                             "cannot have rounded edges")
        return make_footprint(self.name, tuple(size - 2.0 * radius_mm))

    def inside_by(self, xy: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """Which points ``xy`` (m, 2) mm lie inside the shape by at least ``margin`` (m,)
        mm along both face axes (the point moved by its margin either way stays inside)."""
        xy = np.asarray(xy, dtype=np.float64)
        margin = np.asarray(margin, dtype=np.float64)[:, None]
        inside = self.inside(xy)
        for axis in np.eye(2):
            shift = margin * axis
            inside &= self.inside(xy + shift) & self.inside(xy - shift)
        return inside

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
    return Footprint("rectangle", size, lambda xy: np.all(np.abs(xy) <= half, axis=1),
                     lambda xy: np.clip(xy, -half, half))


def _ellipse(size: tuple[float, float]) -> Footprint:
    half = 0.5 * np.asarray(size)
    return Footprint("ellipse", size, lambda xy: np.sum((xy / half) ** 2, axis=1) <= 1.0,
                     lambda xy: _nearest_on_ellipse(np.asarray(xy, dtype=np.float64), half))


def _nearest_on_ellipse(xy: np.ndarray, half: np.ndarray, iterations: int = 60) -> np.ndarray:
    """The nearest point (n, 2) mm of the filled ellipse of semi-axes ``half`` (2,) mm to
    ``xy`` (n, 2) mm: ``xy`` inside; outside, ``half^2 p / (t + half^2)`` with ``t > 0`` the
    root of ``sum((half p / (t + half^2))^2) = 1`` (p = |xy|, found by bisection; the sign
    of ``xy`` put back)."""
    p, a2 = np.abs(xy), half ** 2
    outside = np.sum((xy / half) ** 2, axis=1) > 1.0
    lo = np.zeros(len(xy))
    hi = np.max(half * p, axis=1) + 1.0  # at t >= max(half p) the sum is below 1
    for _ in range(iterations):
        t = 0.5 * (lo + hi)
        big = np.sum((half * p / (t[:, None] + a2)) ** 2, axis=1) > 1.0
        lo, hi = np.where(big, t, lo), np.where(big, hi, t)
    t = 0.5 * (lo + hi)
    on_edge = np.sign(xy) * a2 * p / (t[:, None] + a2)
    return np.where(outside[:, None], on_edge, xy)


register_footprint("rectangle", _rectangle)
register_footprint("ellipse", _ellipse)


def as_footprint(value) -> Footprint:
    """A :class:`Footprint` as is; (long, short) sizes in mm as a rectangle."""
    return value if isinstance(value, Footprint) else make_footprint("rectangle", value)
