"""Lesion tracking against an independent truth: the network tracker, the FE tracker (the
network's teacher) and the rigid assumption against a P2 tetrahedral FE of the same pushes.

    python benchmarks/truth.py CASE [--lesions 3 | --lesion-ids 2,3,7]
                                    [--depths 10 20 30] [--tet-size 10]
                                    [--tet-fine 4] [--tet-rim 1.5] [--friction slip]
                                    [--edge-radius 2.5] [--progress]
                                    [--push-minutes 20] [--retry-failed]
                                    [--reference CASE-p2.json]
                                    [--methods net fem rigid]
                                    [--out FILE]

The case must hold a trained model (``biopsynav train``) unless ``--methods`` leaves ``net``
out: ``--methods fem rigid`` judges the FE engine (the network's teacher) alone, on a case that
has no model yet. For each evaluated lesion (spread
over the list as Table 2 picks them, or named by ``--lesion-ids``) the probe is placed over it
as in Table 2 (:func:`biopsynav.evaluate.placement.place_probe`) and pushed along its beam by
each depth. The truth is ``biopsynav.evaluate.p2``: quadratic tetrahedra of a gmsh mesh of the
same surface, its own assembly and Newton, homogeneous neo-Hookean with the E and nu of the
case's default tissue, the chest-wall plane fixed, the skin under the face at rest moved
rigidly with the probe (the tracker's boundary conditions; ``--friction slip``: none held,
every contact frictionless), the probe a rigid body: a flat face with sharp edges, or with
``--edge-radius`` a body whose face's edges are rounded by that radius. Answers holding
elements folded over at a node (``TetReference.tangled``: skin bent round the probe's edge) are
said so; ``--tet-rim`` refines the mesh there, ``--progress`` logs the load steps. Nothing of
it was used to train or choose the model. The methods:

* ``net``: ``Tracker.load(case, engine="net")``, what ``biopsynav track`` and ``serve`` run
  (its lesion self-check, ``biopsynav.evaluate.lesion_check``, is made first and written
  beside the model where none is current, so that ``--out``'s rows carry each answer's 95 %
  bound as the tracker gives it and the check's relative miss: ``benchmarks/error_bound.py``
  fits on them);
* ``fem``: the FE engine as ``Tracker.load(case, engine="fem")`` builds it, on the grid and
  with the law of the tracking model's teacher (``[refine] teacher_refine`` and
  ``material_model`` when ``[refine] samples`` > 0, else ``[dataset] teacher_refine`` and
  ``[material] model``), the case's ``[tracker] fem_contact``, Table 2's solver tolerances;
* ``rigid``: the lesion stays where it was at rest.

TRE = |predicted - true lesion centre| mm; where the FE engine answered with stiffer springs
than asked (elastic contact's fallback), the table marks it ``*`` and ``--out`` keeps the
factor (``fem_spring_factor``) and the reason. A failed reference push leaves that push out (said
in the table); a method that does not answer a push with a reference counts against
``answered``. The reference's figures are kept in ``--reference`` (default
``CASE/../<case>-p2.json``) after every lesion and reused when the case's anatomy, material,
depths and reference mesh are the same: a stopped run resumes there, and a second model of the
same case is compared without solving the reference again; a file that holds a truth of
another key is kept and the run refused, naming what differs (``--replace-reference`` solves
over it). Within a lesion, the depths solved
so far and the model's state are kept beside it (``<reference>.p2-lesion<index>.partial.npz``,
removed once every depth of the lesion is answered), so a run stopped at 30 mm continues from
its 20 mm answer. ``--push-minutes`` bounds each reference push: one still solving after that
long is recorded as given up at its depth (stored like a failure, the depths before it kept).
``--retry-failed`` solves such lesions again, and those whose reference failed, continuing
from the last depth answered (its state stays beside the reference after a failure).

The last line reads ``RESULT tre_d10_mm=... tre_d30_mm=... answered=N/M`` for the network
(D10: pushes under 12.5 mm, D30: over 27.5 mm, the paper's Table 2 bins), then the same
figures of the FE tracker and the rigid assumption, each prefixed ``fem_`` / ``rigid_`` (without
``net``, only the prefixed figures).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from biopsynav.case import Case  # noqa: E402
from biopsynav.errors import BiopsynavError  # noqa: E402
from biopsynav.evaluate.p2 import chest_key, factor_precision, probe_key  # noqa: E402
from biopsynav.evaluate.placement import place_case_probe  # noqa: E402
from biopsynav.evaluate.references import default_tissue_material, other_materials  # noqa: E402
from biopsynav.evaluate.simulation import evaluation_solver_settings  # noqa: E402
from biopsynav.fileio import write_text_atomic  # noqa: E402
from biopsynav.info import model_teacher  # noqa: E402
from biopsynav.tracker import Tracker  # noqa: E402
from biopsynav.tracker.core import fem_engine  # noqa: E402

# benchmarks/ is this script's folder
from convergence import (  # noqa: E402
    add_reference_arguments,
    check_edge_radius,
    chosen_lesions,
    p2_checkpoint,
    reference_line,
    show_progress,
    tet_pushes,
)

METHODS = ("net", "fem", "rigid")
D10_BELOW_MM, D30_ABOVE_MM = 12.5, 27.5  # the paper's Table 2 bins D10 and D30


def reference_material(case: Case) -> tuple[float, float, bool]:
    """E (MPa) and nu of the case's default tissue, and whether a labelled tissue has another
    material (the reference is homogeneous: such a case is compared with a warning)."""
    return *default_tissue_material(case), bool(other_materials(case))


def reference_key(case: Case, e_mpa: float, nu: float, args) -> dict:
    """What the reference figures depend on: reused only when all of it is the same (the
    reference factors in double precision: :func:`run`)."""
    return {"anatomy": case.anatomy.fingerprint(), "E_mpa": e_mpa, "nu": nu,
            "depths_mm": list(args.depths), "tet_size_mm": args.tet_size,
            "tet_fine_mm": args.tet_fine,
            **probe_key(case.cfg.probe, args.friction, args.tet_rim, args.edge_radius,
                        args.quadrature_degree, single_factors=False), **chest_key(case.anatomy)}


def load_reference(path: Path, key: dict, replace: bool = False) -> dict:
    """The stored reference figures by lesion index (str) when ``path`` holds the same key;
    {} when there is none, or (``replace``) when it holds another one, which the run's
    answers then replace. Without ``replace`` a file of another key is kept and the run
    refused (SystemExit naming what differs): a truth is hours of solves."""
    if not path.is_file():
        return {}
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError) as exc:  # never overwrite what cannot be read
        raise SystemExit(f"{path}: not a readable reference file ({exc}); move it away or "
                         "give another --reference") from None
    if stored.get("key") != key:
        other = stored.get("key") if isinstance(stored.get("key"), dict) else {}
        differs = ", ".join(k for k, v in key.items() if other.get(k) != v) or "its key"
        if not replace:
            raise SystemExit(f"{path}: a truth of another {differs} than asked; kept. Give "
                             "another --reference for this one, or --replace-reference to "
                             "solve it over this file")
        print(f"{path}: another {differs}; solving the reference again over it", flush=True)
        return {}
    return stored.get("lesions", {})


def method_trackers(case: Case, methods: tuple[str, ...] = METHODS) -> dict[str, Tracker]:
    """The trackers of ``methods`` that predict: the network tracker (``net``; its lesion
    self-check made first where the model has none current, as ``biopsynav evaluate`` makes
    it) and the FE tracker (``fem``, Table 2's solver settings) of ``case``."""
    trackers: dict[str, Tracker] = {}
    if "net" in methods:
        trackers["net"] = Tracker.load(case, engine="net")
        if trackers["net"].lesion_check is None:  # its bounds are judged too
            from biopsynav.evaluate.lesion_check import run_lesion_check

            run_lesion_check(case)
            trackers["net"] = Tracker.load(case, engine="net")
    if "fem" in methods:
        trackers["fem"] = fem_engine(case, evaluation_solver_settings(case))
    return trackers


def lesion_rows(case: Case, trackers: dict[str, Tracker], li: int, placement,
                depths: list[float], truth: list) -> list[dict]:
    """One row per depth: the reference displacement, the rigid assumption's and each
    tracker's TRE (None: no answer, with its status), each answer's lesion displacement
    (``moved_mm``) and 95 % bound (``bound_mm``), the network's lesion self-check at that
    depth (``relative_miss``, :mod:`biopsynav.tracker.bound`) and its teacher gap
    (``teacher_gap``), where one was given its reason
    (``reason``) and the FE answer's ``fem_spring_factor`` (1: the springs as asked; 4, inf:
    elastic contact's fallbacks) for lesion index ``li``."""
    rows = []
    for tr in trackers.values():
        tr.set_rest_pose(placement.pose)
    for depth, true_disp in zip(depths, truth, strict=True):
        row = {"lesion": int(case.anatomy.lesions[li].id), "depth_mm": depth,
               "reference_mm": None if true_disp is None else float(np.linalg.norm(true_disp))}
        if true_disp is None:
            rows.append(row)
            continue
        row["tre_mm"] = {"rigid": float(np.linalg.norm(true_disp))}
        row["status"] = {"rigid": "ok"}
        for name, tr in trackers.items():
            res = tr.update(placement.pushed(depth))
            row["status"][name] = res.status if res.reliable else f"{res.status}: {res.reason}"
            row["tre_mm"][name] = (float(np.linalg.norm(res.lesions[li].displacement
                                                        - np.asarray(true_disp)))
                                   if res.reliable else None)
            if res.reliable:
                row.setdefault("moved_mm", {})[name] = float(
                    np.linalg.norm(res.lesions[li].displacement))
                row.setdefault("bound_mm", {})[name] = float(res.lesions[li].bound_mm)
            if name == "net" and tr.lesion_check is not None:
                row["relative_miss"] = float(tr.lesion_check.relative_at(depth)[li])
                gap = float(tr.lesion_check.teacher_gap[li])
                row["teacher_gap"] = gap if np.isfinite(gap) else None
            if res.reason:
                row.setdefault("reason", {})[name] = res.reason
            if name == "fem" and tr.last_solve is not None:
                row["fem_spring_factor"] = tr.last_solve.spring_factor
        rows.append(row)
    return rows


def run(args) -> dict:
    """Every figure of the run (module doc); the reference pushes factor Newton's tangents in
    double precision, as the stored truths were solved (their keys hold no ``factors``)."""
    with factor_precision(single=False):
        return run_in_double(args)


def run_in_double(args) -> dict:
    case = Case.load(args.case_dir)
    check_edge_radius(case, args)
    e_mpa, nu, labelled = reference_material(case)
    if labelled:
        print(f"warning: the reference is homogeneous ({e_mpa * 1e3:g} kPa, nu {nu:g}); the "
              "case's grid mixes tissues of other materials", flush=True)
    key = reference_key(case, e_mpa, nu, args)
    ref_path = args.reference or args.case_dir.resolve().parent / f"{args.case_dir.name}-p2.json"
    stored = load_reference(ref_path, key, args.replace_reference)
    lesions = chosen_lesions(case, args.lesions, args.lesion_ids)
    placements = {li: place_case_probe(case, li) for li in lesions}
    for li in lesions:
        if str(li) not in stored or (args.retry_failed and stored[str(li)]["failure"]):
            disp, facts = tet_pushes(case, e_mpa, nu, placements[li], li, args.depths, args,
                                     checkpoint=p2_checkpoint(ref_path, li))
            stored[str(li)] = {"displacement": disp, **facts}
            write_text_atomic(ref_path, json.dumps({"key": key, "lesions": stored}, indent=1))
            print(reference_line(case, li, facts, args.depths), flush=True)
    rows = []
    if not args.reference_only:
        trackers = method_trackers(case, args.methods)
        for li in lesions:
            rows += lesion_rows(case, trackers, li, placements[li], args.depths,
                                stored[str(li)]["displacement"])
    return {"case": str(args.case_dir), "E_mpa": e_mpa, "nu": nu, "reference": str(ref_path),
            "teacher": model_teacher(case),
            "reference_facts": {k: {f: v for f, v in stored[k].items() if f != "displacement"}
                                for k in map(str, lesions)},
            "rows": rows}


def print_table(rows: list[dict], methods: tuple[str, ...] = METHODS) -> None:
    """The TRE of each of ``methods`` per push; ``*``: the FE engine answered with stiffer
    springs than asked."""
    head = "lesion  push  |u| P2   " + "  ".join(f"TRE {m:>5}" for m in methods)
    print("\n" + head + "\n" + "-" * len(head))
    for row in rows:
        if row["reference_mm"] is None:
            print(f"{row['lesion']:>6}  {row['depth_mm']:4g}  no reference (P2 failed)")
            continue
        cells = [(f"{row['tre_mm'][m]:8.2f}{fallback_mark(row, m)}"
                  if row["tre_mm"][m] is not None else f"{row['status'][m].split(':')[0]:>9}")
                 for m in methods]
        print(f"{row['lesion']:>6}  {row['depth_mm']:4g}  {row['reference_mm']:7.2f}  "
              + "  ".join(cells))


def fallback_mark(row: dict, method: str) -> str:
    """'*' where ``method`` is the FE engine and elastic contact's fallback (stiffer springs,
    or the points met) answered, else ' '."""
    factor = row.get("fem_spring_factor") if method == "fem" else None
    return "*" if factor not in (None, 1.0) else " "


def summary(rows: list[dict], method: str) -> dict:
    """Mean TRE (mm) of ``method`` at D10 and D30 pushes, and its answered pushes."""
    judged = [r for r in rows if r["reference_mm"] is not None]
    answered = [r for r in judged if r["tre_mm"][method] is not None]

    def mean_tre(keep) -> float:
        values = [r["tre_mm"][method] for r in answered if keep(r["depth_mm"])]
        return float(np.mean(values)) if values else float("nan")

    return {"tre_d10_mm": mean_tre(lambda d: d < D10_BELOW_MM),
            "tre_d30_mm": mean_tre(lambda d: d > D30_ABOVE_MM),
            "tre_mean_mm": mean_tre(lambda d: True),
            "answered": f"{len(answered)}/{len(judged)}"}


def reference_differences(case: Case, reference: Path, depths: list[float]) -> list[str]:
    """What keeps the truth file ``reference`` from serving ``case`` at ``depths`` (mm) with
    this script's default reference options: the names of the key entries it holds
    otherwise (all solved again, for hours); [] where it serves. ValueError saying why when
    ``reference`` is no readable truth file (JSON with a ``key`` object)."""
    try:
        stored = json.loads(Path(reference).read_text())["key"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"not a readable truth file ({type(exc).__name__}: {exc})") from None
    if not isinstance(stored, dict):
        raise ValueError("not a truth file (its 'key' is no object)")
    args = parser().parse_args([str(case.dir), "--depths", *map(str, depths)])
    e_mpa, nu, _ = reference_material(case)
    wanted = reference_key(case, e_mpa, nu, args)
    return [k for k, v in wanted.items() if stored.get(k) != v]


def parser() -> argparse.ArgumentParser:
    """The command line of this script."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case_dir", type=Path)
    p.add_argument("--lesions", type=int, default=3, help="lesions evaluated (0: all)")
    p.add_argument("--lesion-ids", default=None,
                   help="ids of the lesions evaluated, e.g. 2,3,7 (instead of --lesions): "
                        "adds chosen lesions to a stored reference")
    p.add_argument("--replace-reference", action="store_true",
                   help="solve the reference again over a --reference file that holds a truth "
                        "of another anatomy, material, depth list, mesh or probe (refused "
                        "without it)")
    p.add_argument("--depths", type=float, nargs="+", default=[10.0, 20.0, 30.0],
                   help="push depths, mm")
    add_reference_arguments(p, fine_mm=4.0)
    p.add_argument("--reference", type=Path, default=None,
                   help="JSON of the reference's figures, read and extended (resumable)")
    p.add_argument("--retry-failed", action="store_true",
                   help="solve again the stored lesions whose reference failed or gave up, "
                        "from the last depth answered where its state was kept")
    p.add_argument("--reference-only", action="store_true",
                   help="solve and store the reference only (no trained model needed yet)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                   help="what is judged against the reference (without net, no trained model "
                        "is needed: the FE engine alone)")
    p.add_argument("--out", type=Path, default=None, help="write the rows as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.methods = tuple(m for m in METHODS if m in args.methods)
    show_progress(args)
    start = time.perf_counter()
    try:
        result = run(args)
    except BiopsynavError as exc:
        print(f"truth.py: error: {exc}", file=sys.stderr)
        return 2
    if args.reference_only:
        return 0
    if "net" in args.methods:
        print(f"\nnet: the trained model, taught by: {result['teacher']}")
    if "fem" in args.methods:
        print("fem: the FE engine on the tracking model's teacher grid ([refine] or [dataset] "
              "teacher_refine); *: answered by elastic contact's stiffer springs")
    print_table(result["rows"], args.methods)
    result["summary"] = {m: summary(result["rows"], m) for m in args.methods}
    result["seconds"] = time.perf_counter() - start
    result["date"] = time.strftime("%Y-%m-%d", time.gmtime())
    result["command"] = "python " + " ".join(sys.argv)
    if args.out:
        write_text_atomic(args.out, json.dumps(result, indent=1))
    print(f"\ntotal {result['seconds'] / 60:.1f} min")
    print(result_line(result["summary"]))
    return 0


def result_line(summaries: dict[str, dict]) -> str:
    """``RESULT`` with the network's figures unprefixed (when judged), then each other
    method's prefixed by its name."""
    def fmt(k: str, v) -> str:
        return f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"

    parts = [fmt(k, v) for k, v in summaries.get("net", {}).items() if k != "tre_mean_mm"]
    parts += [fmt(f"{m}_{k}", v) for m, s in summaries.items() if m != "net"
              for k, v in s.items()]
    return "RESULT " + " ".join(parts)


if __name__ == "__main__":
    raise SystemExit(main())
