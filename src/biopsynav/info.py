"""The case summary printed by ``biopsynav info``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .anatomy.modelled import modelled_lines
from .case import Case, as_case
from .errors import InputError
from .fileio import read_json
from .inference.model_files import RETRAIN
from .layout import META

MODELLED_KEYS = ("breast_volume_ml", "extent_mm", "back_held_share", "lesion_crop_gap_mm",
                 "torso_cut_ml", "torso_cut_where")


def case_summary(case: Case | str | Path) -> dict:
    """Anatomy, lesions, chest wall, grid and stage status of ``case`` (loaded, or its folder)
    as a plain dict (mm, mL)."""
    from .evaluate.run import stale_evaluations

    case = as_case(case)
    a, g = case.anatomy, case.grid
    facts = read_json(case.paths.facts, "rebuild the case with `biopsynav "
                      "init CASE --overwrite`", missing_ok=True) or {}
    tracking = tracking_meta(case)
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
                       "n_surface_vertices": int(a.fixed_vertices.sum()),
                       "kind": facts.get("chest_wall_kind", "plane")},
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
        "tissues": tissue_table(case),
        "crop_vertices": int(np.asarray(a.crop_vertices).sum()),
        "label_map": {k: facts[k] for k in ("breast", "label_volume_ml", "surface_volume_ml",
                                            "voxel_mm", "unlabelled_holes_voxels",
                                            "lesion_specks_left_out",
                                            "lesion_labels_absent")
                      if k in facts},
        "modelled": {k: facts[k] for k in MODELLED_KEYS if k in facts},
        "warnings": list(facts.get("warnings", [])),
        "stages": case.stages_done(),
        "stale_evaluations": stale_evaluations(case),
        "model_teacher": model_teacher(case, tracking),
        "bounds": bound_words(case, tracking),
        "fe_contact": contact_words(case.cfg),
        "refine": refine_words(case.cfg),
        "fingerprint": case.fingerprint()[:16],
    }


def contact_words(cfg) -> str:
    """How the FE engine holds the probe's contact points (``[tracker] fem_contact``)."""
    from .contact.constraints import is_elastic

    kind = cfg.tracker.fem_contact
    if is_elastic(kind):
        return (f"{kind}: each contact point on a spring of beta E A / h, beta "
                f"{cfg.tracker.contact_stiffness:g}")
    return f"{kind}: the contact points met"


def refine_words(cfg) -> str:
    """What ``[refine]`` does in words."""
    r = cfg.refine
    if not r.samples:
        return "off: the case-grid network is the tracker's model"
    if r.teacher != "grid":
        teacher = (f"{r.teacher.upper()} tetrahedra ({r.teacher_fine_mm:g} mm near the probe, "
                   f"{r.teacher_size_mm:g} mm elsewhere)")
    else:
        teacher = ("the case grid" if r.teacher_refine == 1 else
                   f"cells {r.teacher_refine:g} times smaller"
                   + (f", extrapolated (order {r.extrapolation:g})" if r.extrapolation else ""))
        teacher += f", {law_words(r.material_model, r.fictitious_stiffness)}"
    return (f"{r.samples} rigid pushes ({r.held_out} held out) of {teacher}, "
            f"to {r.max_push_mm:g} mm, {r.iterations} iterations")


def law_words(law: str | None, fictitious: float) -> str:
    """A material law's name with its ``fictitious_stiffness`` when not 0."""
    return f"{law} (fictitious stiffness {fictitious:g})" if fictitious else f"{law}"


def tracking_meta(case: Case) -> tuple[Path, dict | None, bool]:
    """The meta.json of the model the tracker uses (``refine/model`` with ``[refine] samples >
    0``, else the case's), read once: its path, its content (None when there is none) and
    whether it is that model's (False: ``[refine]`` has not trained it yet, and the case's
    model stands in)."""
    try:
        meta_path, current = case.tracking_model / META, True
    except InputError:
        meta_path, current = case.paths.model_meta, False
    return meta_path, read_json(meta_path, RETRAIN,
                                missing_ok=True), current


