"""A rigid-probe push solved by NGSolve, a second FE code that shares nothing with biopsynav's
element kernels, assembly, quadrature or Newton: the peer of ``benchmarks/truth_agreement.py``.

The problem is the one of ``biopsynav.evaluate.p2`` with the face glued to the skin (the
skin nodes under the face at rest move rigidly with the probe; other skin is free), so the two
codes can be compared on the same tetrahedra:

* the body: the tetrahedra (points mm, tets) handed in (gmsh's, as the P2 reference meshes
  them), homogeneous compressible neo-Hookean
  ``W = mu / 2 (tr C - 3) - mu ln J + lam / 2 (ln J)^2`` (E MPa, nu), NGSolve's ``VectorH1``
  of any order (2: the P2 reference's element; 3 and up: p refinement on the same mesh),
  integrated by a rule of ``intorder``;
* fixed: the chest wall's vertices handed in (``fixed``), and every edge and face dof whose
  vertices are all fixed (the trace is zero there);
* moved: the boundary vertices that the face holds at rest (``held``: the tracker's rule,
  :func:`biopsynav.tracker.contact_indices` on the mesh's boundary vertices) translate by the
  push, and the higher-order dofs of edges and faces between them stay zero (a rigid
  translation is affine, so its trace has no higher-order part);
* load steps of at most ``step_mm`` of the push, each started from the linear response to
  the step (the tangent at the last state with the new boundary values) and solved by Newton
  with a backtracking line search on the energy that refuses states where it is not finite
  (an element inverted), to ``|du| <= tol * |u|``; a step that fails is halved.

Requires ``ngsolve`` (``pip install 'biopsynav[peer]'``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

try:
    import ngsolve as ngs
    from netgen.meshing import Element3D, FaceDescriptor, MeshPoint, Pnt
    from netgen.meshing import Mesh as NetgenMesh
except ImportError as exc:  # pragma: no cover - said by the benchmark
    raise SystemExit(f"ngsolve_peer: NGSolve does not import ({exc}); install it with "
                     "pip install 'biopsynav[peer]'") from None


def netgen_mesh(points: np.ndarray, tets: np.ndarray) -> ngs.Mesh:
    """An NGSolve mesh of tetrahedra ``tets`` (t, 4) on ``points`` (p, 3) mm, positively
    oriented as biopsynav's (netgen numbers a tetrahedron the other way round)."""
    m = NetgenMesh(dim=3)
    ids = [m.Add(MeshPoint(Pnt(*map(float, p)))) for p in points]
    m.Add(FaceDescriptor(bc=1, domin=1, surfnr=1))
    m.SetMaterial(1, "tissue")
    for t in tets:
        m.Add(Element3D(1, [ids[t[0]], ids[t[2]], ids[t[1]], ids[t[3]]]))
    return ngs.Mesh(m)


@dataclass
class NgPush:
    """One lesion's pushes by NGSolve: the lesion displacement (3,) mm per depth (None past a
    failure), the number of dofs, the failure, if any, and the Newton iterations per step."""

    displacement: list = field(default_factory=list)
    dofs: int = 0
    failure: str = ""
    newton: list = field(default_factory=list)


