"""One breast of the public prone breast MRI collection, from its label map to a tracked tumour.

    python benchmarks/mri_exam.py --collection CLONE --exam 06 --side left
                                  [--workdir DIR] [--push-minutes 8] [--no-truth]
                                  [--recipe NAME] [--tag TAG] [--one-material]

``CLONE``: a local copy of the GitHub repository ``acpelicano/breast_models_repository``
(Pelicano et al., 3 T prone breast MRI models; a git clone, or a folder of ``Exam_NN``
folders). Its licence is unconfirmed: the label map is unpacked into ``DIR`` (default a
temporary folder), never into this project, and nothing of it is kept here but figures.

What it does, as a user would, with the label flags alone (no crop, no plane, no force by
hand):

1. unpacks ``Exam_NN``'s simple label map (labels -4 benign, -3 malignant, -2 skin, -1
   muscle, 1 fat) to ``DIR/Exam_NN/Label_map_simple.mha``;
2. ``biopsynav init DIR/eNN-SIDE --labelmap MAP --breast-labels 1,-2 --lesion-labels -3,-4
   --chest-labels -1 --tissue-labels 1=fat,-2=skin --side SIDE [--recipe NAME]`` (the tumour
   labels the map holds; the default recipe unless ``--recipe``), and what it modelled;
3. ``biopsynav run`` with every default, each stage timed;
4. the tumours' motion under pushes of exactly 10, 20 and 30 mm from Table 2's placement by
   the network and by the FE engine (the network's teacher), and their distance;
5. unless ``--no-truth``: ``benchmarks/truth.py`` with the same pushes, the network and the
   FE engine against the P2 tetrahedral truth, each reference push bounded by
   ``--push-minutes``.

``--one-material`` compares like with like: the P2 truth has one material, so the breast is
made one (``--tissue-labels 1=fat,-2=fat``, a ``--config`` of ``[material] default_tissue =
"fat"`` and the tumours as soft as the fat, :data:`ONE_MATERIAL_CONFIG`), the truth of its pushes
is solved right after ``init`` (``truth.py --reference-only``), and ``run``'s Table 2 is against
it (``[evaluate] reference = "stored"``, ``truth_file`` that reference): the check of
docs/mri.md, "Against the P2 truth, as one material", in one command. Without it the network of
a skin-over-fat breast is compared with the homogeneous truth (``truth.py`` warns).

Run it alone on the machine. Writes ``benchmarks/results/mri-exam-NN-SIDE[-TAG].json``; the last
line reads ``RESULT volume_ml=... total_min=... table1_mean_mm=... net_d30_mm=...
fem_d30_mm=... bound_covered=k/n`` (nan where not measured). ``--case DIR`` takes a case of
that exam and side that ``run`` already finished: steps 4 and 5 and the figures, without
stage times.

The tracker's 95 % bound (``biopsynav.tracker.bound``, fitted on UC Davis) is checked against
the network's TRE of each push: an MRI breast took no part in its fit.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from figures import depth_means
from mri_breasts import LABEL_FLAGS
from resultfile import write_result
from time_to_model import stage_minutes, table1_figures

ROOT = Path(__file__).resolve().parents[1]
TUMOUR_LABELS = (-3, -4)  # malignant, benign
LABEL_MAP = "Label_map_simple.mha"
#: init's tissue flag of ``--one-material``: skin made fat
ONE_MATERIAL_TISSUES = "1=fat,-2=fat"
#: init's --config of ``--one-material``: fat everywhere, the tumours as soft as the fat (E MPa)
#: and as compressible
ONE_MATERIAL_CONFIG = """[material]
default_tissue = "fat"

[material.tissues.lesion]
E_mpa = 0.00446
nu = 0.45
"""
DEPTHS_MM = ("10", "20", "30")


def archive_bytes(collection: Path, exam: str) -> bytes:
    """The bytes of ``Exam_NN``'s simple label-map zip, from a folder of ``Exam_NN`` folders or
    a git repository (a clone, or a bare one such as ``fetch`` leaves)."""
    found = sorted((collection / f"Exam_{exam}").glob("*abel_map_simple.zip"))
    if found:
        return found[0].read_bytes()
    bare = (collection / "objects").is_dir() and (collection / "HEAD").is_file()
    git = ["git", f"--git-dir={collection}"] if bare else ["git", "-C", str(collection)]
    names = subprocess.run([*git, "ls-tree", "-r", "--name-only", "HEAD", f"Exam_{exam}"],
                           capture_output=True, text=True)
    zips = [n for n in names.stdout.split() if n.lower().endswith("label_map_simple.zip")]
    if names.returncode or not zips:
        sys.exit(f"mri_exam: no simple label map of exam {exam} in {collection}")
    return subprocess.run([*git, "show", f"HEAD:{zips[0]}"], capture_output=True,
                          check=True).stdout


def unpack(collection: Path, exam: str, work: Path) -> Path:
    """``work/Exam_NN/Label_map_simple.mha`` (unpacked once)."""
    out = work / f"Exam_{exam}" / LABEL_MAP
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(io.BytesIO(archive_bytes(collection, exam))) as z:
        member = next(n for n in z.namelist() if n.lower().endswith(".mha"))
        tmp = out.with_suffix(".mha.tmp")
        tmp.write_bytes(z.read(member))
        tmp.replace(out)
    return out


def lesion_flag(label_map: Path) -> list[str]:
    """``--lesion-labels`` with the tumour labels the map holds (none: no flag)."""
    import numpy as np

    from biopsynav.anatomy.labelmap import read_label_image

    present = set(np.unique(read_label_image(label_map).labels).tolist())
    held = [str(v) for v in TUMOUR_LABELS if v in present]
    return ["--lesion-labels", ",".join(held)] if held else []


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "biopsynav.cli", *args], check=True,
                          capture_output=True, text=True)


def truth_run(case_dir: Path, push_minutes: float, *flags: str) -> None:
    """``truth.py CASE`` over every lesion at :data:`DEPTHS_MM`, its reference in the default
    place (``CASE/../<case>-p2.json``), with ``flags``."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "truth.py"), str(case_dir),
                    "--lesions", "0", "--depths", *DEPTHS_MM,
                    "--push-minutes", str(push_minutes), *flags], check=True)


