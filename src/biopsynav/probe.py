"""The probe: its contact patch on the skin and the random pushes of the training protocol.

Paper section 2.3 (Mendizabal, Tagliabue et al. 2019), every number from ``[probe]``:

1. a random skin vertex ``p`` that is not on the chest wall and lies at least
   ``min_chest_distance_mm`` in front of the chest-wall plane (pushes hard against the fixed
   support move almost nothing and often have half a footprint behind the wall);
2. an oriented box centred at ``p``: long axis in the tangent plane at a random angle, short
   axis, and the outward normal ``n_p``; size ``footprint_mm`` (50 x 10) x
   ``2 * depth_tolerance_mm``;
3. the contact points ``P``: skin vertices inside the box whose normal faces the same way
   (``n_i . n_p > 0``, so the far side of a thin region is never selected), chest-wall
   vertices excluded; a draw with fewer than ``min_contact_points`` is redrawn from the same
   random stream;
4. the force direction ``d``: ``-n_p`` tilted by ``alpha`` uniform in
   ``[-max_tilt_deg, max_tilt_deg]`` about a random tangent axis (always into the tissue);
5. the total force ``|F|`` uniform in ``[0, f_max_n]`` (a training sample's ``s f_max_n u^e``,
   ``u`` uniform in ``[0, 1]``, ``e`` = ``train_force_exponent``, ``s`` =
   ``train_force_scale``), shared equally by the points of ``P``:
   ``f_max_n`` is the force of the whole probe, so the load does not depend on the density
   of the skin mesh; nodal forces are ``W_P^T (F / |P|)`` with ``W_P`` the trilinear
   embedding of ``P``.

A training push that goes deeper than ``[probe] max_push_mm`` is, with ``[probe]
too_deep_redraw = "same-place"``, solved again at the same place (centre, angle, tilt) with its
``u`` times a new uniform number (:func:`weaker_push`), until it stays within the limit: each
place keeps its share of the training pushes, and the force that is kept follows the protocol's
distribution cut at that place's depth limit (a uniform draw below a bound that is above the
cut is, given that it falls below the cut, uniform below it).

With ``[probe] rigid_share`` > 0 that share of the samples is a rigid-probe push instead
(docs/dataset.md), interleaved at fixed places (:func:`is_rigid_draw`: any first ``n`` samples
hold ``floor(n * rigid_share)`` of them), so that a data set's training and held-out parts
hold known numbers of each kind. Contact points within ``contact_tolerance_mm`` of the face
plane (the tracker's rest contact), avoiding skin in cells anchored to the chest wall; the
direction tilted within ``rigid_max_tilt_deg``; every contact point moved along it (prescribed,
no force) by a depth uniform in ``[0, max_push_mm]`` (a training push's ``max_push_mm u^e``,
``e`` = ``train_depth_exponent``), shorter where that would press the
tissue in front of the chest wall by more than ``max_chest_compression``
(:func:`deepest_rigid_push`).

With ``[probe] lesion_share`` > 0 that share of the samples is centred near a lesion instead
of anywhere (:func:`lesion_for_sample`, :func:`centres_near_lesion`): the biopsy probe sits
over the lesion, and pushes there move the lesions most, which uniform centres on the whole
skin rarely do.

Random numbers: one ``numpy.random.Generator`` per draw, seeded by
``SeedSequence([seed, draw_index, attempt])``, so a sample never depends on which worker
made it, in which order, or how many draws other samples needed. The draw index is the
sample's index in a data set of one kind; in a data set of both (:func:`draw_index`) a rigid
push's is its number among the rigid pushes, so that its ``k``-th rigid push is the ``k``-th
push of a data set of rigid pushes alone (the same seed), and a force patch's its number
among the force patches plus :data:`PATCH_DRAWS` (draws of their own).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from .anatomy.model import Anatomy
from .config import ProbeSection
from .errors import InputError
from .footprint import Footprint, as_footprint

#: A contact point must have ``n_i . n_p`` above this (faces the probe, not away from it).
MIN_NORMAL_COSINE = 0.0
#: Redraws of centre and angle before giving up on a patch with enough contact points.
MAX_PATCH_DRAWS = 200


@dataclass
class ProbePush:
    """One random probe push.

    Attributes:
        vertex: index of the centre skin vertex ``p``.
        center: (3,) its position, mm.  normal: (3,) its outward unit normal.
        long_axis, short_axis: (3,) unit vectors of the footprint in the tangent plane.
        contact: (n,) indices of the skin vertices in contact (the set ``P``).
        direction: (3,) unit force direction (into the tissue).
        tilt_deg: signed tilt of ``direction`` away from ``-normal``, degrees.
        force_n: total probe force, N (0 for a rigid push).
        attempt: which draw of this sample index it is (0 first; a failed solve moves on).
        push_mm: a rigid push (``[probe] rigid_share``): the contact points move by
            ``push_mm * direction``, mm; 0 for a force patch.
    """

    vertex: int
    center: np.ndarray
    normal: np.ndarray
    long_axis: np.ndarray
    short_axis: np.ndarray
    contact: np.ndarray
    direction: np.ndarray
    tilt_deg: float
    force_n: float
    attempt: int = 0
    push_mm: float = 0.0

    @property
    def rigid(self) -> bool:
        """Whether the face is pushed rigidly (prescribed displacement), not by a force."""
        return self.push_mm > 0.0

    @property
    def displacement(self) -> np.ndarray:
        """(3,) prescribed displacement of every contact point of a rigid push, mm."""
        return self.push_mm * self.direction

    @property
    def force(self) -> np.ndarray:
        """(3,) total force vector, N."""
        return self.force_n * self.direction

    @property
    def n_contact(self) -> int:
        return int(len(self.contact))


def tangent_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed right-handed orthonormal pair ``(e1, e2)`` spanning the plane normal to
    ``normal`` (3,): ``e1`` is the world axis least aligned with the normal, projected."""
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    ref = np.eye(3)[int(np.argmin(np.abs(normal)))]
    e1 = ref - (ref @ normal) * normal
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def probe_frame(normal: np.ndarray, angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Long and short unit axes (3,) of a footprint on the plane normal to ``normal``: the long
    axis is :func:`tangent_basis`'s ``e1`` rotated by ``angle_rad`` about the normal; the short
    axis is ``normal x long`` (right-handed frame long, short, normal)."""
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    e1, e2 = tangent_basis(normal)
    long_axis = np.cos(angle_rad) * e1 + np.sin(angle_rad) * e2
    return long_axis, np.cross(normal, long_axis)


def probe_patch(anatomy: Anatomy, center_index: int, long_axis: np.ndarray,
                footprint: Footprint | tuple[float, float] | list[float],
                depth_tol: float) -> np.ndarray:
    """Indices (n,) of the skin vertices under a probe centred on vertex ``center_index``.

    The probe frame: ``long_axis`` (3,) (made orthogonal to the centre's outward normal
    ``n_p``), the short axis ``n_p x long``, and ``n_p``. Kept: vertices under the
    ``footprint`` (a :class:`~biopsynav.footprint.Footprint`, or (long, short) mm: a
    rectangle) within ``depth_tol`` (mm) along ``n_p``, not on the chest wall, with
    ``n_i . n_p > MIN_NORMAL_COSINE``. Sorted ascending.
    """
    normal = anatomy.normals[center_index] / np.linalg.norm(anatomy.normals[center_index])
    long_axis = np.asarray(long_axis, dtype=np.float64)
    long_axis = long_axis - (long_axis @ normal) * normal
    long_axis /= np.linalg.norm(long_axis)
    short_axis = np.cross(normal, long_axis)
    axes = np.stack([long_axis, short_axis, normal], axis=1)
    return skin_under_face(anatomy, anatomy.vertices[center_index], axes,
                           as_footprint(footprint), depth_tol, normal)


def skin_under_face(anatomy: Anatomy, centre: np.ndarray, axes: np.ndarray,
                    footprint: Footprint, depth_tol: float, facing: np.ndarray) -> np.ndarray:
    """Indices (n,) of skin vertices off the chest wall under a probe face, with outward
    normals along ``facing`` (n_i . facing > MIN_NORMAL_COSINE). ``centre`` (3,) mm, ``axes``
    (3, 3) the probe frame's axes as columns (long, short, face normal), ``footprint`` the
    face's shape, ``depth_tol`` mm along the third axis."""
    local = (anatomy.vertices - centre) @ axes
    inside = (footprint.covers(local, depth_tol)
              & (anatomy.normals @ facing > MIN_NORMAL_COSINE)
              & anatomy.pushable)
    return np.flatnonzero(inside)


def eligible_centers(anatomy: Anatomy, min_chest_distance_mm: float) -> np.ndarray:
    """Indices of skin vertices that may centre a push: off the chest wall and crop faces and
    at least ``min_chest_distance_mm`` in front of the wall (:meth:`Anatomy.chest_depth`)."""
    depth = anatomy.chest_depth(anatomy.vertices)
    ok = anatomy.pushable & (depth >= min_chest_distance_mm)
    found = np.flatnonzero(ok)
    if found.size == 0:
        raise InputError(f"no skin vertex lies {min_chest_distance_mm:g} mm or more in front "
                         "of the chest wall", "[probe] min_chest_distance_mm")
    return found


def tilted_direction(normal: np.ndarray, tilt_rad: float, axis_angle_rad: float) -> np.ndarray:
    """``-normal`` rotated by ``tilt_rad`` about the tangent axis at ``axis_angle_rad`` in the
    plane of :func:`tangent_basis`; a unit vector (3,) with ``d . normal = -cos(tilt)``."""
    e1, e2 = tangent_basis(normal)
    axis = np.cos(axis_angle_rad) * e1 + np.sin(axis_angle_rad) * e2
    inward = -np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    # Rodrigues with axis orthogonal to the rotated vector
    return np.cos(tilt_rad) * inward + np.sin(tilt_rad) * np.cross(axis, inward)


def sample_rng(seed: int, index: int, attempt: int) -> np.random.Generator:
    """The generator of one draw: ``SeedSequence([seed, index, attempt])``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index), int(attempt)]))


def draw_push(anatomy: Anatomy, probe: ProbeSection, rng: np.random.Generator,
              centers: np.ndarray | None = None, attempt: int = 0,
              rigid: bool = False, pinned: np.ndarray | None = None,
              force_exponent: float = 1.0, force_scale: float = 1.0,
              depth_exponent: float = 1.0) -> ProbePush:
    """One random push following the protocol (module docstring); ``rigid``: a rigid-probe
    push instead (contact within ``contact_tolerance_mm`` of the face, tilt within
    ``rigid_max_tilt_deg``, a depth ``deepest_rigid_push u^depth_exponent`` (``u`` uniform in
    [0, 1]; 1: uniform) instead of the force; a
    patch holding a ``pinned`` skin vertex (:func:`pinned_skin`) is redrawn).

    ``centers``: the eligible centre vertices (:func:`eligible_centers`, precomputed by
    callers that draw many). The draw order (centre, in-plane angle, then tilt axis, tilt,
    force or depth) is part of the protocol: changing it changes every sample.
    ``force_exponent``, ``force_scale``: the force (N) is ``force_scale f_max_n
    u^force_exponent`` (1, 1: uniform in ``[0, f_max_n]``; the same random numbers whatever
    they are, so the patch and tilt do not depend on them).
    """
    if centers is None:
        centers = eligible_centers(anatomy, probe.min_chest_distance_mm)
    tol = probe.contact_tolerance_mm if rigid else probe.depth_tolerance_mm
    for _ in range(MAX_PATCH_DRAWS):
        vertex = int(centers[rng.integers(len(centers))])
        angle = rng.uniform(0.0, np.pi)  # a footprint is symmetric under a half turn
        normal = anatomy.normals[vertex] / np.linalg.norm(anatomy.normals[vertex])
        long_axis, short_axis = probe_frame(normal, angle)
        contact = probe_patch(anatomy, vertex, long_axis, probe.footprint, tol)
        if rigid and pinned is not None and pinned[contact].any():
            continue
        if len(contact) >= probe.min_contact_points:
            break
    else:
        raise InputError(f"no probe patch with {probe.min_contact_points} or more skin vertices "
                         f"in {MAX_PATCH_DRAWS} draws; the skin mesh is too coarse for the "
                         "footprint" + (" (a rigid push also avoids skin in grid cells anchored "
                                        "to the chest wall)" if rigid else ""),
                         "[probe] min_contact_points")
    axis_angle = rng.uniform(0.0, 2.0 * np.pi)
    max_tilt = probe.rigid_max_tilt_deg if rigid else probe.max_tilt_deg
    tilt = np.radians(rng.uniform(-max_tilt, max_tilt))
    direction = tilted_direction(normal, tilt, axis_angle)
    amount = float(deepest_rigid_push(anatomy, probe, contact, direction)
                   * rng.uniform(0.0, 1.0) ** depth_exponent if rigid else
                   force_scale * probe.f_max_n * rng.uniform(0.0, 1.0) ** force_exponent)
    return ProbePush(vertex, anatomy.vertices[vertex].copy(), normal, long_axis, short_axis,
                     contact, direction,
                     float(np.degrees(tilt)), 0.0 if rigid else amount, attempt,
                     amount if rigid else 0.0)


def chest_distance(anatomy: Anatomy, contact: np.ndarray) -> float:
    """The tissue in front of the chest wall under a probe face (mm): the median chest-wall
    distance (:meth:`Anatomy.chest_depth`) of the skin vertices ``contact`` (indices) it holds."""
    return float(np.median(anatomy.chest_depth(anatomy.vertices[np.asarray(contact)])))


def towards_chest(anatomy: Anatomy, motion: np.ndarray) -> float:
    """The part (mm) of a probe ``motion`` (3,) mm that goes towards the chest wall (along
    its plane's unit normal, as :meth:`Anatomy.chest_depth` measures; 0 for motion away from
    it or along it)."""
    return max(float(np.asarray(motion) @ anatomy.chest_normal), 0.0)


def deepest_rigid_push(anatomy: Anatomy, probe: ProbeSection, contact: np.ndarray,
                       direction: np.ndarray) -> float:
    """The deepest rigid push (mm) along the unit ``direction`` (3,) of the face holding skin
    ``contact``: ``max_push_mm``, and with ``max_chest_compression`` > 0 no deeper than moves
    the face towards the chest wall by that share of :func:`chest_distance`."""
    towards = towards_chest(anatomy, direction)
    if probe.max_chest_compression <= 0.0 or towards <= 0.0:
        return float(probe.max_push_mm)
    allowed = probe.max_chest_compression * max(chest_distance(anatomy, contact), 0.0)
    return min(float(probe.max_push_mm), allowed / towards)


def is_rigid_sample(probe: ProbeSection, index: int) -> bool:
    """Whether sample ``index`` is a rigid-probe push (``[probe] rigid_share``): fixed by its
    place, whatever its attempt, so failed rigid draws are redrawn as rigid ones."""
    return is_rigid_draw(probe.rigid_share, index)


def both_kinds(rigid_share: float) -> bool:
    """Whether a data set of ``rigid_share`` (0-1) holds both kinds of sample: rigid pushes and
    force patches."""
    return 0.0 < rigid_share < 1.0


def rigid_count(rigid_share: float, n: int) -> int:
    """How many of a data set's first ``n`` samples are rigid pushes: ``floor(n *
    rigid_share)`` (``rigid_share``: the share of rigid pushes, 0-1)."""
    if rigid_share <= 0.0:
        return 0
    if rigid_share >= 1.0:
        return int(n)
    return int(np.floor(int(n) * rigid_share + 1e-9))  # 0.55 * 20 is 11, not 10.999...


def is_rigid_draw(rigid_share: float, index: int) -> bool:
    """Whether sample ``index`` of a data set with ``rigid_share`` (0-1) is a rigid push: the
    samples where :func:`rigid_count` steps up, spread evenly over the data set."""
    return rigid_count(rigid_share, index + 1) > rigid_count(rigid_share, index)


#: Where a force patch's draw indices start in a data set of both kinds (:func:`draw_index`):
#: far from the rigid pushes', whose random streams they would otherwise share.
PATCH_DRAWS = 2 ** 36


def draw_index(rigid_share: float, index: int) -> int:
    """The index that seeds sample ``index``'s random streams: ``index`` itself in a data set
    of one kind; in one of both, a rigid push's number among the rigid pushes, a force
    patch's number among the force patches plus :data:`PATCH_DRAWS`."""
    if not both_kinds(rigid_share):
        return int(index)
    before = rigid_count(rigid_share, index)
    if rigid_count(rigid_share, index + 1) > before:  # a rigid push (is_rigid_draw)
        return before
    return PATCH_DRAWS + int(index) - before


