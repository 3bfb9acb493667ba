"""Fit each lesion's 95 % error bound on truth comparisons and check it on a case left out.

    python benchmarks/error_bound.py [--fit FILE ...] [--check FILE ...] [--weight 0.5]
                                     [--teacher-weight 0.5] [--result-name NAME]

The bound (``biopsynav.tracker.bound``) is ``c + |d| (a + b p + k r + k_t g)`` mm: ``d`` the
lesion's displacement from rest as the network predicts it (mm), ``p`` the probe's depth (mm),
``r`` the lesion's relative miss against its own FE teacher in the model's lesion self-check
(``biopsynav.evaluate.lesion_check``: pushes of 15 / 25 / 35 mm, none at the truth's depths),
``g`` the lesion's teacher gap in that check (the teacher against itself on a finer grid, one
push of 15 mm), ``k`` and ``k_t`` their weights (``--weight``, ``--teacher-weight``). Given
them, ``a`` and ``b`` (both >= 0) are those of a grid whose bound, with ``c`` the 95 % quantile
of what is left of the TREs of the ``--fit`` rows, is the least on average: the tightest bound
that holds 95 % of the fitted TREs. The same fit with ``k = k_t = 0`` gives the coefficients of
a model without a current check.

The rows are ``benchmarks/truth.py CASE --lesions 0 --methods net --reference TRUTH --out
FILE`` comparisons of tracking networks with the stored P2 truth: every lesion at 10 / 20 /
30 mm, with the network's lesion displacement and self-check (``truth.py`` makes the check
where the model has none). By default the fit is UC Davis one material and the check the
phantom (``bound-rows-*.json`` under ``benchmarks/results/``; which networks, in each file's
``note``), so the check is on a breast that took no part in the fit; the same is then done
the other way round, and for each weight of a scan, so that the weights' choice shows. Rows
made before the gap was part of the check take it from the ``teacher-gap-*.json`` of their
case (``benchmarks/teacher_gap.py``; :data:`GAP_FILES`: every network of a case has one
teacher). The
check gives the coverage (share of TREs within their bound; asked: 90-97 %) and, per depth,
the bound's mean over the mean TRE (asked: at most 3).

Writes ``benchmarks/results/error-bound.json`` (or ``NAME.json``); the last line reads
``RESULT c=... a=... b=... weight=... coverage=... worst_ratio=... unchecked_coverage=...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from resultfile import write_result

RESULTS = Path(__file__).resolve().parent / "results"
QUANTILE = 0.95
A_GRID = np.linspace(0.0, 0.1, 41)  # a, per |d|
B_GRID = np.linspace(0.0, 0.006, 31)  # b, per |d| and mm of push
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the scan of the check's weight k
TEACHER_WEIGHTS = (0.0, 0.5, 1.0, 2.0)  # the scan of the teacher gap's weight k_t
#: rows-file name prefix -> the teacher_gap.py result of its case (rows without the gap)
GAP_FILES = {"bound-rows-phantom-": "teacher-gap-phantom.json",
             "bound-rows-ucdavis-homogeneous-": "teacher-gap-ucdavis-homogeneous.json",
             "bound-rows-mri01r-homogeneous-": "teacher-gap-mri01r-homogeneous.json",
             "bound-rows-mri05r-homogeneous-": "teacher-gap-mri05r-homogeneous.json"}
FIT_FILES = ["bound-rows-ucdavis-homogeneous-pushes.json",
             "bound-rows-ucdavis-homogeneous-pushes-patches.json",
             "bound-rows-ucdavis-homogeneous-pushes-patches-seed1.json",
             "bound-rows-ucdavis-homogeneous-mixed055.json"]
CHECK_FILES = ["bound-rows-phantom-pushes.json", "bound-rows-phantom-pushes-patches.json",
               "bound-rows-phantom-pushes-patches-seed1.json",
               "bound-rows-phantom-pushes-patches-it8000.json",
               "bound-rows-phantom-mixed055.json", "bound-rows-phantom-pushes-patches-055.json",
               "bound-rows-phantom-chain.json"]


def rows_of(paths: list[Path]) -> np.ndarray:
    """(n, 5): the network's lesion displacement |d| (mm), probe depth (mm), TRE (mm), the
    lesion's relative miss and its teacher gap (NaN where the check has none: the finer grid
    gave no answer), from ``truth.py --out`` files; SystemExit naming a file whose rows lack
    the self-check (made before it) or a gap, in the row and in its case's gap file."""
    out = []
    for path in paths:
        data = json.loads(path.read_text())
        gaps = case_gaps(path)
        for r in data["rows"] if "rows" in data else data["figures"]["rows"]:
            if r.get("status", {}).get("net") != "ok":
                continue
            if "relative_miss" not in r:
                raise SystemExit(f"{path}: rows without the lesion self-check; make them again "
                                 "with benchmarks/truth.py --methods net --out")
            gap = r["teacher_gap"] if "teacher_gap" in r else gaps.get(str(r["lesion"]), ...)
            if gap is ...:
                raise SystemExit(f"{path}: lesion {r['lesion']} has no teacher gap (neither in "
                                 "its row nor in its case's teacher-gap file)")
            out.append((r["moved_mm"]["net"], r["depth_mm"], r["tre_mm"]["net"],
                        r["relative_miss"], np.nan if gap is None else gap))
    return np.array(out, dtype=np.float64).reshape(-1, 5)


