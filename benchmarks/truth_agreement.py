"""Does the P2 truth agree with a second FE code? biopsynav's own P2 tetrahedral FE
(``biopsynav.evaluate.p2``, the truth of ``truth.py`` and Table 2) against NGSolve
(``benchmarks/ngsolve_peer.py``) on the same rigid-probe pushes and the same tetrahedra.

    python benchmarks/truth_agreement.py [CASE] [--lesion-ids 1,5] [--depths 10 20 30]
                                         [--tet-size 10] [--tet-fine 4] [--orders 2 3]
                                         [--h-fine 2.8 2] [--rim 1] [--rim-fine 0.5]
                                         [--quadrature-degree 5] [--intorder 5]
                                         [--stored src/biopsynav/data/truths/phantom.json]
                                         [--push-minutes 20] [--out FILE]
                                         [--result-name NAME | --no-result-file]

CASE: a case folder (default: the built-in phantom, made in a temporary folder). For each
lesion named by ``--lesion-ids`` (the ids of the case's lesion list, as ``truth.py`` takes
them; default: the first lesion; rows and result keys give its 0-based index) the probe is
placed as in Table 2 and pushed along its beam to each depth, with the face glued to the
skin it touches at rest (no probe body: skin the face reaches later is free,
``convergence.py --no-probe-body``), the chest-wall plane fixed, homogeneous neo-Hookean
with the E and nu of the case's default tissue. Answered by:

* ``p2``: biopsynav's P2 reference on gmsh's tetrahedra (``--tet-size`` mm, ``--tet-fine`` mm
  within 35 mm of the probe), integrated by scikit-fem's rule of ``--quadrature-degree``;
* ``ngsolve pK``: NGSolve on the same tetrahedra with elements of each order K of
  ``--orders`` (2: the same element; 3 and up: p refinement on the same mesh, which tells
  how far the P2 answer is from converged on that mesh), integrated by NGSolve's rule of
  ``--intorder``. The two codes' rules of one degree have different points: where the
  answers differ by their quadrature error, raising both degrees brings them together.
  ``--orders`` with no order leaves NGSolve out;
* ``p2 hF``: biopsynav's P2 on a mesh refined near the probe, ``F`` mm within 35 mm of it
  for each F of ``--h-fine`` (h refinement: how far the P2 answer is from converged in the
  mesh size where the probe deforms the tissue most);
* ``p2 rR``: biopsynav's P2 with tetrahedra of ``R`` mm along the edge of the probe face at
  rest for each R of ``--rim-fine`` (rim refinement: the glued skin is the skin vertices
  under the face, so its outline, and with it the held area, is as coarse as the mesh
  there; ``--rim`` gives every mesh, the first one's and ``--h-fine``'s, a rim of that
  size).

Printed per lesion and depth: each answer's lesion displacement |u| (mm) and the distance
between displacement vectors: p2 against NGSolve p2 (the two codes on one discretisation),
NGSolve p2 against its higher orders (p convergence), p2 against p2 on each finer mesh and
each finer mesh against the one before it in ``--h-fine``'s (or ``--rim-fine``'s) order (h
and rim convergence), and, with
``--stored`` (a truth file of ``truth.py``: the probe a rigid body on which reached skin
slides), the stored truth against p2 glued (what the probe body changes: the contact model).
Writes
``benchmarks/results/truth-agreement-<case>.json``; the last line reads ``RESULT
codes_max_mm=... p_max_mm=... h_max_mm=... rim_max_mm=... contact_max_mm=...`` (the largest of each
distance; nan where not asked).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from convergence import add_quadrature_argument, chosen_lesions, non_negative_mm
from resultfile import result_line, write_result

ROOT = Path(__file__).resolve().parents[1]


def load_case(case_dir: Path | None, scratch: Path):
    """The case at ``case_dir``, or the built-in phantom made in the folder ``scratch``."""
    from biopsynav.case import Case, make_phantom_case

    if case_dir is None:
        return make_phantom_case(scratch / "phantom"), "phantom"  # the built-in phantom
    return Case.load(case_dir), case_dir.name


def glued_model(case, e_mpa: float, nu: float, placement, args,
                fine_mm: float | None = None, rim_mm: float | None = None) -> SimpleNamespace:
    """biopsynav's P2 model meshed for ``placement`` and the glued face's node sets, taken
    alike by both codes: the skin vertices the face touches at rest (the tracker's rule) and
    the edge midpoints between two of them (a rigid translation's quadratic trace); the chest
    wall's vertices and the midpoints between two of them. ``fine_mm``: the tetrahedra near
    the probe (default ``--tet-fine``), ``rim_mm`` those along the face's edge at rest
    (default ``--rim``; 0: no rim)."""
    from biopsynav.evaluate.p2 import EDGES, TetReference, rim_at

    probe = case.cfg.probe
    ref = TetReference.build(case.anatomy, args.tet_size, e_mpa, nu,
                             fine_at=placement.pose[:3, 3],
                             fine_mm=args.tet_fine if fine_mm is None else fine_mm,
                             quadrature_degree=args.quadrature_degree,
                             rim=rim_at(placement.pose, probe.footprint,
                                        args.rim if rim_mm is None else rim_mm))
    n_vertices = int(ref.corners.max()) + 1
    touched = ref.contact(placement.pose, probe.footprint, probe.contact_tolerance_mm)
    held = touched[touched < n_vertices]
    fixed = ref.fixed_nodes[ref.fixed_nodes < n_vertices]
    return SimpleNamespace(ref=ref, n_vertices=n_vertices, held=held, fixed=fixed,
                           contact=with_midpoints(ref.elements, EDGES, held, len(ref.nodes)))


def with_midpoints(elements: np.ndarray, edges: np.ndarray, vertices: np.ndarray,
                   n_nodes: int) -> np.ndarray:
    """``vertices`` and the midside nodes (of P2 ``elements`` (t, 10), edges ``edges``)
    whose two ends are both among them."""
    inside = np.zeros(n_nodes, dtype=bool)
    inside[vertices] = True
    both = inside[elements[:, edges]].all(axis=-1)  # (t, 6)
    return np.union1d(vertices, elements[:, 4:][both])


def p2_glued(model: SimpleNamespace, placement, lesion: np.ndarray, depths: list[float],
             args) -> tuple[list, dict]:
    """biopsynav's P2 answers of the glued face (no probe body): the lesion displacement per
    depth (None past a failure) and the run's facts."""
    ref, out, failure = model.ref, [], ""
    t0 = time.perf_counter()
    limit = 60.0 * args.push_minutes if args.push_minutes > 0 else None
    for depth in depths:
        try:
            (u,) = ref.push(placement.pose, [placement.pushed(depth)], model.contact,
                            lesion[None], start=ref.last if out else None, time_limit_s=limit)
        except Exception as exc:  # noqa: BLE001 - a failure (or give-up) ends the lesion
            failure = f"{depth:g} mm: {exc or type(exc).__name__}"
            break
        out.append(u[0].tolist())
    facts = {"dofs": ref.n_dofs, "tets": len(ref.elements), "held_nodes": len(model.contact),
             "seconds": time.perf_counter() - t0, "failure": failure}
    return out + [None] * (len(depths) - len(out)), facts


def ngsolve_glued(model: SimpleNamespace, e_mpa: float, nu: float, placement,
                  lesion: np.ndarray, depths: list[float], order: int, intorder: int) -> dict:
    """NGSolve's answers on the P2 model's own tetrahedra, elements of ``order``, integrated
    by NGSolve's rule of degree ``intorder``."""
    from ngsolve_peer import NgsolvePush, push_depths

    ref = model.ref
    t0 = time.perf_counter()
    problem = NgsolvePush(ref.nodes[:model.n_vertices], ref.corners, e_mpa, nu, model.fixed,
                          model.held, order=order, intorder=intorder)
    out = push_depths(problem, placement.pose[:3, 2], depths, lesion)
    return {"displacement": out.displacement, "dofs": out.dofs, "failure": out.failure,
            "seconds": time.perf_counter() - t0, "newton_per_step": out.newton}


def distance(a, b) -> float | None:
    """|a - b| (mm) of two displacement vectors, None where either is missing."""
    if a is None or b is None:
        return None
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)))