#: The stream that decides whether a sample is centred near a lesion, and which
#: (``SeedSequence([seed, index, 0, LESION_STREAM])``): apart from the draws themselves, so the
#: pushes of ``lesion_share = 0`` are unchanged.
LESION_STREAM = 13


def check_lesion_share(anatomy: Anatomy, probe: ProbeSection) -> None:
    """InputError when ``[probe] lesion_share`` asks for pushes near lesions of a case that has
    none (they would silently be centred anywhere)."""
    if probe.lesion_share > 0.0 and not anatomy.lesions:
        raise InputError(f"lesion_share = {probe.lesion_share:g} centres pushes near lesions, "
                         "but the case has no lesions; set it to 0", "[probe] lesion_share")


def lesion_for_sample(anatomy: Anatomy, probe: ProbeSection, seed: int, index: int
                      ) -> int | None:
    """The lesion (index into ``anatomy.lesions``) near which draw ``index`` is centred
    (``[probe] lesion_share``, each lesion alike), None when it is centred anywhere; decided
    once per sample, whatever its attempt."""
    if probe.lesion_share <= 0.0 or not anatomy.lesions:
        return None
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 0,
                                                        LESION_STREAM]))
    near = rng.uniform() < probe.lesion_share
    lesion = int(rng.integers(len(anatomy.lesions)))
    return lesion if near else None