def reference_path(case_dir: Path) -> Path:
    """Where :func:`truth_run` keeps the P2 truth's answers (``truth.py``'s default)."""
    return case_dir.parent / f"{case_dir.name}-p2.json"


def tumour_motion(case_dir: Path, push_minutes: float) -> dict:
    """``truth.py`` over every lesion at 10, 20, 30 mm: its rows and per-method means."""
    out = case_dir.parent / f"{case_dir.name}-truth.json"
    truth_run(case_dir, push_minutes, "--out", str(out))
    data = json.loads(out.read_text())
    means = {m: depth_means(data, m) for m in ("net", "fem", "rigid")}
    return {"rows": data["rows"], "depth_means_mm": means, "bound": bound_check(data["rows"])}


def model_motion(case_dir: Path, depths: tuple[float, ...] = (10.0, 20.0, 30.0)) -> dict:
    """Each tumour's motion (mm) under pushes of exactly ``depths`` from Table 2's placement,
    by the network and by the FE engine (its teacher's solve), and their distance: what the
    case's own models say where no independent truth was solved. Rows: lesion, depth_mm,
    net_mm and fem_mm (|displacement|, None where that engine did not answer reliably, with
    its status), net_fem_mm."""
    import numpy as np

    from biopsynav.case import Case
    from biopsynav.evaluate.placement import place_case_probe
    from truth import method_trackers

    case = Case.load(case_dir)
    trackers = method_trackers(case)
    rows = []
    for li in range(len(case.anatomy.lesions)):
        placement = place_case_probe(case, li)
        for tr in trackers.values():
            tr.set_rest_pose(placement.pose)
        for depth in depths:
            row, disp = {"lesion": int(case.anatomy.lesions[li].id), "depth_mm": depth}, {}
            for name, tr in trackers.items():
                res = tr.update(placement.pushed(depth))
                row[f"{name}_status"] = res.status
                disp[name] = res.lesions[li].displacement if res.reliable else None
                row[f"{name}_mm"] = None if disp[name] is None else float(
                    np.linalg.norm(disp[name]))
            both = all(d is not None for d in disp.values())
            row["net_fem_mm"] = (float(np.linalg.norm(disp["net"] - disp["fem"]))
                                 if both else None)
            rows.append(row)
            print(f"lesion {row['lesion']} at {depth:g} mm: network {row['net_mm']} mm, FE "
                  f"{row['fem_mm']} mm, apart {row['net_fem_mm']} mm", flush=True)
    return {"depths_mm": list(depths), "rows": rows}


def bound_check(rows: list[dict]) -> dict:
    """The tracker's 95 % bound (``biopsynav.tracker.bound``, fitted on UC Davis; this breast
    took no part) against the network's TRE per push: the bound the tracker gave with that
    answer (``truth.py``'s ``bound_mm``: the network's own displacement and the model's lesion
    self-check, as benchmarks/error_bound.py checks it), and how many TREs it covers."""
    checked = []
    for r in rows:
        if r.get("status", {}).get("net") != "ok" or r.get("reference_mm") is None:
            continue
        b = float(r["bound_mm"]["net"])
        checked.append({"lesion": r["lesion"], "depth_mm": r["depth_mm"], "bound_mm": b,
                        "tre_mm": r["tre_mm"]["net"], "covered": r["tre_mm"]["net"] <= b})
    return {"pushes": checked, "covered": f"{sum(c['covered'] for c in checked)}/{len(checked)}"}


def init_flags(args: argparse.Namespace, work: Path) -> list[str]:
    """``init``'s flags beside the label map, lesions and side: the collection's labels
    (:data:`LABEL_FLAGS`), ``--recipe``, and with ``--one-material`` the skin made fat and
    :data:`ONE_MATERIAL_CONFIG` (written to ``work``)."""
    flags = [*LABEL_FLAGS, *(["--recipe", args.recipe] if args.recipe else [])]
    if args.one_material:
        config = work / "one-material.toml"
        config.write_text(ONE_MATERIAL_CONFIG)
        flags[flags.index("--tissue-labels") + 1] = ONE_MATERIAL_TISSUES
        flags += ["--config", str(config)]
    return flags