def stored_truth(path: Path | None, case) -> dict:
    """The stored truth's lesions (``truth.py``'s file) when it is of this anatomy, else {}."""
    if path is None:
        return {}
    data = json.loads(path.read_text())
    if data["key"]["anatomy"] != case.anatomy.fingerprint():
        print(f"{path}: another anatomy; the contact model's column is left out", flush=True)
        return {}
    depths = data["key"]["depths_mm"]
    return {li: {**entry, "depths_mm": depths} for li, entry in data["lesions"].items()}


def lesion_rows(li: int, depths: list[float], p2: list, ng: dict[int, dict],
                stored: dict, finer: dict[str, list] | None = None) -> list[dict]:
    """One row per depth of lesion index ``li``: every answer's |u| and the distances
    (``finer``: the P2 answers on each finer mesh, by its label of :func:`refinements`; each
    also against the one before it of its kind)."""
    rows = []
    body = stored.get(str(li), {}).get("displacement", [None] * len(depths))
    body_depths = stored.get(str(li), {}).get("depths_mm", depths)
    for k, depth in enumerate(depths):
        row = {"lesion": li, "depth_mm": depth, "p2": p2[k],
               **{f"ngsolve_p{o}": ans["displacement"][k] for o, ans in ng.items()}}
        row["codes_mm"] = distance(p2[k], ng[2]["displacement"][k] if 2 in ng else None)
        for order in ng:
            if order != 2 and 2 in ng:
                row[f"p{order}_mm"] = distance(ng[2]["displacement"][k],
                                               ng[order]["displacement"][k])
        coarser = None  # the answer of the mesh before, for the step of each refinement
        for label, answers in (finer or {}).items():
            row[f"p2_{label}"] = answers[k]
            row[f"{label}_mm"] = distance(p2[k], answers[k])
            if coarser is not None and coarser[0][0] == label[0]:
                row[step_key(coarser[0], label)] = distance(coarser[1][k], answers[k])
            coarser = (label, answers)
        stored_k = body[body_depths.index(depth)] if depth in body_depths else None
        row["probe_body"] = stored_k
        row["contact_mm"] = distance(stored_k, p2[k])
        rows.append(row)
    return rows