def centres_near_lesion(anatomy: Anatomy, centers: np.ndarray, lesion: int,
                        reach_mm: float) -> np.ndarray:
    """The eligible centre vertices ``centers`` within ``reach_mm`` (mm) of the pushable skin
    vertex nearest lesion ``lesion``'s centre; the nearest one alone when none is."""
    nearest = anatomy.vertices[anatomy.nearest_pushable_vertex(anatomy.lesions[lesion].center)]
    dist = np.linalg.norm(anatomy.vertices[centers] - nearest, axis=1)
    near = centers[dist <= reach_mm]
    return near if near.size else centers[[int(np.argmin(dist))]]


def push_for_sample(anatomy: Anatomy, probe: ProbeSection, seed: int, index: int,
                    attempt: int, centers: np.ndarray | None = None,
                    pinned: np.ndarray | None = None, training: bool = False) -> ProbePush:
    """The push of data-set sample ``index``, draw ``attempt`` (deterministic): its kind from
    :func:`is_rigid_sample`, its random streams from :func:`draw_index`; the rest as
    :func:`push_for_draw`."""
    return push_for_draw(anatomy, probe, seed, draw_index(probe.rigid_share, index), attempt,
                         centers, is_rigid_sample(probe, index), pinned, training)


def push_for_draw(anatomy: Anatomy, probe: ProbeSection, seed: int, index: int, attempt: int,
                  centers: np.ndarray | None = None, rigid: bool = False,
                  pinned: np.ndarray | None = None, training: bool = False) -> ProbePush:
    """The push of draw index ``index`` (:func:`draw_index`), draw ``attempt``
    (deterministic); ``rigid``: a rigid push, else a force patch; ``pinned``: see
    :func:`draw_push`; ``training``: a training sample, whose force follows ``[probe]
    train_force_exponent`` and ``train_force_scale`` and whose rigid depth
    ``train_depth_exponent``. A draw :func:`lesion_for_sample` puts
    near a lesion is centred among :func:`centres_near_lesion`, or anywhere when no patch
    there can be drawn."""
    if centers is None:
        centers = eligible_centers(anatomy, probe.min_chest_distance_mm)
    exponent, scale, depth_exponent = (
        (probe.train_force_exponent, probe.train_force_scale, probe.train_depth_exponent)
        if training else (1.0, 1.0, 1.0))
    lesion = lesion_for_sample(anatomy, probe, seed, index)
    if lesion is not None:
        near = centres_near_lesion(anatomy, centers, lesion, probe.lesion_reach_mm)
        try:
            return draw_push(anatomy, probe, sample_rng(seed, index, attempt), near, attempt,
                             rigid, pinned, exponent, scale, depth_exponent)
        except InputError:  # every patch near it holds pinned skin or too few points
            pass
    return draw_push(anatomy, probe, sample_rng(seed, index, attempt), centers, attempt, rigid,
                     pinned, exponent, scale, depth_exponent)


