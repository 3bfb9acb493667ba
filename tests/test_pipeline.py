"""`biopsynav run`: the case folder is read once into a Case and handed down the stages."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from biopsynav.layout import CASE_FILE

_reads: list[str] | None = None


def _count_case_toml_reads(event: str, args: tuple) -> None:
    """Audit hook: every opening of a case.toml for reading, while a test listens."""
    if _reads is None or event != "open" or not isinstance(args[0], (str, Path)):
        return
    mode = args[1] if len(args) > 1 and isinstance(args[1], str) else "r"
    if Path(args[0]).name == CASE_FILE and not set(mode) & set("wax+"):
        _reads.append(str(args[0]))


sys.addaudithook(_count_case_toml_reads)


def _small_settings(case: Path) -> None:
    from biopsynav.config import load_config, save_config

    cfg = load_config(case)
    cfg.network.iterations, cfg.network.val_interval = 6, 3
    cfg.network.warmup_iterations, cfg.network.threads = 2, 1
    cfg.evaluate.timed_predictions = 10
    cfg.evaluate.max_lesions, cfg.evaluate.deformations_per_lesion = 1, 1
    cfg.evaluate.reference_refinement = 1.0
    save_config(case, cfg)


def test_run_reads_case_toml_once_and_runs_every_stage(base_case, tmp_path):
    global _reads
    from biopsynav.cli import main

    case = tmp_path / "case"
    shutil.copytree(base_case, case)
    _small_settings(case)
    (case / "grid.npz").unlink()  # stage 1 rebuilds anatomy and grid as well
    _reads = []
    try:
        assert main(["run", str(case), "--workers", "1"]) == 0
        reads = list(_reads)
    finally:
        _reads = None
    assert len(reads) == 1, reads
    for rel in ("grid.npz", "dataset.zarr", "model/meta.json", "eval/table1.json",
                "eval/table2.json", "report.html"):
        assert (case / rel).exists(), rel
    # the same, with every stage up to date: still one read
    _reads = []
    try:
        assert main(["run", str(case)]) == 0
        assert len(_reads) == 1, _reads
    finally:
        _reads = None
