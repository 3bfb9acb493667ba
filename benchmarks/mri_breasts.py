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

``--all``: every exam in DIR, as a new user of the collection would run ``init``: the label
flags with both tumour labels (``--lesion-labels -3,-4``) and no ``--side``, so that the
tumours choose the breast; where ``init`` refuses (tumours in both breasts), each side in
turn. Per exam: what ``init`` said (modelled, or its one-line refusal), the breast's
volume and extent, the tumours found against the collection's README count for that side,
the warnings. Writes ``benchmarks/results/mri-breasts-all.json``; last line ``RESULT
modelled=<n>/<m> refused=<..> tumours_found=<n>/<m> warned=<..>``. With ``--detailed``, the
graded maps (``DIR/Exam_NN/Label_map_detailed.mha``: fibroglandular 1-3 and the transition 4
as gland, fat 5-7, by a table file) to ``mri-breasts-all-detailed.json``.
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
#: exam -> (tumours in the right breast, in the left), from the collection's README table
TUMOURS = {"01": (2, 0), "02": (2, 1), "03": (1, 0), "04": (2, 0), "05": (2, 0),
           "06": (0, 1), "07": (0, 1), "08": (0, 1), "09": (2, 0), "10": (1, 0),
           "11": (0, 1), "12": (2, 0), "13": (1, 0), "14": (1, 0), "15": (0, 1),
           "16": (0, 1), "17": (0, 1), "18": (2, 0), "19": (0, 1), "20": (1, 0),
           "21": (1, 0), "22": (0, 1), "23": (1, 0), "24": (0, 2), "25": (1, 0),
           "26": (0, 1), "27": (1, 0), "28": (0, 1), "29": (1, 0), "30": (2, 3),
           "31": (0, 1), "32": (0, 1), "33": (0, 1), "34": (0, 1), "35": (1, 0),
           "36": (0, 1), "37": (0, 2), "38": (1, 0), "39": (0, 1), "40": (1, 0),
           "41": (3, 2), "42": (1, 0), "43": (0, 1), "44": (1, 0), "45": (2, 1),
           "46": (2, 3), "47": (0, 2), "48": (1, 1), "49": (1, 0), "50": (1, 0),
           "51": (1, 0), "52": (2, 1), "53": (2, 0), "54": (0, 1), "55": (1, 0)}
SIDES = ("right", "left")
TISSUE = (1, -2, -3, -4)
#: the label flags of the collection's simple maps, but for the lesion labels and the side
LABEL_FLAGS = ["--breast-labels", "1,-2", "--chest-labels", "-1", "--tissue-labels",
               "1=fat,-2=skin"]
#: the detailed maps' grades (fibroglandular 1-3, transition 4, fat 5-7) as a table file's rows
DETAILED_TABLE = "1,gland\n2,gland\n3,gland\n4,gland\n5,fat\n6,fat\n7,fat\n-2,skin\n"
DETAILED_FLAGS = ["--breast-labels", "1,2,3,4,5,6,7,-2", "--chest-labels", "-1"]


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


def init_as_user(path: Path, case_dir: Path, side: str | None, label_flags: list[str]
                 ) -> tuple[dict | None, str]:
    """``init`` with the collection's ``label_flags`` and both tumour labels (``--side`` only
    when given): what it modelled (``info --json``) and the time, or None and its error
    line."""
    flags = [*label_flags, "--lesion-labels", "-3,-4", *(["--side", side] if side else [])]
    start = time.time()
    done = subprocess.run([sys.executable, "-m", "biopsynav.cli", "init", str(case_dir),
                           "--labelmap", str(path), *flags], capture_output=True, text=True)
    if done.returncode:
        return None, (done.stderr.strip().splitlines() or ["(no message)"])[-1]
    info = json.loads(subprocess.run([sys.executable, "-m", "biopsynav.cli", "info",
                                      str(case_dir), "--json"], check=True,
                                     capture_output=True, text=True).stdout)
    return {"init_s": round(time.time() - start, 1), "lesions": info["n_lesions"],
            "active_cells": info["active_cells"], **info["modelled"],
            "warnings": info["warnings"], "breast": info["label_map"].get("breast", "")}, ""


