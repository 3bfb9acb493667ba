"""Mesh convergence of the FE teacher: lesion displacements under rigid-probe pushes on a sequence
of immersed hexahedral grids, against an independent P2 tetrahedral reference in the same run.

    python benchmarks/convergence.py CASE [--cells 7.3 5 3.65] [--depths 10 20 30]
                                          [--contact points cell_average]
                                          [--laws neo-hookean neo-hookean-sri]
                                          [--lesions 3 | --lesion-ids 1,5]
                                          [--tet-size 10] [--tet-fine 2.5]
                                          [--tet-rim 1.5] [--friction slip]
                                          [--edge-radius 2.5] [--progress]
                                          [--push-minutes 20]
                                          [--no-probe-body]
                                          [--teachers 1.46:2 2:0]
                                          [--nu 0.45] [--out convergence.json]
                                          [--reuse-reference earlier.json]

For each evaluated lesion the probe is placed over it as in Table 2
(:func:`biopsynav.evaluate.placement.place_probe`) and pushed along its beam by each depth. The
skin the face touches at rest follows the probe rigidly (the tracker's contact model), the
chest wall is fixed, the material is homogeneous neo-Hookean (E of the case's default tissue,
``--nu``). In the reference the probe is a rigid body: skin the face reaches during the push
slides on it, none passes through it; the hexahedral FE adds that contact when the case sets
``[tracker] contact_follows_pose``. Two discretisations answer:

* biopsynav's FE (``Tracker(engine="fem")``: immersed hexahedra, prescribed contact-point
  displacements) on grids of each ``--cells`` size, the first being the default 7.3 mm, with
  each ``--contact`` kind of constraint (:mod:`biopsynav.contact.constraints`: every contact
  point, or the mean of each cell's points) and each ``--laws`` hexahedral integration of the
  neo-Hookean energy (``neo-hookean``: 2x2x2 Gauss points; ``neo-hookean-sri``: its volumetric
  term at the cell centre, free of volumetric locking);
* the reference, ``biopsynav.evaluate.p2``: quadratic tetrahedra of a gmsh mesh of the
  same surface (about ``--tet-size`` mm, ``--tet-fine`` mm within 35 mm of the probe,
  ``--tet-rim`` mm along the edge of the probe face when given), its own assembly and Newton
  loop; its face holds the skin it touches at rest (``--friction stick``) or lets every
  contact slide (``slip``); the probe is a flat face with sharp edges, or with
  ``--edge-radius`` a body whose face's edges are rounded by that radius and whose sides no
  skin passes (``--progress`` logs its load steps and contact rounds). ``--no-probe-body``
  leaves the body out: only the skin touched at rest is held and the rest of the skin may
  pass through the face, the contact model of the hexahedral FE without ``[tracker]
  contact_follows_pose``; run beside the full reference, it tells how much of a grid's
  error is its contact model rather than its discretisation.

Beside the grids, each ``--teachers REFINE:ORDER`` is a training teacher on the first grid
(``[dataset] teacher_refine`` and ``teacher_extrapolation``, answered by the FE engine as
``track --engine fem`` does): ``1.46:2`` solves on 5 mm cells and on the 7.3 mm grid and
extrapolates from both (Richardson, order 2), ``2:0`` is the 3.65 mm grid fitted to the case
grid.

Printed per variant (law and contact kind), lesion and depth: the lesion displacement |u| of
every grid and of the reference, each grid's error (distance to the reference's displacement
vector, mm), the displacement extrapolated to zero cell size from the two finest grids (first
order, the immersed boundary's), and the observed order from the three finest (when the
sequence is monotone). A lesion is one point of the field: beside them, a table compares the
whole displacement field near the probe, each series' mean error (mm) over up to
``FIELD_POINTS`` points inside the breast, within ``FIELD_RADIUS_MM`` of the probe at rest and
``SKIN_CLEARANCE_MM`` from the skin (drawn with a fixed seed; kept with the reference's answers
so that a reused reference is compared at the same points). The last line reads ``RESULT``
with the mean and largest error of each variant, grid and teacher against the reference, the
field's as ``err_field_...``.

Everything is written to ``CASE/eval/convergence.json`` (or ``--out``), with a ``summary`` of
each series' errors that the case's report shows beside Table 2; a run in progress keeps its
figures in ``convergence.partial.json`` beside it (the P2 pushes of the lesion in progress,
its answers and state after each depth, in ``convergence.p2-lesion<index>.partial.npz``: a
stopped run continues from the last depth solved), and the last finished study stays as it
is until the new one ends.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from biopsynav.case import Case  # noqa: E402
from biopsynav.contact.constraints import contact_constraint_names  # noqa: E402
from biopsynav.errors import BiopsynavError, InputError  # noqa: E402
from biopsynav.evaluate.p2 import QUADRATURE_DEGREE, QUADRATURE_DEGREES  # noqa: E402
from biopsynav.evaluate.placement import place_case_probe  # noqa: E402
from biopsynav.evaluate.simulation import evaluation_solver_settings, select_lesions  # noqa: E402
from biopsynav.fem import FEModel  # noqa: E402
from biopsynav.fileio import load_npz, read_json, save_npz_atomic, write_json_atomic  # noqa: E402
from biopsynav.grid.build import build_grid  # noqa: E402
from biopsynav.grid.embedding import Embedding  # noqa: E402
from biopsynav.layout import CasePaths  # noqa: E402
from biopsynav.reference_registry import P2_FRICTIONS  # noqa: E402
from biopsynav.refine import tracking_teacher_config  # noqa: E402
from biopsynav.tracker import Tracker  # noqa: E402
from biopsynav.tracker.core import fem_engine  # noqa: E402

# the displacement fields are compared at up to FIELD_POINTS points inside the breast, within
# FIELD_RADIUS_MM of the probe at rest and SKIN_CLEARANCE_MM or more from the skin (mm)
FIELD_POINTS, FIELD_RADIUS_MM, SKIN_CLEARANCE_MM = 400, 50.0, 4.0


def homogeneous(case: Case, nu: float) -> tuple[Case, float]:
    """The case with every tissue set to its default tissue's E (MPa) and ``nu``."""
    cfg = copy.deepcopy(case.cfg)
    e_mpa = float(cfg.material.tissues[cfg.material.default_tissue]["E_mpa"])
    cfg.material.model = "neo-hookean"
    cfg.material.tissues = {name: {"E_mpa": e_mpa, "nu": nu} for name in cfg.material.tissues}
    return Case(case.dir, cfg, case.anatomy, case.grid), e_mpa