#: The stream of a training push's same-place redraws
#: (``SeedSequence([seed, index, attempt, WEAKER_FORCE_STREAM, redraw])``).
WEAKER_FORCE_STREAM = 11


def weaker_push(push: ProbePush, probe: ProbeSection, seed: int, index: int, redraw: int
                ) -> ProbePush:
    """Redraw ``redraw`` (1, 2, ...) of sample ``index``'s too-deep training ``push``: the same
    place and direction, its force (N) times ``v^train_force_exponent``, ``v`` uniform in
    [0, 1] (its ``u`` times ``v``; module docstring)."""
    draw = draw_index(probe.rigid_share, index)
    stream = [int(seed), draw, int(push.attempt), WEAKER_FORCE_STREAM, int(redraw)]
    v = np.random.default_rng(np.random.SeedSequence(stream)).uniform(0.0, 1.0)
    return replace(push, force_n=push.force_n * v ** probe.train_force_exponent)


def pinned_skin(fixed_nodes: np.ndarray, skin_nodes: np.ndarray) -> np.ndarray:
    """(n_vertices,) bool: skin vertices in a grid cell with a fixed node. A rigid face holding
    one would drag a cell anchored to the chest wall, which inverts it; rigid training pushes
    avoid them. ``fixed_nodes`` the grid's fixed-node mask, ``skin_nodes`` (n_vertices, 8) the
    flat nodes of each skin vertex's cell (:class:`~biopsynav.grid.embedding.Embedding`)."""
    return np.asarray(fixed_nodes, dtype=bool).ravel()[skin_nodes].any(axis=1)


