"""Probe pose in, lesion positions out.

Probe frame (documented once, used everywhere): origin at the centre of the probe face, z along
the ultrasound beam into the tissue, x along the long (50 mm) side of the face, y = z x x.
A pose ``T`` is the 4 x 4 (or top 3 x 4) probe-to-anatomy transform in mm.

At the rest pose (probe just touching the skin) the contact points are the skin vertices under
the footprint (|x| <= L/2, |y| <= W/2 in the probe frame) within ``[probe]
contact_tolerance_mm`` of the face plane, facing the probe. They then follow the rigid motion of
the probe from the rest pose (the paper's assumption); their displacement, spread on the grid,
drives the network (or the FE model with prescribed displacements), and lesions are read off
the predicted grid displacement by trilinear interpolation. The network's prediction is
projected onto the contact (:mod:`biopsynav.contact.projection`, ``[network]
contact_projection``): it moves the contact points exactly as the probe does. With ``[tracker]
contact_follows_pose`` skin that the face reaches during a push joins the contact set, held on
the face (both engines; :mod:`biopsynav.tracker.contactset` for the network's).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..anatomy.display import lesion_mesh
from ..case import Case, as_case
from ..contact.lesions import PointOperator
from ..errors import InputError, SolverError
from ..footprint import Footprint, as_footprint
from ..grid.embedding import Embedding, surface_embedding
from ..grid.index import field_to_tensor
from ..probe import (
    ContactInputOperator,
    chest_distance,
    contact_input_operator,
    skin_under_face,
    towards_chest,
)
from . import result as st
from .bound import LesionCheck, basis_words, error_bound_mm
from .contactset import (
    MAX_GROWN_SETS,
    NetContactSet,
    behind_face,
    onto_face,
    pinned_by_contact,
    reach_candidates,
)
from .result import LesionResult, TrackingResult

if TYPE_CHECKING:
    from ..fem import SolverSettings

LIFT_OFF_MM = 0.5  # contact points moved this far out of the tissue: the probe left the skin
AT_REST_MM = 1e-6  # no contact point moved further: the rest pose (up to rounding), no solve
PENETRATION_TOL_MM = 0.1  # FE engine: skin further behind the probe face is held on it
CONTACT_ROUNDS = 4  # network engine: most predictions of the grown contact set
FE_CONTACT_ROUNDS = 8  # FE engine: most solves of the active set (skin the face reaches)
#: FE engine with ``continuation``: prescribed displacements within this share of their norm
#: of a multiple of the last push's lie on its line (a push along the probe axis: rounding)
CONTINUATION_TOLERANCE = 1e-9


def as_pose(matrix: np.ndarray) -> np.ndarray:
    """A 4 x 4 float64 pose from a 4 x 4 or 3 x 4 array (no checks)."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return m


def pose_problem(matrix: np.ndarray, tol: float) -> str:
    """Empty if ``matrix`` is a finite rigid transform, else why it is not.

    Plain float arithmetic on the 12-16 numbers, no NumPy reductions: this runs first on every
    pose, and took 0.1 ms hot / 0.4 ms after 10 ms idle with ``allclose`` and ``det``.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((4, 4), (3, 4)):
        return f"pose has shape {m.shape}, expected 4 x 4 or 3 x 4"
    rows = m.tolist()
    if not all(math.isfinite(v) for row in rows for v in row):
        return "pose contains NaN or infinite values"
    if len(rows) == 4 and max(abs(a - b) for a, b in zip(rows[3], (0.0, 0.0, 0.0, 1.0),
                                                         strict=True)) > tol:
        return "pose last row is not (0, 0, 0, 1)"
    r = [row[:3] for row in rows[:3]]
    cols = list(zip(*r, strict=True))  # R^T R - I: dot products of the columns
    dev = max(abs(sum(a * b for a, b in zip(cols[i], cols[j], strict=True)) - (i == j))
              for i in range(3) for j in range(i, 3))
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
           - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    if dev > tol or det < 0:
        return f"pose rotation is not rigid (orthonormality error {dev:.2g}, det {det:.3g})"
    return ""


def contact_indices(anatomy, pose: np.ndarray, footprint: Footprint | tuple[float, float],
                    tol: float) -> np.ndarray:
    """Indices of skin vertices in contact with the probe face at ``pose`` (rest pose):
    under ``footprint`` (or (long, short) mm: a rectangle), within ``tol`` mm of the face."""
    pose = as_pose(pose)
    r = pose[:3, :3]
    # outward skin normals against the beam (the probe's z axis)
    return skin_under_face(anatomy, pose[:3, 3], r, as_footprint(footprint), tol, -r[:, 2])


def lesion_meshes(lesions) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Lesion id -> (vertices (k, 3) mm, faces (m, 3)) of a closed mesh of its surface points
    (:func:`biopsynav.anatomy.display.lesion_mesh`); lesions whose points span no volume get
    none."""
    out = {}
    for les in lesions:
        try:
            out[les.id] = lesion_mesh(les.points)
        except ValueError:
            continue
    return out


