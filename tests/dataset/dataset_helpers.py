"""Helpers shared by the dataset tests (a module with a unique name, importable from tests)."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import DATASET_N_TEST as N_TEST  # noqa: F401  (the base case's counts)
from tests.conftest import DATASET_N_TRAIN as N_TRAIN  # noqa: F401

from biopsynav.config import load_config, save_config


def edit_config(case_dir: Path, **sections: dict) -> None:
    """Change case.toml values: ``edit_config(d, solver={"max_iterations": 8})``."""
    cfg = load_config(case_dir)
    for section, values in sections.items():
        for key, value in values.items():
            setattr(getattr(cfg, section), key, value)
    save_config(case_dir, cfg)
