"""An independent FE reference for rigid-probe pushes: quadratic (10-node, P2) tetrahedra on a
gmsh tetrahedral mesh of the breast surface, compressible neo-Hookean, Newton on the
displacement.

Nothing is shared with biopsynav's FE: another mesh (tetrahedra fitted to the surface, not an
immersed hexahedral grid), another element (P2 tetrahedra, 14-point degree-5 rule from
scikit-fem, every weight positive: :data:`QUADRATURE_DEGREE`), another formulation (spatial:
Kirchhoff stress ``tau = mu (b - I) + lam ln J I`` and its tangent ``c = lam I x I + 2 (mu -
lam ln J) II``, on spatial shape-function gradients; the biopsynav kernel works in the
reference configuration), its own element kernels (numba,
:mod:`~biopsynav.evaluate.p2_kernels`), assembly and Newton loop (MKL Pardiso for the linear
solves). The boundary conditions: the chest wall fixed (its plane, or a label map's curved
muscle interface as the case grid holds it: :func:`held_by_chest_wall`); the skin the probe face
touches at the rest pose (within the contact tolerance, under the footprint, facing the probe;
:func:`biopsynav.probe.skin_under_face`) moved rigidly with the probe (stuck to it, as the
tracker's contact points); and, given the face's footprint, the probe a rigid body
(:mod:`~biopsynav.evaluate.p2_contact`: a flat face with sharp edges, or a body whose face's
edges are rounded): skin that a load step pushes into the probe is put on its surface where it
met it and slides on it without friction (an active set: grown where skin passes the probe,
let go where the probe would pull, its planes taken again where the surface is curved, within
Newton as well), so that no skin passes through the probe; the rest free. Newton is damped on
the stored energy (line search, and a Levenberg-Marquardt shift where the direction does not
descend). Used by ``benchmarks/convergence.py``, ``benchmarks/truth.py`` and Table 2's ``p2``
reference; needs gmsh.
"""

from __future__ import annotations

import hashlib
import logging
import signal
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from ..materials import lame_constants
from ..probe import skin_under_face
from ..reference_registry import P2_FRICTIONS as FRICTIONS
from .p2_contact import Sliding, in_plane_directions, probe_surface
from .p2_kernels import element_terms, scatter_add

log = logging.getLogger("biopsynav.p2")  # progress of a push: load steps, contact rounds

#: local vertex pairs of the six edge nodes of a 10-node tetrahedron (nodes 4-9)
EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
#: barycentric coordinates (10, 4) of a 10-node tetrahedron's nodes (vertices, then edges)
NODE_BARYCENTRIC = np.vstack([np.eye(4), 0.5 * (np.eye(4)[EDGES[:, 0]] + np.eye(4)[EDGES[:, 1]])])
NEWTON_ITERATIONS = 40
#: Most surface triangles handed to gmsh (:func:`meshable_surface`): the built-in breasts' skins
#: have fewer and are meshed as they are; a label map's marching-cubes skin (about 10^5) is
#: decimated first (docs/mri.md, "Against the P2 truth")
MAX_SURFACE_TRIANGLES = 20_000
LINE_SEARCH_HALVINGS = 8
#: Levenberg-Marquardt shifts (times the tangent's diagonal) tried in turn where the Newton
#: direction does not descend or its line search fails: 0, then 1e-4, 1e-3, ... 1e2
SHIFTS = (0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)
#: Degree of the quadrature rule over each tetrahedron: scikit-fem's 14-point rule, exact to
#: degree 5, whose weights are all positive. A rule with a negative weight (the 11-point rule
#: of degree 4 weighs the centroid by -0.0132) makes the discrete energy unbounded below: an
#: element lowers it without limit by crushing its centroid towards J = 0, and Newton follows.
QUADRATURE_DEGREE = 5
#: The degrees a reference may ask for: scikit-fem's rules with positive weights only, exact
#: at least to degree 5 (14, 15 and 24 points; its rules of degree 8 and 9 weigh some
#: points negatively). At 30 mm pushes the degree-5 rule leaves a quadrature error of
#: 0.1-0.3 mm at a phantom lesion (docs/evaluation.md, "The truth against a second FE code").
QUADRATURE_DEGREES = (5, 6, 7)
#: Newton reuses a factored tangent (modified Newton) after a full update that cut the
#: residual to this share of the one before, and goes on reusing it while each update cuts
#: it to FROZEN_CONTRACTION; otherwise the current tangent is factored. Over phantom lesion
#: 1 at 10 mm (55,446 dofs): 25 factorisations and 42 back-substitutions instead of 35
#: factorisations, the same answer to 1e-9 mm.
FRESH_CONTRACTION = 0.5
FROZEN_CONTRACTION = 0.5
#: Pardiso factors the tangents in single precision; the forces, energies, residuals and
#: so the converged answer stay double precision (Newton corrects the inexact directions).
#: What it saves, and how far the answers move: ``benchmarks/p2_push.py``, docs/evaluation.md.
SINGLE_PRECISION_FACTORS = True
ARMIJO = 1e-4  # sufficient decrease of the energy along a step, as a share of its slope
#: The probe of this reference (:meth:`TetReference.push` with a footprint), in the answer
#: caches' keys: answers of another probe model are solved again.
P2_PROBE = ("rigid face: rest contact held, skin it reaches slides on it, let go where "
            "pulled; skin beside it not held")
LIFT_TOL_MM = 1e-9  # a held node's prescribed move below this is no move
RELEASE_SHARE = 0.1  # a held node pulled by more than this share of the largest push is let go
CONTACT_ROUNDS = 12  # solves of one load step while its contact set or planes change
#: then up to this many more, in which held skin is let go only where it slid off the probe
#: (not where the probe pulls it): the set that cycled settles
HOLDING_ROUNDS = 12
#: held skin nearer the probe's surface than this lies on it (half the penetration that
#: free skin may have)
SURFACE_TOL_MM = 0.05
#: a load step that had to be halved makes the next half as long, at most this many times
#: in a row (:meth:`TetReference._load_steps`)
SHORTER_STEPS = 3
#: A point is looked for first among the tetrahedra whose centroids are this many nearest it
#: (:meth:`TetReference.interpolation`), then among all within the largest one's reach
LOCATE_CANDIDATES = 16
LOCATE_CHUNK = 400_000  # point-candidate pairs a chunk of the search holds


def probe_key(probe: Any, friction: str = "stick", rim_mm: float = 0.0,
              edge_radius_mm: float = 0.0, quadrature_degree: int = QUADRATURE_DEGREE,
              single_factors: bool | None = None) -> dict:
    """What a P2 answer depends on in ``[probe]`` (a ``ProbeSection``), the face's
    ``friction``, the tetrahedra along its edge (``rim_mm``, :func:`rim_at`) and the radius
    of its rounded edges (``edge_radius_mm``, :mod:`~biopsynav.evaluate.p2_contact`): the
    part of every answer cache's key (Table 2's ``p2`` reference, ``benchmarks/truth.py``)
    that names the probe, with the quadrature rule's degree (:data:`QUADRATURE_DEGREE` by
    default) and, where Newton's tangents are factored in single precision
    (``single_factors``; None: as now, :func:`factors_single`), ``"factors": "single"``. The
    probe's defaults add nothing to it; a key without ``factors`` names answers factored in
    double precision (as every answer before single precision was the default)."""
    key = {"footprint": [probe.shape, *probe.footprint_mm],
           "contact_tolerance_mm": probe.contact_tolerance_mm, "probe": P2_PROBE,
           "quadrature_degree": int(quadrature_degree)}
    if friction != "stick":
        key["friction"] = friction
    if rim_mm:
        key["rim_mm"] = rim_mm
    if edge_radius_mm:
        key["edge_radius_mm"] = edge_radius_mm
    if factors_single() if single_factors is None else single_factors:
        key["factors"] = "single"
    return key