class Tracker:
    """Lesion tracker of one case, backed by the U-Net (``engine="net"``) or the FE model."""

    def __init__(self, case: Case, engine: str, surrogate=None, fem_model=None,
                 fem_settings=None, teacher=None, continuation: bool = False,
                 lesion_check: LesionCheck | None = None) -> None:
        """``lesion_check``: the network's lesion self-check that widens each bound (None:
        none, or stale; :meth:`load` reads the model's). ``teacher``: a refined
        :class:`~biopsynav.fem.teacher.Teacher` whose grid the FE engine solves on
        (``fem_model`` is its model), its answer fitted to the case grid;
        None: the FE engine solves on the case grid. ``continuation`` (FE engine): a push
        further along the line of the last one over the same rest pose starts from that
        push's equilibrium instead of from rest (:meth:`_continuation_start`)."""
        self.case = case
        self.continuation = continuation
        self._last_push: tuple[np.ndarray, np.ndarray] | None = None
        self._teacher = teacher
        self._fem_contact: Embedding | None = None  # contact points in the FE engine's grid
        self._fem_surface: Embedding | None = None
        self._vertex_areas: np.ndarray | None = None  # skin area per vertex, mm^2
        self._case_e_mpa: np.ndarray | None = None  # the case grid's element moduli, MPa
        self.engine = engine
        self._surrogate = surrogate
        self._fem_model = fem_model
        self._fem_settings = fem_settings
        a = case.anatomy
        self._lesion_ids = [les.id for les in a.lesions]
        self._lesion_centres = np.array([les.center for les in a.lesions]).reshape(-1, 3)
        self.lesion_meshes = lesion_meshes(a.lesions)
        self._lesion_points, self._lesion_emb = self._lesion_embedding()
        self._centre_emb = self._lesion_emb.subset(np.arange(len(self._lesion_ids)))
        self._rest: np.ndarray | None = None
        self._contact: np.ndarray = np.zeros(0, dtype=np.int64)
        self._contact_emb: Embedding | None = None
        self._fem_rows: dict = {}  # the FE engine's constraint rows and springs, by grid
        self.last_touched = np.zeros(0, dtype=np.int64)  # skin the face reached, last update
        self._input = np.zeros((4, *case.grid.node_shape), dtype=np.float32)
        self._input_flat = self._input.reshape(4, -1)
        self._surface_emb: Embedding | None = None
        self._net: NetContactSet | None = None  # the net engine's rest pose contact set
        self._grown: dict[bytes, NetContactSet] = {}  # ... grown by skin the face reached
        self._reach = np.zeros(0, dtype=np.int64)  # skin vertices the face may reach
        self._reach_emb: Embedding | None = None
        self._input_op: ContactInputOperator | None = None  # the input last written
        self._compliance = None
        self.last_solve = None  # the FE engine's last SolveReport (biopsynav.fem.solver)
        env = surrogate.envelope if surrogate is not None else {}
        self.max_contact_mm = float(env.get("max_contact_disp_mm", np.inf))
        # the deepest training push (mean contact-point displacement); models trained before
        # it was recorded have only the contact bound
        self.max_probe_mm = float(env.get("max_probe_disp_mm", np.inf))
        # rigid pushes compressing the tissue in front of the chest wall under the face by no
        # more than this share (models trained before the limit, or without rigid pushes: 0)
        self.max_compression = float(env.get("max_chest_compression", 0.0))
        self._chest_mm = np.inf  # the rest contact's distance to the chest wall, mm
        self.envelope_margin = case.cfg.tracker.envelope_margin
        self.lesion_check = lesion_check

    def _lesion_embedding(self) -> tuple[np.ndarray, Embedding]:
        """The points read off the displacement field: lesion centres first, then the vertices
        of each lesion mesh (one embedding, so the hot path moves the lesion surfaces with the
        same operators as the centres). Centres only, and no meshes, when a mesh vertex lies
        outside the grid."""
        grid = self.case.grid
        points = np.vstack([self._lesion_centres] + [v for v, _ in self.lesion_meshes.values()])
        try:
            return points, Embedding.build(grid, points, where="lesion surfaces")
        except InputError:
            self.lesion_meshes = {}
            return self._lesion_centres, Embedding.build(grid, self._lesion_centres,
                                                         where="lesions")

    @classmethod
    def load(cls, case: Case | str | Path, engine: str | None = None,
             threads: int | None = None) -> Tracker:
        """The tracker of ``case`` (loaded, or its folder) with its engine: ``"net"`` (the
        tracking model, fingerprint-checked, on the case's ``[network] runtime``:
        :func:`~biopsynav.inference.surrogate.load_for_case`, with its lesion self-check where
        current) or ``"fem"`` (finite elements
        with prescribed contact displacements). ``threads``: CPU threads of the network
        (None: ``[network] threads``; 0: the idle cores)."""
        case = as_case(case)
        engine = engine or case.cfg.tracker.engine
        if engine == "net":
            from ..inference.surrogate import load_for_case

            surrogate = load_for_case(case, threads=threads)
            ids = [les.id for les in case.anatomy.lesions]
            check = LesionCheck.load(surrogate.model_dir, surrogate.meta, ids)
            return cls(case, engine, surrogate=surrogate, lesion_check=check)
        if engine == "fem":
            return fem_engine(case, fem_solver_settings(case))
        raise InputError(f"unknown engine {engine!r}; use net or fem", "tracker")

    @property
    def bound_basis(self) -> str:
        """What each lesion's ``bound_mm`` rests on, in words (:mod:`.bound`)."""
        if self.engine != "net":
            return "the network's bound without a lesion self-check (the FE engine)"
        return basis_words(self.lesion_check)

    @property
    def surrogate(self):
        """The network engine's model (:class:`~biopsynav.inference.surrogate.Surrogate`);
        None for the FE engine."""
        return self._surrogate

    @property
    def has_rest_pose(self) -> bool:
        return self._rest is not None

    @property
    def rest_pose(self) -> np.ndarray | None:
        """The rest pose (4, 4) or None."""
        return self._rest

    @property
    def n_contact(self) -> int:
        return len(self._contact)

    def _beyond_trained_compression(self, u_c: np.ndarray) -> str:
        """Why the face's motion ``u_c`` (n, 3) mm presses the tissue before the chest wall
        under it beyond ``envelope_margin`` x the trained share, '' when it does not (or the
        model has no such limit)."""
        if self.max_compression <= 0.0:
            return ""
        share = towards_chest(self.case.anatomy, u_c.mean(axis=0)) / max(self._chest_mm, 1e-9)
        if share <= self.max_compression * self.envelope_margin:
            return ""
        return (f"the probe compresses the {self._chest_mm:.0f} mm of tissue in front of the "
                f"chest wall by {100 * share:.0f} %, beyond the trained "
                f"{100 * self.max_compression:.0f} %")

    def set_rest_pose(self, pose: np.ndarray) -> int:
        """Take ``pose`` (probe just touching the skin) as the rest pose; return the number of
        contact points. Raises InputError for a pose that is not a finite rigid transform."""
        problem = pose_problem(pose, self.case.cfg.tracker.rigid_tolerance)
        if problem:
            raise InputError(problem, "rest pose")
        pose = as_pose(pose)
        cfg = self.case.cfg.probe
        idx = contact_indices(self.case.anatomy, pose, cfg.footprint,
                              cfg.contact_tolerance_mm)
        self._rest = pose
        self._rest_inv = np.linalg.inv(pose)
        self._contact = idx
        self._contact_points = self.case.anatomy.vertices[idx]
        self._contact_normals = self.case.anatomy.normals[idx]
        self._chest_mm = chest_distance(self.case.anatomy, idx) if len(idx) else np.inf
        self._forget_contact_sets()
        if len(idx):
            self._contact_emb = Embedding.build(self.case.grid, self._contact_points,
                                                where="contact points")
            if self.engine == "net":
                from ..threads import one_thread

                if self.case.cfg.tracker.contact_follows_pose:
                    self._set_reach(pose)
                with one_thread():  # many small dense solves (docs/igtl.md, rest pose)
                    self._net = self._net_contact_set(np.zeros(0, dtype=np.int64))
        return len(idx)

    def _forget_contact_sets(self) -> None:
        """Drop everything built for the previous rest pose's contact set."""
        self._fem_rows = {}
        self._last_push = None
        self._fem_contact = self._net = self._reach_emb = None
        self._input_op = None
        self._grown = {}
        self._reach = np.zeros(0, dtype=np.int64)
        self._input[:] = 0.0

    def clear_rest_pose(self) -> None:
        """Forget the rest pose (and its contact set); ``update`` answers ``no_rest_pose``."""
        self._rest = None
        self._contact = np.zeros(0, dtype=np.int64)
        self._contact_emb = None
        self._forget_contact_sets()

    def _set_reach(self, pose: np.ndarray) -> None:
        """The skin vertices a push from the rest ``pose`` may add to the net engine's
        contact set (:func:`~biopsynav.tracker.contactset.reach_candidates`)."""
        a, skin = self.case.anatomy, self._surface_embedding()
        pinned = pinned_by_contact(skin.nodes, self._contact_emb.nodes,
                                   int(np.prod(self.case.grid.node_shape)))
        self._reach = reach_candidates(a.vertices, a.normals, a.pushable, pose[:3, 2],
                                       self._contact, pinned)
        self._reach_emb = skin.subset(self._reach) if len(self._reach) else None

    def _net_contact_set(self, touched: np.ndarray) -> NetContactSet:
        """The net engine's :class:`~biopsynav.tracker.contactset.NetContactSet` of the rest
        contact plus the skin vertices ``touched`` (t,): the contact projection (``[network]
        contact_projection``, or a model trained through it) and the operators asked of the
        surrogate (:meth:`Surrogate.point_operator`; None without a physics baseline or
        lesions). The rest set's lesion operator covers the lesion meshes at once; a grown
        set's is built when asked for (:meth:`_lesion_operator`)."""
        sur, n = self._surrogate, len(self._lesion_ids)
        emb = self._contact_emb
        if len(touched):
            emb = Embedding.build(self.case.grid, self.case.anatomy.vertices[
                np.concatenate([self._contact, touched])], where="contact points")
        op = self._input_operator_of(emb, np.concatenate([self._contact, touched]))
        proj = (sur.contact_projection(emb.matrix, op)
                if sur.projects(self.case.cfg.network.contact_projection) else None)
        lesion_op = centre_op = None
        if n and not len(touched):
            lesion_op = sur.point_operator(self._lesion_emb, op, proj)
            centre_op = None if lesion_op is None else lesion_op.first(n)
        elif n:
            centre_op = sur.point_operator(self._centre_emb, op, proj)
        reach_op = (None if self._reach_emb is None
                    else sur.point_operator(self._reach_emb, op, proj))
        return NetContactSet(touched, emb, op, proj, centre_op, lesion_op, reach_op)

    def _lesion_operator(self, state: NetContactSet) -> PointOperator | None:
        """The lesion centres' and mesh vertices' operator of ``state``, built once."""
        if state.lesion_op is None and state.centre_op is not None:
            state.lesion_op = self._surrogate.point_operator(
                self._lesion_emb, state.input_op, state.projection)
        return state.lesion_op

    def _grown_set(self, touched: np.ndarray) -> NetContactSet:
        """The contact set of the rest contact plus ``touched`` (sorted), built once per rest
        pose (the oldest of more than ``MAX_GROWN_SETS`` forgotten)."""
        key = touched.tobytes()
        state = self._grown.get(key)
        if state is None:
            from ..threads import one_thread

            with one_thread():
                state = self._grown[key] = self._net_contact_set(touched)
            if len(self._grown) > MAX_GROWN_SETS:
                del self._grown[next(iter(self._grown))]
        return state

    @property
    def projects_contact(self) -> bool:
        """Whether the net engine's predictions honour the contact points exactly (the
        contact projection, docs/network.md) for the current rest pose."""
        return self._net is not None and self._net.projection is not None

    @property
    def contact_input_kind(self) -> str:
        """How contact displacements become the network input: the model's kind (net
        engine) or the case's ``[dataset] contact_input``."""
        if self._surrogate is not None:
            return self._surrogate.contact_input
        return self.case.cfg.dataset.contact_input

    def input_operator(self) -> ContactInputOperator:
        """The network input of the rest pose's contact set as a linear map of the contact
        displacements (:func:`biopsynav.probe.contact_input_operator`, as the data set)."""
        if self._contact_emb is None:
            raise InputError("no contact points: set a rest pose with skin under the probe",
                             "tracker")
        return self._input_operator_of(self._contact_emb, self._contact)

    def _input_operator_of(self, points: Embedding, vertices: np.ndarray
                           ) -> ContactInputOperator:
        """The network input operator of the contact points ``points``, the skin
        ``vertices`` (n,): with springs when the model learnt elastic contact, as its data
        were built (:func:`biopsynav.dataset.worker.input_springs`)."""
        kind = self.contact_input_kind
        compliance = self._contact_compliance() if kind == "elastic" else None
        springs = None
        beta = self._learnt_contact_stiffness()
        if beta is not None and kind == "elastic":
            from ..contact.constraints import grid_springs
            from ..contact.springs import case_young_moduli

            if self._case_e_mpa is None:
                self._case_e_mpa = case_young_moduli(self.case)
            springs = grid_springs(beta, self._case_e_mpa, self.case.grid, points.cells,
                                   self._skin_areas()[vertices])
        return contact_input_operator(points.matrix, kind, compliance, springs)

    def _learnt_contact_stiffness(self) -> float | None:
        """The springs' beta of the elastic contact the network learnt (its ``meta.json``
        teacher), None for a model that did not (or the FE engine)."""
        sur = self._surrogate
        if sur is None or not sur.learnt_elastic_contact:
            return None
        beta = (sur.meta.get("teacher") or {}).get("contact_stiffness")
        return self.case.cfg.tracker.contact_stiffness if beta is None else float(beta)

    def _contact_compliance(self):
        """The case's :class:`~biopsynav.contact.greens.ContactCompliance`: the baseline's when
        the model has one, else computed once."""
        baseline = getattr(self._surrogate, "baseline", None)
        if baseline is not None:
            return baseline.compliance
        if self._compliance is None:
            from ..contact.greens import ContactCompliance
            from ..refine import tracking_teacher_case

            self._compliance = ContactCompliance.from_case(tracking_teacher_case(self.case))
        return self._compliance

    def contact_displacement(self, pose: np.ndarray) -> np.ndarray:
        """Displacement (n_contact, 3) mm of the contact points moved rigidly with the probe."""
        rel = as_pose(pose) @ self._rest_inv
        moved = self._contact_points @ rel[:3, :3].T + rel[:3, 3]
        return moved - self._contact_points

    def update(self, pose: np.ndarray, with_surface: bool = False,
               lesion_surfaces: bool = False, with_field: bool = False) -> TrackingResult:
        """Lesion positions for probe ``pose``; the status says whether to trust them.

        ``with_surface``: also the moved skin (``result.surface``, from the full grid field);
        ``lesion_surfaces``: also each lesion's moved mesh vertices (``LesionResult.surface``);
        ``with_field``: also the case grid's displacement (``result.grid_displacement``,
        (n_nodes, 3) mm).
        """
        start = time.perf_counter()
        self.last_solve = None
        self.last_touched = self._reach[:0]
        problem = pose_problem(pose, self.case.cfg.tracker.rigid_tolerance)
        if problem:
            return self._unreliable(st.INVALID_POSE, problem, start)
        if self._rest is None:
            return self._unreliable(st.NO_REST_POSE, "no rest pose set", start)
        if not len(self._contact):
            return self._unreliable(st.NO_CONTACT, "no skin under the probe face at the rest "
                                    "pose", start)
        u_c = self.contact_displacement(pose)
        push = -np.einsum("ij,ij->i", u_c, self._contact_normals)  # into the tissue
        if np.median(push) < -LIFT_OFF_MM:
            return self._rest_result(st.NO_CONTACT, "probe lifted off the skin", start)
        norms = np.linalg.norm(u_c, axis=1)
        largest, depth = float(norms.max()), float(norms.mean())
        if largest <= AT_REST_MM:  # the rest pose itself: nothing moved, no solve or prediction
            return self._rest_result(st.OK, "", start)
        if largest > self.max_contact_mm * self.envelope_margin:
            return self._unreliable(st.OUT_OF_ENVELOPE, f"contact displacement {largest:.1f} mm "
                                    f"beyond the trained {self.max_contact_mm:.1f} mm", start)
        if depth > self.max_probe_mm * self.envelope_margin:
            return self._unreliable(st.OUT_OF_ENVELOPE, f"probe displacement {depth:.1f} mm "
                                    f"beyond the deepest trained push, {self.max_probe_mm:.1f} "
                                    "mm", start)
        pressed = self._beyond_trained_compression(u_c)
        if pressed:
            return self._unreliable(st.OUT_OF_ENVELOPE, pressed, start)
        try:
            if self.engine == "net":
                field, disp = self._net_answer(u_c, as_pose(pose), with_surface or with_field,
                                               lesion_surfaces)
            else:
                field = self._fem_field(u_c, as_pose(pose))
                emb = self._lesion_emb if lesion_surfaces else self._centre_emb
                disp = emb.interpolate(field)
        except SolverError as exc:  # the FE engine did not converge: say so, not "unusual pose"
            return self._unreliable(st.SOLVER_FAILED, exc.what, start)
        except Exception as exc:  # never a confident number from a failed prediction
            return self._unreliable(st.TRACKER_ERROR, f"{type(exc).__name__}: {exc}", start)
        note = "" if self.last_solve is None else self.last_solve.fallback_note()
        res = TrackingResult(self._lesion_results(disp, st.OK, depth), st.OK, note, 0.0)
        if with_surface:
            res.surface = self.case.anatomy.vertices + self._surface_embedding().interpolate(field)
        if with_field:
            res.grid_displacement = field
        res.latency_ms = (time.perf_counter() - start) * 1e3
        return res

    def _net_answer(self, u_c: np.ndarray, pose: np.ndarray, with_surface: bool,
                    surfaces: bool) -> tuple[np.ndarray | None, np.ndarray]:
        """The net engine's grid field (n_nodes, 3) mm when ``with_surface`` (else None) and
        the displacements (n_points, 3) mm of the lesion centres, with ``surfaces`` of their
        mesh vertices too, for the rest contact's displacements ``u_c`` (n, 3) mm at ``pose``.
        Without the full field: the network's residual and the surrogate's point operator
        (:class:`~biopsynav.contact.lesions.PointOperator`; the hot path of :meth:`update`)."""
        state, g, net = self._net, u_c, None
        if self._reach_emb is not None:
            state, g, net = self._settled_contact(u_c, pose)
        self.last_touched = state.touched
        op = self._lesion_operator(state) if surfaces else state.centre_op
        if op is not None and not with_surface:
            if net is None:
                net = self._network_residual(state, g)
            return None, op.displacement(net, g)
        field = self._net_field(state, g)
        return field, (self._lesion_emb if surfaces else self._centre_emb).interpolate(field)

    def _settled_contact(self, u_c: np.ndarray, pose: np.ndarray
                         ) -> tuple[NetContactSet, np.ndarray, np.ndarray]:
        """The net engine's contact set at ``pose`` (4, 4) grown by the skin the prediction
        puts behind the face (at most ``CONTACT_ROUNDS`` predictions), the displacements
        (n, 3) mm of its points (the rest contact's ``u_c``, then the touched skin held on
        the face) and the network's output for it."""
        state, g = self._net, u_c
        net = self._network_residual(state, g)
        fp, beam = as_footprint(self.case.cfg.probe.footprint), pose[:3, 2]
        rest = self.case.anatomy.vertices[self._reach]
        for _ in range(CONTACT_ROUNDS - 1):
            disp = self._reach_displacement(state, net, g)
            behind, depth = behind_face(rest + disp, pose, fp, PENETRATION_TOL_MM)
            held = np.isin(self._reach, state.touched)
            if not (behind & ~held).any():
                break
            keep = held | behind
            g = np.vstack([u_c, onto_face(disp[keep], depth[keep], beam)])
            state = self._grown_set(self._reach[keep])
            net = self._network_residual(state, g)
        return state, g, net

    def _reach_displacement(self, state: NetContactSet, net: np.ndarray,
                            g: np.ndarray) -> np.ndarray:
        """Predicted displacement (m, 3) mm of the skin the face may reach, for the network
        output ``net`` of ``state`` with its points moved by ``g``."""
        if state.reach_op is not None:
            return state.reach_op.displacement(net, g)
        return self._reach_emb.interpolate(net.reshape(3, -1).T)  # no baseline: net is u

    def _network_residual(self, state: NetContactSet, g: np.ndarray) -> np.ndarray:
        """The exported network's output (3, nx, ny, nz) mm for the points of ``state``
        moved by ``g`` (n, 3) mm."""
        self._set_input(g, state.input_op)
        return self._surrogate.predict_network(self._input)

    def _net_field(self, state: NetContactSet, g: np.ndarray) -> np.ndarray:
        """The surrogate's grid displacement (n_nodes, 3) mm for the points of ``state``
        moved by ``g`` (n, 3) mm (projected onto them when ``state`` projects)."""
        self._set_input(g, state.input_op)
        if state.projection is not None:
            out = self._surrogate.predict(self._input, state.projection, g)
        else:
            out = self._surrogate.predict(self._input)
        return out.reshape(3, -1).T

    def _fem_field(self, u_c: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """The FE engine's grid displacement (n_nodes, 3) mm for contact displacements
        ``u_c`` (n_contact, 3) mm at ``pose`` (4, 4): the rest pose's contact points
        move with the probe (``[tracker] fem_contact`` constraints); with ``[tracker]
        contact_follows_pose`` skin that the face reaches is added as frictionless contact
        (an active set: solve, find skin behind the face plane under the footprint, hold it
        on the plane along the beam, free to slide, let go held skin that elastic contact's
        springs pull (a vertex at most once: one that passes the face again stays held), and
        solve again; at most ``FE_CONTACT_ROUNDS`` solves). ``self.last_touched``: the skin
        vertices added. With a refined teacher the solve runs on its grid and the answer is
        fitted to the case grid; when that teacher extrapolates (``[dataset]
        teacher_extrapolation``), the case grid solves the same contact too and the answer is
        extrapolated from both, as the teacher's data are (cells it would stretch beyond
        ``[dataset] max_edge_stretch`` keep the fitted field)."""
        touched = released = np.zeros(0, dtype=np.int64)
        u = self._fem_solve(u_c, pose, touched)
        if self.case.cfg.tracker.contact_follows_pose:
            for _ in range(FE_CONTACT_ROUNDS - 1):
                moved = self._moved_skin(u)
                new = self._skin_behind_face(moved, pose, touched)
                pulled = np.setdiff1d(self._skin_pulled(moved, pose, touched), released)
                if not len(new) and not len(pulled):
                    break
                touched = np.union1d(np.setdiff1d(touched, pulled), new)
                released = np.union1d(released, pulled)
                u = self._fem_solve(u_c, pose, touched)
        self.last_touched = touched
        if self._teacher is None:
            return u
        u_case = None
        if self._teacher.coarse is not None:
            u_case = self._fem_solve(u_c, pose, touched, on_case_grid=True)
        return self._teacher.case_field(u, (self._contact_emb.matrix, u_c), u_case,
                                        self.case.cfg.dataset.max_edge_stretch)

    def _fem_solve(self, u_c: np.ndarray, pose: np.ndarray, touched: np.ndarray,
                   on_case_grid: bool = False) -> np.ndarray:
        """One solve: the rest contact points prescribed to ``u_c`` and the skin vertices
        ``touched`` held on the face plane (normal component only); on the FE engine's grid,
        or with ``on_case_grid`` on the case grid by the extrapolating teacher's model."""
        from ..fem import Loads, solve

        if on_case_grid:
            model, contact, surface = (self._teacher.coarse, self._contact_emb,
                                       self._surface_embedding())
        else:
            model, contact, surface = (self._fem_model, self._fem_contact_embedding(),
                                       self._fem_surface_embedding())
        key = "case" if on_case_grid else "fem"
        rows, springs = self._constraint_rows(contact, model, key)
        w, g = rows @ contact.matrix, rows @ u_c
        normals = None
        if len(touched):
            beam = pose[:3, 2]
            rest = self.case.anatomy.vertices[touched]
            depth = (rest - pose[:3, 3]) @ beam  # < 0: behind the face, rest position
            held = surface.subset(touched)
            w = sp.vstack([w, held.matrix]).tocsr()
            g = np.vstack([g, -depth[:, None] * beam])
            normals = np.vstack([np.zeros((rows.shape[0], 3)), np.tile(beam, (len(touched), 1))])
            if springs is not None:
                springs = np.concatenate([springs, self._springs(model, key, held.cells,
                                                                 touched)])
        continuing = self.continuation and not on_case_grid and not len(touched)
        u, report = solve(model, Loads(
            prescribed_matrix=w, prescribed_displacement=g, prescribed_normals=normals,
            prescribed_stiffness=springs), self._fem_settings,
            self._continuation_start(g) if continuing else None)
        if continuing:
            self._keep_for_continuation(g, report)
        if not on_case_grid:
            self.last_solve = report
        return u

    def _continuation_start(self, g: np.ndarray) -> tuple[float, np.ndarray] | None:
        """Where the solve of prescribed displacements ``g`` (n, 3) mm starts: when the last
        kept push of this rest pose prescribed ``t g`` for some t in (0, 1) (the probe further
        along the same line, as Table 2's deeper pushes are), at load factor t from its
        equilibrium, (t, free displacement (n_eq,) mm): the same load path as from rest, its
        first part already solved; else None (from rest)."""
        if self._last_push is None or self._last_push[0].shape != g.shape:
            return None
        g_last, u_free = self._last_push
        gg = float(np.sum(g * g))
        t = float(np.sum(g_last * g)) / gg if gg > 0.0 else 0.0
        on_line = np.linalg.norm(g_last - t * g) <= CONTINUATION_TOLERANCE * np.sqrt(gg)
        return (t, u_free) if 0.0 < t < 1.0 and on_line else None

    def _keep_for_continuation(self, g: np.ndarray, report) -> None:
        """Keep a solve's prescribed displacements ``g`` (n, 3) mm and equilibrium for the
        next push; only an answer of the springs as asked (a stiffer fallback's state is of
        other loads)."""
        as_asked = report.spring_factor in (None, 1.0) and report.reached is not None
        self._last_push = (g.copy(), report.reached[1]) if as_asked else None

    def _moved_skin(self, u: np.ndarray) -> np.ndarray:
        """Every skin vertex (n_vertices, 3) mm moved by the displacement ``u``
        (n_fem_nodes, 3) mm of the FE engine's grid."""
        return self.case.anatomy.vertices + self._fem_surface_embedding().interpolate(u)

    def _skin_behind_face(self, moved: np.ndarray, pose: np.ndarray, touched: np.ndarray
                          ) -> np.ndarray:
        """Skin vertices not yet held (off the chest wall, facing the probe, not in a cell of
        the rest contact set) that lie, moved to ``moved`` (n_vertices, 3) mm by the FE
        engine (:meth:`_moved_skin`), under the footprint and more than
        ``PENETRATION_TOL_MM`` behind the face plane at ``pose``."""
        a = self.case.anatomy
        skin = self._fem_surface_embedding()
        behind, _ = behind_face(moved, pose, as_footprint(self.case.cfg.probe.footprint),
                                PENETRATION_TOL_MM)
        behind &= (a.normals @ pose[:3, 2] < 0.0) & a.pushable
        behind[self._contact] = False
        behind[touched] = False
        # nodes of the cells holding rest contact points move with the probe already: a
        # constraint on a point of a cell sharing them could only contradict them (and, with a
        # small weight on the other nodes, invert the cell)
        behind &= ~pinned_by_contact(skin.nodes, self._fem_contact_embedding().nodes,
                                     self._fem_model.n_nodes)
        return np.flatnonzero(behind)

    def _skin_pulled(self, moved: np.ndarray, pose: np.ndarray, touched: np.ndarray
                     ) -> np.ndarray:
        """The ``touched`` skin vertices that lie, moved to ``moved`` (n_vertices, 3) mm by
        the FE engine (:meth:`_moved_skin`), in front of the face plane at ``pose``: with
        elastic contact their springs pull them towards the probe, which a face cannot do.
        Empty when the contact points are met (they lie on the plane)."""
        from ..contact.constraints import is_elastic

        if not is_elastic(self.case.cfg.tracker.fem_contact):
            return touched[:0]
        return touched[(moved[touched] - pose[:3, 3]) @ pose[:3, 2] > 0.0]

    def _fem_contact_embedding(self) -> Embedding:
        """The rest contact points in the FE engine's grid (the teacher's, or the case's)."""
        if self._teacher is None:
            return self._contact_emb
        if self._fem_contact is None:
            self._fem_contact = Embedding.build(self._teacher.grid, self._contact_points,
                                                where="contact points")
        return self._fem_contact

    def _fem_surface_embedding(self) -> Embedding:
        """Every skin vertex in the FE engine's grid."""
        if self._teacher is None:
            return self._surface_embedding()
        if self._fem_surface is None:
            self._fem_surface = surface_embedding(self._teacher.grid, self.case.anatomy)
        return self._fem_surface

    def _constraint_rows(self, contact: Embedding, model, key: str):
        """The constraint rows (n_constraints, n_contact) of the rest pose's contact set
        embedded as ``contact`` in the grid named ``key`` ("fem" or "case") of ``model``
        (``[tracker] fem_contact``, :mod:`biopsynav.contact.constraints`) and their springs
        (n_contact,) N/mm with elastic contact (else None), built once per rest pose."""
        if key not in self._fem_rows:
            from ..contact.constraints import constraint_rows

            self._fem_rows[key] = (constraint_rows(self.case.cfg.tracker.fem_contact,
                                                   contact.cells),
                                   self._springs(model, key, contact.cells, self._contact))
        return self._fem_rows[key]

    def _springs(self, model, key: str, cells: np.ndarray, vertices: np.ndarray
                 ) -> np.ndarray | None:
        """Spring stiffness (n,) N/mm of the skin ``vertices`` (n,) in the flat ``cells``
        (n,) of the grid named ``key`` ("fem" or "case") with elastic contact (``[tracker]
        fem_contact``, ``contact_stiffness``); None when the points are met."""
        from ..contact.constraints import contact_springs

        cfg = self.case.cfg.tracker
        grid = self.case.grid if key == "case" or self._teacher is None else self._teacher.grid
        return contact_springs(cfg.fem_contact, cfg.contact_stiffness, model.E_mpa, grid,
                               cells, self._skin_areas()[vertices])

    def _skin_areas(self) -> np.ndarray:
        """The skin area (n_vertices,) mm^2 each vertex stands for, computed once."""
        if self._vertex_areas is None:
            from ..contact.constraints import vertex_areas

            self._vertex_areas = vertex_areas(self.case.anatomy.vertices,
                                              self.case.anatomy.faces)
        return self._vertex_areas

    def _set_input(self, u_c: np.ndarray, op: ContactInputOperator) -> None:
        """Write ``self._input`` for the contact points of the input operator ``op`` moved by
        ``u_c`` (n, 3) mm (the weight channel and the zeros around the written values only
        when ``op`` changed)."""
        if op is not self._input_op:
            self._input[:] = 0.0
            self._input_flat[3] = op.weights
            self._input_op = op
        self._input.reshape(-1)[op.positions] = op.matrix @ u_c.ravel()

    def network_input(self, u_c: np.ndarray) -> np.ndarray:
        """The (4, nx, ny, nz) network input for contact displacements, built as the dataset
        builds it (:func:`biopsynav.probe.contact_input` is ``contact_input_operator(...)
        .field(u)``); the hot path writes the same operator's values into its own buffer."""
        field = self.input_operator().field(u_c)
        return field_to_tensor(field, self.case.grid.node_shape).astype(np.float32)

    def _surface_embedding(self) -> Embedding:
        if self._surface_emb is None:
            self._surface_emb = surface_embedding(self.case.grid, self.case.anatomy)
        return self._surface_emb

    def _lesion_results(self, disp: np.ndarray, status: str,
                        depth_mm: float = 0.0) -> list[LesionResult]:
        """Lesions moved by ``disp`` (n_points, 3) mm at ``_lesion_points`` by a push of
        ``depth_mm``: centres, their 95 % bounds and, when ``disp`` covers them, the mesh
        vertices."""
        n = len(self._lesion_ids)
        check = self.lesion_check
        bounds = (error_bound_mm(disp[:n], depth_mm) if check is None else
                  error_bound_mm(disp[:n], depth_mm, check.relative_at(depth_mm),
                                 check.teacher_gap))
        if len(disp) == n:
            return [LesionResult(i, c + d, d, status, bound_mm=float(b)) for i, c, d, b in
                    zip(self._lesion_ids, self._lesion_centres, disp, bounds, strict=True)]
        moved = self._lesion_points + disp
        out, at = [], n
        for k, i in enumerate(self._lesion_ids):
            res = LesionResult(i, moved[k], disp[k], status, bound_mm=float(bounds[k]))
            if i in self.lesion_meshes:
                size = len(self.lesion_meshes[i][0])
                res.surface, at = moved[at:at + size], at + size
            out.append(res)
        return out

    @property
    def skin_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The breast surface at rest: vertices (nv, 3) mm and faces (nf, 3); ``update(pose,
        with_surface=True).surface`` gives the vertices where they moved to."""
        return self.case.anatomy.vertices, self.case.anatomy.faces

    def prepare_surface(self) -> None:
        """Build now what the first ``update(pose, with_surface=True)`` would otherwise
        build: the skin vertices' embedding in the grid (on a clinical skin of 10^5
        vertices, longer than ten updates)."""
        self._surface_embedding()

    def _rest_result(self, status: str, reason: str, start: float) -> TrackingResult:
        lesions = self._lesion_results(np.zeros_like(self._lesion_points), status)
        return TrackingResult(lesions, status, reason, (time.perf_counter() - start) * 1e3)

    def _unreliable(self, status: str, reason: str, start: float) -> TrackingResult:
        nan = np.full(3, np.nan)
        lesions = [LesionResult(i, nan.copy(), nan.copy(), status) for i in self._lesion_ids]
        return TrackingResult(lesions, status, reason, (time.perf_counter() - start) * 1e3)


def fem_solver_settings(case: Case) -> SolverSettings:
    """The FE engine's solver settings: ``[solver]``, with elastic contact's springs as asked
    given ``[tracker] spring_budget`` Newton iterations before their fallbacks."""
    from ..fem import SolverSettings

    settings = SolverSettings.from_config(case.cfg.solver)
    settings.first_attempt_budget = int(case.cfg.tracker.spring_budget)
    return settings


def finer_grid_spring_budget(settings: SolverSettings | None, refinement: float
                             ) -> SolverSettings | None:
    """``settings`` for a grid ``refinement`` times finer than the case's: the budget of the
    springs as asked scaled by ``refinement`` (None stays None: the solver's defaults have
    none; 0, no budget, stays 0). ``[tracker] spring_budget`` was measured on the case grid,
    and finer grids converge more slowly: on 3.65 mm cells (2 times finer) a first attempt
    converged after 110 Newton iterations, under the 160 this gives (docs/experiments.md, "The FE
    engine's budget")."""
    import dataclasses

    if settings is None:
        return None
    budget = math.ceil(settings.first_attempt_budget * max(float(refinement), 1.0))
    return dataclasses.replace(settings, first_attempt_budget=budget)


def fem_engine(case: Case, settings, on_teacher: bool = True,
               continuation: bool = False) -> Tracker:
    """A tracker backed by the FE model with solver ``settings``: on the teacher's grid when
    ``on_teacher`` and the tracking model's teacher is refined (``[dataset] teacher_refine``
    > 1, or ``[refine]``: the FE that taught the network), else on ``case``'s own grid;
    with that teacher's law either way (``[refine] material_model`` with ``[refine]``).
    ``continuation``: see :class:`Tracker`."""
    from ..fem import FEModel
    from ..fem.teacher import build_teacher, teacher_refinement
    from ..refine import tracking_teacher_case

    taught_by = tracking_teacher_case(case)
    refinement = teacher_refinement(taught_by.cfg)
    if on_teacher and refinement > 1:
        teacher = build_teacher(taught_by)
        return Tracker(case, "fem", fem_model=teacher.model,
                       fem_settings=finer_grid_spring_budget(settings, refinement),
                       teacher=teacher, continuation=continuation)
    return Tracker(case, "fem", fem_model=FEModel.from_case(taught_by), fem_settings=settings,
                   continuation=continuation)