def nodal_forces(contact_matrix: sp.csr_matrix, force: np.ndarray) -> np.ndarray:
    """Node forces (n_nodes, 3), N: the total ``force`` (3,) shared equally by the contact
    points (rows of ``contact_matrix`` ``W_P``, (n, n_nodes)) and spread with ``W_P^T``."""
    n = contact_matrix.shape[0]
    per_point = np.broadcast_to(np.asarray(force, dtype=np.float64) / n, (n, 3))
    return np.asarray(contact_matrix.T @ np.ascontiguousarray(per_point))


#: Regularisation of the elastic contact input, relative to the mean diagonal of ``A^T A``
#: (1e-6 left 0.6 % misfit of the point displacements on the coarse phantom; 1e-8 fits to
#: 0.1 %, and its Table 1 baseline error is within 6 % of hard constraints on the true nodal
#: displacement):
#: picks the least-energy nodal forces where the contact points do not determine them.
ELASTIC_REGULARISATION = 1e-8
CONTACT_INPUTS = ("elastic", "average")


@dataclass
class ContactInputOperator:
    """The network input as a linear map of the contact-point displacements, for one contact
    set (rows of ``contact_matrix``): see :func:`contact_input_operator`.

    Attributes:
        weights: (n_nodes,) weight sums ``W_P^T 1`` (input channel 3).
        positions: (q,) channel-major flat positions (``component * n_nodes + node``) of the
            input values that depend on the contact displacement.
        matrix: (q, 3 n) dense map from the point-major flat contact displacement
            ``contact_u.ravel()`` (mm) to those values (mm).
    """

    weights: np.ndarray
    positions: np.ndarray
    matrix: np.ndarray

    def field(self, contact_u: np.ndarray) -> np.ndarray:
        """The input node field (n_nodes, 4) for contact displacements (n, 3) mm."""
        n_nodes = self.weights.shape[0]
        values = np.zeros(3 * n_nodes)
        values[self.positions] = self.matrix @ np.asarray(contact_u, dtype=np.float64).ravel()
        return np.hstack([values.reshape(3, n_nodes).T, self.weights[:, None]])

    def rows_at(self, positions: np.ndarray) -> np.ndarray:
        """The row of :attr:`matrix` that writes each channel-major flat input position
        (k,), or -1 where the operator writes none."""
        row_of = np.full(3 * self.weights.shape[0], -1, dtype=np.int64)
        row_of[self.positions] = np.arange(len(self.positions))
        return row_of[positions]


