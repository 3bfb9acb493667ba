"""What the anatomy models, in numbers a user can check, and the warnings they raise.

A breast model is checked where it enters (``init``) against what a breast is: a volume of
100-3,000 mL, no longer than 250 mm in any direction, its back held by the chest wall, and its
lesions away from the faces where the image or the torso cut ended it (those faces are free
in the FE model, so a lesion near one moves as if the tissue beyond were not there).
"""

from __future__ import annotations

import numpy as np

from .model import Anatomy, face_cross

VOLUME_RANGE_ML = (100.0, 3000.0)
MAX_EXTENT_MM = 250.0
MIN_BACK_HELD = 0.70
MIN_CROP_GAP_MM = 10.0
BACK_COS = 0.5  # a face is on the back when its normal is within 60 degrees of the wall's


def modelled_facts(anatomy: Anatomy) -> dict:
    """Volume (mL), extent (mm along RAS x, y, z), share of the back face held by the chest
    wall and each lesion's distance to the nearest crop face (mm; None without crop faces)."""
    extent = np.ptp(anatomy.vertices, axis=0)
    return {"breast_volume_ml": round(anatomy.volume_ml(), 1),
            "extent_mm": np.round(extent, 1).tolist(),
            "back_held_share": round(back_held_share(anatomy), 3),
            "lesion_crop_gap_mm": lesion_crop_gaps(anatomy)}


def back_held_share(anatomy: Anatomy) -> float:
    """Area share of the back face (faces off crop faces whose outward normal is within 60
    degrees of the chest wall's outward normal) whose three vertices the chest wall holds."""
    cross = face_cross(anatomy.vertices, anatomy.faces)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    facing = (cross @ anatomy.chest_normal) > BACK_COS * 2.0 * area
    crop = np.asarray(anatomy.crop_vertices, bool)[anatomy.faces].all(axis=1)
    back = facing & ~crop
    held = np.asarray(anatomy.fixed_vertices, bool)[anatomy.faces].all(axis=1)
    total = float(area[back].sum())
    return float(area[back & held].sum()) / total if total > 0 else 0.0


def lesion_crop_gaps(anatomy: Anatomy) -> list[float] | None:
    """Distance (mm) from each lesion's surface to the nearest crop-face vertex."""
    crop = anatomy.vertices[np.asarray(anatomy.crop_vertices, bool)]
    if len(crop) == 0:
        return None
    from scipy.spatial import cKDTree

    tree = cKDTree(crop)
    return [round(float(tree.query(les.points)[0].min()), 1) for les in anatomy.lesions]


def modelled_warnings(facts: dict, lesion_ids: list[int]) -> list[str]:
    """One line per check of :func:`modelled_facts` that a breast should pass and this one
    does not."""
    out = []
    vol = facts["breast_volume_ml"]
    lo, hi = VOLUME_RANGE_ML
    if not lo <= vol <= hi:
        out.append(f"the breast holds {vol:.0f} mL, outside {lo:.0f}-{hi:.0f} mL: check the "
                   "breast labels and the side")
    longest = max(facts["extent_mm"])
    if longest > MAX_EXTENT_MM:
        axis = "RAS"[int(np.argmax(facts["extent_mm"]))]
        out.append(f"the breast is {longest:.0f} mm long along {axis}, over "
                   f"{MAX_EXTENT_MM:.0f} mm: it may hold torso tissue ([anatomy] "
                   "breast_protrusion_mm)")
    if facts["back_held_share"] < MIN_BACK_HELD:
        out.append(f"the chest wall holds {100 * facts['back_held_share']:.0f} % of the "
                   f"breast's back, under {100 * MIN_BACK_HELD:.0f} %: check --chest-labels or "
                   "--chest-wall")
    for lid, gap in zip(lesion_ids, facts["lesion_crop_gap_mm"] or [], strict=False):
        if gap < MIN_CROP_GAP_MM:
            out.append(f"lesion {lid} lies {gap:.1f} mm from a crop face (under "
                       f"{MIN_CROP_GAP_MM:.0f} mm): the tissue beyond the cut is not modelled"
                       + ("; a lower [anatomy] breast_protrusion_mm cuts the torso further "
                          "out" if facts.get("torso_cut_ml") else ""))
    return out


def modelled_lines(facts: dict) -> list[str]:
    """What was modelled, for ``init`` and ``info``: the breast line, then one line a
    warning."""
    if "breast_volume_ml" not in facts:
        return []
    x, y, z = facts["extent_mm"]
    which = f"{facts['breast']}: " if facts.get("breast") else ""  # a label map's choice
    held = 100 * facts["back_held_share"]
    line = (f"  breast    {which}{facts['breast_volume_ml']:.0f} mL, {x:.0f} x {y:.0f} x "
            f"{z:.0f} mm (RAS x, y, z); the chest wall holds {held:.0f} % of its back")
    if facts.get("torso_cut_ml"):
        where = facts.get("torso_cut_where", {})
        line += (f"; {facts['torso_cut_ml']:.0f} mL of the map's torso tissue cut away ("
                 + ", ".join(f"{k} {100 * v:.0f} %" for k, v in where.items()) + ")")
    absent = facts.get("lesion_labels_absent")
    note = ([f"  lesions   no voxel of lesion label {', '.join(absent)} in the map"]
            if absent else [])
    return [line, *note, *(f"  warning   {w}" for w in facts.get("warnings", []))]