def sized_grid(case: Case, cell_mm: float):
    """The immersed grid of ``case``'s anatomy with cells of ``cell_mm`` mm, its other
    ``[grid]`` settings as the case's."""
    section = dataclasses.replace(case.cfg.grid, cell_size_mm=float(cell_mm))
    return build_grid(case.anatomy, section,
                      chest_tol_mm=case.cfg.anatomy.chest_wall_tolerance_mm)


def hex_tracker(case: Case, cell_mm: float, variant: str = "neo-hookean/points"
                ) -> tuple[Tracker, int]:
    """biopsynav's FE tracker of ``case`` on a grid of ``cell_mm`` cells for ``variant``
    (``law/contact``: material law and contact constraints); its active cells."""
    law, contact = variant.split("/")
    grid = sized_grid(case, cell_mm)
    cfg = copy.deepcopy(case.cfg)
    cfg.tracker.fem_contact = contact
    cfg.material.model = law
    sized = Case(case.dir, cfg, case.anatomy, grid)
    tracker = Tracker(sized, "fem", fem_model=FEModel.from_case(sized),
                      fem_settings=evaluation_solver_settings(sized))
    return tracker, int(grid.active_cells.sum())


def teacher_tracker(case: Case, cell_mm: float, teacher: str) -> Tracker:
    """The FE engine of the training teacher ``teacher`` ("REFINE:ORDER": ``[dataset]
    teacher_refine`` and ``teacher_extrapolation``) on the case with ``cell_mm`` cells."""
    refine, order = (float(v) for v in teacher.split(":"))
    grid = sized_grid(case, cell_mm)
    cfg = copy.deepcopy(case.cfg)
    cfg.refine.samples = 0  # the teacher named here, not the case's [refine] one
    cfg.dataset.teacher_refine, cfg.dataset.teacher_extrapolation = refine, order
    sized = Case(case.dir, cfg, case.anatomy, grid)
    return fem_engine(sized, evaluation_solver_settings(sized))


def teacher_spec(text: str) -> str:
    """A ``--teachers`` item: REFINE:ORDER, REFINE in [1, 4] (1: the grid itself), ORDER >= 0."""
    try:
        refine, order = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give REFINE:ORDER, e.g. 1.46:2") from None
    if not (1.0 <= refine <= 4.0 and 0.0 <= order <= 8.0) or (order > 0 and refine == 1.0):
        raise argparse.ArgumentTypeError(f"{text!r}: REFINE in [1, 4], ORDER in [0, 8] (> 0 "
                                         "only with REFINE > 1)")
    return f"{refine:g}:{order:g}"


def field_points(anatomy, centre: np.ndarray, radius_mm: float = FIELD_RADIUS_MM,
                 n: int = FIELD_POINTS, seed: int = 0) -> np.ndarray:
    """Up to ``n`` points (k, 3) mm inside the breast within ``radius_mm`` of ``centre`` (3,)
    mm (the probe at rest), at least ``SKIN_CLEARANCE_MM`` from every skin vertex, drawn with
    a fixed ``seed``: where the displacement fields are compared, beside the lesions."""
    from scipy.spatial import cKDTree

    from biopsynav.anatomy.model import winding_number

    rng = np.random.default_rng(seed)
    pts = centre + rng.uniform(-radius_mm, radius_mm, size=(8 * n, 3))
    pts = pts[np.linalg.norm(pts - centre, axis=1) <= radius_mm]
    pts = pts[winding_number(pts, anatomy.vertices, anatomy.faces) > 0.5]
    pts = pts[cKDTree(anatomy.vertices).query(pts)[0] >= SKIN_CLEARANCE_MM]
    return pts[:n]


def hex_pushes(tracker: Tracker, placement, lesion: int, depths: list[float],
               points: np.ndarray | None = None) -> dict:
    """For each depth: ``displacement``, the lesion's (3,) mm, and ``field``, the displacement
    (k, 3) mm at ``points`` (k, 3) mm (None without points); None where the solve failed."""
    emb = None if points is None else Embedding.build(tracker.case.grid, points,
                                                      where="field points")
    tracker.set_rest_pose(placement.pose)
    disp, field = [], []
    for depth in depths:
        res = tracker.update(placement.pushed(depth), with_field=emb is not None)
        ok = res.status == "ok"
        disp.append(res.lesions[lesion].displacement.tolist() if ok else None)
        field.append(emb.interpolate(res.grid_displacement).tolist()
                     if ok and emb is not None else None)
    return {"displacement": disp, "field": field}