@contextmanager
def gmsh_session() -> Iterator[Any]:
    """The ``gmsh`` module, initialised for one meshing and finalised after. gmsh's
    initialisation resets the process's SIGPIPE disposition to the system default
    (terminate); Python's own (ignore: a write to a closed socket or pipe raises
    ``BrokenPipeError``) is put back, or a service or test run in the same process would die
    silently when a peer goes away."""
    import gmsh

    pipe = getattr(signal, "SIGPIPE", None)
    handler = signal.getsignal(pipe) if pipe is not None else None
    gmsh.initialize(interruptible=False)
    try:
        _restore_signal(pipe, handler)
        yield gmsh
    finally:
        gmsh.finalize()
        _restore_signal(pipe, handler)


def _restore_signal(signum: Any, handler: Any) -> None:
    """Set ``handler`` for ``signum`` again (where the platform has it and, as Python
    requires, from the main thread)."""
    if signum is not None and handler is not None \
            and threading.current_thread() is threading.main_thread():
        signal.signal(signum, handler)


RIM_GROWTH = 0.5  # mm of element size per mm away from the probe face's edge (Rim)


@dataclass(frozen=True)
class Rim:
    """A finer mesh along the edge of the probe face at rest: within ``depth_mm`` under the
    face plane of ``pose`` (4, 4), tetrahedra of ``size_mm`` at the edge of ``footprint``
    (a :class:`~biopsynav.footprint.Footprint`), growing by ``RIM_GROWTH`` mm per mm away
    from it. There the skin bends round the rigid face's edge and the deformation is
    steepest. (Finer tetrahedra there still fold over, :meth:`TetReference.tangled`: the
    edge is sharp; docs/fem.md.)"""

    pose: np.ndarray
    footprint: Any
    size_mm: float
    depth_mm: float = 12.0

    @cached_property
    def _edge(self) -> Any:
        """A k-d tree of points on the footprint's edge (face frame, mm)."""
        from scipy.spatial import cKDTree

        return cKDTree(_outline(self.footprint))

    def sizes(self, points: np.ndarray) -> np.ndarray:
        """Mesh size (k,) mm asked for at ``points`` (k, 3) mm."""
        local = (points - self.pose[:3, 3]) @ self.pose[:3, :3]
        lateral, _ = self._edge.query(local[:, :2])
        below = np.maximum(np.maximum(local[:, 2] - self.depth_mm, -local[:, 2]), 0.0)
        return self.size_mm + RIM_GROWTH * np.hypot(lateral, below)


def rim_at(pose: np.ndarray, footprint: Any, size_mm: float) -> Rim | None:
    """The :class:`Rim` of the face ``footprint`` at rest ``pose`` (4, 4) with tetrahedra of
    ``size_mm`` at its edge; None for a ``size_mm`` of 0 (no finer rim)."""
    return Rim(np.asarray(pose, dtype=np.float64), footprint, size_mm) if size_mm > 0 else None


def _outline(footprint: Any, step_mm: float = 0.25) -> np.ndarray:
    """Points (k, 2) mm on the edge of ``footprint``: samples of a ``step_mm`` lattice over
    its bounding rectangle that lie inside with a neighbour outside."""
    half = footprint.half_mm + 2 * step_mm
    axes = [np.arange(-h, h + step_mm / 2, step_mm) for h in half]
    xy = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    inside = footprint.inside(xy.reshape(-1, 2)).reshape(xy.shape[:2])
    edge = inside.copy()
    edge[1:-1, 1:-1] &= ~(inside[2:, 1:-1] & inside[:-2, 1:-1] & inside[1:-1, 2:]
                          & inside[1:-1, :-2])
    return xy[edge]