def bound_words(case: Case, tracking: tuple[Path, dict | None, bool] | None = None) -> str:
    """What the tracking model's 95 % bounds rest on (:func:`biopsynav.tracker.bound.
    basis_words`); empty when there is no tracking model yet. ``tracking``:
    :func:`tracking_meta` of ``case``, when the caller has it."""
    from .tracker.bound import LesionCheck, basis_words

    meta_path, meta, current = tracking or tracking_meta(case)
    if not meta or not current:
        return ""
    return basis_words(LesionCheck.load(meta_path.parent, meta,
                                        [les.id for les in case.anatomy.lesions]))


def model_teacher(case: Case, tracking: tuple[Path, dict | None, bool] | None = None) -> str:
    """What taught the case's trained model, in words; empty when there is no model. Models
    written before the teacher was recorded load as they are: they were taught by the case
    grid's FE with force patches, the only teacher of their time. With ``[refine] samples >
    0`` the model the tracker uses is the one trained further on the fine teacher's pushes
    (``refine/model``); until it exists, the case's model with a note. ``tracking``:
    :func:`tracking_meta` of ``case``, when the caller has it."""
    meta_path, meta, current = tracking or tracking_meta(case)
    pending = "" if current else " ([refine]: not trained further yet)"
    if not meta:
        return ""
    t = meta.get("teacher")
    if not t:
        return (f"case grid ({case.grid.spacing:g} mm cells), force patches (not recorded: "
                "a model trained before teachers were recorded)")
    words = teacher_words(t, case.grid.spacing)
    source = (meta.get("training") or {}).get("init_from")
    if source:  # [network] init_from: trained further from another model
        words += (f"; started from the model in {source.get('path')}, taught by "
                  f"{teacher_words(source.get('teacher') or {}, case.grid.spacing)}")
    case_meta = meta if meta_path == case.paths.model_meta else read_json(
        case.paths.model_meta, RETRAIN, missing_ok=True)
    prior = ((case_meta or {}).get("training") or {}).get("prior")
    if prior:  # [network] prior: the case network started from another breast's
        words += f"; the case network started from the packaged network {prior.get('name')!r}"
    return words + pending


def teacher_words(t: dict, spacing: float) -> str:
    """A model's recorded teacher (meta.json ``teacher``) in words; ``spacing``: the case
    grid's cell size, mm."""
    if t.get("teacher", "grid") != "grid":
        return converged_teacher_words(t)
    refine = float(t.get("teacher_refine", 1))
    order = float(t.get("teacher_extrapolation", 0.0))
    grid = (f"case grid ({spacing:g} mm cells)" if refine == 1 else
            f"grid of {spacing / refine:.3g} mm cells fitted to the case grid")
    if refine > 1 and order > 0:
        grid += f", extrapolated from the case grid (order {order:g})"
    rigid = float(t.get("rigid_share", 0.0))
    pushes = "force patches" if rigid == 0 else f"{rigid:.0%} rigid-probe pushes"
    if rigid and t.get("fem_contact"):
        beta = t.get("contact_stiffness")
        pushes += f" ({t['fem_contact']} contact" + (f", beta {beta:g})" if beta else ")")
    law = law_words(t.get("material_model"), float(t.get("fictitious_stiffness", 0.0)))
    return f"{grid}, {law}, {pushes}"


def converged_teacher_words(t: dict) -> str:
    """A model's recorded teacher other than the grid FE (``[dataset] teacher``, e.g. the P2
    tetrahedra of Table 2's truth) in words, from its ``teacher_protocol``."""
    p = t.get("teacher_protocol") or {}
    name = str(t.get("teacher"))
    mesh = (f"{name.upper()} tetrahedra ({float(p['fine_mm']):g} mm near the probe, "
            f"{float(p['size_mm']):g} mm elsewhere)" if "fine_mm" in p and "size_mm" in p
            else f"the {name!r} teacher")
    probe = f" ({p['probe']})" if p.get("probe") else ""
    return f"{mesh} fitted to the case grid, rigid-probe pushes{probe}"