def judge_by_truth(case_dir: Path, push_minutes: float) -> None:
    """Solve the P2 truth of every lesion's pushes (``truth.py --reference-only``) and make it
    the reference of ``run``'s Table 2 (``[evaluate] reference = "stored"``)."""
    from biopsynav.config import load_config, save_config

    truth_run(case_dir, push_minutes, "--reference-only")
    cfg = load_config(case_dir)
    cfg.evaluate.reference = "stored"
    cfg.evaluate.truth_file = f"../{reference_path(case_dir).name}"  # relative to the case
    save_config(case_dir, cfg)


def from_label_map(args: argparse.Namespace) -> tuple[Path, float, dict, float]:
    """Unpack, ``init`` and ``run`` (every default; with ``--one-material`` the truth solved
    between them): the case folder, init's seconds, the run's stage seconds and its minutes
    in all."""
    from biopsynav.pipeline import run_case

    work = args.workdir or Path(tempfile.mkdtemp(prefix="mri-"))
    label_map = unpack(args.collection, args.exam, work)
    case_dir = work / f"e{args.exam}-{args.side}"
    if case_dir.exists():
        sys.exit(f"mri_exam: {case_dir} exists; the benchmark starts from the label map")
    t = time.perf_counter()
    print(cli("init", str(case_dir), "--labelmap", str(label_map), *init_flags(args, work),
              *lesion_flag(label_map), "--side", args.side).stdout.strip())
    init_s = time.perf_counter() - t
    if args.one_material:
        judge_by_truth(case_dir, args.push_minutes)
    start = time.perf_counter()
    timings = run_case(case_dir)["timings_s"]
    return case_dir, init_s, timings, (time.perf_counter() - start) / 60


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--collection", type=Path, default=None)
    p.add_argument("--exam", required=True, help="two digits, e.g. 06")
    p.add_argument("--side", choices=("left", "right"), required=True)
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--push-minutes", type=float, default=8.0)
    p.add_argument("--no-truth", action="store_true")
    p.add_argument("--recipe", default=None, help="init's --recipe (default: init's default)")
    p.add_argument("--tag", default=None, help="a suffix of the result file's name")
    p.add_argument("--one-material", action="store_true",
                   help="the breast made one material (skin and tumours as fat), Table 2 and "
                        "the figures against the P2 truth of that one material")
    p.add_argument("--case", type=Path, default=None,
                   help="a case of this exam and side that `run` finished: its tumours' motion "
                        "and figures only (no stage times)")
    args = p.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    if args.case is None and args.collection is None:
        sys.exit("mri_exam: give --collection (from the label map) or --case (a finished run)")
    if args.case is None:
        case_dir, init_s, timings, total_min = from_label_map(args)
    else:
        case_dir, init_s, timings, total_min = args.case, math.nan, {}, math.nan
    info = json.loads(cli("info", str(case_dir), "--json").stdout)
    table1 = json.loads((case_dir / "eval" / "table1.json").read_text())
    table2 = json.loads((case_dir / "eval" / "table2.json").read_text())
    summary = json.loads((case_dir / "dataset_summary.json").read_text())
    pushes = case_dir / "refine" / "dataset_summary.json"
    pushes = json.loads(pushes.read_text()) if pushes.is_file() else {}
    motion = {} if args.no_truth else tumour_motion(case_dir, args.push_minutes)
    models = model_motion(case_dir)
    d30 = {m: motion.get("depth_means_mm", {}).get(m, [math.nan] * 3)[2]
           for m in ("net", "fem")}
    figures = {"modelled": info["modelled"], "warnings": info["warnings"],
               "active_cells": info["active_cells"], "lesions": info["n_lesions"],
               "init_s": init_s, "total_min": total_min,
               "stages_min": stage_minutes(case_dir, timings, 0.0),
               "generate": {k: summary.get(k) for k in ("failures", "too_deep", "minutes")},
               "refine_pushes": {k: pushes.get(k) for k in ("failures", "too_deep", "minutes")},
               **table1_figures(table1), "table2_placements": table2["placements"],
               "table2_tables": table2["tables"], "tumour_motion": motion,
               "model_motion": models}
    tag = args.tag or ("one-material" if args.one_material else None)
    tag = f"-{tag}" if tag else ""
    write_result(f"mri-exam-{args.exam}-{args.side}{tag}", figures)
    print(f"RESULT volume_ml={info['modelled']['breast_volume_ml']:.0f} "
          f"total_min={total_min:.1f} table1_mean_mm={table1['mean_e_mm']:.4f} "
          f"net_d30_mm={d30['net']:.2f} fem_d30_mm={d30['fem']:.2f} "
          f"bound_covered={motion.get('bound', {}).get('covered', 'nan')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
