"""``biopsynav evaluate``: Table 1 (network engineer's), then Table 2; files into CASE/eval."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..case import Case, as_case
from ..dataset.pool import check_workers
from ..errors import InputError
from ..fileio import read_json, write_json_atomic, write_text_atomic
from ..layout import EVAL_DIR, META, TABLE2, TABLE2_MEASURED
from ..reference_registry import check_reference
from ..refine import fine_case
from .measured import evaluate_measured
from .paper import PAPER_TABLE2_COL_MEAN, PAPER_TABLE2_MAX_ROW_MEAN
from .simulation import run_simulation
from .table import BIN_EDGES_MM, METHOD_TITLES, format_markdown, format_text, table_from_dict


def require_model(case: Case) -> None:
    """Raise InputError unless the case has a trained model (and, with ``[refine] samples >
    0``, the model trained further on the fine teacher's pushes)."""
    meta = case.paths.model_meta
    if not meta.is_file():
        raise InputError("missing: no trained model in this case; run `biopsynav train "
                         f"{case.dir}` first (and `biopsynav generate` before it)", str(meta))
    if case.cfg.refine.samples:
        case.tracking_model  # noqa: B018 - InputError naming refine/model while it is missing


def evaluate_case(case: Case | str | Path, table2: bool = True, measured: str | Path | None = None,
                  poses: str | Path | None = None, quick: bool = False,
                  log: Callable[[str], None] = print, workers: int = 0) -> dict:
    """Table 1, each lesion's self-check (:mod:`~biopsynav.evaluate.lesion_check`, with Table
    2), then Table 2 (by simulation, or from ``poses`` + ``measured`` CSVs).

    Writes ``CASE/eval/table1.json`` (+ PNGs, by :mod:`biopsynav.network.evaluate`),
    ``CASE/eval/table2.json`` and ``table2.md`` (simulation) or ``table2_measured.json`` and
    ``.md`` (user data), ``lesion_check.json`` in the tracking model's folder (with Table
    2), and prints the tables. ``quick`` evaluates a subset (3 lesions, a 1.5 times finer
    reference); ``workers``: local processes of the self-check, the FE teacher and a
    fine-grid ground truth (0: one per core). Returns ``{"table1": ..., "lesion_check": ...,
    "table2": ...}`` (the last two absent with ``table2=False``, the check for a case
    without lesions).
    """
    check_workers(workers)
    if (measured is None) != (poses is None):
        raise InputError("--poses and --measured go together: the tracked probe poses and the "
                         "lesion positions measured in those frames", "evaluate")
    case = as_case(case)
    require_model(case)
    if table2 and measured is None:
        check_reference(case)
    from ..network.evaluate import evaluate_network_case as table1_case
    from ..network.evaluate import format_table1

    out: dict = {"table1": table1_case(case)}
    log("Table 1: " + format_table1(out["table1"]))
    if case.cfg.refine.samples:
        out["table1_refined"] = table1_case(fine_case(case))
        log("Table 1 of the model trained further on the fine teacher (its held-out fine "
            "pushes, refine/eval): " + format_table1(out["table1_refined"]))
    if table2 and case.anatomy.lesions:  # before Table 2, whose bounds it widens
        from .lesion_check import run_lesion_check

        out["lesion_check"] = run_lesion_check(case, workers, log=log)
    if measured is not None:
        result = evaluate_measured(case, poses, measured, log=log)
        out["table2"] = write_table2(case.dir, result | tracking_model_checksum(case),
                                     TABLE2_MEASURED, log)
    elif table2:
        result = run_simulation(case, quick=quick, log=log, workers=workers)
        out["table2"] = write_table2(case.dir, result | tracking_model_checksum(case), TABLE2,
                                     log)
    return out


#: how to rebuild a damaged evaluation file
REEVALUATE = "run `biopsynav evaluate CASE` again"


def made_with_another_model(result: dict, model_dir: Path) -> bool:
    """Whether ``result`` (table1.json, table2.json) records the model it evaluated
    (``model_checksum``) and the model now in ``model_dir`` is another (trained since);
    False for a file from before the checksum was recorded, or no model."""
    from ..inference.model_files import RETRAIN, meta_checksum

    made_with = result.get("model_checksum")
    meta = read_json(Path(model_dir) / META, RETRAIN, missing_ok=True) if made_with else None
    return isinstance(meta, dict) and meta_checksum(meta) != made_with


def stale_evaluations(case: Case) -> list[str]:
    """The names of ``case``'s Table 1 and Table 2 files made with another model than the
    one now evaluated (:func:`made_with_another_model`); a damaged one is left to its
    reader (the report names it)."""
    paths = case.paths
    files = [(paths.table1, paths.model)] + [
        (paths.table2(stem), paths.tracking_model(bool(case.cfg.refine.samples)))
        for stem in (TABLE2, TABLE2_MEASURED)]
    return [f.name for f, model in files
            if made_with_another_model(readable_json(f), model)]


def readable_json(path: Path) -> dict:
    """The JSON object at ``path``; {} when it is missing, damaged or not an object."""
    try:
        found = read_json(path, REEVALUATE, missing_ok=True)
    except InputError:
        return {}
    return found if isinstance(found, dict) else {}


def tracking_model_checksum(case: Case) -> dict:
    """``{"model_checksum": ...}`` of the model the tracker uses (its ``meta.json``), so that
    the report can tell a model trained since; {} where it has none."""
    from ..inference.model_files import RETRAIN, meta_checksum

    meta = read_json(case.paths.tracking_model(bool(case.cfg.refine.samples)) / META, RETRAIN,
                     missing_ok=True)
    return {"model_checksum": meta_checksum(meta)} if isinstance(meta, dict) else {}


def write_table2(case_dir: Path, result: dict, stem: str,
                 log: Callable[[str], None] = print) -> dict:
    """Write ``eval/<stem>.json`` and ``eval/<stem>.md``, print the tables; return result."""
    eval_dir = Path(case_dir) / EVAL_DIR
    write_json_atomic(eval_dir / f"{stem}.json", result)
    write_text_atomic(eval_dir / f"{stem}.md", table2_markdown(result))
    log(table2_text(result))
    return result


def _source_line(result: dict) -> str:
    if result["source"] == "measured":
        return (f"Ground truth: lesion positions measured by the user "
                f"({result['inputs']['measured']}; poses {result['inputs']['poses']}).")
    ref = result["reference"]
    chosen = f" ({ref['chosen']})" if ref.get("chosen") else ""
    if ref.get("kind") == "stored":
        return (f"Ground truth: {ref['description']}{chosen}; the same rigid-probe pushes, each "
                "lesion to the stored depths.")
    if ref.get("kind") == "p2":
        return (f"Ground truth: {ref['description']}; the same rigid-probe contact (training "
                f"grid {ref['training_cell_size_mm']:g} mm, {ref['training_active_cells']} "
                "cells).")
    return (f"Ground truth: biopsynav's own FE (the teacher's code: not independent) on a "
            f"{ref['cell_size_mm']:.2f} mm grid ({ref['active_cells']} active cells; training "
            f"grid {ref['training_cell_size_mm']:g} mm, {ref['training_active_cells']} cells), "
            f"same prescribed contact displacements{chosen}.")


def table2_text(result: dict) -> str:
    """All method tables of a Table 2 result as aligned plain text, with failures; a case
    without lesions: its note alone."""
    if "note" in result:
        return f"Table 2 ({result['source']}): {result['note']}."
    parts = [f"Table 2 ({result['source']}): TRE in mm per lesion and probe displacement "
             f"(edges {', '.join(f'{e:g}' for e in BIN_EDGES_MM)} mm). " + _source_line(result)]
    for m, what in shown_tables(result):
        parts.append(format_text(table_from_dict(result["tables"][m])))
        overall = result["tables"][m]["overall_mean"]
        parts.append(f"  average {what} over all cells: "
                     f"{'-' if overall is None else f'{overall:.3f}'} mm")
    parts.append(_failures_text(result))
    if "total_s" in result.get("timing", {}):
        parts.append(f"Table 2 took {result['timing']['total_s']:.1f} s")
    return "\n\n".join(p for p in parts if p)


def shown_tables(result: dict) -> list[tuple[str, str]]:
    """(table key, what its cells are) of a Table 2 result: the methods' tables ("TRE"), then
    the network-against-FE agreement when there is one ("distance")."""
    return [(m, "TRE") for m in result["methods"]] + [
        (m, "distance") for m in result["tables"] if m not in result["methods"]]


def _failures_text(result: dict) -> str:
    fails = [f for f in result["failures"] if f["method"] != "reference"]
    if not fails:
        return ""
    lines = [f"{len(fails)} entries without a TRE ('-' in the tables):"]
    for f in fails:
        lines.append(f"  lesion {f['lesion']} push {f['push']} "
                     f"({f['displacement_mm']:.1f} mm) {f['method']}: {f['status']}: "
                     f"{f['reason']}")
    return "\n".join(lines)


def table2_markdown(result: dict) -> str:
    """Table 2 as a Markdown document (one table per method, the paper's figures, failures);
    a case without lesions: its note."""
    if "note" in result:
        note = result["note"]
        return f"# Table 2 ({result['source']})\n\n{note[0].upper()}{note[1:]}.\n"
    lines = [f"# Table 2 ({result['source']})", "",
             "Target registration error (mm) of the lesion under the probe, per lesion and "
             "probe displacement range (D10 < 12.5 mm, D15 [12.5, 17.5), D20 [17.5, 22.5), "
             "D25 [22.5, 27.5), D30 >= 27.5 mm); '-': no push in that range, or no "
             "trustworthy result (listed below).", "", _source_line(result), ""]
    for m, what in shown_tables(result):
        t = result["tables"][m]
        lines += [f"## {METHOD_TITLES.get(m, m)}", "", format_markdown(table_from_dict(t)), ""]
        if t["overall_mean"] is not None:
            lines.append(f"Average {what} over all cells: {t['overall_mean']:.3f} mm; largest "
                         f"lesion mean {t['max_row_mean']:.3f} mm.")
        if m in PAPER_TABLE2_COL_MEAN:
            cols = ", ".join(f"{v:.3f}" for v in PAPER_TABLE2_COL_MEAN[m])
            lines.append(f"The paper (CIRS phantom, measured in US images): column means "
                         f"{cols} mm; largest lesion mean {PAPER_TABLE2_MAX_ROW_MEAN[m]:.3f} mm.")
        lines.append("")
    fails = _failures_text(result)
    if fails:
        lines += ["## Missing entries", "", "```", fails, "```", ""]
    timing = result.get("timing", {})
    if timing.get("total_s") is not None:
        lines.append(f"Run time: {timing['total_s']:.1f} s.")
        for m, ms in timing.get("mean_ms", {}).items():
            lines.append(f"- {m}: {ms:.1f} ms per push (mean)")
    return "\n".join(lines) + "\n"
