"""The case summary printed by ``biopsynav info``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .case import Case, as_case
from .fileio import read_json


def case_summary(case: Case | str | Path) -> dict:
    """Anatomy, lesions, chest wall, grid and stage status of ``case`` (loaded, or its folder)
    as a plain dict (mm, mL)."""
    case = as_case(case)
    a, g = case.anatomy, case.grid
    facts = read_json(case.paths.facts, "rebuild the case with `biopsynav "
                      "init CASE --overwrite`", missing_ok=True) or {}
    return {
        "case": case.cfg.case.name,
        "case_dir": str(case.dir),
        "n_vertices": int(len(a.vertices)),
        "n_faces": int(len(a.faces)),
        "volume_ml": round(a.volume_ml(), 3),
        "bounding_box_mm": np.round(a.bounds, 3).tolist(),
        "pinch_vertices_split": int(facts.get("pinch_vertices_split", 0)),
        "chest_wall": {"point_mm": np.round(a.chest_point, 3).tolist(),
                       "normal": np.round(a.chest_normal, 4).tolist(),
                       "n_surface_vertices": int(a.fixed_vertices.sum())},
        "n_lesions": len(a.lesions),
        "lesions": [{"id": les.id, "center_mm": np.round(les.center, 3).tolist(),
                     "radius_mm": round(les.radius_mm, 3)} for les in a.lesions],
        "grid_shape": list(g.node_shape),
        "cell_size_mm": g.spacing,
        "active_cells": int(g.active_cells.sum()),
        "boundary_cells": int((g.status == 1).sum()),
        "inside_cells": int((g.status == 2).sum()),
        "active_nodes": int(g.active_nodes.sum()),
        "n_fixed_nodes": int(g.fixed_nodes.sum()),
        "grid_volume_ml": round(float(g.fraction.sum()) * g.spacing ** 3 / 1000.0, 3),
        "tissue_labels": sorted(int(v) for v in np.unique(g.label[g.active_cells]) if v >= 0),
        "stages": case.stages_done(),
        "fingerprint": case.fingerprint()[:16],
    }


def format_summary(s: dict) -> str:
    """Human-readable text of :func:`case_summary`."""
    bb = s["bounding_box_mm"]
    lines = [
        f"case {s['case']} ({s['case_dir']})",
        f"  anatomy   {s['n_vertices']} vertices, {s['n_faces']} faces, {s['volume_ml']:.1f} mL, "
        f"box {bb[0]} .. {bb[1]} mm",
        f"  chest     {s['chest_wall']['n_surface_vertices']} surface vertices on the plane "
        f"through {s['chest_wall']['point_mm']} with outward normal {s['chest_wall']['normal']}",
        f"  lesions   {s['n_lesions']}",
    ]
    lines += [f"    #{les['id']}: centre {les['center_mm']} mm, radius {les['radius_mm']} mm"
              for les in s["lesions"]]
    lines += [
        f"  grid      {' x '.join(map(str, s['grid_shape']))} nodes, "
        f"cell {s['cell_size_mm']:g} mm, "
        f"{s['active_cells']} active cells ({s['boundary_cells']} boundary, "
        f"{s['inside_cells']} inside), {s['active_nodes']} active nodes, "
        f"{s['n_fixed_nodes']} fixed nodes, immersed volume {s['grid_volume_ml']:.1f} mL",
        "  stages    " + ", ".join(f"{k} {'done' if v else '-'}" for k, v in s["stages"].items()),
    ]
    return "\n".join(lines)