def case_gaps(rows_file: Path) -> dict:
    """{lesion id: teacher gap} of the case of ``rows_file`` (:data:`GAP_FILES`), {} where
    none is named."""
    name = next((g for prefix, g in GAP_FILES.items() if rows_file.name.startswith(prefix)),
                None)
    if name is None:
        return {}
    return json.loads((rows_file.parent / name).read_text())["figures"]["lesions"]


def with_check(rows: np.ndarray, k: float, kt: float = 0.0) -> np.ndarray:
    """The rows a bound of weights ``k``, ``kt`` applies to: where either weighs, those whose
    self-check has a teacher gap (the tracker bounds the others' lesions by the coefficients
    without the check, which every row takes part in)."""
    return rows if k == 0.0 and kt == 0.0 else rows[np.isfinite(rows[:, 4])]


def bound(coef: tuple[float, float, float], k: float, rows: np.ndarray,
          kt: float = 0.0) -> np.ndarray:
    """c + |d| (a + b p + k r + k_t g), mm, for coef = (c, a, b)."""
    c, a, b = coef
    return c + rows[:, 0] * (a + b * rows[:, 1] + k * rows[:, 3] + kt * rows[:, 4])


def fit(rows: np.ndarray, k: float, kt: float = 0.0) -> tuple[float, float, float]:
    """(c, a, b) of the least mean bound holding :data:`QUANTILE` of ``rows``' TREs, with
    the weights ``k`` and ``kt``: ``a``, ``b`` over the grid, ``c`` >= 0 the quantile of the
    rest. Rows without a teacher gap are left out where a weight is not 0 (:func:`with_check`)."""
    rows = with_check(rows, k, kt)
    a, b = np.meshgrid(A_GRID, B_GRID, indexing="ij")
    slope = rows[:, 0] * (a[..., None] + b[..., None] * rows[:, 1] + k * rows[:, 3]
                          + kt * rows[:, 4])
    c = np.maximum(np.quantile(rows[:, 2] - slope, QUANTILE, axis=-1), 0.0)
    i, j = np.unravel_index(np.argmin(c + slope.mean(axis=-1)), c.shape)
    return float(c[i, j]), float(A_GRID[i]), float(B_GRID[j])


def check(coef: tuple[float, float, float], k: float, rows: np.ndarray,
          kt: float = 0.0) -> dict:
    """Coverage and, per depth, the mean bound over the mean TRE, over the rows the bound
    applies to (:func:`with_check`)."""
    rows = with_check(rows, k, kt)
    b = bound(coef, k, rows, kt)
    by_depth = {}
    for depth in np.unique(rows[:, 1]):
        at = rows[:, 1] == depth
        by_depth[f"{depth:g}"] = {"mean_tre_mm": float(rows[at, 2].mean()),
                                  "mean_bound_mm": float(b[at].mean()),
                                  "ratio": float(b[at].mean() / rows[at, 2].mean()),
                                  "covered": f"{int((rows[at, 2] <= b[at]).sum())}/{at.sum()}"}
    return {"coverage": float((rows[:, 2] <= b).mean()), "n": len(rows), "by_depth": by_depth,
            "worst_ratio": max(v["ratio"] for v in by_depth.values())}


def both_ways(fit_rows: np.ndarray, check_rows: np.ndarray, k: float, kt: float = 0.0) -> dict:
    """Fitted on one breast, checked on the other, and the other way round, at weights k,
    kt."""
    coef, reverse = fit(fit_rows, k, kt), fit(check_rows, k, kt)
    return {"coef": coef, "on_fit": check(coef, k, fit_rows, kt),
            "left_out": check(coef, k, check_rows, kt),
            "other_way_round": check(reverse, k, fit_rows, kt)}


