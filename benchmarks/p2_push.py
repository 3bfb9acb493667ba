"""What one push of the P2 truth costs, and what its single-precision factors save.

    python benchmarks/p2_push.py [CASE] --lesion-ids 5 [--depths 10 20 30]
                                 [--tet-size 10] [--tet-fine 4] [--edge-radius 2.5]
                                 [--push-minutes 30] [--result-name NAME | --no-result-file]

CASE: a case folder of one material (the truth's, ``biopsynav.evaluate.p2``; default: the
built-in phantom, made in a temporary folder). The probe is
placed over the lesion as Table 2 and ``truth.py`` place it and pushed along its beam to each
depth in turn (each from the last answer, as ``truth.py`` does), on one mesh (``--tet-size`` mm
tetrahedra, ``--tet-fine`` mm within 35 mm of the probe; the probe a rigid body, its face's
edges rounded by ``--edge-radius``). The same pushes are solved twice, alone and in turn: with
Newton's tangents factored in single precision (the truth's default,
``p2.SINGLE_PRECISION_FACTORS``) and in double precision (the full solve, as before). Printed
per depth and precision: the seconds, the factorisations and analyses (a new contact set's
pattern), the lesion's displacement, and the distance between the two answers. ``--push-minutes``
bounds each push (a push still solving then is recorded as given up). The target of
"a P2 push in seconds" is a 30 mm UC Davis push in at most 10 s within 0.05 mm of the full solve.

Writes ``benchmarks/results/p2-push-<case>-lesion<id>.json``; the last line reads ``RESULT
push_s=... full_s=... speedup=... max_diff_mm=...`` (the sums over the depths both answered).
Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from convergence import chosen_lesions, non_negative_minutes, non_negative_mm
from resultfile import result_line, write_result
from speedprobe import speed_probes

PRECISIONS = {"single": True, "double": False}


def solve_depths(case, lesion: int, depths: list[float], single: bool, args) -> dict:
    """The pushes of lesion index ``lesion`` to ``depths`` with the factors in ``single``
    precision (or double) on a mesh built for them: per depth the seconds, factorisations,
    analyses and lesion displacement (None from a failed or given-up push on)."""
    from biopsynav.evaluate import p2
    from biopsynav.evaluate.placement import place_case_probe
    from biopsynav.evaluate.references import homogeneous_material

    e_mpa, nu = homogeneous_material(case)
    probe, placement = case.cfg.probe, place_case_probe(case, lesion)
    ref = p2.TetReference.build(case.anatomy, args.tet_size, e_mpa, nu,
                                fine_at=placement.pose[:3, 3], fine_mm=args.tet_fine)
    contact = ref.contact(placement.pose, probe.footprint, probe.contact_tolerance_mm)
    centre = np.array([case.anatomy.lesions[lesion].center])
    solver = p2.set_factor_precision(single)
    rows, failure = [], ""
    limit = 60.0 * args.push_minutes if args.push_minutes > 0 else None
    for depth in depths:
        before = (solver.factorisations, solver.analyses)
        start = time.perf_counter()
        try:
            (u,) = ref.push(placement.pose, [placement.pushed(depth)], contact, centre,
                            start=ref.last if rows else None, footprint=probe.footprint,
                            edge_radius_mm=args.edge_radius, time_limit_s=limit)
        except Exception as exc:  # noqa: BLE001 - a failure or give-up ends the lesion
            failure = f"{depth:g} mm: {exc or type(exc).__name__}"
            break
        rows.append({"depth_mm": depth, "seconds": time.perf_counter() - start,
                     "factorisations": solver.factorisations - before[0],
                     "analyses": solver.analyses - before[1],
                     "displacement_mm": u[0].tolist()})
        print(f"  {'single' if single else 'double'} {depth:g} mm: {rows[-1]['seconds']:.1f} s, "
              f"{rows[-1]['factorisations']} factorisations, |u| "
              f"{np.linalg.norm(u[0]):.4f} mm", flush=True)
    return {"dofs": ref.n_dofs, "tets": len(ref.elements), "rows": rows, "failure": failure}


def compare(runs: dict) -> list[dict]:
    """Per depth both precisions answered: their seconds and the distance (mm) between their
    lesion displacements."""
    single, double = runs["single"]["rows"], runs["double"]["rows"]
    out = []
    for a, b in zip(single, double, strict=False):
        out.append({"depth_mm": a["depth_mm"], "single_s": a["seconds"],
                    "double_s": b["seconds"],
                    "diff_mm": float(np.linalg.norm(np.subtract(a["displacement_mm"],
                                                                b["displacement_mm"])))})
    return out


def summary(rows: list[dict]) -> dict:
    """The sums over the depths both answered and the largest distance."""
    push_s = sum(r["single_s"] for r in rows)
    full_s = sum(r["double_s"] for r in rows)
    return {"push_s": push_s, "full_s": full_s,
            "speedup": full_s / push_s if push_s else float("nan"),
            "max_diff_mm": max((r["diff_mm"] for r in rows), default=float("nan"))}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case_dir", type=Path, nargs="?", default=None)
    p.add_argument("--lesion-ids", required=True, help="one lesion id, as the case spells it")
    p.add_argument("--depths", type=non_negative_mm, nargs="+", default=[30.0])
    p.add_argument("--tet-size", type=non_negative_mm, default=10.0)
    p.add_argument("--tet-fine", type=non_negative_mm, default=4.0)
    p.add_argument("--edge-radius", type=non_negative_mm, default=2.5)
    p.add_argument("--push-minutes", type=non_negative_minutes, default=30.0,
                   help="give a push up after this long (0: never)")
    p.add_argument("--result-name", default=None)
    p.add_argument("--no-result-file", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    import tempfile

    from biopsynav.case import Case, make_phantom_case

    args = parser().parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        if args.case_dir is None:
            case, case_name = make_phantom_case(Path(scratch) / "phantom"), "phantom"
        else:
            case, case_name = Case.load(args.case_dir), args.case_dir.name
        return measure(case, case_name, args)


def measure(case, case_name: str, args: argparse.Namespace) -> int:
    """Both precisions' pushes, printed and written (see the module doc)."""
    (lesion,) = chosen_lesions(case, 1, args.lesion_ids.split(",")[0])
    runs = {}
    for name, single in PRECISIONS.items():
        runs[name] = solve_depths(case, lesion, sorted(args.depths), single, args)
    rows = compare(runs)
    figures = {**summary(rows), "lesion": int(case.anatomy.lesions[lesion].id),
               "depths_mm": sorted(args.depths), "rows": rows,
               "dofs": runs["single"]["dofs"], "tets": runs["single"]["tets"],
               "runs": runs, "tet_size_mm": args.tet_size, "tet_fine_mm": args.tet_fine,
               "edge_radius_mm": args.edge_radius, "target_s": 10.0}
    for r in rows:
        print(f"{r['depth_mm']:g} mm: single {r['single_s']:.1f} s, double {r['double_s']:.1f} "
              f"s, {r['diff_mm']:.2e} mm apart")
    if not args.no_result_file:
        name = args.result_name or f"p2-push-{case_name}-lesion{figures['lesion']}"
        write_result(name, figures, speed_probes=speed_probes())
    print(result_line(figures, ("push_s", "full_s", "speedup", "max_diff_mm")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