def tet_pushes(case: Case, e_mpa: float, nu: float, placement, lesion: int,
               depths: list[float], args, points: np.ndarray | None = None,
               probe_body: bool = True, checkpoint: Path | None = None) -> tuple[list, dict]:
    """The P2 reference's lesion displacements for each depth, and its mesh facts; with
    ``points`` (k, 3) mm the facts hold them (``field_points``) and the displacement there
    per depth (``field``, None past a failure). Without ``probe_body`` only the skin touched
    at rest is held (other skin may pass through the face). With ``checkpoint`` (an ``.npz``
    path) the answers and the model's state are kept there after each depth, a run stopped
    between depths continues after the last one kept (the same mesh and settings; else it
    starts again), and the file is removed once every depth is answered; after a failure
    (or a push given up) it stays, so that a later run continues after the last depth
    answered (``truth.py --retry-failed``)."""
    from biopsynav.evaluate.p2 import PushTimeout

    t0 = time.perf_counter()
    probe = case.cfg.probe
    ref, contact = reference_model(case, e_mpa, nu, placement, args)
    centre = np.asarray(case.anatomy.lesions[lesion].center)[None]
    at = centre if points is None else np.vstack([centre, points])
    kept = PushCheckpoint(checkpoint, push_key(ref, e_mpa, nu, placement, at, args, probe_body)
                          ) if checkpoint is not None else None
    got = kept.load(ref, depths) if kept is not None else new_answers()
    failure = ""
    rest = placement.pose
    for depth in depths[len(got["disp"]):]:  # one push at a time, each from the last
        try:
            (u,) = ref.push(rest, [placement.pushed(depth)], contact, at,
                            start=ref.last if got["disp"] else None,
                            footprint=probe.footprint if probe_body else None,
                            edge_radius_mm=args.edge_radius, time_limit_s=push_limit_s(args))
        except (FloatingPointError, RuntimeError) as exc:  # a failure ends the lesion
            failure = f"{depth:g} mm: {exc}"
            break
        except PushTimeout:
            failure = f"{depth:g} mm: gave up after {args.push_minutes:g} min (--push-minutes)"
            break
        record_depth(got, ref, u, centre[0])
        if kept is not None:
            kept.save(ref, got, depths, time.perf_counter() - t0)
    if kept is not None and not failure:
        kept.clear()
    return pushes_facts(ref, contact, got, depths, points, failure,
                        got["seconds"] + time.perf_counter() - t0)


def reference_model(case: Case, e_mpa: float, nu: float, placement, args) -> tuple:
    """The P2 model (:class:`~biopsynav.evaluate.p2.TetReference`) of ``case``'s anatomy
    meshed for pushes at ``placement`` (``args``' mesh sizes), and its skin nodes the face
    holds at rest."""
    from biopsynav.evaluate.p2 import TetReference, rim_at

    probe = case.cfg.probe
    ref = TetReference.build(case.anatomy, args.tet_size, e_mpa, nu,
                             fine_at=placement.pose[:3, 3], fine_mm=args.tet_fine,
                             rim=rim_at(placement.pose, probe.footprint, args.tet_rim),
                             quadrature_degree=args.quadrature_degree)
    return ref, ref.contact(placement.pose, probe.footprint, probe.contact_tolerance_mm,
                            args.friction)


def push_limit_s(args) -> float | None:
    """Seconds a reference push may run (``--push-minutes``; None: no limit)."""
    return 60.0 * args.push_minutes if args.push_minutes > 0 else None


def new_answers() -> dict:
    """The answers of no depth yet: lesion displacement, field, folded elements, nearest fold
    per depth, and the seconds spent before this run (a resumed run's earlier time)."""
    return {"disp": [], "field": [], "tangled": [], "nearest": [], "seconds": 0.0}


def record_depth(got: dict, ref, u: np.ndarray, centre: np.ndarray) -> None:
    """Add one depth's answer ``u`` (1 + k, 3) mm (the lesion, then the field points) to
    ``got`` (:func:`new_answers`), with the folds of ``ref``'s last push."""
    got["disp"].append(u[0].tolist())
    got["field"].append(u[1:].tolist())
    got["tangled"].append(len(ref.tangled(ref.last)))
    got["nearest"].append(nearest_fold_mm(ref, ref.last, centre + u[0]))


def pushes_facts(ref, contact: np.ndarray, got: dict, depths: list[float],
                 points: np.ndarray | None, failure: str, seconds: float) -> tuple[list, dict]:
    """:func:`tet_pushes`' answer: the lesion displacement per depth (None past a failure)
    and the facts of the mesh and the run."""
    pad = [None] * (len(depths) - len(got["disp"]))
    facts = {"tets": len(ref.elements), "dofs": ref.n_dofs, "contact_nodes": len(contact),
             "seconds": seconds, "failure": failure,
             "tangled_elements": got["tangled"], "nearest_fold_mm": got["nearest"]}
    if points is not None:
        facts["field_points"] = points.tolist()
        facts["field"] = got["field"] + pad
    return got["disp"] + pad, facts


