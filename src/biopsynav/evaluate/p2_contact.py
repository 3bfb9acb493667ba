"""The probe of the P2 reference (:mod:`biopsynav.evaluate.p2`) as a contact surface, and the
skin held on it.

Two shapes of the rigid probe, both in the face frame of a pose (x along the long side, y
along the short side, z along the beam into the tissue; mm):

* :class:`FlatFace`: the face plane ``z = 0`` over the footprint, with sharp edges and no
  sides: skin that comes in beside the face is not held;
* :class:`RoundedBody`: the probe's body, a prism over the footprint (its sides parallel to
  the beam) whose edges round the face with a radius: the points within ``radius`` of the
  prism over the footprint shrunk by ``radius``, below ``z = -radius``. Its surface is
  smooth, so skin bends round a curve that quadratic elements can follow; every point of
  skin that enters it, from the face or beside it, is put back on its surface.

A held skin node slides without friction on the plane tangent to the surface at its nearest
point (:class:`Sliding`); the P2 reference finds those planes again after each solve until
the nodes lie on the curved surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

PENETRATION_TOL_MM = 0.1  # skin further inside the probe is put on its surface


@dataclass(frozen=True)
class FlatFace:
    """The probe face as a plane over its ``footprint`` (a
    :class:`~biopsynav.footprint.Footprint`) with sharp edges and no sides."""

    footprint: Any

    def closest(self, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points ``local`` (m, 3) mm in the face frame: the nearest point of the face
        plane (m, 3) mm, its outward normal (m, 3) and the signed distance (m,) mm (negative
        behind the plane)."""
        foot = np.column_stack([local[:, :2], np.zeros(len(local))])
        return foot, np.tile([0.0, 0.0, 1.0], (len(local), 1)), local[:, 2].copy()

    def penetrating(self, local: np.ndarray) -> np.ndarray:
        """Which points ``local`` (m, 3) mm lie more than ``PENETRATION_TOL_MM`` behind the
        face plane, under the footprint and nearer the face than the footprint's edge
        (further behind it than from the edge, the skin came in beside the probe, where its
        side, not its face, would stop it)."""
        depth = -local[:, 2]
        return (depth > PENETRATION_TOL_MM) & self.footprint.inside_by(local[:, :2], depth)

    def slid_off(self, local: np.ndarray) -> np.ndarray:
        """Which held points ``local`` (m, 3) mm slid off the face (out of the footprint)."""
        return ~self.footprint.inside(local[:, :2])