def contact_input_operator(contact_matrix: sp.csr_matrix, kind: str = "elastic",
                           compliance=None, springs: np.ndarray | None = None
                           ) -> ContactInputOperator:
    """How the contact displacement becomes the network input (channels 0-2; channel 3 is the
    weight sum ``w = W_P^T 1``), for the contact points of ``contact_matrix`` ``W_P`` (n,
    n_nodes), on the nodes ``c`` of the cells that hold them (``w > 0``); zero elsewhere.

    ``kind = "elastic"`` (default; needs ``compliance``, a
    :class:`~biopsynav.contact.greens.ContactCompliance`): the nodal values ``U_c = Z_cc f`` of
    the linear-elastic field that moves the points as given, ``W_P U = u_P``, with forces
    ``f`` on the contact nodes only: least squares ``min |W_P Z_cc f - u_P|`` regularised by
    the energy ``f^T Z_cc f`` (:data:`ELASTIC_REGULARISATION`) where the points leave ``f``
    undetermined. The point forces are spread to the nodes with the trilinear weights
    (``f = W_P^T f_P`` at the least-squares optimum), and a hard linear-elastic response to
    ``U_c`` reproduces the point-constrained linear solution exactly.

    With ``springs`` (n,) N/mm (elastic contact, :mod:`biopsynav.contact.constraints`) the
    points are tied to their displacements by springs instead: ``f`` minimises the linear
    system's potential ``f^T Z_cc f / 2 + |W_P Z_cc f - u_P|^2_k / 2``, that is
    ``(A^T k A + Z_cc) f = A^T k u_P`` with ``A = W_P Z_cc``: the linear-elastic field of the
    teacher's contact, whose points lag as its springs let them.

    ``kind = "average"``: the trilinear-weighted average ``(W_P^T u_P) / w`` (first version;
    a node in the far corner of a contact cell gets the mean of points that are not near it).
    """
    n_nodes = contact_matrix.shape[1]
    weights = np.asarray(contact_matrix.sum(axis=0), dtype=np.float64).ravel()
    nodes = np.flatnonzero(weights > 0)
    n_pts = contact_matrix.shape[0]
    if kind == "average":
        spread = contact_matrix[:, nodes].T.toarray() / weights[nodes][:, None]  # (n_c, n)
        # value (axis, node) from point-major u_P: spread on the same axis only
        matrix = np.einsum("ac,jp->ajpc", np.eye(3), spread).reshape(3 * len(nodes), 3 * n_pts)
        positions = (np.arange(3)[:, None] * n_nodes + nodes[None, :]).ravel()
        return ContactInputOperator(weights, positions, matrix)
    if kind != "elastic":
        raise InputError(f"unknown contact input {kind!r}; use {' or '.join(CONTACT_INPUTS)}",
                         "[dataset] contact_input")
    if compliance is None:
        raise InputError("the elastic contact input needs the case's contact compliance",
                         "contact input")
    rows, local = compliance.contact_dofs(nodes)
    k = len(rows)
    dense = contact_matrix[:, nodes].toarray()  # (n, n_c)
    a3 = np.zeros((n_pts, 3, k))  # point p, axis c -> its trilinear weights on the dofs
    for axis in range(3):  # three axes, not a loop over points or nodes
        free = local[:, axis] >= 0
        a3[:, axis, local[free, axis]] = dense[:, free]
    a3 = a3.reshape(3 * n_pts, k)
    zcc = compliance.block(rows)
    a = a3 @ zcc  # point displacements per unit nodal force
    matrix = zcc @ _fitted_forces(a, zcc, springs)
    free_nodes, free_axes = np.nonzero(local >= 0)
    positions = free_axes * n_nodes + nodes[free_nodes]
    order = local[free_nodes, free_axes]
    return ContactInputOperator(weights, positions, matrix[order])