def print_fit(name: str, k: float, ways: dict, kt: float = 0.0) -> None:
    c, a, b = ways["coef"]
    print(f"{name}: bound = {c:.4f} + |d| ({a:.4f} + {b:.5f} p + {k:g} r + {kt:g} g)")
    for label in ("on_fit", "left_out", "other_way_round"):
        v = ways[label]
        print(f"  {label.replace('_', ' ')}: coverage {v['coverage']:.0%} of {v['n']}; " +
              "; ".join(f"{d} mm: bound {x['mean_bound_mm']:.2f} / TRE {x['mean_tre_mm']:.2f}"
                        f" = {x['ratio']:.1f}x, {x['covered']}"
                        for d, x in v["by_depth"].items()))


def teacher_weight_scan(fit_rows: np.ndarray, check_rows: np.ndarray, k: float) -> dict:
    """For each of :data:`TEACHER_WEIGHTS`: coverage and worst ratio left out and the other
    way round."""
    out = {}
    for kt in TEACHER_WEIGHTS:
        ways = both_ways(fit_rows, check_rows, k, kt)
        out[f"{kt:g}"] = {f"{w}{suffix}": ways[w][key] for w in ("left_out", "other_way_round")
                          for suffix, key in (("", "coverage"), ("_ratio", "worst_ratio"))}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fit", type=Path, nargs="+", default=[RESULTS / f for f in FIT_FILES])
    p.add_argument("--check", type=Path, nargs="+", default=[RESULTS / f for f in CHECK_FILES])
    p.add_argument("--weight", type=float, default=0.5, help="k, the self-check's weight")
    p.add_argument("--teacher-weight", type=float, default=0.5,
                   help="k_t, the teacher gap's weight")
    p.add_argument("--result-name", default="error-bound")
    args = p.parse_args(argv)
    fit_rows, check_rows = rows_of(args.fit), rows_of(args.check)
    for name, rows in (("fit", fit_rows), ("check", check_rows)):
        if not np.isfinite(rows[:, 4]).all():
            print(f"{name}: {int(np.isnan(rows[:, 4]).sum())} of {len(rows)} rows have no "
                  "teacher gap: bounded as the tracker bounds them, without the check")
    kt = args.teacher_weight
    fits = {k: both_ways(fit_rows, check_rows, k, kt)
            for k in dict.fromkeys((args.weight, *WEIGHTS))}
    checked, unchecked = fits[args.weight], both_ways(fit_rows, check_rows, 0.0)
    print_fit("with the lesion self-check", args.weight, checked, kt)
    print_fit("without it", 0.0, unchecked)
    scan = {f"{k:g}": {way: fits[k][way]["coverage"] for way in ("left_out", "other_way_round")}
            for k in WEIGHTS}
    print(f"the weight k (k_t {kt:g}): coverage left out / the other way round: " + "; ".join(
        f"{k}: {v['left_out']:.0%} / {v['other_way_round']:.0%}" for k, v in scan.items()))
    teacher_scan = teacher_weight_scan(fit_rows, check_rows, args.weight)
    print(f"the weight k_t (k {args.weight:g}): coverage left out / the other way round, worst "
          "ratio of each: " + "; ".join(
              f"{t}: {v['left_out']:.0%} / {v['other_way_round']:.0%}, {v['left_out_ratio']:.1f}x"
              f" / {v['other_way_round_ratio']:.1f}x" for t, v in teacher_scan.items()))
    per_file = {f.name: check(checked["coef"], args.weight, rows_of([f]), kt)
                for f in args.check}
    for name, c in per_file.items():
        print(f"  {name}: {int(round(c['coverage'] * c['n']))} of {c['n']} within the bound")
    (c, a, b), (uc, ua, ub) = checked["coef"], unchecked["coef"]
    left, u_left = checked["left_out"], unchecked["left_out"]
    write_result(args.result_name,
                 {"c": c, "a": a, "b": b, "weight": args.weight, "teacher_weight": kt,
                  "coverage": left["coverage"], "worst_ratio": left["worst_ratio"],
                  "unchecked_c": uc, "unchecked_a": ua, "unchecked_b": ub,
                  "unchecked_coverage": u_left["coverage"],
                  "unchecked_worst_ratio": u_left["worst_ratio"],
                  "other_way_round_coverage": checked["other_way_round"]["coverage"],
                  "unchecked_other_way_round_coverage":
                      unchecked["other_way_round"]["coverage"]},
                 fit=[f.name for f in args.fit], check=[f.name for f in args.check],
                 checked=checked, unchecked=unchecked, weight_scan=scan,
                 teacher_weight_scan=teacher_scan,
                 per_check_file={k: {"coverage": v["coverage"], "n": v["n"]}
                                 for k, v in per_file.items()})
    print(f"RESULT c={c:.4f} a={a:.4f} b={b:.5f} weight={args.weight:g} teacher_weight={kt:g} "
          f"coverage={left['coverage']:.3f} worst_ratio={left['worst_ratio']:.2f} "
          f"unchecked_coverage={u_left['coverage']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