@dataclass(frozen=True)
class RoundedBody:
    """The probe's body: the prism over ``footprint`` with its face's edges rounded by
    ``radius_mm`` (the face flat over the footprint shrunk by the radius, then curving back
    to the sides). ``core`` is that shrunk footprint (:func:`rounded_body`)."""

    footprint: Any
    core: Any
    radius_mm: float

    def closest(self, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points ``local`` (m, 3) mm in the face frame: the nearest point of the body's
        surface (m, 3) mm, its outward normal (m, 3) and the signed distance (m,) mm
        (negative inside the body). A point more than the radius behind the face's flat
        part goes back through the face, the way the probe passed it."""
        r = self.radius_mm
        axis = np.column_stack([self.core.nearest(local[:, :2]), np.minimum(local[:, 2], -r)])
        off = local - axis
        length = np.linalg.norm(off, axis=1)
        deep = length <= 0.0  # on the axis prism: behind the flat part by the radius or more
        normal = np.where(deep[:, None], [0.0, 0.0, 1.0],
                          off / np.where(deep, 1.0, length)[:, None])
        point = np.where(deep[:, None], local * [1.0, 1.0, 0.0], axis + r * normal)
        return point, normal, np.where(deep, local[:, 2], length - r)

    def penetrating(self, local: np.ndarray) -> np.ndarray:
        """Which points ``local`` (m, 3) mm lie more than ``PENETRATION_TOL_MM`` inside."""
        return self.closest(local)[2] < -PENETRATION_TOL_MM

    def slid_off(self, local: np.ndarray) -> np.ndarray:
        """None: the body's surface has no edge to slide off."""
        return np.zeros(len(local), dtype=bool)


def rounded_body(footprint: Any, radius_mm: float) -> RoundedBody:
    """The :class:`RoundedBody` over ``footprint`` with edges of ``radius_mm``; ValueError
    where the footprint cannot have them (:meth:`~biopsynav.footprint.Footprint.rounded_core`)."""
    return RoundedBody(footprint, footprint.rounded_core(radius_mm), float(radius_mm))


def probe_surface(footprint: Any, radius_mm: float) -> FlatFace | RoundedBody:
    """The probe's contact surface: a :class:`RoundedBody` with edges of ``radius_mm``, the
    :class:`FlatFace` for 0."""
    return rounded_body(footprint, radius_mm) if radius_mm > 0 else FlatFace(footprint)


@dataclass
class Sliding:
    """Skin nodes held on planes, free to slide on them: ``nodes`` (m,), unit plane
    ``normals`` (m, 3) and ``offsets`` (m,) mm, so that a node's displacement ``u`` satisfies
    ``u . normal = offset``."""

    nodes: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @classmethod
    def none(cls) -> Sliding:
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0))

    @classmethod
    def on_surface(cls, nodes: np.ndarray, rest: np.ndarray, where: np.ndarray,
                   face: np.ndarray, surface: FlatFace | RoundedBody,
                   came_from: np.ndarray | None = None) -> Sliding:
        """``nodes`` (m,) at rest at ``rest`` (m, 3) mm, now at ``where`` (m, 3) mm, held
        on the planes tangent to ``surface`` of the probe at pose ``face`` (4, 4): at their
        nearest points or, given where they were in the probe's frame before the probe's
        last move (``came_from``, (m, 3) mm), where they met its surface on the way
        (:func:`meeting_points`)."""
        rot = face[:3, :3]
        local = (where - face[:3, 3]) @ rot
        if came_from is None:
            point, normal, _ = surface.closest(local)
        else:
            point, normal = meeting_points(surface, came_from, local)
        normals = normal @ rot.T
        offsets = np.einsum("mi,mi->m", point @ rot.T + face[:3, 3] - rest, normals)
        return cls(np.asarray(nodes, dtype=np.int64), normals, offsets)

    def lift(self, u: np.ndarray) -> np.ndarray:
        """The move (m, 3) mm along the normals that puts the nodes of ``u`` on the plane."""
        gap = self.offsets - np.einsum("mi,mi->m", u[self.nodes], self.normals)
        return gap[:, None] * self.normals

    def halfway(self, u: np.ndarray) -> Sliding:
        """The same nodes on a plane halfway between where ``u`` has them and this one."""
        now = np.einsum("mi,mi->m", u[self.nodes], self.normals)
        return Sliding(self.nodes, self.normals, 0.5 * (now + self.offsets))


def meeting_points(surface: FlatFace | RoundedBody, came_from: np.ndarray,
                   now: np.ndarray, halvings: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Where points that moved in the probe's frame from ``came_from`` to ``now`` (m, 3)
    mm met ``surface``: the point (m, 3) mm and outward normal (m, 3). A point that entered
    the probe on the way meets it where the segment first crosses the surface (bisection); a
    point already inside at ``came_from`` (held on the surface before) at its nearest point
    from there; one that never entered, or whose ``came_from`` row is NaN, at its nearest
    point from ``now``. A probe that advanced along its beam by more than its edge radius
    so pushes the skin it swept with the face that swept it, not out of the side that is
    nearest now."""
    known = np.isfinite(came_from).all(axis=1)
    came = np.where(known[:, None], came_from, now)
    start = surface.closest(came)[2]
    enters = known & (start >= 0.0) & (surface.closest(now)[2] < 0.0)
    lo, hi = np.zeros(len(now)), np.ones(len(now))
    step = now - came
    for _ in range(halvings):
        mid = 0.5 * (lo + hi)
        outside = surface.closest(came + mid[:, None] * step)[2] >= 0.0
        lo, hi = np.where(outside, mid, lo), np.where(outside, hi, mid)
    at = np.where(enters[:, None], came + hi[:, None] * step,
                  np.where((known & (start < 0.0))[:, None], came, now))
    point, normal, _ = surface.closest(at)
    return point, normal


def in_plane_directions(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (m, 3) each, orthogonal to each other and to ``normals`` (m, 3)."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normals, t1)