def step_key(coarser: str, fine: str) -> str:
    """The row key of the distance between the P2 answers on two successive finer meshes of
    one kind (their labels, :func:`refinements`): how far one more refinement moves the
    lesion."""
    return f"{coarser}-{fine}_mm"


def refinements(args) -> dict[str, tuple[float, float]]:
    """The finer meshes asked for, label -> (tetrahedron size near the probe, along the face's
    edge) mm, in order: ``hF`` for each F of ``--h-fine`` (with ``--rim``), then ``rR`` for
    each R of ``--rim-fine`` (with ``--tet-fine``)."""
    out = {f"h{f:g}": (f, args.rim) for f in args.h_fine}
    out.update({f"r{r:g}": (args.tet_fine, r) for r in args.rim_fine})
    return out


def failed_text(facts: dict) -> str:
    """`` (why it failed)`` for a solve's ``facts`` that hold a failure, else ''."""
    return f" ({facts['failure']})" if facts["failure"] else ""


def norm_text(v) -> str:
    return "-" if v is None else f"{np.linalg.norm(v):6.2f}"


def num_text(v) -> str:
    return "-" if v is None else f"{v:6.3f}"


def print_rows(rows: list[dict], orders: list[int], labels: list[str] = ()) -> None:
    """The table: |u| of each answer and the distances, mm (``labels``: the finer meshes',
    :func:`refinements`)."""
    higher = [o for o in orders if o != 2]
    steps = [(a, b) for a, b in zip(labels[:-1], labels[1:], strict=True)
             if a[0] == b[0]]  # successive refinements of one kind
    head = (["lesion", "depth", "|u| p2", *[f"|u| ng p{o}" for o in orders], "p2-ng"]
            + [f"ng p2-p{o}" for o in higher] + [f"p2-{f}" for f in labels]
            + [f"{a}-{b}" for a, b in steps] + ["|u| body", "body-glued"])
    print("  ".join(f"{h:>9}" for h in head))
    for r in rows:
        cells = ([str(r["lesion"]), f"{r['depth_mm']:g}", norm_text(r["p2"])]
                 + [norm_text(r.get(f"ngsolve_p{o}")) for o in orders] + [num_text(r["codes_mm"])]
                 + [num_text(r.get(f"p{o}_mm")) for o in higher]
                 + [num_text(r.get(f"{f}_mm")) for f in labels]
                 + [num_text(r.get(step_key(a, b))) for a, b in steps]
                 + [norm_text(r["probe_body"]), num_text(r["contact_mm"])])
        print("  ".join(f"{c:>9}" for c in cells), flush=True)


