"""Crop faces held or free: lesion motion of the breast cut from a torso, against a model that
keeps the whole side of the torso.

    python benchmarks/crop_faces.py LABELMAP --side right --lesion-labels -3
        [--breast-labels 1,-2] [--chest-labels -1] [--tissue-labels 1=fat,-2=skin]
        [--depths 10 20 30] [--out FILE]

Three cases of the same label map, each made by ``biopsynav init`` with the same label flags:

* ``torso``: no torso cut (``[anatomy] breast_protrusion_mm = 0``): the whole side of the
  anterior torso, cut from the other side at the sternum; the reference;
* ``free``: the default breast, its crop faces traction-free;
* ``held``: the same breast, its crop faces fixed (``[anatomy] crop_faces = "held"``).

For each lesion the probe is placed over it on the breast (Table 2's placement) and pushed
along its beam by each depth; each case's FE engine (the network's teacher, Table 2's solver
settings) answers the same poses. Printed: each lesion's displacement in the torso model and
how far the free and the held breast's lesion lies from it (mm). Last line ``RESULT
free_mm=<mean> held_mm=<mean> free_d30_mm=<..> held_d30_mm=<..>``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from biopsynav.case import Case
from biopsynav.cli import main as cli
from biopsynav.evaluate.placement import place_case_probe
from biopsynav.evaluate.simulation import evaluation_solver_settings
from biopsynav.tracker.core import fem_engine

VARIANTS = {"torso": "breast_protrusion_mm = 0.0\n", "free": 'crop_faces = "free"\n',
            "held": 'crop_faces = "held"\n'}


def make_case(root: Path, name: str, args) -> Case:
    """``init`` of variant ``name`` with the label flags of ``args``."""
    config = root / f"{name}.toml"
    config.write_text("[anatomy]\n" + VARIANTS[name], encoding="utf-8")
    flags = ["--breast-labels", args.breast_labels, "--lesion-labels", args.lesion_labels,
             "--chest-labels", args.chest_labels, "--tissue-labels", args.tissue_labels,
             "--side", args.side, "--config", str(config)]
    code = cli(["init", str(root / name), "--labelmap", str(args.labelmap), *flags])
    if code:
        sys.exit(code)
    return Case.load(root / name)


def matching_lesion(case: Case, centre: np.ndarray) -> int:
    """Index of the lesion of ``case`` whose centre is nearest ``centre`` (3,) mm."""
    gaps = [np.linalg.norm(les.center - centre) for les in case.anatomy.lesions]
    return int(np.argmin(gaps))


def lesion_motion(cases: dict[str, Case], depths: list[float]) -> list[dict]:
    """One row per lesion of the breast and depth: each case's lesion displacement (mm)."""
    engines = {n: fem_engine(c, evaluation_solver_settings(c)) for n, c in cases.items()}
    rows = []
    breast = cases["free"]
    for li, les in enumerate(breast.anatomy.lesions):
        placement = place_case_probe(breast, li)
        index = {n: matching_lesion(c, les.center) for n, c in cases.items()}
        for engine in engines.values():
            engine.set_rest_pose(placement.pose)
        for depth in depths:
            row = {"lesion": int(les.id), "depth_mm": depth}
            for name, engine in engines.items():
                res = engine.update(placement.pushed(depth))
                row[name] = (res.lesions[index[name]].displacement.tolist() if res.reliable
                             else None)
            rows.append(row)
    return rows


def gaps(rows: list[dict], name: str, min_depth: float = 0.0) -> list[float]:
    """|displacement of ``name`` - the torso's| (mm) of the rows both answered."""
    return [float(np.linalg.norm(np.subtract(r[name], r["torso"]))) for r in rows
            if r[name] is not None and r["torso"] is not None and r["depth_mm"] >= min_depth]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("labelmap", type=Path)
    p.add_argument("--side", required=True, choices=("left", "right"))
    p.add_argument("--lesion-labels", required=True)
    p.add_argument("--breast-labels", default="1,-2")
    p.add_argument("--chest-labels", default="-1")
    p.add_argument("--tissue-labels", default="1=fat,-2=skin")
    p.add_argument("--depths", type=float, nargs="+", default=[10.0, 20.0, 30.0])
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cases = {name: make_case(Path(tmp), name, args) for name in VARIANTS}
        rows = lesion_motion(cases, args.depths)
    for r in rows:
        moved = "-" if r["torso"] is None else f"{np.linalg.norm(r['torso']):6.2f}"
        line = [f"lesion {r['lesion']:2d} {r['depth_mm']:4.0f} mm: torso moves it {moved} mm"]
        for name in ("free", "held"):
            gap = gaps([r], name)
            line.append(f"{name} {gap[0]:5.2f}" if gap else f"{name} -")
        print(", ".join(line))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    deep = max(args.depths) - 2.5
    means = {f"{n}{s}_mm": float(np.mean(gaps(rows, n, d)) if gaps(rows, n, d) else np.nan)
             for n in ("free", "held") for s, d in (("", 0.0), ("_d30", deep))}
    print("RESULT " + " ".join(f"{k}={v:.3f}" for k, v in means.items()))


if __name__ == "__main__":
    main()
