"""README.md's and BENCHMARKS.md's figures come from the result files of benchmarks/results/
(benchmarks/figures.py renders them); the documentation the code points to exists."""

from __future__ import annotations

import ast
import json
import re
import shutil
from pathlib import Path

import pytest

from tests.runs import BENCHMARKS

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def figures(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import figures

    return figures


@pytest.mark.parametrize("doc", ["readme", "benchmarks"])
def test_every_shown_figure_is_its_result_files(figures, doc):
    """The block in the file is what the result files render to: a re-measured result file
    without `python benchmarks/figures.py --write` (or a figure edited by hand) fails."""
    shown = figures.current_block(doc)
    assert shown is not None, f"{figures.DOCS[doc].name} has lost its figures block"
    assert shown == figures.rendered_block(doc), (
        f"{figures.DOCS[doc].name}'s figures differ from benchmarks/results/: run "
        "`python benchmarks/figures.py --write` after re-measuring")


def test_a_changed_result_file_changes_the_rendering(figures, tmp_path, monkeypatch):
    """The check above can fail: one figure of a cited result file moved by 0.1 mm gives
    another table."""
    copy = tmp_path / "results"
    shutil.copytree(figures.RESULTS, copy)
    path = copy / "phantom-default-mixed-d30-all-truth.json"
    data = json.loads(path.read_text())
    data["rows"][0]["tre_mm"]["fem"] += 1.0  # one of ten D10 pushes: the mean moves by 0.1
    path.write_text(json.dumps(data))
    before = figures.rendered_block("benchmarks")
    monkeypatch.setattr(figures, "RESULTS", copy)
    assert figures.rendered_block("benchmarks") != before


def test_a_latency_is_shown_with_its_days_speed_probe(figures):
    """A result that holds the day's speed probe shows it (the reference machine's probe
    time gives 1.00x); one without shows its figures alone."""
    from biopsynav.runtime import REFERENCE

    render = figures.with_speed(figures.pair("update_p50_ms", "update_p99_ms"))
    data = {"figures": {"update_p50_ms": 1.0, "update_p99_ms": 2.0}}
    assert render(data) == "1.00 / 2.00 ms"
    data["speed_probes"] = {"unet_step_s": 2 * REFERENCE["probe_s"], "matmul_1024_s": 0.01}
    assert render(data) == "1.00 / 2.00 ms (speed probe 2.00x)"


def test_a_missing_result_file_says_how_to_make_it(figures, tmp_path, monkeypatch):
    monkeypatch.setattr(figures, "RESULTS", tmp_path)
    assert "not measured (`python benchmarks/fem_solve.py`)" in figures.bench_block()


DOC_REF = re.compile(r"docs/([a-z_]+\.md)(?:, [\"']([^\"']+)[\"'])?")


def _texts():
    """(file, text) of every string of the package (help texts and docstrings, implicit
    concatenations joined) and of the Markdown files a reader opens first."""
    for path in sorted((ROOT / "src").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                yield path, node.value
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        yield path, path.read_text()


def _references():
    for path, text in _texts():
        for m in DOC_REF.finditer(" ".join(text.split())):
            yield path.relative_to(ROOT), m.group(1), m.group(2)


def _titles(page: Path) -> list[str]:
    """A page's section headings and the bold or italic leads of its paragraphs."""
    text = page.read_text()
    flat = " ".join(text.split())
    return ([line for line in text.splitlines() if line.startswith("#")]
            + re.findall(r"\*\*([^*]+)\*\*", flat) + re.findall(r"(?<![*\w])\*([^*]+)\*", flat))


def test_every_documentation_page_the_code_names_exists_with_its_section():
    docs = ROOT / "docs"
    missing = []
    for where, page, section in _references():
        target = docs / page
        if not target.is_file():
            missing.append(f"{where}: docs/{page}")
        elif section and section.lower() not in " ".join(_titles(target)).lower():
            missing.append(f"{where}: docs/{page}, section {section!r}")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize("page", sorted(p.name for p in (ROOT / "docs").glob("*.md")
                                        if p.name not in ("experiments.md", "case_toml.md")))
def test_a_reference_page_stays_a_reference(page):
    """About 20 KB at most: dated narratives go to docs/experiments.md."""
    assert (ROOT / "docs" / page).stat().st_size <= 21_000


def test_a_push_the_truth_did_not_answer_leaves_its_depth_out(figures):
    """A truth comparison's row without a truth answer (the reference push failed: no
    ``status``) counts in no depth's mean instead of stopping the rendering."""
    import math

    data = {"rows": [{"lesion": 1, "depth_mm": 10.0, "status": {"net": "ok"},
                      "tre_mm": {"net": 0.2}},
                     {"lesion": 1, "depth_mm": 30.0, "reference_mm": None}]}
    means = figures.depth_means(data, "net")
    assert means[0] == pytest.approx(0.2) and math.isnan(means[1]) and math.isnan(means[2])