def push_key(ref, e_mpa: float, nu: float, placement, at: np.ndarray, args,
             probe_body: bool) -> dict:
    """What a lesion's P2 pushes depend on besides their depths: the mesh, the material, the
    probe's pose and body, the quadrature rule and the points answered."""
    return {"mesh": ref.mesh_fingerprint(), "E_mpa": e_mpa, "nu": nu,
            "pose": np.asarray(placement.pose).tolist(), "friction": args.friction,
            "edge_radius_mm": args.edge_radius, "probe_body": probe_body,
            "quadrature_degree": args.quadrature_degree,
            "points": hashlib.sha256(np.ascontiguousarray(at, dtype=np.float64).tobytes()
                                     ).hexdigest()}


#: what a lesion's P2 checkpoint holds: the answers so far, then TetReference.push_state
PUSH_STATE_KEYS = ("answers", "last", "last_rel", "sliding", "kept")


def p2_checkpoint(beside: Path, lesion: int) -> Path:
    """Where the P2 pushes over lesion index ``lesion`` keep their answers and state between
    depths: ``<beside's stem>.p2-lesion<lesion>.partial.npz`` beside ``beside``."""
    return beside.with_name(f"{beside.stem}.p2-lesion{lesion}.partial.npz")


@dataclasses.dataclass(frozen=True)
class PushCheckpoint:
    """A lesion's P2 pushes kept after each depth (``path``, an ``.npz``): the answers so
    far and :meth:`TetReference.push_state`, valid for pushes of the same ``key``."""

    path: Path
    key: dict

    def load(self, ref, depths: list[float]) -> dict:
        """The answers kept for the first depths of ``depths``, with ``ref`` set to continue
        after them; new answers (and a line saying why) when there are none to continue."""
        if not self.path.is_file():
            return new_answers()
        try:
            state = load_npz(self.path, PUSH_STATE_KEYS, "starting the lesion again")
            kept = json.loads(str(state.pop("answers")))
        except (InputError, ValueError) as exc:
            print(f"{self.path}: unreadable ({exc}); starting the lesion again", flush=True)
            return new_answers()
        done = kept["depths_mm"]
        if kept["key"] != self.key or done != list(depths[:len(done)]):
            print(f"{self.path}: another mesh, probe or depth list; starting the lesion again",
                  flush=True)
            return new_answers()
        ref.resume(state)
        print(f"{self.path}: continuing after {', '.join(f'{d:g}' for d in done)} mm",
              flush=True)
        return kept["answers"]

    def save(self, ref, got: dict, depths: list[float], seconds: float) -> None:
        """Keep ``got`` (:func:`new_answers`, for the first of ``depths``; ``seconds`` more
        spent) and ``ref``'s state."""
        answers = {**got, "seconds": got["seconds"] + seconds}
        text = json.dumps({"key": self.key, "depths_mm": list(depths[:len(got["disp"])]),
                           "answers": answers})
        save_npz_atomic(self.path, answers=np.array(text), **ref.push_state())

    def clear(self) -> None:
        """Remove the file (every depth of the lesion is answered)."""
        self.path.unlink(missing_ok=True)


def nearest_fold_mm(ref, u: np.ndarray, point: np.ndarray) -> float | None:
    """How far (mm) from ``point`` (3,) mm lies the nearest node of an element that the
    displacement ``u`` (n, 3) mm folds over (:meth:`TetReference.tangled`), both deformed;
    None when none is folded."""
    folded = ref.tangled(u)
    if not len(folded):
        return None
    nodes = np.unique(ref.elements[folded])
    return float(np.linalg.norm(ref.nodes[nodes] + u[nodes] - point, axis=1).min())


def non_negative_mm(text: str) -> float:
    """A size in mm given on the command line: a finite number, 0 or more."""
    return non_negative(text, "a size in mm")


def non_negative_minutes(text: str) -> float:
    """A time in minutes given on the command line: a finite number, 0 or more."""
    return non_negative(text, "a time in minutes")


def non_negative(text: str, what: str) -> float:
    """``text`` as a finite number, 0 or more; else an argument error saying it must be
    ``what``."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: {what}, 0 or more")
    return value


def add_reference_arguments(p: argparse.ArgumentParser, fine_mm: float) -> None:
    """The P2 reference's options: its mesh sizes (``fine_mm`` near the probe by default)
    and its probe face's friction."""
    p.add_argument("--tet-size", type=float, default=10.0, help="reference tetrahedra, mm")
    p.add_argument("--tet-fine", type=float, default=fine_mm,
                   help="reference tetrahedra within 35 mm of the probe, mm")
    p.add_argument("--tet-rim", type=non_negative_mm, default=0.0,
                   help="reference tetrahedra at the edge of the probe face, mm (0: no finer "
                        "rim)")
    p.add_argument("--friction", choices=P2_FRICTIONS, default="stick",
                   help="the reference's probe face: 'stick' (the skin it touches at rest moves "
                        "with it, as the tracker's contact points) or 'slip' (frictionless)")
    p.add_argument("--edge-radius", type=non_negative_mm, default=0.0,
                   help="the reference's probe: its face's edges rounded by this radius, mm, "
                        "with sides that no skin passes (0: a flat face with sharp edges)")
    add_quadrature_argument(p)
    p.add_argument("--progress", action="store_true",
                   help="log the reference's load steps and contact rounds to stderr")
    p.add_argument("--push-minutes", type=non_negative_minutes, default=0.0,
                   help="give up a reference push still solving after this many minutes: "
                        "that depth and the deeper ones are recorded as failed ('gave up'), "
                        "the depths before kept (0: no limit)")


