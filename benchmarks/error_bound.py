"""Fit each lesion's 95 % error bound on truth comparisons and check it on a case left out.

    python benchmarks/error_bound.py [--fit FILE ...] [--check FILE ...] [--result-name NAME]

The bound (``biopsynav.tracker.bound``) is ``c + |d| (a + b p)`` mm: ``d`` the lesion's
predicted displacement from rest (mm), ``p`` the probe's depth (mm; the mean displacement of
the contact points, as the tracker and Table 2 measure it). A lesion that moves further errs
further, and the share of its motion that is missed grows with the push (the teacher's contact
error, docs/fem.md "Limits"). ``c`` (mm), ``a`` and ``b`` minimise the 95 % pinball loss of
the tracking network's TRE over the rows of the ``--fit`` files (``benchmarks/truth.py
--out`` comparisons of the default pipeline against the P2 truth; by default UC Davis, two
training seeds). The ``--check`` files (by default the phantom), which take no part in the
fit, give the coverage (share of TREs within their bound; asked: 90-97 %) and, per depth, the
bound's mean over the mean TRE (asked: at most 3); the same is then done the other way round.
The rows carry the true displacement, not the network's; the network's |d| is within its TRE
of it, so both the fit and the check take the least it can be, ``max(|d_true| - TRE, 0)``.

Each ``--check`` file's own coverage is printed and kept too (one network each: a check over
several networks of other recipes or seeds). Writes ``benchmarks/results/error-bound.json``
(or ``NAME.json``); the last line reads ``RESULT c=... a=... b=... coverage=...
worst_ratio=...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from resultfile import write_result

RESULTS = Path(__file__).resolve().parent / "results"
QUANTILE = 0.95


def rows_of(paths: list[Path]) -> np.ndarray:
    """(n, 3): reference displacement |d| (mm), probe depth (mm), network TRE (mm), from
    ``truth.py --out`` files or result files holding their rows (``pushes_only.py``)."""
    out = []
    for path in paths:
        data = json.loads(path.read_text())
        for r in data["rows"] if "rows" in data else data["figures"]["rows"]:
            if r["status"].get("net") == "ok":
                out.append((r["reference_mm"], r["depth_mm"], r["tre_mm"]["net"]))
    return np.array(out)


def bound(coef: np.ndarray, disp: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """c + |d| (a + b p), mm, for coef = (c, a, b)."""
    return coef[0] + disp * (coef[1] + coef[2] * depth)


def least_displacement(rows: np.ndarray) -> np.ndarray:
    """The least the network's |d| can be: the true one less the TRE (mm)."""
    return np.maximum(rows[:, 0] - rows[:, 2], 0.0)


def pinball(coef: np.ndarray, rows: np.ndarray) -> float:
    r = rows[:, 2] - bound(coef, least_displacement(rows), rows[:, 1])
    return float(np.mean(np.maximum(QUANTILE * r, (QUANTILE - 1) * r)))


def fit(rows: np.ndarray) -> np.ndarray:
    """(c, a, b) of the 95 % quantile (Nelder-Mead on the pinball loss)."""
    return minimize(pinball, np.array([0.1, 0.05, 0.0]), args=(rows,), method="Nelder-Mead",
                    options={"xatol": 1e-7, "fatol": 1e-10, "maxiter": 8000}).x


def check(coef: np.ndarray, rows: np.ndarray) -> dict:
    """Coverage and, per depth, the mean bound over the mean TRE."""
    b = bound(coef, least_displacement(rows), rows[:, 1])
    by_depth = {}
    for depth in np.unique(rows[:, 1]):
        at = rows[:, 1] == depth
        by_depth[f"{depth:g}"] = {"mean_tre_mm": float(rows[at, 2].mean()),
                                  "mean_bound_mm": float(b[at].mean()),
                                  "ratio": float(b[at].mean() / rows[at, 2].mean()),
                                  "covered": f"{int((rows[at, 2] <= b[at]).sum())}/{at.sum()}"}
    return {"coverage": float((rows[:, 2] <= b).mean()), "n": len(rows), "by_depth": by_depth}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fit", type=Path, nargs="+",
                   default=[RESULTS / "ucdavis-default-mixed-d30-all-truth.json",
                            RESULTS / "ucdavis-default-mixed-seed1-d30-all-truth.json"])
    p.add_argument("--check", type=Path, nargs="+",
                   default=[RESULTS / "phantom-default-mixed-d30-all-truth.json"])
    p.add_argument("--result-name", default="error-bound")
    args = p.parse_args(argv)
    fit_rows, check_rows = rows_of(args.fit), rows_of(args.check)
    coef = fit(fit_rows)
    on_fit, left_out = check(coef, fit_rows), check(coef, check_rows)
    # the other way round: fitted on the checked case, checked on the fitted one
    reverse = check(fit(check_rows), fit_rows)
    print(f"bound = {coef[0]:.4f} + |d| ({coef[1]:.5f} + {coef[2]:.6f} p)   fitted on "
          f"{len(fit_rows)} pushes")
    for name, c in (("fit", on_fit), ("left out", left_out), ("the other way round", reverse)):
        print(f"{name}: coverage {c['coverage']:.0%} of {c['n']}; " + "; ".join(
            f"{d} mm: bound {v['mean_bound_mm']:.2f} / TRE {v['mean_tre_mm']:.2f} = "
            f"{v['ratio']:.1f}x, {v['covered']}" for d, v in c["by_depth"].items()))
    per_file = {f.name: check(coef, rows_of([f])) for f in args.check}
    for name, c in per_file.items():
        print(f"  {name}: {int(round(c['coverage'] * c['n']))} of {c['n']} within the bound")
    worst = max(v["ratio"] for v in left_out["by_depth"].values())
    write_result(args.result_name, {"c": float(coef[0]), "a": float(coef[1]), "b": float(coef[2]),
                                 "coverage": left_out["coverage"], "worst_ratio": worst},
                 fit=[f.name for f in args.fit], check=[f.name for f in args.check],
                 on_fit=on_fit, left_out=left_out, other_way_round=reverse,
                 per_check_file={k: {"coverage": v["coverage"], "n": v["n"]}
                                 for k, v in per_file.items()})
    print(f"RESULT c={coef[0]:.4f} a={coef[1]:.5f} b={coef[2]:.6f} "
          f"coverage={left_out['coverage']:.3f} "
          f"worst_ratio={worst:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
