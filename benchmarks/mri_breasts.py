"""The breast found in clinical prone breast MRI segmentations, against a hand crop.

Runs ``biopsynav init`` with the label flags alone (and ``--side``) on each exam and side of a
local copy of the public 3 T prone breast MRI collection of Pelicano et al. (GitHub
``acpelicano/breast_models_repository``; its licence is unconfirmed, so it is read from where
you unpacked it and nothing of it is kept here). Each exam's ``Label_map_simple.zip`` unpacked
as ``DIR/Exam_NN/Label_map_simple.mha``. Prints, per breast: the modelled volume, the hand
crop's volume and their difference, the extent, the torso tissue cut away, the share of the
back held by the chest wall, the warnings and the time of ``init``.

The hand crops (:data:`HAND_CROPS`) are region-of-interest boxes placed by eye, as 3D Slicer's
Crop Volume module does: on the axial slice through both nipples and the sagittal slice
through each nipple, the box's sides stand at the creases where the breast's skin leaves the
chest (the inframammary fold below, the cleft medially, where the lateral slope and the
upper pole meet the chest wall); the volume is every tissue voxel in the box, skin to chest.

Writes ``benchmarks/results/mri-breasts.json``; last line ``RESULT within15=<n>/<m>
max_diff_pct=<..> warned=<..>``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# exam -> side -> (i0, i1, j0, j1): voxel index bounds of the box (i: patient right to left,
# j: superior to inferior), all depths; lesion label of the exam
HAND_CROPS = {"01": ({"right": (90, 155, 60, 225), "left": (190, 255, 60, 215)}, -4),
              "02": ({"right": (50, 150, 70, 230), "left": (200, 320, 60, 225)}, -3),
              "05": ({"right": (55, 150, 45, 200), "left": (195, 305, 50, 200)}, -4),
              "06": ({"right": (52, 158, 75, 225), "left": (198, 293, 78, 228)}, -3),
              "07": ({"right": (85, 150, 70, 225), "left": (193, 258, 80, 228)}, -3),
              "10": ({"right": (30, 165, 30, 200), "left": (215, 330, 40, 190)}, -3),
              "13": ({"right": (68, 158, 55, 215), "left": (188, 270, 60, 213)}, -3)}
TISSUE = (1, -2, -3, -4)
#: the label flags of the collection's simple maps, but for the lesion labels and the side
LABEL_FLAGS = ["--breast-labels", "1,-2", "--chest-labels", "-1", "--tissue-labels",
               "1=fat,-2=skin"]


def hand_crop_ml(path: Path, box: tuple[int, int, int, int]) -> float:
    """Tissue volume (mL) in a hand-crop box of the label map at ``path``."""
    from biopsynav.anatomy.labelmap import read_label_image

    image = read_label_image(path)
    i0, i1, j0, j1 = box
    tissue = np.isin(image.labels[i0:i1 + 1, j0:j1 + 1], TISSUE)
    return float(tissue.sum()) * image.voxel_mm3 / 1000.0


def modelled(path: Path, side: str, lesion: int, case_dir: Path) -> dict:
    """``init`` with the label flags alone; what it modelled (``info --json``) and its time."""
    flags = [*LABEL_FLAGS, "--lesion-labels", str(lesion), "--side", side]
    start = time.time()
    subprocess.run([sys.executable, "-m", "biopsynav.cli", "init", str(case_dir),
                    "--labelmap", str(path), *flags], check=True, capture_output=True)
    seconds = time.time() - start
    info = json.loads(subprocess.run([sys.executable, "-m", "biopsynav.cli", "info",
                                      str(case_dir), "--json"], check=True,
                                     capture_output=True, text=True).stdout)
    return {"init_s": round(seconds, 1), "lesions": info["n_lesions"],
            "active_cells": info["active_cells"], **info["modelled"],
            "warnings": info["warnings"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--exams", type=Path, required=True, help="folder of Exam_NN folders")
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parent / "results" / "mri-breasts.json")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for exam, (sides, lesion) in HAND_CROPS.items():
            path = args.exams / f"Exam_{exam}" / "Label_map_simple.mha"
            for side, box in sides.items():
                got = modelled(path, side, lesion, Path(tmp) / f"{exam}{side}")
                hand = hand_crop_ml(path, box)
                diff = 100.0 * (got["breast_volume_ml"] / hand - 1.0)
                rows.append({"exam": exam, "side": side, "hand_crop_ml": round(hand, 1),
                             "diff_pct": round(diff, 1), **got})
                print(f"exam {exam} {side:5}: {got['breast_volume_ml']:7.0f} mL, hand crop "
                      f"{hand:6.0f} mL ({diff:+5.1f} %), extent {got['extent_mm']} mm, torso "
                      f"cut {got.get('torso_cut_ml', 0):.0f} mL, back held "
                      f"{100 * got['back_held_share']:.0f} %, {got['lesions']} lesions, "
                      f"init {got['init_s']:.1f} s; warnings: {got['warnings'] or 'none'}")
    within = sum(abs(r["diff_pct"]) <= 15.0 for r in rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d", time.gmtime()),
                                     "rows": rows, "within15": within}, indent=1) + "\n")
    print(f"RESULT within15={within}/{len(rows)} "
          f"max_diff_pct={max(abs(r['diff_pct']) for r in rows):.1f} "
          f"warned={sum(bool(r['warnings']) for r in rows)}")


if __name__ == "__main__":
    main()
