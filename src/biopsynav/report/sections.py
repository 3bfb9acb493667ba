"""The report's sections, each built from its stage's outputs or a "not run yet" note."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .. import fileio
from ..case import Case
from ..config import CaseConfig
from ..errors import BiopsynavError, InputError
from ..evaluate.paper import PAPER_TABLE1
from ..evaluate.run import TABLE2, TABLE2_MEASURED, shown_tables, table2_text
from ..evaluate.table import METHOD_TITLES, format_text, table_from_dict
from ..info import law_words
from ..layout import (
    ANATOMY_PICTURE,
    CONVERGENCE_FILE,
    DATASET_PLOT,
    DATASET_SUMMARY,
    FACTS_FILE,
    LESION_CHECK,
    LOSS_CURVE,
    META,
    REPORT_FILES,
    TABLE1_FILE,
    CasePaths,
)
from .blocks import GridTable, Image, Note, Para, Pre, Section
from .figures import plot_table2, plot_timing, timing_rows
from .machine import versions_and_machine

FIG_DIR = REPORT_FILES


def not_run(stage: str, case_dir: Path, what: str) -> Note:
    """The note of a missing stage output."""
    return Note(f"{what}: not run yet: run `biopsynav {stage} {case_dir}`.")


def read_stage_json(path: Path) -> dict | None:
    """The JSON object at ``path``, or None if missing; InputError naming a damaged one."""
    doc = fileio.read_json(path, f"rebuild it with the stage that writes it "
                                 f"({_WRITER.get(path.name, 'biopsynav run')})", missing_ok=True)
    if doc is not None and not isinstance(doc, dict):
        raise InputError(f"damaged: not a JSON object; rebuild it with "
                         f"{_WRITER.get(path.name, 'biopsynav run')}", str(path))
    return doc


#: The command that writes each JSON file the report reads.
_WRITER = {TABLE1_FILE: "`biopsynav evaluate`", f"{TABLE2}.json": "`biopsynav evaluate`",
           META: "`biopsynav train`", DATASET_SUMMARY: "`biopsynav generate`",
           FACTS_FILE: "`biopsynav init --overwrite`",
           CONVERGENCE_FILE: "`python benchmarks/convergence.py CASE`",
           LESION_CHECK: "`biopsynav evaluate`"}


def _num(v, fmt: str = ".4g") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, fmt)
    return str(v)


def case_section(case_dir: Path, cfg: CaseConfig, case: Case | None = None) -> Section:
    """The case's name, description and anatomy picture (``case``: the loaded case, when the
    caller has it)."""
    s = Section("The case")
    s.blocks.append(Para(f"{cfg.case.name}: {cfg.case.description or 'no description'}. "
                         "Units: mm, N, MPa."))
    picture = anatomy_picture(case_dir, case)
    if isinstance(picture, Path):
        s.blocks.append(Image(picture, "Anatomy: surface, chest wall, lesions and the active "
                                       "grid cells (3D view and three mid-slices)."))
    else:
        s.blocks.append(picture)
    return s


def parameters_section(cfg: CaseConfig) -> Section:
    """Every case.toml parameter (folded in the HTML report)."""
    rows = []
    for section, values in cfg.to_dict().items():
        for key, value in values.items():
            shown = json.dumps(value) if isinstance(value, (dict, list)) else str(value)
            rows.append([f"[{section}] {key}", shown])
    return Section("Parameters (case.toml)", [GridTable(["parameter", "value"], rows)],
                   folded=True)


def anatomy_picture(case_dir: Path, case: Case | None = None) -> Path | Note:
    """``CASE/anatomy.png`` (rendered when missing or older than the grid, from ``case`` or
    the folder's files), or a note."""
    paths = CasePaths(case_dir)
    png, grid = case_dir / ANATOMY_PICTURE, paths.grid
    if not grid.is_file() or not paths.anatomy.is_file():
        return not_run("init", case_dir, "Anatomy and grid")
    if png.is_file() and png.stat().st_mtime >= grid.stat().st_mtime:
        return png
    try:
        from ..show import render_case

        return render_case(case if case is not None else Case.load(case_dir), png)
    except (BiopsynavError, OSError, ValueError) as exc:
        return Note(f"The anatomy picture could not be rendered: {exc}")


def dataset_section(case_dir: Path) -> Section:
    """Data generation summary and histograms."""
    s = Section("Training data (FE simulations)")
    summary = read_stage_json(CasePaths(case_dir).dataset_summary)
    if summary is None:
        s.blocks.append(not_run("generate", case_dir, "Data generation"))
        return s
    s.blocks.append(GridTable(["quantity", "value"], [[k, _num(v)] for k, v in summary.items()]))
    if (case_dir / DATASET_PLOT).is_file():
        s.blocks.append(Image(case_dir / DATASET_PLOT, "Distributions of probe force, tilt, "
                                                        "maximal nodal and probe displacement."))
    return s


def training_section(case_dir: Path) -> Section:
    """Architecture, training figures and the loss curve."""
    s = Section("Network training")
    meta = read_stage_json(CasePaths(case_dir).model_meta)
    if meta is None:
        s.blocks.append(not_run("train", case_dir, "Training"))
        return s
    rows = [["architecture", json.dumps(meta.get("architecture", "-"))],
            ["parameters", _num(meta.get("n_parameters"))]]
    rows += [[k, _num(v)] for k, v in (meta.get("training") or {}).items()
             if not isinstance(v, (list, dict))]
    s.blocks.append(GridTable(["item", "value"], rows))
    paths = CasePaths(case_dir)
    curve = next((p for p in (paths.model / LOSS_CURVE, paths.eval / LOSS_CURVE)
                  if p.is_file()), None)
    if curve is not None:
        s.blocks.append(Image(curve, "Training loss and validation error against iterations."))
    return s


def table1_section(case_dir: Path, cfg: CaseConfig) -> Section:
    """Table 1 beside the paper's, error histogram, Figure 4 (worst, largest deformation);
    ``cfg``: the case's configuration (the teachers' laws)."""
    s = Section("Table 1: network against FE on the held-out samples")
    t1 = read_stage_json(CasePaths(case_dir).table1)
    if t1 is None:
        s.blocks.append(not_run("evaluate", case_dir, "Table 1"))
        return s
    p = PAPER_TABLE1
    rows = [
        ["mean norm error e (mm; the mean of each node's error norm)", _num(t1.get("mean_e_mm")),
         _num(p["mean_e_mm"])],
        ["std of e (mm)", _num(t1.get("std_e_mm")), _num(p["std_e_mm"])],
        ["max of e (mm)", _num(t1.get("max_e_mm")), _num(p["max_e_mm"])],
        ["e per degree of freedom, mean / max (mm): eq. (3) as written, the mean absolute "
         "error of the 3 n displacement components", f"{_num(t1.get('mean_e_dof_mm'))} / "
         f"{_num(t1.get('max_e_dof_mm'))}", f"{_num(p['mean_e_mm'])} / {_num(p['max_e_mm'])} "
         "(which reading the paper's figures are is not said)"],
        ["prediction time (ms)", f"{_num(t1.get('predict_mean_ms'))} ± "
                                 f"{_num(t1.get('predict_std_ms'))} (median "
                                 f"{_num(t1.get('predict_p50_ms'))}, p99 "
                                 f"{_num(t1.get('predict_p99_ms'))})",
         f"{p['predict_mean_ms']} ± {p['predict_std_ms']}"],
        ["training time (min)", _num(t1.get("train_min")), _num(p["train_min"])],
        ["max nodal displacement (mm)", _num(t1.get("max_disp_mm")), _num(p["max_disp_mm"])],
        ["test samples", _num(t1.get("n_samples")), _num(p["n_test"])],
        ["runtime / precision", f"{t1.get('runtime', '-')} / {t1.get('precision', '-')}",
         "PyTorch, GPU"],
    ]
    if "baseline_mean_e_mm" in t1:  # what training adds to the network's physics baseline
        rows.append(["the physics baseline alone (the network's head at zero), mean / max e "
                     "(mm)", f"{_num(t1['baseline_mean_e_mm'])} / "
                     f"{_num(t1['baseline_max_e_mm'])}", "not reported"])
    if "inverted_samples" in t1:  # det F <= 0 somewhere: the predicted field is not physical
        rows.append(["predictions that invert a cell (FE targets)",
                     f"{t1['inverted_samples']} of {_num(t1.get('n_samples'))}, at most "
                     f"{t1['inverted_cells_max']} cells ({t1['inverted_samples_fe']})",
                     "not reported"])
    rows += kind_table1_rows(t1)
    s.blocks.append(GridTable(["", "this case", "the paper"], rows))
    s.blocks += earlier_model_blocks(t1, CasePaths(case_dir).model, "Table 1", case_dir)
    s.blocks += rigid_table1_blocks(cfg, t1) + refined_table1_blocks(case_dir, cfg)
    figures = [("error_histogram.png", "Histogram of the mean norm error e over the test "
                                       "samples."),
               ("largest_deformation.png", "Figure 4(a): prediction (network) against FE on "
                                           "the sample with the largest deformation."),
               ("worst_sample.png", "Figure 4(b): prediction against FE on the sample with "
                                    "the largest mean norm error.")]
    for name, caption in figures:
        path = CasePaths(case_dir).eval / name
        s.blocks.append(Image(path, caption) if path.is_file() else
                        Note(f"{name} is missing: run `biopsynav evaluate {case_dir}` again."))
    return s


def earlier_model_blocks(result: dict, model_dir: Path, what: str, case_dir: Path) -> list:
    """A note when ``result`` (table1.json, table2.json) records the model it evaluated
    (``model_checksum``) and the model now in ``model_dir`` is another (trained since);
    none otherwise (a file from before the checksum was recorded, or no model)."""
    from ..evaluate.run import made_with_another_model

    if not made_with_another_model(result, model_dir):
        return []
    return [Note(f"{what} was made with an earlier model than the one now in "
                 f"{model_dir.relative_to(case_dir)}/ (trained since): its figures are not "
                 f"this model's; run `biopsynav evaluate {case_dir}` to remake it.")]


def kind_table1_rows(t1: dict) -> list[list[str]]:
    """Table 1 rows of each kind of held-out sample in a data set of both (``by_kind``, the
    ``pushes-patches`` recipe): mean / max e and count, the paper's column beside the force
    patches."""
    from ..network.evaluate import KIND_LABELS

    p = PAPER_TABLE1
    paper = {"force_patches": f"{_num(p['mean_e_mm'])} / {_num(p['max_e_mm'])} "
                              f"({_num(p['n_test'])})"}
    return [[f"{KIND_LABELS[kind]}: mean / max e (mm) (samples)",
             f"{_num(v.get('mean_e_mm'))} / {_num(v.get('max_e_mm'))} ({_num(v.get('n_samples'))})",
             paper.get(kind, "-")]
            for kind, v in (t1.get("by_kind") or {}).items()]


def rigid_table1_blocks(cfg: CaseConfig, t1: dict) -> list:
    """A note, for a case whose samples are all rigid-probe pushes (the ``pushes`` recipe,
    :mod:`biopsynav.recipes`), that its Table 1 (``t1``, table1.json) measures the tracking
    network on held-out rigid pushes, not the paper's force patches; for one of both kinds
    (``pushes-patches``) whose Table 1 splits them (``by_kind``), that the table's last rows
    do; none otherwise."""
    law = law_words(cfg.material.model, cfg.material.fictitious_stiffness)
    if t1.get("by_kind"):
        return [Note("The held-out samples are of two kinds, drawn as the training's (law "
                     f"{law}): rigid-probe pushes up to {_num(cfg.probe.max_push_mm)} mm, as "
                     "the tracker meets them, and the paper's force patches; the table's last "
                     "rows give each kind's error, the force patches' beside the paper's "
                     "(docs/pipeline.md, \"Recipes\").")]
    if cfg.probe.rigid_share < 1.0:
        return []
    return [Note("The held-out samples are rigid-probe pushes, as the tracker meets them (up "
                 f"to {_num(cfg.probe.max_push_mm)} mm, law {law}), not the paper's force "
                 "patches: this is the network the tracker uses, against its own FE teacher, "
                 "on deeper pushes than the paper's test set, so its errors are larger than "
                 "the paper's column (docs/pipeline.md, \"Recipes\"). Its error on the "
                 "paper's force patches: `python benchmarks/table1_patches.py CASE`.")]


def refined_table1_blocks(case_dir: Path, cfg: CaseConfig) -> list:
    """A note with Table 1 of the model trained further on the refine teacher's pushes
    (``refine/eval/table1.json``, ``[refine]``), the tracker's model, naming both teachers'
    laws from ``cfg``; none without one."""
    t1 = read_stage_json(CasePaths(CasePaths(case_dir).refine).table1)
    if t1 is None:
        return []
    return [Note(f"The tracker uses the model trained further on {_num(t1.get('n_samples'))} "
                 "held-out and the other rigid pushes of its refine teacher ([refine], "
                 f"{refine_teacher_words(cfg)}, refine/eval): mean / max e against that "
                 f"teacher {_num(t1.get('mean_e_mm'))} / {_num(t1.get('max_e_mm'))} mm. The "
                 "table above is the case-grid network it started from, against its own "
                 f"teacher, the case grid's {case_samples_words(cfg)}, law "
                 f"{law_words(cfg.material.model, cfg.material.fictitious_stiffness)}.")]


def case_samples_words(cfg: CaseConfig) -> str:
    """The case data set's kind of sample in words (``[probe] rigid_share``)."""
    share = cfg.probe.rigid_share
    if share >= 1.0:
        return "rigid-probe pushes"
    return "force patches" if share <= 0.0 else "rigid-probe pushes and force patches"


def refine_teacher_words(cfg: CaseConfig) -> str:
    """The refine teacher in words: the grid FE's law, or the P2 FE's mesh."""
    r = cfg.refine
    if r.teacher == "p2":
        return (f"the P2 tetrahedral FE, {r.teacher_fine_mm:g} mm tetrahedra near the probe "
                f"and {r.teacher_size_mm:g} mm elsewhere")
    return f"law {law_words(r.material_model, r.fictitious_stiffness)}"


def table2_section(case_dir: Path, fig_dir: Path, cfg: CaseConfig | None = None) -> Section:
    """Table 2 by simulation and, when present, from measured data; three methods each; then
    the tracking model's lesion self-check (of ``cfg``'s tracking model), when made."""
    s = Section("Table 2: target registration error per lesion and probe displacement")
    found = False
    for stem, title in ((TABLE2, "by simulation"), (TABLE2_MEASURED, "from measured data")):
        result = read_stage_json(CasePaths(case_dir).table2(stem))
        if result is None:
            continue
        found = True
        if cfg is not None:
            model = CasePaths(case_dir).tracking_model(bool(cfg.refine.samples))
            s.blocks += earlier_model_blocks(result, model, f"Table 2 {title}", case_dir)
        s.blocks += table2_blocks(result, title, fig_dir / f"{stem}.png")
    if not found:
        s.blocks.append(not_run("evaluate", case_dir, "Table 2"))
    if cfg is not None:
        model = CasePaths(case_dir).tracking_model(bool(cfg.refine.samples))
        s.blocks += lesion_check_blocks(model / LESION_CHECK)
    return s


def lesion_check_blocks(path: Path) -> list:
    """The lesion self-check's table: each lesion's share of its motion the network missed
    against its teacher at each check depth, and its teacher gap (a check made before the gap
    was part of it shows none); nothing when it was not made."""
    from ..evaluate.lesion_check import share_words

    check = read_stage_json(path)
    if check is None:
        return []
    try:
        depths = [float(d) for d in check["depths_mm"]]
        teacher = check.get("teacher_check", {})
        rows = [[str(i)] + [share_words(_float_or_none(r)) for r in v["relative"]]
                + [share_words(_float_or_none(v.get("teacher_gap")))]
                for i, v in check["lesions"].items()]
        gap_title = (f"teacher gap ({float(teacher['refinement']):g}x finer grid, "
                     f"{float(teacher['depth_mm']):g} mm)" if teacher else "teacher gap")
    except (KeyError, TypeError, ValueError, AttributeError):
        raise InputError("damaged: not a lesion check; rebuild it with `biopsynav evaluate`",
                         str(path)) from None
    return [Para("Each lesion's self-check (the tracking network against its own FE teacher, "
                 "the probe pushed over the lesion; no truth takes part): the share of the "
                 "lesion's motion the network missed, and the share by which the teacher on a "
                 "finer grid moves it otherwise (the teacher gap: how far the teacher is from "
                 "converged there). Both widen that lesion's 95 % bound "
                 "(docs/tracker.md, \"Error bound\")."),
            GridTable(["lesion"] + [f"{d:g} mm" for d in depths] + [gap_title], rows)]


def _float_or_none(value) -> float | None:
    """``value`` as a float (ValueError or TypeError for neither a number nor None)."""
    return None if value is None else float(value)


def table2_blocks(result: dict, title: str, png: Path) -> list:
    """Tables (one per method), the paper's figures, a summary figure and the failures; for
    a case without lesions, its note alone."""
    if "note" in result:
        return [Para(f"Table 2 {title}: {result['note']}.")]
    blocks: list = [Para(f"Table 2 {title}: " + table2_text(result).split("\n\n")[0]
                         .split(": ", 1)[1])]
    for m, what in shown_tables(result):
        t = result["tables"][m]
        header, *rows = _grid_rows(t)
        blocks += [Para(f"{METHOD_TITLES.get(m, m)}: average {what} "
                        f"{_num(t['overall_mean'], '.3f')} mm."), GridTable(header, rows)]
    coverage = bound_coverage(result.get("records", []))
    if coverage:
        blocks.append(Para(coverage))
    blocks.append(Para("The paper, on the CIRS phantom with positions from ultrasound "
                       "images: average TRE below 6.194 mm (U-Net) and 6.080 mm (FE) per "
                       "lesion; column means D10 ... D30 of 2.75, 3.39, 4.22, 5.12, 5.76 mm "
                       "(U-Net) and 2.02, 2.62, 3.55, 4.68, 4.96 mm (FE)."))
    blocks.append(Image(plot_table2(result, png), "Mean TRE per displacement range (bars: "
                                                  "this case; circles: the paper) and the "
                                                  "distribution of all TREs."))
    fails = [f for f in result.get("failures", []) if f["method"] != "reference"]
    if fails:
        blocks.append(Pre("\n".join(f"lesion {f['lesion']} push {f['push']} "
                                    f"({f['displacement_mm']:.1f} mm) {f['method']}: "
                                    f"{f['status']}: {f['reason']}" for f in fails)))
    return blocks


def bound_coverage(records: list[dict], method: str = "net") -> str:
    """How often the tracker's 95 % bound held the network's TRE in these records ('' when
    none carries a bound)."""
    rows = [(r["tre_mm"], r["bound_mm"]) for r in records
            if r.get("method") == method and r.get("tre_mm") is not None
            and r.get("bound_mm") is not None and math.isfinite(r["bound_mm"])]
    if not rows:
        return ""
    tre, bound = np.array(rows).T
    return (f"Each lesion's 95 % bound (what the tracker sends with every position; "
            f"docs/tracker.md, \"Error bound\"): the network's TRE lies within it in "
            f"{int((tre <= bound).sum())} of {len(rows)} pushes here (mean bound "
            f"{bound.mean():.2f} mm, mean TRE {tre.mean():.2f} mm).")


def _grid_rows(t: dict) -> list[list[str]]:
    """Header and rows of a method table as strings (re-using the text formatter)."""
    lines = format_text(table_from_dict(t)).splitlines()[1:]
    rows = [line.split() for i, line in enumerate(lines) if i != 1]
    width = len(rows[0])
    return [r + [""] * (width - len(r)) for r in rows]


def convergence_section(case_dir: Path) -> Section:
    """The FE against an independent P2 reference on a sequence of grids
    (``eval/convergence.json`` of ``benchmarks/convergence.py``), or how to run it."""
    s = Section("Convergence: the FE against an independent reference")
    study = read_stage_json(CasePaths(case_dir).convergence)
    if study is None:
        s.blocks.append(Note("No convergence study: `python benchmarks/convergence.py "
                             f"{case_dir}` (a P2 tetrahedral reference per lesion: minutes "
                             "to hours) writes eval/convergence.json, shown here."))
    else:
        s.blocks += study_blocks(study)
    return s


def study_blocks(study: dict) -> list:
    """The blocks of a convergence study, or a note naming what is wrong with its file."""
    again = "run `python benchmarks/convergence.py CASE` again"
    if not isinstance(study.get("summary"), dict):
        return [Note(f"eval/convergence.json holds no summary (an unfinished run, or one of "
                     f"an older script): {again}.")]
    try:
        return convergence_blocks(study["summary"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        return [Note(f"eval/convergence.json is damaged ({type(exc).__name__}: {exc}): "
                     f"{again}.")]


def convergence_blocks(summary: dict) -> list:
    """What the reference was, then one row per FE series: the lesion error mean (max) and
    the field error mean at each push depth, mm."""
    depths = summary["depths_mm"]
    header = ["FE", "active cells"] + [f"{d:g} mm: lesion mean (max)" for d in depths] + \
             [f"{d:g} mm: field" for d in depths]
    rows = [[_series_title(row["name"], summary.get("case_series")),
             _num(row.get("active_cells"))]
            + [_mean_max(row["lesion_error_mm"], k) for k in range(len(depths))]
            + [_mean_max(row["field_error_mm"], k, with_max=False) for k in range(len(depths))]
            for row in summary["series"]]
    return [Para(_reference_text(summary)), GridTable(header, rows)]


def _reference_text(summary: dict) -> str:
    ref, mat = summary["reference"], summary["material"]
    body = ("the probe a rigid body (skin it reaches slides on it)" if ref.get("probe_body")
            else "only the skin touched at rest held (no probe body)")
    return (f"Error (mm) of each FE against an independent reference: quadratic tetrahedra "
            f"(P2) of a gmsh mesh, {_num(ref.get('tet_size_mm'))} mm, "
            f"{_num(ref.get('tet_fine_mm'))} mm within 35 mm of the probe, face friction "
            f"{ref.get('friction', '-')}, {body}; homogeneous neo-Hookean, E = "
            f"{_num(1e3 * mat['E_mpa'])} kPa, nu = {_num(mat['nu'])}. Probe over "
            f"{_lesions_text(summary['lesion_ids'])} as in Table 2. Lesion: distance "
            "between the lesion displacements, mean (max) over the lesions; field: mean "
            "distance over points inside the breast within 50 mm of the probe."
            + _folded_text(ref.get("folded") or []))


def _lesions_text(ids: list) -> str:
    return ("lesion " if len(ids) == 1 else "lesions ") + ", ".join(map(str, ids))


def _folded_text(folded: list) -> str:
    """The reference's answers with elements folded over at a node, as a sentence."""
    if not folded:
        return ""
    where = ", ".join(f"lesion {lid} at {depth:g} mm ({n})" for lid, depth, n in folded)
    return (f" Reference answers holding elements folded over at a node (not to be trusted; "
            f"elements): {where}.")


def _series_title(name: str, own: str | None) -> str:
    """A series key (``law/contact cell``) as a row title; the case's own FE marked."""
    title = f"{name} ([dataset] teacher_refine:teacher_extrapolation)" \
        if name.startswith("teacher") else f"{name} mm"
    return title + (" (this case's FE)" if name == own else "")


def _mean_max(errors: list, k: int, with_max: bool = True) -> str:
    """Mean (max) over the lesions of depth ``k``'s errors, mm; '-' when none answered."""
    values = [e[k] for e in errors if e[k] is not None]
    if not values:
        return "-"
    text = f"{sum(values) / len(values):.2f}"
    return text + (f" ({max(values):.2f})" if with_max else "")


def timing_section(case_dir: Path, fig_dir: Path) -> Section:
    """FE against network times, with the paper's."""
    s = Section("Timing")
    paths = CasePaths(case_dir)
    summary = read_stage_json(paths.dataset_summary)
    t1 = read_stage_json(paths.table1)
    t2 = read_stage_json(paths.table2(TABLE2))
    rows = timing_rows(summary, t1, t2)
    if len(rows) == 2:
        s.blocks.append(not_run("generate", case_dir, "Timings (data generation, training, "
                                                      "evaluation)"))
    s.blocks.append(GridTable(["", "mean (ms)", "std (ms)"],
                         [[lab, f"{v:.4g}", "-" if e is None else f"{e:.3g}"]
                          for lab, v, e in rows]))
    s.blocks.append(Image(plot_timing(rows, fig_dir / "timing.png"),
                          "Time per deformation: FE (red) against the network (green); "
                          "lighter bars: the paper's."))
    if t2 and "timing" in t2:
        s.blocks.append(Para(table2_time(t2["timing"])))
    return s


def table2_time(timing: dict) -> str:
    """How long Table 2 by simulation took, from its ``timing`` record (a case without
    lesions built no reference)."""
    built = timing.get("reference_build_s")
    return (f"Table 2 by simulation took {timing['total_s']:.1f} s"
            + ("." if built is None else f" (reference built in {built:.1f} s)."))


def machine_section() -> Section:
    return Section("Versions and machine", [GridTable(["item", "value"], versions_and_machine())])


def stages_section(case_dir: Path) -> Section:
    """Which pipeline stages have their outputs."""
    from ..case import STAGES

    rows = [[name, rel, "yes" if (case_dir / rel).exists() else "no"]
            for name, rel in STAGES.items() if name != "report"]
    return Section("Pipeline stages", [GridTable(["stage", "output", "done"], rows)])


def dumps_compact(obj) -> str:
    return json.dumps(obj, separators=(",", ":"))


__all__ = ["FIG_DIR", "Image", "Note", "Pre", "case_section", "dataset_section",
           "machine_section", "stages_section", "table1_section", "table2_section",
           "timing_section", "training_section"]