def side_of(breast: str) -> str:
    """The side named in ``info``'s breast line ("the patient's left one of 2 breasts ...")."""
    return next((side for side in SIDES if f"patient's {side}" in breast), "")


def sweep_exam(exam: str, path: Path, work: Path, label_flags: list[str]) -> list[dict]:
    """One exam as a new user meets it: ``init`` without ``--side``, then each side where
    it asks for one; a row per attempt."""
    got, error = init_as_user(path, work / exam, None, label_flags)
    rows = [sweep_row(exam, None, got, error)]
    if got is None and "--side" in error:
        rows += [sweep_row(exam, side, *init_as_user(path, work / f"{exam}{side}", side,
                                                      label_flags))
                 for side in SIDES]
    return rows


def sweep_row(exam: str, side: str | None, got: dict | None, error: str) -> dict:
    """A row of the sweep: the side asked, what was modelled and the README's tumour count
    for the side modelled."""
    row = {"exam": exam, "side_asked": side or "", "error": error}
    if got is not None:
        modelled_side = side or side_of(got["breast"])
        counts = dict(zip(SIDES, TUMOURS.get(exam, (None, None)), strict=True))
        row.update(got, tumours_readme=counts.get(modelled_side))
    print(f"exam {exam} {side or '(no side)':9}: " + (error or (
        f"{got['breast']}: {got['breast_volume_ml']:.0f} mL, "
        f"{got['lesions']} lesions (README {row['tumours_readme']}), "
        f"{got['active_cells']} cells, init {got['init_s']:.1f} s; warnings: "
        f"{got['warnings'] or 'none'}")), flush=True)
    return row


def sweep(exams: Path, out: Path, detailed: bool) -> None:
    """``--all``: every exam of ``exams`` as a new user would run ``init`` (``detailed``: on
    the graded maps, their grades mapped by a table file); the result file and its RESULT
    line."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        flags = LABEL_FLAGS
        if detailed:
            table = Path(tmp) / "grades.csv"
            table.write_text(DETAILED_TABLE, encoding="utf-8")
            flags = [*DETAILED_FLAGS, "--tissue-labels", str(table)]
        name = "Label_map_detailed.mha" if detailed else "Label_map_simple.mha"
        for folder in sorted(exams.glob("Exam_*")):
            rows += sweep_exam(folder.name.split("_")[1], folder / name, Path(tmp), flags)
    done = [r for r in rows if not r["error"]]
    refused = [r for r in rows if r["error"] and not r["side_asked"]
               and "--side" not in r["error"]]
    found = sum(r["lesions"] == r["tumours_readme"] for r in done)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d", time.gmtime()), "rows": rows,
                               "modelled": len(done), "refused": len(refused),
                               "tumours_found": found}, indent=1) + "\n")
    print(f"RESULT modelled={len(done)}/{len(rows)} refused={len(refused)} "
          f"tumours_found={found}/{len(done)} warned={sum(bool(r['warnings']) for r in done)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--exams", type=Path, required=True, help="folder of Exam_NN folders")
    parser.add_argument("--all", action="store_true",
                        help="every exam, as a new user would run init (see above)")
    parser.add_argument("--detailed", action="store_true",
                        help="with --all: the graded maps (DIR/Exam_NN/Label_map_detailed.mha)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    results = Path(__file__).parent / "results"
    if args.all:
        name = "mri-breasts-all-detailed.json" if args.detailed else "mri-breasts-all.json"
        sweep(args.exams, args.out or results / name, args.detailed)
        return
    args.out = args.out or results / "mri-breasts.json"
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