def largest(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if r.get(key) is not None]
    return max(values) if values else float("nan")


def rule_degree(text: str) -> int:
    """NGSolve's quadrature degree given on the command line: an integer, 2 or more (a P2
    stiffness needs degree 2; NGSolve takes anything lower, negative included, as a
    one-point rule without a word)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 2:
        raise argparse.ArgumentTypeError(f"{text!r}: a rule's degree, an integer, 2 or more")
    return value


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case_dir", type=Path, nargs="?", default=None)
    p.add_argument("--lesion-ids", default=None,
                   help="ids of the lesions, comma-separated, as truth.py takes them (default: "
                   "the first lesion)")
    p.add_argument("--depths", type=float, nargs="+", default=[10.0, 20.0, 30.0])
    p.add_argument("--tet-size", type=float, default=10.0)
    p.add_argument("--tet-fine", type=float, default=4.0)
    p.add_argument("--orders", type=int, nargs="*", default=[2, 3],
                   help="NGSolve's element orders (none: NGSolve left out)")
    p.add_argument("--h-fine", type=non_negative_mm, nargs="*", default=[],
                   help="biopsynav's P2 again with tetrahedra of these sizes within 35 mm of "
                        "the probe, mm (h refinement; each below --tet-fine)")
    add_quadrature_argument(p)
    p.add_argument("--rim", type=non_negative_mm, default=0.0,
                   help="tetrahedra of this size (mm) along the face's edge at rest in the "
                        "first mesh and those of --h-fine (0: none)")
    p.add_argument("--rim-fine", type=non_negative_mm, nargs="*", default=[],
                   help="further meshes of --tet-fine near the probe with tetrahedra of each "
                        "of these sizes along the face's edge, mm (rim refinement; each below "
                        "--rim when it is set)")
    p.add_argument("--intorder", type=rule_degree, default=5,
                   help="degree of NGSolve's quadrature rule (2 or more)")
    p.add_argument("--push-minutes", type=float, default=0.0,
                   help="give a P2 push up that long (0: no limit)")
    p.add_argument("--stored", type=Path, default=None,
                   help="a truth.py file of the same case: the probe-body truth")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--result-name", default=None,
                   help="the result file's name (default truth-agreement-<case>)")
    p.add_argument("--no-result-file", action="store_true",
                   help="write no file under benchmarks/results (a check, not a benchmark)")
    args = p.parse_args(argv)
    if not all(0 < f < args.tet_fine for f in args.h_fine):
        p.error(f"--h-fine: each size above 0 and below --tet-fine ({args.tet_fine:g} mm): a "
                "finer mesh")
    if not all(0 < r and (args.rim == 0 or r < args.rim) for r in args.rim_fine):
        p.error(f"--rim-fine: each size above 0 (and below --rim, {args.rim:g} mm, when set): "
                "a finer rim")
    sys.stdout.reconfigure(line_buffering=True)
    with tempfile.TemporaryDirectory(prefix="agree-") as scratch:  # the phantom, if made
        case, name = load_case(args.case_dir, Path(scratch))
        return agree(case, name, args)


def agree(case, name: str, args) -> int:
    """Solve, print and write the agreement on ``case`` (``name``: its result file's)."""
    from biopsynav.evaluate.placement import place_case_probe
    from biopsynav.evaluate.references import default_tissue_material

    e_mpa, nu = default_tissue_material(case)
    stored = stored_truth(args.stored, case)
    rows, facts = [], {}
    meshes = refinements(args)  # label -> (size near the probe, rim) mm
    where = None if args.case_dir else "the built-in phantom"
    for li in chosen_lesions(case, 1, args.lesion_ids, where):  # no ids: the first lesion
        placement = place_case_probe(case, li)
        lesion = np.asarray(case.anatomy.lesions[li].center)
        model = glued_model(case, e_mpa, nu, placement, args)
        p2, p2_facts = p2_glued(model, placement, lesion, args.depths, args)
        ng = {o: ngsolve_glued(model, e_mpa, nu, placement, lesion, args.depths, o,
                               args.intorder)
              for o in args.orders}
        finer = {label: p2_glued(glued_model(case, e_mpa, nu, placement, args, fine, rim),
                                 placement, lesion, args.depths, args)
                 for label, (fine, rim) in meshes.items()}  # -> (answers, facts)
        facts[str(li)] = {"p2": p2_facts,
                          **{f"p2_{label}": f for label, (_, f) in finer.items()},
                          **{f"ngsolve_p{o}": {k: v for k, v in a.items() if k != "displacement"}
                             for o, a in ng.items()}}
        parts = ([f"P2 {p2_facts['dofs']} dofs {p2_facts['seconds']:.0f} s"
                  + failed_text(p2_facts)]
                 + [f"NGSolve p{o} {a['dofs']} dofs {a['seconds']:.0f} s" + failed_text(a)
                    for o, a in ng.items()]
                 + [f"P2 {f['dofs']} dofs, mesh {label}, {f['seconds']:.0f} s" + failed_text(f)
                    for label, (_, f) in finer.items()])
        print(f"lesion {li} (id {case.anatomy.lesions[li].id}): " + "; ".join(parts),
              flush=True)
        rows += lesion_rows(li, args.depths, p2, ng, stored,
                            {label: answers for label, (answers, _) in finer.items()})
    labels = list(meshes)
    print_rows(rows, args.orders, labels)
    higher = [o for o in args.orders if o != 2]
    figures = {"codes_max_mm": largest(rows, "codes_mm"),
               "p_max_mm": max((largest(rows, f"p{o}_mm") for o in higher), default=float("nan")),
               "h_max_mm": max((largest(rows, f"{f}_mm") for f in labels if f[0] == "h"),
                               default=float("nan")),
               "rim_max_mm": max((largest(rows, f"{f}_mm") for f in labels if f[0] == "r"),
                                 default=float("nan")),
               "contact_max_mm": largest(rows, "contact_mm"),
               "E_mpa": e_mpa, "nu": nu, "tet_size_mm": args.tet_size,
               "tet_fine_mm": args.tet_fine, "h_fine_mm": args.h_fine, "rim_mm": args.rim,
               "rim_fine_mm": args.rim_fine,
               "quadrature_degree": args.quadrature_degree,
               "intorder": args.intorder, "rows": rows, "facts": facts}
    if args.out:
        args.out.write_text(json.dumps(figures, indent=1))
    if not args.no_result_file:
        write_result(args.result_name or f"truth-agreement-{name}", figures)
    print(result_line(figures, ("codes_max_mm", "p_max_mm", "h_max_mm", "rim_max_mm",
                                "contact_max_mm")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