class NgsolvePush:
    """The glued-face push problem of a mesh in NGSolve (module doc)."""

    def __init__(self, points: np.ndarray, tets: np.ndarray, e_mpa: float, nu: float,
                 fixed: np.ndarray, held: np.ndarray, order: int = 2, intorder: int = 5,
                 threads: int = 2) -> None:
        ngs.SetNumThreads(threads)
        self.mesh = netgen_mesh(points, tets)
        self.fes = ngs.VectorH1(self.mesh, order=order)
        mu = e_mpa / (2.0 * (1.0 + nu))
        lam = e_mpa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        u = self.fes.TrialFunction()
        f = ngs.Id(3) + ngs.Grad(u)
        c = f.trans * f
        j = ngs.Det(f)
        energy = mu / 2 * (ngs.Trace(c) - 3) - mu * ngs.log(j) + lam / 2 * ngs.log(j) ** 2
        self.form = ngs.BilinearForm(self.fes, symmetric=True)
        self.form += ngs.Variation(energy.Compile() * ngs.dx(
            intrules={ngs.TET: ngs.IntegrationRule(ngs.TET, intorder)}))
        self.free = self.fes.FreeDofs()
        for d in (*self._dofs_of(held), *self._dofs_of(fixed)):
            self.free.Clear(int(d))
        self.u = ngs.GridFunction(self.fes)
        self._vertex_dofs = self._vertex_component_dofs(held)

    def _dofs_of(self, vertices: np.ndarray) -> np.ndarray:
        """Every dof (all components) of the vertices ``vertices`` and of the edges, faces and
        cells whose vertices are all among them."""
        inside = np.zeros(self.mesh.nv, dtype=bool)
        inside[np.asarray(vertices, dtype=np.int64)] = True
        dofs = []
        for kind, nodes in ((ngs.VERTEX, self.mesh.vertices), (ngs.EDGE, self.mesh.edges),
                            (ngs.FACE, self.mesh.faces)):
            for node in nodes:
                vs = [v.nr for v in node.vertices] if kind != ngs.VERTEX else [node.nr]
                if inside[vs].all():
                    dofs += list(self.fes.GetDofNrs(ngs.NodeId(kind, node.nr)))
        return np.array(sorted(set(dofs)), dtype=np.int64)

    def _vertex_component_dofs(self, vertices: np.ndarray) -> np.ndarray:
        """The (k, 3) dofs of the x, y, z components of each vertex of ``vertices``."""
        rows = [list(self.fes.GetDofNrs(ngs.NodeId(ngs.VERTEX, int(v)))) for v in vertices]
        return np.array(rows, dtype=np.int64).reshape(len(rows), 3)

    @property
    def n_dofs(self) -> int:
        return int(self.fes.ndof)

    def boundary_values(self, shift: np.ndarray) -> ngs.BaseVector:
        """A vector that holds ``shift`` (3,) mm on the held vertices' dofs, 0 elsewhere."""
        g = self.u.vec.CreateVector()
        g[:] = 0.0
        arr = g.FV().NumPy()
        for axis in range(3):
            arr[self._vertex_dofs[:, axis]] = shift[axis]
        return g

    def energy(self, vec: ngs.BaseVector) -> float:
        value = self.form.Energy(vec)
        return value if np.isfinite(value) else np.inf

    def _newton_step(self, delta: ngs.BaseVector) -> ngs.BaseVector:
        """The Newton update at the current state with the constrained dofs moved by
        ``delta``: ``du`` equal to ``delta`` there, ``K_ff du_f = -(r + K delta)_f``."""
        self.form.AssembleLinearization(self.u.vec)
        res = self.u.vec.CreateVector()
        self.form.Apply(self.u.vec, res)
        res.data += self.form.mat * delta
        du = delta.CreateVector()
        du.data = delta
        du.data -= self.form.mat.Inverse(self.free, inverse="sparsecholesky") * res
        return du

    def _line_search(self, du: ngs.BaseVector, e0: float) -> bool:
        """u += s du with the largest s in 1, 1/2, ... (10 halvings) whose energy is finite
        and, once the constrained dofs sit at their values, not above ``e0``; False when
        none is."""
        trial = self.u.vec.CreateVector()
        s = 1.0
        for _ in range(11):
            trial.data = self.u.vec + s * du
            e = self.energy(trial)
            if np.isfinite(e) and e <= e0 + 1e-12 * max(abs(e0), 1.0):
                self.u.vec.data = trial
                return True
            s /= 2.0
        return False

    def solve_step(self, target: np.ndarray, tol: float = 1e-8, max_iter: int = 40) -> int:
        """Move the held vertices to ``target`` (3,) mm from where they are and solve;
        the Newton iterations used; RuntimeError when it does not converge."""
        now = self.u.vec.FV().NumPy()[self._vertex_dofs[0]] if len(self._vertex_dofs) else 0
        delta = self.boundary_values(np.asarray(target) - now)
        saved = self.u.vec.CreateVector()
        saved.data = self.u.vec
        du = self._newton_step(delta)
        trial = self.u.vec.CreateVector()
        trial.data = self.u.vec + du
        if not np.isfinite(self.energy(trial)):  # the linear predictor inverts an element
            self.u.vec.data = saved
            raise RuntimeError("the step's predictor inverts an element")
        self.u.vec.data = trial
        zero = self.boundary_values(np.zeros(3))
        for it in range(1, max_iter + 1):
            du = self._newton_step(zero)
            if not self._line_search(du, self.energy(self.u.vec)):
                self.u.vec.data = saved
                raise RuntimeError("no admissible decrease of the energy")
            size = ngs.Norm(du)
            if size <= tol * max(ngs.Norm(self.u.vec), 1.0):
                return it
        self.u.vec.data = saved
        raise RuntimeError(f"Newton did not converge in {max_iter} iterations")

    def displacement_at(self, point: np.ndarray) -> np.ndarray:
        """The displacement (3,) mm at ``point`` (3,) mm."""
        return np.array(self.u(self.mesh(*map(float, point))))


def push_depths(problem: NgsolvePush, direction: np.ndarray, depths: list[float],
                lesion: np.ndarray, step_mm: float = 2.5, min_step_mm: float = 0.1) -> NgPush:
    """Push along ``direction`` (3,) unit to each of ``depths`` (mm, increasing) in load
    steps of at most ``step_mm`` (halved where one fails), the lesion ``lesion`` (3,) mm
    displacement recorded at each depth."""
    out = NgPush(dofs=problem.n_dofs)
    done = 0.0
    for depth in depths:
        while done < depth - 1e-9:
            step = min(step_mm, depth - done)
            while True:
                try:
                    out.newton.append(problem.solve_step((done + step) * np.asarray(direction)))
                    done += step
                    break
                except RuntimeError as exc:
                    step /= 2.0
                    if step < min_step_mm:
                        out.failure = f"{depth:g} mm: {exc}"
                        out.displacement += [None] * (len(depths) - len(out.displacement))
                        return out
        out.displacement.append(problem.displacement_at(lesion).tolist())
    return out
