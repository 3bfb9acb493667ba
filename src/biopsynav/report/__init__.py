"""``biopsynav report``: ``CASE/report.html`` (self-contained) and ``CASE/report.md``.

Sections, the headline first: Table 1 (with the paper's, and Figure 4: a prediction against
FE), Table 2 (three methods, with the paper's), timing (FE against network against the
paper's); then the pipeline stages, the case (anatomy picture), training data, training,
versions and machine, and every case.toml parameter (folded in the HTML). A section whose
stage has not run says so ("not run yet: run `biopsynav <stage> CASE`"); the report never fails
on a partial case.
Figures the report makes itself go to ``CASE/report_files/``; the Markdown links every image
relative to the case folder, the HTML embeds them as base64 data URIs.
"""

from __future__ import annotations

import datetime
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

from ..case import Case  # noqa: E402
from ..config import load_config  # noqa: E402
from ..fileio import write_text_atomic  # noqa: E402
from ..layout import REPORT_HTML, REPORT_MD
from .blocks import to_html, to_markdown  # noqa: E402
from .sections import (  # noqa: E402
    FIG_DIR,
    case_section,
    convergence_section,
    dataset_section,
    machine_section,
    parameters_section,
    stages_section,
    table1_section,
    table2_section,
    timing_section,
    training_section,
)

HTML_FILE, MD_FILE = REPORT_HTML, REPORT_MD


def build_sections(case_dir: Path, case: Case | None = None) -> tuple[str, list]:
    """Title and sections of the report of ``case_dir`` (makes the report's own figures);
    ``case``: the loaded case, when the caller has it (else case.toml is read here, and the
    report is written for a partial case too)."""
    cfg = case.cfg if case is not None else load_config(case_dir)
    fig_dir = case_dir / FIG_DIR
    fig_dir.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    title = f"biopsynav report: {cfg.case.name} ({stamp})"
    sections = [table1_section(case_dir, cfg), table2_section(case_dir, fig_dir, cfg),
                timing_section(case_dir, fig_dir), convergence_section(case_dir),
                stages_section(case_dir),
                case_section(case_dir, cfg, case), dataset_section(case_dir),
                training_section(case_dir), machine_section(), parameters_section(cfg)]
    return title, sections


def write_report(case: Case | str | Path) -> list[Path]:
    """Write ``CASE/report.html`` and ``CASE/report.md`` of ``case`` (loaded, or its folder);
    return their paths (HTML first)."""
    loaded = case if isinstance(case, Case) else None
    case_dir = loaded.dir if loaded is not None else Path(case)
    title, sections = build_sections(case_dir, loaded)
    html_path = write_text_atomic(case_dir / HTML_FILE, to_html(title, sections))
    md_path = write_text_atomic(case_dir / MD_FILE, to_markdown(title, sections, case_dir))
    return [html_path, md_path]


__all__ = ["HTML_FILE", "MD_FILE", "build_sections", "write_report"]