def tissue_table(case: Case) -> list[dict]:
    """One row per tissue label of the grid (and one for the unlabelled default tissue when
    present): label, segment name, tissue, E (kPa), nu, the cells holding it and its volume
    (mL)."""
    from .fem.tissues import label_tissues

    g, cfg = case.grid, case.cfg
    share = g.active_label_share().astype(np.float64)
    cells_ml = g.active_fraction() * g.spacing ** 3 / 1000.0
    names = {v: n for n, v in case.anatomy.segments.items()}
    tissues = label_tissues(g.label_values, cfg, case.anatomy)
    rows = [_tissue_row(str(int(v)), names.get(int(v), ""), t, share[:, i], cells_ml, cfg)
            for i, (v, t) in enumerate(zip(g.label_values, tissues, strict=True))]
    rest = np.clip(1.0 - share.sum(axis=1), 0.0, 1.0)
    if rest.max(initial=0.0) > 1e-6:
        rows.append(_tissue_row("none", "", cfg.material.default_tissue, rest, cells_ml, cfg))
    return rows


def _tissue_row(label: str, segment: str, tissue: str, share: np.ndarray, cells_ml: np.ndarray,
                cfg) -> dict:
    params = cfg.material.tissues[tissue]
    return {"label": label, "segment": segment, "tissue": tissue,
            "E_kpa": round(1000.0 * params.get("E_mpa", float("nan")), 3),
            "nu": params.get("nu"), "cells": int((share > 0).sum()),
            "volume_ml": round(float(share @ cells_ml), 2)}


def format_summary(s: dict) -> str:
    """Human-readable text of :func:`case_summary`."""
    bb = s["bounding_box_mm"]
    lines = [
        f"case {s['case']} ({s['case_dir']})",
        f"  anatomy   {s['n_vertices']} vertices, {s['n_faces']} faces, {s['volume_ml']:.1f} mL, "
        f"box {bb[0]} .. {bb[1]} mm",
        f"  chest     {s['chest_wall']['n_surface_vertices']} surface vertices on "
        + ("the muscle interface, whose mean plane runs "
           if s["chest_wall"]["kind"].startswith("interface") else "the plane ")
        + f"through {s['chest_wall']['point_mm']} with outward normal {s['chest_wall']['normal']}",
        f"            ({s['chest_wall']['kind']})",
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
        *_label_map_lines(s),
        *modelled_lines({**s["modelled"], "warnings": s["warnings"]}),
        "  tissues   label   segment         tissue    E (kPa)    nu  cells  volume (mL)",
        *[f"            {t['label']:>5}   {t['segment'][:14]:<14}  {t['tissue']:<8} "
          f"{t['E_kpa']:>8.3g} {t['nu']:>5}  {t['cells']:>5}  {t['volume_ml']:>8.1f}"
          for t in s["tissues"]],
        "  stages    " + ", ".join(f"{k} {'done' if v else '-'}" for k, v in s["stages"].items()),
    ]
    if s.get("stale_evaluations"):
        lines.append(f"  evaluation {', '.join(s['stale_evaluations'])} of an earlier model "
                     "(trained since): run `biopsynav evaluate CASE`")
    lines.append(f"  contact   {s['fe_contact']}")
    lines.append(f"  refine    {s['refine']}")
    if s.get("model_teacher"):
        lines.append(f"  teacher   {s['model_teacher']}")
    if s.get("bounds"):
        lines.append(f"  bounds    95 % bounds {s['bounds']}")
    return "\n".join(lines)


def _label_map_lines(s: dict) -> list[str]:
    """The label-map facts of a summary: which breast, labelled against surface volume, crop
    vertices (none for other inputs)."""
    m = s.get("label_map") or {}
    if not m:
        return []
    return [f"  labelmap  {m.get('breast', '')}; voxels {m.get('voxel_mm')} mm; labels "
            f"{m.get('label_volume_ml')} mL, surface {m.get('surface_volume_ml')} mL; "
            f"{s['crop_vertices']} surface vertices on crop faces (never pushed)"
            + (f"; {m['unlabelled_holes_voxels']} unlabelled voxels inside the breast take "
               "the nearest labelled tissue" if m.get("unlabelled_holes_voxels") else "")
            + (f"; {m['lesion_specks_left_out']} lesion-label specks (under 0.05 mL, a "
               "sliver thick) left out" if m.get("lesion_specks_left_out") else "")
            + (f"; lesion labels not in the map: {', '.join(m['lesion_labels_absent'])}"
               if m.get("lesion_labels_absent") else "")]