def add_quadrature_argument(p: argparse.ArgumentParser) -> None:
    """``--quadrature-degree``: the degree of the P2 reference's rule over each tetrahedron,
    one of :data:`~biopsynav.evaluate.p2.QUADRATURE_DEGREES` (rules with positive weights)."""
    p.add_argument("--quadrature-degree", type=int, choices=QUADRATURE_DEGREES,
                   default=QUADRATURE_DEGREE,
                   help="the degree of the P2 reference's quadrature rule over each "
                        f"tetrahedron, scikit-fem's (default {QUADRATURE_DEGREE}: the stored "
                        "truths')")


def check_edge_radius(case: Case, args) -> None:
    """SystemExit, before any work, when ``--edge-radius`` does not fit the case's probe
    face (below half its short side)."""
    if args.edge_radius:
        from biopsynav.evaluate.p2_contact import rounded_body

        try:
            rounded_body(case.cfg.probe.footprint, args.edge_radius)
        except ValueError as exc:
            raise SystemExit(f"--edge-radius: {exc}") from None


def show_progress(args) -> None:
    """With ``--progress``, the P2 reference's log (``biopsynav.p2``) on stderr."""
    if args.progress:
        import logging

        logging.basicConfig(format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
        logging.getLogger("biopsynav.p2").setLevel(logging.INFO)


def reference_line(case: Case, lesion: int, facts: dict, depths: list[float]) -> str:
    """One line on the P2 reference of ``lesion`` (index): its mesh, time, any failure, and
    the depths whose answer holds folded elements (:meth:`TetReference.tangled`) with the
    distance of the nearest from the lesion."""
    counts = facts.get("tangled_elements", [])
    near = facts.get("nearest_fold_mm", [None] * len(counts))
    folded = [f"{n} at {d:g} mm" + (f" (nearest {m:.1f} mm from the lesion)" if m else "")
              for d, n, m in zip(depths, counts, near, strict=False) if n]
    return (f"  P2 reference, lesion {case.anatomy.lesions[lesion].id}: {facts['tets']} "
            f"tetrahedra, {facts['dofs']} dofs, {facts['contact_nodes']} contact nodes, "
            f"{facts['seconds']:.0f} s" + (f"; failed at {facts['failure']}"
                                           if facts["failure"] else "")
            + (f"; elements folded over at a node (not to be trusted): {', '.join(folded)}"
               if folded else ""))


def extrapolated(cells: list[float], values: list) -> np.ndarray | None:
    """First-order extrapolation to zero cell size from the two finest grids (3,) mm; None
    with fewer than two grids or a failed one."""
    if len(cells) < 2:
        return None
    (h2, u2), (h3, u3) = sorted(zip(cells, values, strict=True), reverse=True)[-2:]
    if u2 is None or u3 is None:
        return None
    u2, u3 = np.asarray(u2), np.asarray(u3)
    return u3 + (u3 - u2) * h3 / (h2 - h3)


def observed_order(cells: list[float], values: list) -> float | None:
    """Order p of |u(h)| = |u*| + C h^p through the three finest grids (bisection), or None
    when the sequence is not monotone."""
    pts = sorted(zip(cells, values, strict=True), reverse=True)[-3:]
    if len(pts) < 3 or any(v is None for _, v in pts):
        return None
    (h1, a), (h2, b), (h3, c) = [(h, float(np.linalg.norm(v))) for h, v in pts]
    if (a - b) * (b - c) <= 0:
        return None
    ratio = (a - b) / (b - c)

    def gap(p: float) -> float:
        return (h1 ** p - h2 ** p) / (h2 ** p - h3 ** p) - ratio

    lo, hi = 0.05, 6.0
    if gap(lo) * gap(hi) > 0:
        return None
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(lo) * gap(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def run(args) -> dict:
    loaded = Case.load(args.case_dir)
    own = case_series(loaded)
    case, e_mpa = homogeneous(loaded, args.nu)
    check_edge_radius(case, args)
    lesions = chosen_lesions(case, args.lesions, args.lesion_ids)
    placements = {li: place_case_probe(case, li) for li in lesions}
    print(f"case {args.case_dir}: homogeneous neo-Hookean E = {e_mpa * 1e3:g} kPa, "
          f"nu = {args.nu:g}; lesions {', '.join(str(case.anatomy.lesions[i].id) for i in lesions)}"
          f"; pushes {', '.join(f'{d:g}' for d in args.depths)} mm", flush=True)
    if args.no_probe_body:
        print("P2 reference without the probe body: only the skin touched at rest is held, "
              "other skin may pass through the face", flush=True)
    earlier = reused_reference(args, e_mpa)
    points = {li: np.asarray(earlier[str(li)]["field_points"])
              if "field_points" in earlier.get(str(li), {})
              else field_points(case.anatomy, placements[li].pose[:3, 3]) for li in lesions}
    grids = {}
    for variant in variants(args):
        for cell in args.cells:
            t0 = time.perf_counter()
            tracker, active = hex_tracker(case, cell, variant)
            grids[series_key(variant, cell)] = {
                "active_cells": active, "n_equations": int(tracker._fem_model.n_eq),
                **series_answers(tracker, placements, points, args.depths),
                "seconds": time.perf_counter() - t0}
            save(args.out, {"grids": grids})
            print(f"  hex {cell:g} mm, {variant}: {active} active cells, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    for teacher in args.teachers:
        t0 = time.perf_counter()
        tracker = teacher_tracker(case, args.cells[0], teacher)
        grids[f"teacher {teacher}"] = {**series_answers(tracker, placements, points, args.depths),
                                       "seconds": time.perf_counter() - t0}
        save(args.out, {"grids": grids})
        print(f"  teacher {teacher} on the {args.cells[0]:g} mm grid: "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    reference = {}
    for li in lesions:
        if str(li) in earlier:
            reference[li] = earlier[str(li)]
            print(f"  P2 reference, lesion {case.anatomy.lesions[li].id}: from "
                  f"{args.reuse_reference}", flush=True)
            continue
        disp, facts = tet_pushes(case, e_mpa, args.nu, placements[li], li, args.depths, args,
                                 points[li], probe_body=not args.no_probe_body,
                                 checkpoint=p2_checkpoint(args.out, li))
        reference[li] = {"displacement": disp, **facts}
        save(args.out, {"grids": grids, "reference": reference})
        print(reference_line(case, li, facts, args.depths), flush=True)
    return {"case": str(args.case_dir), "E_mpa": e_mpa, "nu": args.nu,
            "depths_mm": args.depths, "cells_mm": args.cells, "variants": variants(args),
            "teachers": args.teachers,
            "lesions": lesions,
            "lesion_ids": [int(case.anatomy.lesions[i].id) for i in lesions],
            "grids": grids, "reference": reference,
            "tet_size_mm": args.tet_size, "tet_fine_mm": args.tet_fine,
            "tet_rim_mm": args.tet_rim, "friction": args.friction,
            "edge_radius_mm": args.edge_radius, "probe_body": not args.no_probe_body,
            "case_series": own}


def case_series(case: Case) -> str:
    """The key (:func:`series_key`) of the series that is the case's own FE: the tracking
    model's teacher's material law (``[refine] material_model`` with ``[refine]``),
    ``[tracker] fem_contact`` and cell size."""
    law = tracking_teacher_config(case.cfg).material.model
    variant = f"{law}/{case.cfg.tracker.fem_contact}"
    return series_key(variant, case.cfg.grid.cell_size_mm)


def series_answers(tracker: Tracker, placements: dict, points: dict, depths: list[float]
                   ) -> dict:
    """One series' ``displacement`` and ``field`` answers (:func:`hex_pushes`) by lesion
    index, every lesion of ``placements`` with its field ``points``."""
    answers = {li: hex_pushes(tracker, pl, li, depths, points[li])
               for li, pl in placements.items()}
    return {key: {li: a[key] for li, a in answers.items()} for key in ("displacement", "field")}


def chosen_lesions(case: Case, count: int, ids: str | None = None,
                   where: str | None = None) -> list[int]:
    """Indices of the lesions evaluated: those whose ids the comma list ``ids`` names (e.g.
    '2,3,7', as the case's lesion list spells them), else ``count`` of them spread over the
    list as Table 2 picks them (0: all). SystemExit with one line for an id the case lacks,
    naming the case as ``where`` (default: its folder)."""
    if not ids:
        return select_lesions(len(case.anatomy.lesions), count)
    index = {int(lesion.id): i for i, lesion in enumerate(case.anatomy.lesions)}
    try:
        wanted = [int(v) for v in ids.split(",")]
    except ValueError:
        raise SystemExit(f"error: --lesion-ids {ids!r} is not a comma list of lesion ids "
                         "(e.g. 2,3,7)") from None
    unknown = [v for v in wanted if v not in index]
    if unknown:
        raise SystemExit(f"error: --lesion-ids: {where or case.dir} has no lesion with id "
                         f"{', '.join(map(str, unknown))} (its ids: "
                         f"{', '.join(map(str, sorted(index)))})")
    return sorted({index[v] for v in wanted})


def variants(args) -> list[str]:
    """Every ``law/contact`` pair asked for."""
    return [f"{law}/{contact}" for law in args.laws for contact in args.contact]


def reused_reference(args, e_mpa: float) -> dict:
    """The P2 figures of an earlier run (``--reuse-reference``) by lesion index, when it ran
    the same depths, material and reference mesh sizes; else {} (the reference runs)."""
    if args.reuse_reference is None:
        return {}
    earlier = read_json(args.reuse_reference, "give the --out JSON of a finished run")
    if not isinstance(earlier, dict):
        raise SystemExit(f"error: {args.reuse_reference}: not a convergence.py result")
    same = (earlier.get("depths_mm") == args.depths and earlier.get("nu") == args.nu
            and earlier.get("E_mpa") == e_mpa and earlier.get("tet_size_mm") == args.tet_size
            and earlier.get("tet_fine_mm") == args.tet_fine
            and earlier.get("tet_rim_mm", 0.0) == args.tet_rim
            and earlier.get("friction", "stick") == args.friction
            and earlier.get("edge_radius_mm", 0.0) == args.edge_radius
            and earlier.get("probe_body", True) == (not args.no_probe_body))
    if not same:
        raise SystemExit(f"{args.reuse_reference}: another depth list, material or reference "
                         "mesh; run the reference again")
    return earlier.get("reference", {})


def series_key(variant: str, cell: float) -> str:
    """The key of one grid series in the figures: variant and cell size."""
    return f"{variant} {cell:g}"


def partial_path(out: Path) -> Path:
    """Where a run keeps what it has computed so far, beside ``out`` (which keeps the last
    finished study until this one ends)."""
    return out.with_name(out.stem + ".partial.json")


def save(path: Path, partial: dict) -> None:
    """Write what is computed so far (a long run keeps its figures if a later part fails)."""
    write_json_atomic(partial_path(path), partial)


def finish(out: Path, result: dict) -> None:
    """Write the finished study to ``out`` atomically and remove its partial file."""
    write_json_atomic(out, result)
    partial_path(out).unlink(missing_ok=True)


def lesion_error(answer: list | None, reference: list | None) -> float | None:
    """Distance (mm) between two lesion displacements (3,) mm; None where either is missing."""
    if answer is None or reference is None:
        return None
    return float(np.linalg.norm(np.asarray(answer) - np.asarray(reference)))


def summary(result: dict) -> dict:
    """The study as plain data for the report (``eval/convergence.json``, key ``summary``):
    each series' lesion and field errors (mm) against the reference, ``[lesion][depth]``
    (None where a solve or the reference failed), and what the reference was."""
    ref, depths = result["reference"], result["depths_mm"]
    series = []
    for key, grid in result["grids"].items():
        fields = grid.get("field", {})
        series.append({
            "name": key, "active_cells": grid.get("active_cells"),
            "lesion_error_mm": [[lesion_error(grid["displacement"][li][k],
                                              ref[li]["displacement"][k])
                                 for k in range(len(depths))] for li in result["lesions"]],
            "field_error_mm": [[field_error((fields.get(li) or [None] * len(depths))[k],
                                            (ref[li].get("field") or [None] * len(depths))[k])
                                for k in range(len(depths))] for li in result["lesions"]]})
    return {"depths_mm": depths, "lesion_ids": result["lesion_ids"], "series": series,
            "case_series": result.get("case_series"),
            "material": {"E_mpa": result["E_mpa"], "nu": result["nu"]},
            "reference": {**{key: result[key] for key in
                             ("tet_size_mm", "tet_fine_mm", "tet_rim_mm", "friction",
                              "edge_radius_mm", "probe_body")},
                          "folded": folded_answers(result)}}


def folded_answers(result: dict) -> list[list]:
    """[lesion id, depth (mm), elements] of every reference answer with elements folded over
    at a node (:meth:`TetReference.tangled`: not to be trusted)."""
    return [[lid, depth, int(n)]
            for li, lid in zip(result["lesions"], result["lesion_ids"], strict=True)
            for depth, n in zip(result["depths_mm"],
                                result["reference"][li].get("tangled_elements", []),
                                strict=False) if n]


def report(result: dict) -> dict[str, list[float]]:
    """Print one table per variant; return each series' errors against the reference (mm),
    keyed as :func:`series_key`."""
    errors: dict[str, list[float]] = {}
    for variant in result["variants"]:
        errors.update(report_variant(result, variant))
    if result.get("teachers"):
        errors.update(report_teachers(result))
    errors.update(report_fields(result))
    return errors


def field_error(answer: list | None, reference: list | None) -> float | None:
    """Mean distance (mm) between two displacement fields (k, 3) mm at the same points; None
    where either is missing."""
    if answer is None or reference is None:
        return None
    return float(np.linalg.norm(np.asarray(answer) - np.asarray(reference), axis=1).mean())


def report_fields(result: dict) -> dict[str, list[float]]:
    """The table of the displacement fields: each series' mean error (mm) against the
    reference at the points inside the breast within ``FIELD_RADIUS_MM`` of the probe
    (:func:`field_points`), lesion by lesion (``-`` where a reference holds no field)."""
    keys = [k for k in result["grids"] if "field" in result["grids"][k]]
    errors: dict[str, list[float]] = {f"field {k}": [] for k in keys}
    head = "lesion  push  points  |u| P2  " + "  ".join(f"{k:>24}" for k in keys)
    print(f"\nfield error, mean over points inside the breast within {FIELD_RADIUS_MM:g} mm of "
          "the probe (mm)\n" + head + "\n" + "-" * len(head))
    for li, lid in zip(result["lesions"], result["lesion_ids"], strict=True):
        ref = result["reference"][li]
        fields = ref.get("field") or [None] * len(result["depths_mm"])
        for k, depth in enumerate(result["depths_mm"]):
            mags = "       -" if fields[k] is None else \
                f"{np.linalg.norm(fields[k], axis=1).mean():8.2f}"
            cols = []
            for key in keys:
                err = field_error(result["grids"][key]["field"][li][k], fields[k])
                cols.append(f"{'-' if err is None else f'{err:.2f}':>24}")
                if err is not None:
                    errors[f"field {key}"].append(err)
            print(f"{lid:>6}  {depth:4g}  {len(ref.get('field_points', [])):6d}  {mags}  "
                  + "  ".join(cols))
    return errors


def report_teachers(result: dict) -> dict[str, list[float]]:
    """The table of the ``--teachers`` (each against the reference)."""
    keys = [f"teacher {t}" for t in result["teachers"]]
    errors: dict[str, list[float]] = {key: [] for key in keys}
    head = "lesion  push  |u| P2   " + "  ".join(f"err {k[8:]:>8}" for k in keys)
    print(f"\nteachers on the {result['cells_mm'][0]:g} mm grid (REFINE:ORDER)\n" + head
          + "\n" + "-" * len(head))
    for li, lid in zip(result["lesions"], result["lesion_ids"], strict=True):
        for k, depth in enumerate(result["depths_mm"]):
            ref_k = result["reference"][li]["displacement"][k]
            cols = []
            for key in keys:
                err = lesion_error(result["grids"][key]["displacement"][li][k], ref_k)
                cols.append(f"{'-' if err is None else f'{err:.2f}':>12}")
                if err is not None:
                    errors[key].append(err)
            ref = "      -" if ref_k is None else f"{np.linalg.norm(ref_k):7.2f}"
            print(f"{lid:>6}  {depth:4g}  {ref}  " + "  ".join(cols))
    return errors


def report_variant(result: dict, variant: str) -> dict[str, list[float]]:
    """The table of one variant (every grid against the reference)."""
    cells, depths = result["cells_mm"], result["depths_mm"]
    keys = [series_key(variant, c) for c in cells]
    errors: dict[str, list[float]] = {key: [] for key in keys}
    head = ("lesion  push  " + "  ".join(f"|u| {c:>4g}" for c in cells)
            + "  |u| P2   " + "  ".join(f"err {c:>4g}" for c in cells)
            + "  |u| h->0  order")
    print(f"\n{variant}\n" + head + "\n" + "-" * len(head))
    for li, lid in zip(result["lesions"], result["lesion_ids"], strict=True):
        for k, depth in enumerate(depths):
            values = [result["grids"][key]["displacement"][li][k] for key in keys]
            ref_k = result["reference"][li]["displacement"][k]
            ref = np.full(3, np.nan) if ref_k is None else np.asarray(ref_k)
            mags, errs = [], []
            for key, v in zip(keys, values, strict=True):
                mags.append("  failed" if v is None else f"{np.linalg.norm(v):8.2f}")
                err = lesion_error(v, ref_k)
                errs.append("       -" if err is None else f"{err:8.2f}")
                if err is not None:
                    errors[key].append(err)
            ext = extrapolated(cells, values)
            order = observed_order(cells, values)
            print(f"{lid:>6}  {depth:4g}  " + "  ".join(mags) + f"  {np.linalg.norm(ref):7.2f}  "
                  + "  ".join(errs) + ("  " + ("       -" if ext is None else
                                               f"{np.linalg.norm(ext):8.2f}"))
                  + ("      -" if order is None else f"  {order:5.2f}"))
    return errors


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case_dir", type=Path)
    p.add_argument("--cells", type=float, nargs="+", default=[7.3, 5.0, 3.65],
                   help="hexahedral cell sizes, mm (the first: the default grid)")
    p.add_argument("--depths", type=float, nargs="+", default=[10.0, 20.0, 30.0],
                   help="push depths, mm")
    p.add_argument("--contact", nargs="+", default=list(contact_constraint_names()),
                   choices=contact_constraint_names(), help="contact constraint kinds")
    p.add_argument("--laws", nargs="+", default=["neo-hookean"],
                   choices=["neo-hookean", "neo-hookean-sri"],
                   help="hexahedral integration of the neo-Hookean energy")
    p.add_argument("--lesions", type=int, default=3, help="lesions evaluated (0: all)")
    p.add_argument("--lesion-ids", default=None,
                   help="comma list of the lesion ids evaluated (instead of --lesions)")
    p.add_argument("--teachers", type=teacher_spec, nargs="*", default=["1.46:2"],
                   help="training teachers on the first grid, REFINE:ORDER ([dataset] "
                        "teacher_refine and teacher_extrapolation; none: grids only)")
    add_reference_arguments(p, fine_mm=2.5)
    p.add_argument("--no-probe-body", action="store_true",
                   help="the reference holds the skin touched at rest only: other skin may "
                        "pass through the probe face (the hexahedral FE's contact without "
                        "[tracker] contact_follows_pose)")
    p.add_argument("--nu", type=float, default=0.45)
    p.add_argument("--out", type=Path, default=None,
                   help="write the figures as JSON here (default: CASE/eval/convergence.json, "
                        "which the case's report shows)")
    p.add_argument("--reuse-reference", type=Path, default=None,
                   help="take the P2 figures of an earlier run's --out JSON (same case, depths, "
                        "material and reference mesh) instead of running the reference again")
    args = p.parse_args(argv)
    if args.no_probe_body and args.edge_radius:
        p.error("--edge-radius shapes the probe body that --no-probe-body leaves out")
    show_progress(args)
    args.out = args.out or CasePaths(args.case_dir).convergence
    start = time.perf_counter()
    try:
        result = run(args)
        errors = report(result)
        result["seconds"] = time.perf_counter() - start
        result["summary"] = summary(result)
        finish(args.out, result)
    except BiopsynavError as exc:  # a bad case, a failed reference mesh, an unwritable file
        raise SystemExit(f"error: {exc}") from None
    print(f"\ntotal {result['seconds'] / 60:.1f} min; written to {args.out}")
    names = {key: key.replace(" ", "_").replace("/", ":") for key in errors}
    print("RESULT " + " ".join(
        f"err_{names[key]}mm_mean={np.mean(e):.3f} err_{names[key]}mm_max={np.max(e):.3f}"
        for key, e in errors.items() if e))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
