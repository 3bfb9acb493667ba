"""Is the probe-body truth converged? Compare ``truth.py`` references of one anatomy solved at
several resolutions (rim, mesh near the probe, quadrature), lesion by lesion and depth by depth.

    python benchmarks/truth.py CASE --lesion-ids 1 --depths 10 20 30 --reference-only \\
        --edge-radius 2.5 --tet-rim 2 --reference rim2.json        # one per resolution
    python benchmarks/truth_refinement.py rim2=rim2.json rim1=rim1.json [q7=rim1-q7.json]
        [--stored src/biopsynav/data/truths/phantom.json] [--result-name NAME | --no-result-file]

Each ``LABEL=FILE`` is a reference file of ``truth.py`` (``--reference``, resumable): the probe
a rigid body on which reached skin slides (``--friction``, ``--edge-radius``), P2 tetrahedra of
``--tet-size`` / ``--tet-fine`` / ``--tet-rim`` mm, scikit-fem's rule of
``--quadrature-degree``. Give them coarse to fine: each is compared with the one before it
(one refinement step: how far it moves each lesion's displacement vector, mm) and with the
last (the finest). All must be of one anatomy, material and footprint; the lesions and depths
compared are those every file answered. ``--stored`` adds a stored truth (``truth.py``'s shipped
file) against the finest: how far the truth that Table 2 and ``truth.py`` use lies from the
converged one.

Printed per lesion and depth: every file's |u| and the distances. Writes
``benchmarks/results/<NAME>.json`` (default ``truth-refinement-<first label>-<last label>``);
the last line reads ``RESULT step_max_mm=... finest_max_mm=... stored_max_mm=...`` (the
largest last refinement step, the largest distance of any file to the finest, and of the
stored truth to the finest; nan where not asked).
"""

from __future__ import annotations

import argparse
import json
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np

from resultfile import result_line, write_result
from truth_agreement import distance, largest

#: Keys of a reference's ``key`` that must match for two files to answer one problem
SAME_PROBLEM = ("anatomy", "E_mpa", "nu", "footprint")
#: Keys of a reference's ``key`` that say how it was solved (shown per file)
RESOLUTION = ("tet_size_mm", "tet_fine_mm", "rim_mm", "quadrature_degree", "edge_radius_mm",
              "friction", "probe")


def labelled_file(text: str) -> tuple[str, Path]:
    """``LABEL=FILE`` -> (label, path)."""
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LABEL=FILE")
    return label, Path(path)


def read_reference(path: Path) -> dict:
    """A ``truth.py`` reference file; SystemExit naming the file when it is not one."""
    try:
        data = json.loads(path.read_text())
        data["key"], data["lesions"]  # noqa: B018 - both must be there
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a truth.py reference file ({type(exc).__name__}: {exc})"
                         ) from None
    return data


def check_same_problem(files: dict[str, dict]) -> None:
    """SystemExit naming the first key on which two files pose different problems."""
    first_label, first = next(iter(files.items()))
    for label, data in files.items():
        for k in SAME_PROBLEM:
            if data["key"].get(k) != first["key"].get(k):
                raise SystemExit(f"{label} and {first_label} differ in {k!r}: "
                                 f"{data['key'].get(k)} against {first['key'].get(k)}")


def answers(data: dict) -> dict[tuple[str, float], np.ndarray]:
    """(lesion index, depth mm) -> the lesion's displacement vector (3,), mm, of every depth
    the reference answered."""
    depths = data["key"]["depths_mm"]
    out = {}
    for li, entry in data["lesions"].items():
        for depth, u in zip(depths, entry.get("displacement", []), strict=False):
            if u is not None and np.all(np.isfinite(u)):
                out[(li, float(depth))] = np.asarray(u, dtype=float)
    return out


def rows_of(files: dict[str, dict], stored: dict | None) -> list[dict]:
    """One row per (lesion, depth) that every file answered: |u| of each file, each file's
    distance to the one before and to the last, the stored truth's to the last (None
    where it has no answer there)."""
    labels = list(files)
    solved = {label: answers(data) for label, data in files.items()}
    common = sorted(set.intersection(*(set(s) for s in solved.values())),
                    key=lambda k: (int(k[0]), k[1]))
    kept = answers(stored) if stored else {}
    rows = []
    for li, depth in common:
        u = {label: solved[label][(li, depth)] for label in labels}
        row = {"lesion": int(li), "depth_mm": depth,
               **{f"u_{label}_mm": float(np.linalg.norm(u[label])) for label in labels}}
        for before, label in pairwise(labels):
            row[f"step_{before}_{label}_mm"] = distance(u[before], u[label])
        for label in labels[:-1]:
            row[f"finest_{label}_mm"] = distance(u[label], u[labels[-1]])
        row["stored_truth_to_finest_mm"] = distance(kept.get((li, depth)), u[labels[-1]])
        rows.append(row)
    return rows


def print_rows(rows: list[dict], labels: list[str]) -> None:
    """The table: lesion, depth, each |u|, each step, the stored truth's distance."""
    steps = [f"step_{a}_{b}_mm" for a, b in pairwise(labels)]
    head = (["lesion", "depth"] + [f"|u| {label}" for label in labels]
            + [f"{a}->{b}" for a, b in pairwise(labels)] + ["stored->finest"])
    print(" ".join(f"{h:>12}" for h in head))
    for r in rows:
        vals = ([r["lesion"], r["depth_mm"]] + [r[f"u_{label}_mm"] for label in labels]
                + [r[k] for k in steps] + [r["stored_truth_to_finest_mm"]])
        print(" ".join(f"{v:>12.3f}" if isinstance(v, float) else f"{'-' if v is None else v:>12}"
                       for v in vals))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", type=labelled_file, nargs="+", metavar="LABEL=FILE",
                   help="truth.py reference files, coarse to fine")
    p.add_argument("--stored", type=Path, default=None,
                   help="a stored truth compared with the finest file")
    p.add_argument("--result-name", default=None)
    p.add_argument("--no-result-file", action="store_true")
    args = p.parse_args(argv)
    labels = [label for label, _ in args.files]
    if len(labels) < 2 or len(set(labels)) < len(labels):
        p.error("give two or more LABEL=FILE, coarse to fine, with distinct labels")
    files = {label: read_reference(path) for label, path in args.files}
    stored = read_reference(args.stored) if args.stored else None
    check_same_problem({**files, **({"--stored": stored} if stored else {})})
    rows = rows_of(files, stored)
    if not rows:
        raise SystemExit("no lesion and depth answered by every file")
    print_rows(rows, labels)
    figures = {"step_max_mm": largest(rows, f"step_{labels[-2]}_{labels[-1]}_mm"),
               "finest_max_mm": max(largest(rows, f"finest_{label}_mm")
                                    for label in labels[:-1]),
               "stored_max_mm": largest(rows, "stored_truth_to_finest_mm"),
               "files": {label: {"path": str(path),
                                 **{k: files[label]["key"].get(k) for k in RESOLUTION}}
                         for label, path in args.files},
               "stored": str(args.stored) if args.stored else None, "rows": rows}
    if not args.no_result_file:
        write_result(args.result_name or f"truth-refinement-{labels[0]}-{labels[-1]}", figures)
    print(result_line(figures, ("step_max_mm", "finest_max_mm", "stored_max_mm")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