def _fitted_forces(a: np.ndarray, zcc: np.ndarray, springs: np.ndarray | None) -> np.ndarray:
    """Nodal forces (k, 3n) per point-major point displacement: the regularised least-squares
    fit of the points (``a`` (3n, k) mm/N, ``zcc`` (k, k) mm/N), or with ``springs`` (n,)
    N/mm the minimum of the potential with the points on springs."""
    if springs is None:
        normal = a.T @ a
        reg = ELASTIC_REGULARISATION * max(float(np.trace(normal)) / max(len(zcc), 1), 1e-300)
        return scipy.linalg.solve(normal + reg * zcc, a.T, assume_a="pos")
    ka = np.repeat(np.asarray(springs, dtype=np.float64), 3)[:, None] * a  # point-major rows
    return scipy.linalg.solve(a.T @ ka + zcc, ka.T, assume_a="pos")


def contact_input(contact_matrix: sp.csr_matrix, contact_u: np.ndarray, kind: str = "elastic",
                  compliance=None, springs: np.ndarray | None = None) -> np.ndarray:
    """The network input as a node field (n_nodes, 4): channels 0-2 the contact displacement
    ``contact_u`` (n, 3) mm on the contact nodes (:func:`contact_input_operator`, with the
    points on ``springs`` (n,) N/mm when given), channel 3 the weight sum ``W_P^T 1``."""
    return contact_input_operator(contact_matrix, kind, compliance, springs).field(contact_u)


__all__ = ["CONTACT_INPUTS", "ContactInputOperator", "ELASTIC_REGULARISATION",
           "MIN_NORMAL_COSINE", "ProbePush", "centres_near_lesion", "check_lesion_share",
           "contact_input", "contact_input_operator", "draw_push", "eligible_centers",
           "PATCH_DRAWS", "draw_index", "is_rigid_draw", "is_rigid_sample", "lesion_for_sample",
           "nodal_forces", "pinned_skin", "probe_frame", "probe_patch", "push_for_draw",
           "push_for_sample", "rigid_count", "sample_rng", "skin_under_face",
           "tangent_basis", "tilted_direction"]