def tet_mesh(vertices: np.ndarray, faces: np.ndarray, size_mm: float,
             fine_at: np.ndarray | None = None, fine_mm: float = 2.0, fine_radius_mm: float = 35.0,
             rim: Rim | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedra of the closed surface (vertices (n, 3) mm, faces (m, 3)) with edges of about
    ``size_mm``, and of ``fine_mm`` within ``fine_radius_mm`` of ``fine_at`` (3,) mm when
    given (under the probe), finer still along the probe face's edge with a ``rim``: points
    (p, 3) mm and tetrahedra (t, 4), positively oriented.

    gmsh reparametrises and remeshes the surface, then fills it. Where it cannot (a surface
    whose remeshed facets intersect, as the UC Davis breast's at its chest-wall pinch), the
    volume is filled inside the surface's own triangles, kept as they are (sizes then apply
    inside only), and a warning says so. InputError when neither route meshes it."""
    sizes = (size_mm, fine_at, fine_mm, fine_radius_mm, rim)
    vertices, faces = meshable_surface(vertices, faces)
    try:
        return _gmsh_tets(vertices, faces, *sizes, remesh=True)
    except Exception as exc:  # noqa: BLE001 - gmsh raises a bare Exception
        remeshed = str(exc).strip()[:120]
    log.warning("gmsh could not remesh the surface (%s); the volume is filled inside its "
                "own triangles", remeshed)
    try:
        return _gmsh_tets(vertices, faces, *sizes, remesh=False)
    except Exception as exc:  # noqa: BLE001 - gmsh raises a bare Exception
        raise InputError(f"gmsh cannot fill the breast surface with tetrahedra, remeshed "
                         f"({remeshed}) or as it is ({str(exc).strip()[:120]}): is it closed?",
                         "P2 reference") from None


def held_by_chest_wall(anatomy: Any, points: np.ndarray, tol_mm: float) -> np.ndarray:
    """(k,) bool: which surface ``points`` (k, 3) mm the chest wall holds. A flat wall: those
    within ``tol_mm`` of its plane. A curved one (a label map's interface with the muscle,
    ``anatomy.chest_curved``): those whose nearest surface vertex is a chest-wall vertex, on its
    outer side or within ``tol_mm`` inside, as the case grid fixes its nodes
    (:func:`biopsynav.grid.build.behind_curved_wall`)."""
    if getattr(anatomy, "chest_curved", False):
        from ..grid.build import behind_curved_wall

        return behind_curved_wall(anatomy, np.asarray(points, dtype=np.float64), tol_mm)
    normal = anatomy.chest_normal / np.linalg.norm(anatomy.chest_normal)
    return np.abs((points - anatomy.chest_point) @ normal) <= tol_mm


def chest_key(anatomy: Any) -> dict:
    """The chest wall's part of a P2 answer's key: nothing for a flat wall (the keys of the
    truths made before curved walls were held as such), the rule for a curved one."""
    return {"chest_wall": "curved"} if getattr(anatomy, "chest_curved", False) else {}


def meshable_surface(vertices: np.ndarray, faces: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface (vertices (n, 3) mm, faces (m, 3)) that :func:`tet_mesh` hands to
    gmsh: as it is with at most :data:`MAX_SURFACE_TRIANGLES` faces, else decimated to that
    many (:func:`biopsynav.anatomy.display.quadric_decimated`). gmsh remeshes the surface at
    the tetrahedra's size, so the triangles beyond that number only slow its classification.
    The decimated vertices stay where the quadric metric puts them, not projected onto the
    original surface as :func:`~biopsynav.anatomy.display.decimate` does for display: so
    moved, their triangles no longer parametrise (gmsh refuses)."""
    from ..anatomy.display import quadric_decimated

    return quadric_decimated(vertices, faces, MAX_SURFACE_TRIANGLES)


def _gmsh_tets(vertices: np.ndarray, faces: np.ndarray, size_mm: float,
               fine_at: np.ndarray | None, fine_mm: float, fine_radius_mm: float,
               rim: Rim | None, *, remesh: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tet_mesh` by one route: the surface remeshed (``remesh``) or kept as it is."""
    import trimesh

    with tempfile.TemporaryDirectory() as tmp, gmsh_session() as gmsh:
        stl = Path(tmp) / "surface.stl"
        trimesh.Trimesh(vertices, faces, process=False).export(stl)
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.merge(str(stl))
        if remesh:
            gmsh.model.mesh.classifySurfaces(np.radians(40.0), True, True, np.pi)
            gmsh.model.mesh.createGeometry()
        loop = gmsh.model.geo.addSurfaceLoop([t for _, t in gmsh.model.getEntities(2)])
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        _mesh_sizes(gmsh, size_mm, fine_at, fine_mm, fine_radius_mm, rim)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, elem_nodes = gmsh.model.mesh.getElementsByType(4)  # 4-node tetrahedra
    return _oriented_tets(tags, coords, elem_nodes)


def _mesh_sizes(gmsh: Any, size_mm: float, fine_at: np.ndarray | None, fine_mm: float,
                fine_radius_mm: float, rim: Rim | None) -> None:
    """gmsh's size options: ``size_mm`` at most, the ball under the probe, the rim."""
    gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    if fine_at is not None:
        _ball_field(fine_at, fine_mm, size_mm, fine_radius_mm)
    if rim is not None:
        gmsh.model.mesh.setSizeCallback(
            lambda dim, tag, x, y, z, lc: min(lc, float(rim.sizes(np.array([[x, y, z]]))[0])))
        gmsh.option.setNumber("Mesh.MeshSizeMin", rim.size_mm)


def _oriented_tets(tags: np.ndarray, coords: np.ndarray, elem_nodes: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """gmsh's nodes and tetrahedra as points (p, 3) mm and tets (t, 4), unused nodes dropped,
    every tetrahedron positively oriented."""
    index = np.full(int(tags.max()) + 1, -1)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets = index[np.asarray(elem_nodes, dtype=np.int64).reshape(-1, 4)]
    used = np.unique(tets)
    remap = np.full(len(tags), -1)
    remap[used] = np.arange(len(used))
    points, tets = coords.reshape(-1, 3)[used], remap[tets]
    flip = _volumes(points, tets) < 0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return points, tets


def _ball_field(centre: np.ndarray, fine_mm: float, size_mm: float, radius_mm: float) -> None:
    """gmsh background size: ``fine_mm`` within ``radius_mm`` of ``centre``, growing to
    ``size_mm`` over another radius."""
    import gmsh

    mesh_field = gmsh.model.mesh.field
    tag = mesh_field.add("Ball")
    for key, value in (("Radius", radius_mm), ("Thickness", radius_mm), ("VIn", fine_mm),
                       ("VOut", size_mm), ("XCenter", centre[0]), ("YCenter", centre[1]),
                       ("ZCenter", centre[2])):
        mesh_field.setNumber(tag, key, float(value))
    mesh_field.setAsBackgroundMesh(tag)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMin", fine_mm)


def _volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    e = points[tets[:, 1:]] - points[tets[:, :1]]
    return np.linalg.det(e) / 6.0


def p2_nodes(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n, 3) mm of the P2 mesh (vertices, then edge midpoints) and the (t, 10)
    element node lists (4 vertices, then the edges in :data:`EDGES` order)."""
    pairs = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    elements = np.hstack([tets, len(points) + inverse.reshape(-1, 6)])
    return np.vstack([points, points[edges].mean(axis=1)]), elements


def shape_gradients(bary: np.ndarray, grad_l: np.ndarray) -> np.ndarray:
    """Gradients (t, 10, 3) of the P2 shape functions at barycentric point ``bary`` (4,) of
    elements whose barycentric gradients are ``grad_l`` (t, 4, 3)."""
    vertex = (4.0 * bary - 1.0)[None, :, None] * grad_l
    i, j = EDGES[:, 0], EDGES[:, 1]
    edge = 4.0 * (bary[i][None, :, None] * grad_l[:, j] + bary[j][None, :, None] * grad_l[:, i])
    return np.concatenate([vertex, edge], axis=1)


def element_quadrature(points: np.ndarray, tets: np.ndarray,
                       degree: int = QUADRATURE_DEGREE) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients (t, q, 10, 3) per mm and weights x volume (t, q) mm^3 at the
    quadrature points of the ``degree`` rule over tetrahedra ``tets`` (t, 4) of ``points``
    (n, 3) mm, element-major as :mod:`~biopsynav.evaluate.p2_kernels` reads them; ValueError
    for a rule with a weight <= 0 (:data:`QUADRATURE_DEGREE`)."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    xq, wq = get_quadrature(RefTet, degree)
    if (wq <= 0.0).any():
        raise ValueError(f"the degree-{degree} tetrahedron rule has a weight <= 0: the "
                         "hyperelastic energy would be unbounded below")
    bary = np.vstack([1.0 - xq.sum(axis=0), xq]).T  # (q, 4)
    grad_l = _barycentric_gradients(points, tets)
    grads = np.stack([shape_gradients(b, grad_l) for b in bary], axis=1)
    return grads, 6.0 * wq[None, :] * _volumes(points, tets)[:, None]


def shape_values(bary: np.ndarray) -> np.ndarray:
    """P2 shape function values (k, 10) at barycentric points (k, 4)."""
    vertex = bary * (2.0 * bary - 1.0)
    edge = 4.0 * bary[:, EDGES[:, 0]] * bary[:, EDGES[:, 1]]
    return np.hstack([vertex, edge])


class PushTimeout(Exception):
    """A push ran past its time limit (:meth:`TetReference.push`, ``time_limit_s``): the
    reference gave up, which says nothing about the model's answer."""


@dataclass
class TetReference:
    """The P2 model of one case's anatomy (homogeneous neo-Hookean, chest wall fixed)."""

    nodes: np.ndarray  # (n, 3) mm
    elements: np.ndarray  # (t, 10)
    corners: np.ndarray  # (t, 4) the linear tetrahedra
    grads: np.ndarray  # (t, q, 10, 3) reference shape-function gradients per quadrature point
    weights: np.ndarray  # (t, q) quadrature weight x volume
    mu: float
    lam: float
    fixed_nodes: np.ndarray
    skin: SimpleNamespace  # boundary nodes as an anatomy: vertices, normals, fixed_vertices
    skin_nodes: np.ndarray  # (k,) node index of each skin entry

    @classmethod
    def build(cls, anatomy, size_mm: float, e_mpa: float, nu: float,
              fine_at: np.ndarray | None = None, fine_mm: float = 2.0,
              chest_tol_mm: float = 0.05, rim: Rim | None = None,
              quadrature_degree: int = QUADRATURE_DEGREE) -> TetReference:
        """The reference of ``anatomy`` (a biopsynav Anatomy) on tetrahedra of about
        ``size_mm`` (``fine_mm`` around ``fine_at``, finer along the ``rim``: :func:`tet_mesh`)
        with a homogeneous material (E MPa, nu), integrated by the rule of
        ``quadrature_degree`` (:func:`element_quadrature`)."""
        from scipy.spatial import cKDTree

        points, tets = tet_mesh(anatomy.vertices, anatomy.faces, size_mm, fine_at, fine_mm,
                                rim=rim)
        nodes, elements = p2_nodes(points, tets)
        grads, weights = element_quadrature(points, tets, quadrature_degree)
        mu, lam = lame_constants(np.array([e_mpa]), np.array([nu]))
        skin_nodes = _boundary_nodes(tets, len(points), elements)
        locs = nodes[skin_nodes]
        on_chest = held_by_chest_wall(anatomy, locs, chest_tol_mm)
        _, nearest = cKDTree(anatomy.vertices).query(locs)
        skin = SimpleNamespace(vertices=locs, normals=anatomy.normals[nearest],
                               fixed_vertices=on_chest, pushable=~on_chest)
        return cls(nodes, elements, tets, grads, weights, float(mu[0]), float(lam[0]),
                   skin_nodes[on_chest], skin, skin_nodes)

    @property
    def n_dofs(self) -> int:
        return 3 * len(self.nodes)

    def contact(self, pose: np.ndarray, footprint, tol_mm: float,
                friction: str = "stick") -> np.ndarray:
        """Node indices of the skin the probe face touches at rest ``pose`` (as the
        tracker's :func:`biopsynav.tracker.contact_indices`), which :meth:`push` moves with
        the face; none with a ``slip`` face (:data:`FRICTIONS`)."""
        if friction not in FRICTIONS:
            raise ValueError(f"friction {friction!r}: not one of {', '.join(FRICTIONS)}")
        if friction == "slip":
            return np.zeros(0, dtype=np.int64)
        r = np.asarray(pose)[:3, :3]
        found = skin_under_face(self.skin, np.asarray(pose)[:3, 3], r, footprint, tol_mm,
                                -r[:, 2])
        return self.skin_nodes[found]

    def forces_and_tangent(self, u: np.ndarray, tangent: bool = True):
        """Internal forces (3 n,) N and, with ``tangent``, the stiffness (3 n, 3 n) N/mm at
        the nodal displacement ``u`` (n, 3) mm (node-major dofs); FloatingPointError when an
        element inverts (:mod:`~biopsynav.evaluate.p2_kernels`)."""
        f, k, _ = self._element_terms(u, tangent)
        forces = np.bincount(self._element_dofs.ravel(), f.ravel(), minlength=self.n_dofs)
        if not tangent:
            return forces
        indptr, indices, slot = self._stiffness_pattern
        data = scatter_add(slot, k.reshape(-1), len(indices))
        stiff = sp.csr_matrix((data, indices, indptr), shape=(self.n_dofs, self.n_dofs))
        stiff.has_sorted_indices = True
        return forces, stiff

    def _element_terms(self, u: np.ndarray, tangent: bool
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Element forces (t, 10, 3) N, tangents (t, 30, 30) N/mm (empty without
        ``tangent``) and energies (t,) N mm at ``u`` (n, 3) mm; FloatingPointError when an
        element inverts (J <= 0 at a quadrature point)."""
        f, k, energies, valid = element_terms(np.ascontiguousarray(u[self.elements]),
                                              self.grads, self.weights, self.mu, self.lam,
                                              tangent)
        if not valid.all():
            raise FloatingPointError("an element inverted")
        return f, k, energies

    @cached_property
    def _element_dofs(self) -> np.ndarray:
        """The node-major dofs (t, 30) int64 of each element's nodes."""
        n_el = len(self.elements)
        return (3 * self.elements[:, :, None] + np.arange(3)).reshape(n_el, 30).astype(np.int64)

    @cached_property
    def _stiffness_pattern(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stiffness's CSR pattern (indptr, indices: sorted, no duplicates) and the slot
        (t * 900,) of each element matrix entry (element-major, row-major 30 x 30) in it."""
        rows, n = self._element_dofs, self.n_dofs
        key = (np.repeat(rows, 30, axis=1) * n + np.tile(rows, (1, 30))).ravel()
        entries, slot = np.unique(key, return_inverse=True)
        indptr = np.searchsorted(entries, np.arange(n + 1, dtype=np.int64) * n)
        return indptr, entries % n, slot

    def energy(self, u: np.ndarray) -> float:
        """The stored energy (N mm) at the nodal displacement ``u`` (n, 3) mm:
        ``W = mu / 2 (tr b - 3) - mu ln J + lam / 2 (ln J)^2`` integrated over the mesh (the
        potential of :meth:`forces_and_tangent`'s forces); FloatingPointError when an
        element inverts."""
        return float(self._element_terms(u, tangent=False)[2].sum())

    def tangled(self, u: np.ndarray) -> np.ndarray:
        """Elements (k,) that the nodal displacement ``u`` (n, 3) mm folds over: J <= 0 at one
        of their ten nodes. The energy and forces see J only at the quadrature points, where
        it may still be positive: such a state is no deformation of the continuum (the skin
        bent round the probe face's sharp edge, where finer elements fold as well), and an
        answer holding it is not to be trusted."""
        ue = u[self.elements]
        grad_l = _barycentric_gradients(self.nodes, self.corners)
        folded = np.zeros(len(self.elements), dtype=bool)
        for bary in NODE_BARYCENTRIC:
            g0 = shape_gradients(bary, grad_l)
            folded |= np.linalg.det(np.eye(3) + np.einsum("tai,taj->tij", ue, g0)) <= 0.0
        return np.flatnonzero(folded)

    last: np.ndarray | None = None  # the nodal displacement of the last push (n, 3) mm
    last_rel: np.ndarray | None = None  # the last push's pose relative to its rest pose
    #: skin nodes held on the face plane in the last push
    sliding: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: sliding nodes that passed the face again once let go: held for the rest of the push
    kept: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: the time (of :attr:`clock`) after which the push in progress gives up (PushTimeout);
    #: None: never
    deadline: float | None = None
    #: the clock of :attr:`deadline`: wall time, or the calling thread's CPU time (``push(...,
    #: cpu_time=True)``: a Dask worker may solve several pushes at once, one a thread)
    clock = staticmethod(time.monotonic)

    def mesh_fingerprint(self) -> str:
        """A hash of the mesh (node coordinates and elements): equal for the same mesh."""
        digest = hashlib.sha256(np.ascontiguousarray(self.nodes, dtype=np.float64).tobytes())
        digest.update(np.ascontiguousarray(self.elements, dtype=np.int64).tobytes())
        return digest.hexdigest()

    def push_state(self) -> dict[str, np.ndarray]:
        """What the next push from ``self.last`` continues with (``start=self.last``): the
        equilibrium (n, 3) mm, the last pose relative to the rest pose (4, 4; NaN: none), the
        sliding and kept skin nodes. Plain arrays, for :meth:`resume` (a stopped run)."""
        if self.last is None:
            raise ValueError("no push to continue from: push first")
        rel = np.full((4, 4), np.nan) if self.last_rel is None else self.last_rel
        return {"last": np.asarray(self.last, dtype=np.float64), "last_rel": rel,
                "sliding": np.asarray(self.sliding, dtype=np.int64),
                "kept": np.asarray(self.kept, dtype=np.int64)}

    def resume(self, state: dict[str, np.ndarray]) -> None:
        """Take the state of :meth:`push_state` (of a model of the same mesh) as the last
        push's, so that ``push(..., start=self.last)`` continues as the stopped run would."""
        last = np.asarray(state["last"], dtype=np.float64)
        if last.shape != self.nodes.shape:
            raise ValueError(f"a push state of {last.shape[0]} nodes for a mesh of "
                             f"{len(self.nodes)}")
        rel = np.asarray(state["last_rel"], dtype=np.float64)
        self.last, self.last_rel = last, None if np.isnan(rel).any() else rel
        self.sliding = np.asarray(state["sliding"], dtype=np.int64)
        self.kept = np.asarray(state["kept"], dtype=np.int64)

    def push(self, rest: np.ndarray, poses: list[np.ndarray], contact: np.ndarray,
             points: np.ndarray, step_mm: float = 5.0, tol: float = 1e-6,
             start: np.ndarray | None = None, footprint: Any = None,
             edge_radius_mm: float = 0.0, time_limit_s: float | None = None,
             cpu_time: bool = False) -> list[np.ndarray]:
        """Displacements (k, 3) mm at ``points`` (k, 3) for each of ``poses`` (in turn, each
        solve starting from the last; the first from ``start``, an equilibrium (n, 3) mm of
        the same contact set, or from rest): the contact nodes follow the probe rigidly from
        ``rest``, in load steps of at most ``step_mm`` (halved where a step fails).

        With ``footprint`` (the face's :class:`~biopsynav.footprint.Footprint`) the probe is
        a rigid body (:func:`~biopsynav.evaluate.p2_contact.probe_surface`: a flat face, or
        with ``edge_radius_mm`` > 0 a body whose edges are rounded by it): skin that a load
        step puts more than ``PENETRATION_TOL_MM`` inside it is held on its surface, free to
        slide (frictionless), and the step is solved again (at most ``CONTACT_ROUNDS`` +
        ``HOLDING_ROUNDS`` times: :meth:`_contact_step`); ``self.sliding`` lists those
        nodes. Without it, skin may pass through the face. With no ``contact`` nodes (a
        ``slip`` face, :meth:`contact`) only the face pushes, so a ``footprint`` is needed;
        the load steps follow the face's corners. With ``time_limit_s``, a call still
        solving after that many seconds raises :class:`PushTimeout` (checked at each Newton
        iteration): seconds of wall time, or with ``cpu_time`` of the calling thread's CPU
        time (what a push costs whatever else the machine runs)."""
        if not len(contact) and footprint is None:
            raise ValueError("a push with no contact nodes needs the face's footprint")
        self.clock = time.thread_time if cpu_time else time.monotonic
        self.deadline = None if time_limit_s is None else self.clock() + time_limit_s
        x0 = self.nodes[contact]
        surface = None if footprint is None else probe_surface(footprint, edge_radius_mm)
        u = np.zeros_like(self.nodes) if start is None else np.array(start, dtype=np.float64)
        done = u[contact].copy()
        if start is None:
            self.sliding, self.last_rel = np.zeros(0, dtype=np.int64), None
            self.kept = np.zeros(0, dtype=np.int64)
        done_rel = np.eye(4) if self.last_rel is None else self.last_rel
        out = []
        interp = self._interpolation(np.asarray(points, dtype=np.float64))
        for pose in poses:
            rel = np.asarray(pose) @ np.linalg.inv(rest)
            target = x0 @ rel[:3, :3].T + rel[:3, 3] - x0
            travel = max(np.abs(target - done).max(initial=0.0),
                         _face_travel(rest, done_rel, rel, footprint))
            share = 1.0 / max(1, int(np.ceil(travel / step_mm)))
            u = self._load_steps(u, contact, (done, target), (done_rel @ np.asarray(rest),
                                                             rel @ np.asarray(rest)),
                                 share, tol, surface)
            done, done_rel = target, rel
            self.last, self.last_rel = u, rel
            out.append(interp @ u)
        return out

    def _load_steps(self, u: np.ndarray, contact: np.ndarray,
                    values: tuple[np.ndarray, np.ndarray], faces: tuple[np.ndarray, np.ndarray],
                    share: float, tol: float, surface: Any) -> np.ndarray:
        """The equilibrium (n, 3) mm after the probe moved from the pose ``faces[0]`` (4, 4),
        where ``u`` is the equilibrium with the ``contact`` nodes at ``values[0]`` (n_c, 3)
        mm, to ``faces[1]``, with them at ``values[1]``: load steps of ``share`` of the move
        (:meth:`_contact_step`, poses and values interpolated linearly). A step that had to
        be halved (:meth:`_step`) makes the next one half as long, down to ``share /
        2**SHORTER_STEPS``; one solved whole makes the next twice as long, up to
        ``share``. Where no step is halved, the steps are the equal ones of before."""
        (start, end), (was, to) = values, faces
        frac, step, k = 0.0, share, 0
        while frac < 1.0:
            nxt = 1.0 if frac + step > 1.0 - 1e-9 else frac + step
            k += 1
            log.info("load step %d: %.1f to %.1f %% of the move", k, 100 * frac, 100 * nxt)
            u, halved = self._contact_step(u, contact, start + (end - start) * nxt, tol,
                                           (was + (to - was) * frac, was + (to - was) * nxt),
                                           surface)
            frac = nxt
            step = (max(step / 2, share / 2**SHORTER_STEPS) if halved
                    else min(2 * step, share))
        return u

    def _contact_step(self, u: np.ndarray, contact: np.ndarray, values: np.ndarray,
                      tol: float, poses: tuple[np.ndarray, np.ndarray],
                      surface: Any) -> tuple[np.ndarray, int]:
        """One load step of the probe from the pose ``poses[0]`` (4, 4), where ``u`` is the
        equilibrium, to ``poses[1]``: the equilibrium (n, 3) mm there and how many times a
        solve of it was halved (:meth:`_step`). With its contact ``surface``
        (:mod:`~biopsynav.evaluate.p2_contact`), an active set: the held skin keeps its
        place on the moving surface, and the skin that the probe's move passes (inside the
        probe where the step's linear response puts it) is put where it met the surface
        (:func:`~biopsynav.evaluate.p2_contact.meeting_points`) before the solve; then,
        until it settles, skin that still passes the probe is added where it met it, skin
        the probe would have to pull or that slid off it is released, the planes of the held
        skin are taken again where it now touches a curved surface, and the step is solved
        again from there (frictionless and elastic: the equilibrium does not depend on the
        path). A node is released at most once a step, and one that passes the probe again
        once free stays held for the rest of the push (``self.kept``). After
        ``CONTACT_ROUNDS`` solves, skin that the probe pulls is no longer let go (only skin
        that slid off it), for up to ``HOLDING_ROUNDS`` more: a set that cycled settles, with
        the pulled nodes it holds logged; a step settled within ``CONTACT_ROUNDS`` is as
        before."""
        if surface is None:
            return self._step(u, contact, values, tol, Sliding.none())
        was, face = poses
        predicted = self._predicted_on(u, contact, values, poses, surface)
        new = self._penetrating(predicted, face, surface, contact)
        self.sliding = np.union1d(self.sliding, new)
        slide = self._sliding_at(predicted, face, surface,
                                 self._face_local(self.sliding, u, was))
        released = np.zeros(0, dtype=np.int64)
        halved = 0
        for round_ in range(CONTACT_ROUNDS + HOLDING_ROUNDS):
            before = u
            u, more = self._step(u, contact, values, tol, slide, on=(face, surface))
            halved += more
            new = self._penetrating(u, face, surface, contact)
            self.kept = np.union1d(self.kept, np.intersect1d(new, released))
            off = np.setdiff1d(self._released(u, face, surface, round_ < CONTACT_ROUNDS),
                               np.union1d(released, self.kept))
            gap = self._gap(self.sliding, u, face, surface)
            log.info("  contact round: %d held, %d more pass the probe, %d let go, held skin "
                     "%.3f mm off the probe", len(self.sliding), len(new), len(off), gap)
            if not len(new) and not len(off) and gap <= SURFACE_TOL_MM:
                self._say_pulled(u, face, surface, round_)
                return u, halved
            self.sliding = np.union1d(np.setdiff1d(self.sliding, off), new)
            released = np.union1d(released, off)
            slide = self._sliding_at(u, face, surface, self._came_from(new, before, face))
        raise RuntimeError(f"P2 reference: skin still passes the probe or leaves its surface "
                           f"after {CONTACT_ROUNDS + HOLDING_ROUNDS} contact rounds (the last "
                           f"{HOLDING_ROUNDS} letting go no skin the probe pulls)")

    def _say_pulled(self, u: np.ndarray, face: np.ndarray, surface: Any, round_: int) -> None:
        """Log how many held skin nodes the probe pulls at the equilibrium ``u`` when the
        contact set settled in a holding round (``round_`` >= ``CONTACT_ROUNDS``)."""
        if round_ >= CONTACT_ROUNDS:
            pulled = self._released(u, face, surface)
            log.info("  contact settled after %d rounds with %d held skin nodes that the probe "
                     "pulls (not let go after round %d)", round_ + 1, len(pulled),
                     CONTACT_ROUNDS)

    def _came_from(self, new: np.ndarray, before: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Where ``before`` (n, 3) mm had the ``new`` sliding nodes in the frame of ``face``
        (4, 4), as rows (m, 3) mm of ``self.sliding``; NaN for the others (held before)."""
        came = np.full((len(self.sliding), 3), np.nan)
        rows = np.searchsorted(self.sliding, new)
        came[rows] = self._face_local(new, before, face)
        return came

    def _sliding_at(self, u: np.ndarray, face: np.ndarray, surface: Any,
                    came_from: np.ndarray | None = None) -> Sliding:
        """``self.sliding`` held on the planes tangent to ``surface`` of the probe at
        ``face`` (4, 4): where ``u`` (n, 3) mm puts them nearest or, given where they were
        in the probe's frame before (``came_from``, (m, 3) mm, NaN rows: nearest), where
        they met the surface (:meth:`Sliding.on_surface`)."""
        nodes = self.sliding
        return Sliding.on_surface(nodes, self.nodes[nodes], self.nodes[nodes] + u[nodes], face,
                                  surface, came_from)

    def _gap(self, nodes: np.ndarray, u: np.ndarray, face: np.ndarray, surface: Any) -> float:
        """How far (mm) ``u`` puts the one of the sliding ``nodes`` (m,) furthest from
        ``surface`` at ``face`` (on its tangent plane, a node may have slid off a curved
        surface)."""
        local = self._face_local(nodes, u, face)
        return float(np.abs(surface.closest(local)[2]).max(initial=0.0))

    def _penetrating(self, u: np.ndarray, face: np.ndarray, surface: Any,
                     contact: np.ndarray) -> np.ndarray:
        """Skin nodes (not held, facing the probe at rest) that ``u`` puts more than
        ``PENETRATION_TOL_MM`` inside the probe at ``face`` (4, 4): ``surface.penetrating``."""
        nodes = self.skin_nodes
        local = self._face_local(nodes, u, face)
        inside = (surface.penetrating(local) & (self.skin.normals @ face[:3, 2] < 0.0)
                  & self.skin.pushable)
        held = np.concatenate([contact, self.fixed_nodes, self.sliding])
        return np.setdiff1d(nodes[inside], held)

    def _face_local(self, nodes: np.ndarray, u: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Where ``u`` (n, 3) mm puts ``nodes`` (m,), in the frame of the face pose ``face``
        (4, 4): (m, 3) mm, z along the beam (negative: behind the face plane)."""
        return (self.nodes[nodes] + u[nodes] - face[:3, 3]) @ face[:3, :3]

    def _predicted_on(self, u: np.ndarray, contact: np.ndarray, values: np.ndarray,
                      poses: tuple[np.ndarray, np.ndarray], surface: Any) -> np.ndarray:
        """Where the step's linear response from the equilibrium ``u`` (n, 3) mm at the
        probe pose ``poses[0]`` (4, 4) puts the nodes: ``contact`` at ``values`` and the
        sliding nodes where they were on ``surface``, moved with the probe to ``poses[1]``."""
        was, face = poses
        slide = self._sliding_at(u, face, surface, self._face_local(self.sliding, u, was))
        held = np.concatenate([contact, self.fixed_nodes])
        return self._predicted(u, self._lift(u, contact, values, slide), self._basis(held, slide))

    def _released(self, u: np.ndarray, face: np.ndarray, surface: Any,
                  pulled_too: bool = True) -> np.ndarray:
        """Sliding nodes the probe no longer holds at the equilibrium ``u``: those it pulls
        by more than ``RELEASE_SHARE`` of its largest push on one node (a node's push is its
        internal force along the surface's outward normal there, the gradient of the energy
        that the probe's force balances) and those that slid off ``surface``. Slight pulls
        stay: node-to-plane contact of quadratic elements pulls slightly at face corners,
        where a uniform pressure's consistent nodal load is zero, and releasing them only
        makes them pass the face again. Without ``pulled_too``, only those that slid off."""
        nodes = self.sliding
        if not len(nodes):
            return nodes
        slid_off = surface.slid_off(self._face_local(nodes, u, face))
        if not pulled_too:
            return nodes[slid_off]
        normals = self._sliding_at(u, face, surface).normals
        forces = self.forces_and_tangent(u, tangent=False).reshape(-1, 3)[nodes]
        push = np.einsum("mi,mi->m", forces, normals)
        pulled = push < -RELEASE_SHARE * push.max(initial=0.0)
        return nodes[pulled | slid_off]

    def _step(self, u: np.ndarray, contact: np.ndarray, values: np.ndarray, tol: float,
              slide: Sliding, depth: int = 0, on: tuple | None = None
              ) -> tuple[np.ndarray, int]:
        """One load step to ``values`` at the contact nodes: the equilibrium (n, 3) mm and how
        many times the step was split in two because a solve failed (the first half on
        planes halfway, so without ``on``: :meth:`_newton`)."""
        try:
            return self._newton(u, contact, values, tol, slide, on), 0
        except (FloatingPointError, RuntimeError) as exc:
            if depth >= 5:
                raise
            log.info("  load step failed (%s): halved", exc)
            half = 0.5 * (u[contact] + values)
            mid = slide.halfway(u)
            u, first = self._step(u, contact, half, tol, mid, depth + 1)
            u, second = self._step(u, contact, values, tol, slide, depth + 1, on)
            return u, 1 + first + second

    def _newton(self, u: np.ndarray, contact: np.ndarray, values: np.ndarray,
                tol: float, slide: Sliding, on: tuple | None = None) -> np.ndarray:
        """Equilibrium with ``values`` (n_c, 3) mm at the ``contact`` nodes and the sliding
        nodes on their planes, from the equilibrium ``u``: the first iteration carries the
        prescribed increment through the tangent, the linear response to it (no element is
        distorted by moving the held nodes alone; skipped when nothing held moves, as after
        a release); the later ones, on the residual, are damped (:meth:`_descend`).
        Increments live in the span of :meth:`_basis` (every dof of a free node, the plane
        of a sliding node). ``on``, the probe's pose (4, 4) and its surface, returns the
        sliding nodes to that surface after an update that takes one further from it than
        half ``SURFACE_TOL_MM``, their planes tangent where they now touch it
        (:meth:`_retracted`): a node that slides over a curved edge follows it within the
        solve rather than running off along one plane. Once a full Newton update has cut
        the residual to ``FRESH_CONTRACTION`` of the one before, the next updates reuse its
        factored tangent (:meth:`_descend_frozen`: a back-substitution instead of a
        factorisation) while each cuts the residual to ``FROZEN_CONTRACTION``; the converged
        answer is the same, to the tolerance."""
        held = np.concatenate([contact, self.fixed_nodes])
        basis = self._basis(held, slide)
        lift = self._lift(u, contact, values, slide)
        if np.abs(lift).max(initial=0.0) > LIFT_TOL_MM:
            u = self._predicted(u, lift, basis)
        r0, last, shift, frozen = None, None, 0, False
        for it in range(NEWTON_ITERATIONS):
            self._check_deadline()
            forces = self.forces_and_tangent(u, tangent=False)
            rhs = -(basis.T @ forces)
            r_norm = float(np.linalg.norm(rhs))
            r0 = r_norm if r0 is None else r0
            if r_norm <= tol * r0 or r_norm < 1e-12:
                log.debug("    Newton: %d iterations", it)
                return u
            frozen = frozen and last is not None and r_norm <= FROZEN_CONTRACTION * last
            moved = self._descend_frozen(u, rhs, basis) if frozen else None
            if moved is None:
                _, stiff = self.forces_and_tangent(u)
                moved, shift = self._descend(u, (basis.T @ stiff @ basis).tocsr(), rhs, basis,
                                             shift)
                frozen = shift == 0 and last is not None and r_norm <= FRESH_CONTRACTION * last
            u, last = moved, r_norm
            if on is not None and self._gap(slide.nodes, u, *on) > 0.5 * SURFACE_TOL_MM:
                u, slide = self._retracted(u, slide, *on)
                basis, frozen = self._basis(held, slide), False
        raise RuntimeError("P2 reference: Newton did not converge")

    def _check_deadline(self) -> None:
        """PushTimeout when the push in progress has run past ``self.deadline``."""
        if self.deadline is not None and self.clock() > self.deadline:
            raise PushTimeout("the push ran past its time limit")

    def _retracted(self, u: np.ndarray, slide: Sliding, face: np.ndarray,
                   surface: Any) -> tuple[np.ndarray, Sliding]:
        """``u`` (n, 3) mm with the sliding nodes moved to their nearest points of
        ``surface`` at the probe pose ``face`` (4, 4), and those nodes held on the planes
        tangent there. A flat face's plane is its surface: nothing moves. An element the move
        inverts fails the solve at the next force evaluation (FloatingPointError), which
        halves the load step (:meth:`_step`)."""
        nodes = slide.nodes
        point, _, _ = surface.closest(self._face_local(nodes, u, face))
        u = u.copy()
        u[nodes] = point @ face[:3, :3].T + face[:3, 3] - self.nodes[nodes]
        return u, Sliding.on_surface(nodes, self.nodes[nodes], self.nodes[nodes] + u[nodes],
                                     face, surface)

    def _lift(self, u: np.ndarray, contact: np.ndarray, values: np.ndarray,
              slide: Sliding) -> np.ndarray:
        """The move (n, 3) mm from ``u`` that puts the ``contact`` nodes at ``values`` (n_c, 3)
        mm and the sliding nodes on their planes; zero elsewhere."""
        lift = np.zeros_like(u)
        lift[contact] = values - u[contact]
        lift[slide.nodes] = slide.lift(u)
        return lift

    def _predicted(self, u: np.ndarray, lift: np.ndarray, basis: sp.csr_matrix) -> np.ndarray:
        """``u`` (n, 3) mm moved by ``lift`` at the held nodes and, in the span of ``basis``,
        by the tangent's linear response to it."""
        _, stiff = self.forces_and_tangent(u)
        rhs = -(basis.T @ (stiff @ lift.ravel()))
        du = basis @ solve_symmetric((basis.T @ stiff @ basis).tocsr(), rhs)
        return u + (du + lift.ravel()).reshape(u.shape)

    def _descend(self, u: np.ndarray, reduced: sp.csr_matrix, rhs: np.ndarray,
                 basis: sp.csr_matrix, shift: int) -> tuple[np.ndarray, int]:
        """One damped Newton update of ``u`` (n, 3) mm from the reduced tangent and residual
        ``rhs`` (minus the reduced forces): the direction solves ``(K + s diag|K|) d = rhs``
        for the shifts ``SHIFTS[shift:]`` in turn (Levenberg-Marquardt, where the tangent is
        indefinite past a limit point or the full step overshoots) until it descends in
        energy and :meth:`_line_search` finds a step along it. Returns the new ``u`` and the
        shift index to start from next time (one smaller: the shift relaxes as Newton
        converges); RuntimeError when no shift gives one."""
        scale = sp.diags(np.abs(reduced.diagonal()))
        energy = self.energy(u)
        for k in range(shift, len(SHIFTS)):
            matrix = reduced + SHIFTS[k] * scale if SHIFTS[k] else reduced
            d = solve_symmetric(matrix.tocsr(), rhs)
            slope = -float(rhs @ d)  # the energy's derivative along d
            if slope >= 0.0:
                continue
            found = self._line_search(u, (basis @ d).reshape(u.shape), basis, rhs, energy,
                                      slope)
            if found is not None:
                return found, max(k - 1, 0)
        raise RuntimeError("P2 reference: the line search found no admissible decrease, "
                           f"even with the tangent shifted by {SHIFTS[-1]:g} times its diagonal")

    def _descend_frozen(self, u: np.ndarray, rhs: np.ndarray,
                        basis: sp.csr_matrix) -> np.ndarray | None:
        """``u`` (n, 3) mm moved along the direction that the last factored tangent gives
        for the residual ``rhs`` (modified Newton), with the line search of
        :meth:`_descend`; None where that direction does not descend or no step along it
        is admissible (the caller factors the current tangent instead)."""
        d = resolve_symmetric(rhs)
        slope = -float(rhs @ d)
        if not slope < 0.0:
            return None
        return self._line_search(u, (basis @ d).reshape(u.shape), basis, rhs, self.energy(u),
                                 slope)

    def _basis(self, held: np.ndarray, slide: Sliding) -> sp.csr_matrix:
        """(3 n, r) basis of admissible increments: the unit vectors of every dof of a node
        neither ``held`` nor sliding, and the two in-plane directions of each sliding node;
        with no sliding node, the selection of the free dofs in their order."""
        n = len(self.nodes)
        kind = np.zeros(n, dtype=np.int8)
        kind[slide.nodes] = 1
        kind[held] = 2
        free = np.flatnonzero(np.repeat(kind == 0, 3))
        rows, cols, vals = [free], [np.arange(len(free))], [np.ones(len(free))]
        on_plane = kind[slide.nodes] == 1
        nodes, normals = slide.nodes[on_plane], slide.normals[on_plane]
        if len(nodes):
            t1, t2 = in_plane_directions(normals)
            col = len(free) + np.arange(2 * len(nodes)).reshape(-1, 2)
            for k, t in enumerate((t1, t2)):
                rows.append((3 * nodes[:, None] + np.arange(3)).ravel())
                cols.append(np.repeat(col[:, k], 3))
                vals.append(t.ravel())
        width = len(free) + 2 * len(nodes)
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols))),
                             shape=(self.n_dofs, width))

    def _line_search(self, u: np.ndarray, du: np.ndarray, basis: sp.csr_matrix,
                     rhs: np.ndarray, energy: float, slope: float) -> np.ndarray | None:
        """``u + a du`` for the largest ``a`` in 1, 1/2, 1/4, ... whose elements are not
        inverted and which lowers the energy (from ``energy``, N mm, by at least ``ARMIJO``
        of ``a slope``) or the residual norm in the span of ``basis`` (from ``|rhs|``: near
        equilibrium the energy's change drowns in round-off); None when none of
        ``LINE_SEARCH_HALVINGS`` halvings does."""
        step, r_norm = 1.0, float(np.linalg.norm(rhs))
        for _ in range(LINE_SEARCH_HALVINGS):
            trial = u + step * du
            try:
                if (self.energy(trial) <= energy + ARMIJO * step * slope
                        or np.linalg.norm(basis.T @ self.forces_and_tangent(
                            trial, tangent=False)) <= r_norm):
                    return trial
            except FloatingPointError:
                pass
            step *= 0.5
        return None

    def _interpolation(self, points: np.ndarray) -> sp.csr_matrix:
        """(k, n) P2 interpolation at ``points`` (k, 3) mm; ValueError outside the mesh."""
        matrix, inside = self.interpolation(points)
        if not inside.all():
            raise ValueError(f"point {points[np.flatnonzero(~inside)[0]]} lies outside the "
                             "tetrahedral mesh")
        return matrix

    def interpolation(self, points: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """The P2 interpolation (k, n) at ``points`` (k, 3) mm and which of them lie in the
        mesh, (k,) bool (the rows of the others are empty)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        element, bary = self._locate(points)
        inside = element >= 0
        rows = np.repeat(np.flatnonzero(inside), 10)
        cols = self.elements[element[inside]].ravel()
        vals = shape_values(bary[inside]).ravel()
        matrix = sp.csr_matrix((vals, (rows, cols)), shape=(len(points), len(self.nodes)))
        return matrix, inside

    def _locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The element (k,) holding each of ``points`` (k, 3) mm (-1: none) and the point's
        barycentric coordinates (k, 4) in it: among the :data:`LOCATE_CANDIDATES` nearest
        centroids, then, for a point not found there, among every tetrahedron whose centroid
        lies within the largest tetrahedron's reach of it."""
        k = min(LOCATE_CANDIDATES, len(self.corners))
        element, bary = self._locate_among(points, k)
        for i in np.flatnonzero(element < 0):
            cand = np.asarray(self._centroid_tree.query_ball_point(points[i], self._reach),
                              dtype=np.int64)
            if cand.size:
                found, lam = self._best_of(points[i][None], cand[None])
                element[i], bary[i] = found[0], lam[0]
        return element, bary

    def _locate_among(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_locate` among the ``k`` tetrahedra whose centroids are nearest each point
        (in chunks, so that memory stays bounded)."""
        element = np.full(len(points), -1, dtype=np.int64)
        bary = np.zeros((len(points), 4))
        chunk = max(1, LOCATE_CHUNK // k)
        for start in range(0, len(points), chunk):
            x = points[start:start + chunk]
            _, cand = self._centroid_tree.query(x, k=k)
            rows = slice(start, start + len(x))
            element[rows], bary[rows] = self._best_of(x, np.asarray(cand).reshape(len(x), k))
        return element, bary

    def _best_of(self, x: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Of the candidate tetrahedra ``cand`` (m, k) of each point ``x`` (m, 3) mm, the
        one holding it (-1: none) and its barycentric coordinates (m, 4)."""
        lam = np.einsum("ckij,ckj->cki", self._inverse_edges[cand],
                        x[:, None, :] - self.nodes[self.corners[cand, 0]])
        full = np.concatenate([1.0 - lam.sum(axis=2, keepdims=True), lam], axis=2)
        score = full.min(axis=2)
        best = np.argmax(score, axis=1)
        rows = np.arange(len(x))
        ok = score[rows, best] >= -1e-9
        return np.where(ok, cand[rows, best], -1), full[rows, best]

    @cached_property
    def _centroid_tree(self) -> Any:
        from scipy.spatial import cKDTree

        return cKDTree(self.nodes[self.corners].mean(axis=1))

    @cached_property
    def _inverse_edges(self) -> np.ndarray:
        """(t, 3, 3): maps ``x - x0`` to the barycentric coordinates 1-3 of each tetrahedron."""
        p, t = self.nodes, self.corners
        return np.linalg.inv((p[t[:, 1:]] - p[t[:, :1]]).transpose(0, 2, 1))

    @cached_property
    def _reach(self) -> float:
        """The largest distance (mm) from a tetrahedron's centroid to one of its corners."""
        corners = self.nodes[self.corners]
        return float(np.linalg.norm(corners - corners.mean(axis=1, keepdims=True),
                                    axis=2).max())


class _SymmetricSolver:
    """MKL Pardiso in its symmetric indefinite mode (``mtype = -2``, Bunch-Kaufman pivoting,
    the upper triangle; :class:`~biopsynav.fem.linsolve.PardisoHandle`) that keeps the
    analysis (ordering, symbolic factorisation) of the last matrix pattern: a matrix of that
    pattern (Newton's next tangent while the contact set stands) is only factored again, with
    the same ordering and so the same factors (scaling and weighted matching, which would
    make the analysis depend on the values, stay off). With ``single`` the factors are single
    precision (:data:`SINGLE_PRECISION_FACTORS`); a matrix Pardiso refuses so is factored
    again in double precision before the solve is called failed."""

    def __init__(self, single: bool = True) -> None:
        self.single = single
        self.handle = None  # the PardisoHandle of the pattern below
        self.pattern: tuple[np.ndarray, np.ndarray] | None = None
        self.analyses = 0  # how many patterns were analysed (a new handle each)
        self.factorisations = 0  # how many matrices were factored (the fallback's counted)

    def solve(self, upper: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray:
        """``upper``'s symmetric matrix ^-1 ``rhs`` (n,); RuntimeError where Pardiso refuses
        it in double precision too (the next pattern is single precision again)."""
        if not np.diff(upper.indptr).all():
            raise RuntimeError("P2 reference: the linear solve failed (an empty row)")
        known = self.pattern is not None and np.array_equal(upper.indptr, self.pattern[0]) \
            and np.array_equal(upper.indices, self.pattern[1])
        if not known:  # no pattern (nor handle) after _forget
            self._analyse(upper, self.single)
        refused = self._factor(upper)
        if refused is not None and self.handle.dtype != np.float64:
            self._analyse(upper, single=False)  # the fallback: double precision
            refused = self._factor(upper)
        if refused is not None:
            self._forget()
            raise RuntimeError(f"P2 reference: the linear solve failed ({refused})")
        return self.resolve(rhs)

    def _factor(self, upper: sp.csr_matrix) -> Exception | None:
        """Factor ``upper`` on the current handle; the error where Pardiso refuses it."""
        from ..fem.linsolve import FactorizationError

        self.factorisations += 1
        try:
            self.handle.factor(upper.data)
        except FactorizationError as exc:
            return exc
        return None

    def resolve(self, rhs: np.ndarray) -> np.ndarray:
        """The last factored matrix ^-1 ``rhs`` (a back-substitution, phase 33), in double
        precision; RuntimeError where nothing is factored or Pardiso refuses."""
        from ..fem.linsolve import FactorizationError

        if self.handle is None or not self.handle.analysed:
            raise RuntimeError("P2 reference: no factored tangent to reuse")
        try:
            return self.handle.solve(np.asarray(rhs, dtype=np.float64))
        except FactorizationError as exc:
            self._forget()
            raise RuntimeError(f"P2 reference: the linear solve failed ({exc})") from None

    def _analyse(self, upper: sp.csr_matrix, single: bool) -> None:
        """A new handle for ``upper``'s pattern (analysed at its first factorisation), the
        last one released."""
        from ..fem.linsolve import pardiso_handle

        self._forget()
        self.handle = pardiso_handle(upper.indptr, upper.indices, -2, single)
        self.pattern = (upper.indptr.copy(), upper.indices.copy())
        self.analyses += 1

    def _forget(self) -> None:
        """Release the handle (Pardiso's memory); neither its analysis nor its factors serve
        a later solve."""
        if self.handle is not None:
            self.handle.release()
        self.handle = self.pattern = None


_SYMMETRIC_SOLVER: _SymmetricSolver | None = None  # one instance: one Pardiso memory at a time


def solve_symmetric(matrix: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs`` for a symmetric ``matrix`` (the tangent: positive definite, or
    indefinite past a limit point) with MKL Pardiso in its symmetric indefinite mode: half
    the storage and work of a general LU, the analysis of a pattern done once, the factors in
    single precision (:class:`_SymmetricSolver`). RuntimeError where the solver refuses the
    matrix (a load step that fails, halved by :meth:`TetReference._step`)."""
    global _SYMMETRIC_SOLVER
    if _SYMMETRIC_SOLVER is None:
        _SYMMETRIC_SOLVER = _SymmetricSolver(SINGLE_PRECISION_FACTORS)
    upper = sp.triu(matrix, format="csr")
    upper.sort_indices()
    return _SYMMETRIC_SOLVER.solve(upper, np.asarray(rhs, dtype=np.float64))


def set_factor_precision(single: bool = SINGLE_PRECISION_FACTORS) -> _SymmetricSolver:
    """Make the later solves factor in single precision (``single``) or in double, with a
    fresh solver (its counters at zero); the solver."""
    global _SYMMETRIC_SOLVER
    if _SYMMETRIC_SOLVER is not None:
        _SYMMETRIC_SOLVER._forget()
    _SYMMETRIC_SOLVER = _SymmetricSolver(single)
    return _SYMMETRIC_SOLVER


def factors_single() -> bool:
    """Whether the solves factor Newton's tangents in single precision now."""
    if _SYMMETRIC_SOLVER is None:
        return SINGLE_PRECISION_FACTORS
    return _SYMMETRIC_SOLVER.single


@contextmanager
def factor_precision(single: bool) -> Iterator[None]:
    """The solves inside factor in ``single`` precision (or double); the precision before is
    restored after."""
    before = factors_single()
    set_factor_precision(single)
    try:
        yield
    finally:
        set_factor_precision(before)


def resolve_symmetric(rhs: np.ndarray) -> np.ndarray:
    """The matrix of the last :func:`solve_symmetric` ^-1 ``rhs``, from its factors
    (:meth:`_SymmetricSolver.resolve`)."""
    if _SYMMETRIC_SOLVER is None:
        raise RuntimeError("P2 reference: no factored tangent to reuse")
    return _SYMMETRIC_SOLVER.resolve(np.asarray(rhs, dtype=np.float64))


def _face_travel(rest: np.ndarray, start: np.ndarray, end: np.ndarray, footprint: Any) -> float:
    """How far (mm) a corner of ``footprint``'s bounding rectangle on the face at ``rest``
    (4, 4) moves from the relative pose ``start`` (4, 4) to ``end``; 0 without a footprint."""
    if footprint is None:
        return 0.0
    half = footprint.half_mm
    corners = np.array([[sx * half[0], sy * half[1], 0.0, 1.0] for sx in (-1, 1)
                        for sy in (-1, 1)]) @ np.asarray(rest).T
    return float(np.abs(corners @ (end - start).T).max())


def _barycentric_gradients(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(t, 4, 3) gradients of the barycentric coordinates of each tetrahedron."""
    e = points[tets[:, 1:]] - points[tets[:, :1]]  # rows: x1 - x0, x2 - x0, x3 - x0
    inv = np.linalg.inv(e)  # columns: gradients of lambda_1..3
    g123 = inv.transpose(0, 2, 1)
    return np.concatenate([-g123.sum(axis=1, keepdims=True), g123], axis=1)


def _boundary_nodes(tets: np.ndarray, n_points: int, elements: np.ndarray) -> np.ndarray:
    """P2 node indices (vertices and edge nodes) on the boundary faces of the tetrahedra."""
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]],
                                    tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]), axis=1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    vertices = np.unique(boundary)
    on_boundary = np.zeros(n_points, dtype=bool)
    on_boundary[vertices] = True
    # an edge node is on the boundary when its edge is an edge of a boundary face
    pairs = np.sort(np.concatenate([boundary[:, [0, 1]], boundary[:, [1, 2]],
                                    boundary[:, [0, 2]]]), axis=1)
    face_edges = {tuple(p) for p in np.unique(pairs, axis=0)}
    edge_nodes = []
    for el, tet in zip(elements, tets, strict=True):
        for k, (a, b) in enumerate(EDGES):
            key = (min(tet[a], tet[b]), max(tet[a], tet[b]))
            if key in face_edges:
                edge_nodes.append(el[4 + k])
    return np.concatenate([vertices, np.unique(edge_nodes)]).astype(np.int64)
