"""The report on a partial case (only init) and on a case with (synthetic) stage outputs."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import pytest

from biopsynav.evaluate.run import TABLE2, write_table2
from biopsynav.evaluate.table import Record, aggregate, bin_name
from biopsynav.report import write_report


@pytest.fixture()
def init_only(tmp_path):
    from biopsynav.case import make_phantom_case

    return make_phantom_case(tmp_path / "case", cell_size_mm=15).dir


class _Checker(HTMLParser):
    """Collects tag balance, resource references and image sources."""

    VOID = {"meta", "img", "br", "hr", "link", "input"}

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[str] = []
        self.srcs: list[str] = []
        self.refs: list[str] = []
        self.errors: list[str] = []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("src", "href") and v is not None:
                (self.srcs if k == "src" else self.refs).append(v)
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack.pop() != tag:
            self.errors.append(tag)


def _check_self_contained(html: str) -> _Checker:
    c = _Checker()
    c.feed(html)
    assert not c.errors and not c.stack, "unbalanced tags"
    assert not c.refs and "<link" not in html and "<script" not in html
    assert all(s.startswith("data:image/png;base64,") for s in c.srcs)
    assert not re.search(r"https?://|file:", html)
    return c


def test_partial_case_gives_both_files_with_not_run_notes(init_only):
    paths = write_report(init_only)
    assert [p.name for p in paths] == ["report.html", "report.md"]
    html, md = (p.read_text() for p in paths)
    for stage in ("generate", "train", "evaluate"):
        assert f"not run yet: run `biopsynav {stage} {init_only}`" in md
        assert f"not run yet: run <code>biopsynav {stage} {init_only}</code>" in html
    c = _check_self_contained(html)
    assert len(c.srcs) >= 2  # anatomy picture and timing bars (the paper's)
    assert "](anatomy.png)" in md and "](report_files/timing.png)" in md
    assert "[grid] cell_size_mm" in md and "407.7" in md
    assert "model name" not in md and "python" in md


def _fake_outputs(case_dir):
    (case_dir / "model").mkdir()
    (case_dir / "model" / "meta.json").write_text(json.dumps(
        {"architecture": {"levels": 3}, "n_parameters": 350000,
         "training": {"train_time_s": 60.0, "best_val_e_mm": 0.05}}))
    (case_dir / "dataset_summary.json").write_text(json.dumps(
        {"count": 80, "mean_solve_s": 0.4, "max_disp_mm": 30.0}))
    (case_dir / "eval").mkdir()
    (case_dir / "eval" / "table1.json").write_text(json.dumps(
        {"mean_e_mm": 0.04, "std_e_mm": 0.02, "max_e_mm": 0.2, "predict_mean_ms": 2.0,
         "predict_std_ms": 0.1, "predict_p50_ms": 1.9, "predict_p99_ms": 2.5,
         "train_min": 1.0, "max_disp_mm": 30.0, "n_samples": 16, "runtime": "torchscript",
         "precision": "fp32", "inverted_samples": 3, "inverted_cells_max": 7,
         "inverted_cells_total": 11, "inverted_samples_fe": 0, "mean_e_dof_mm": 0.021,
         "max_e_dof_mm": 0.109, "baseline_mean_e_mm": 0.31, "baseline_max_e_mm": 1.27}))
    recs = [Record(lid, k, mm, bin_name(mm), m, None if (m == "net" and mm > 28) else
                   0.1 * lid + mm / 10 + (m == "rigid") * mm,
                   status="ok" if not (m == "net" and mm > 28) else "out_of_envelope",
                   reason="" if not (m == "net" and mm > 28) else "beyond the envelope",
                   time_ms=5.0)
            for lid in (1, 2) for k, mm in enumerate((10.0, 16.0, 21.0, 30.0))
            for m in ("net", "fem", "rigid")]
    result = {"source": "simulation", "methods": ["net", "fem", "rigid"],
              "records": [r.to_dict() for r in recs],
              "tables": {m: aggregate(recs, m, [1, 2]).to_dict() for m in ("net", "fem",
                                                                           "rigid")},
              "reference": {"cell_size_mm": 7.5, "training_cell_size_mm": 15.0,
                            "active_cells": 900, "training_active_cells": 150},
              "failures": [r.to_dict() for r in recs if r.tre_mm is None],
              "timing": {"total_s": 12.0, "reference_build_s": 0.5,
                         "mean_ms": {"net": 3.0, "fem": 300.0, "reference": 900.0}}}
    write_table2(case_dir, result, TABLE2, log=lambda s: None)


def test_report_with_all_outputs_holds_both_tables(init_only):
    _fake_outputs(init_only)
    html, md = (p.read_text() for p in write_report(init_only))
    assert "not run yet" not in md
    assert "0.04" in md and "0.052" in md  # Table 1 beside the paper's
    assert "3 of 16, at most 7 cells (0)" in md  # inverted cells of the predictions
    assert "the physics baseline alone" in md and "0.31 / 1.27" in md
    assert "| 0.021 / 0.109 | 0.052 / 0.266 (which reading" in md  # eq. (3) per dof
    assert "U-Net (network)" in md and "FE model, training resolution" in md
    assert "Rigid (lesions do not move)" in md
    assert "beyond the envelope" in md  # failures listed, never silent
    assert "| 1 | 1.100 | 1.700 | 2.200 | - |" in md  # lesion 1 of the network table
    _check_self_contained(html)
    assert (init_only / "report_files" / "table2.png").is_file()
    assert (init_only / "eval" / "table2.md").read_text().startswith("# Table 2")


def test_tables_of_a_model_trained_since_are_flagged(init_only):
    """table1.json and table2.json record the model they evaluated; once the model is trained
    again the report says their figures are not the new model's."""
    from biopsynav.config import load_config, save_config
    from biopsynav.inference.model_files import meta_checksum
    from biopsynav.info import case_summary

    cfg = load_config(init_only)
    cfg.refine.samples = 0  # the tracker's model is the case's
    save_config(init_only, cfg)
    _fake_outputs(init_only)
    meta = json.loads((init_only / "model" / "meta.json").read_text())
    for name in ("table1.json", "table2.json"):
        path = init_only / "eval" / name
        path.write_text(json.dumps(json.loads(path.read_text())
                                   | {"model_checksum": meta_checksum(meta)}))
    md = write_report(init_only)[1].read_text()
    assert "earlier model" not in md
    assert case_summary(init_only)["stale_evaluations"] == []
    meta["training"]["train_time_s"] = 61.0  # trained again
    (init_only / "model" / "meta.json").write_text(json.dumps(meta))
    md = write_report(init_only)[1].read_text()
    assert "Table 1 was made with an earlier model than the one now in model/" in md
    assert "Table 2 by simulation was made with an earlier model" in md
    assert f"run `biopsynav evaluate {init_only}` to remake it" in md
    assert case_summary(init_only)["stale_evaluations"] == ["table1.json", "table2.json"]


def test_headline_first_parameters_folded_last(init_only):
    """Table 1, Table 2 and the timing open the report; the 80-odd parameters come last,
    folded (HTML <details>)."""
    _fake_outputs(init_only)
    html, md = (p.read_text() for p in write_report(init_only))
    headings = re.findall(r"<h2>([^<]+)</h2>|<summary>([^<]+)</summary>", html)
    titles = [a or b for a, b in headings]
    assert titles[0].startswith("Table 1") and titles[1].startswith("Table 2")
    assert titles[2].startswith("Timing") and titles[-1] == "Parameters (case.toml)"
    assert html.index("<details><summary>Parameters") > html.index("Versions")
    assert md.index("## Parameters (case.toml)") > md.index("## Table 2")
