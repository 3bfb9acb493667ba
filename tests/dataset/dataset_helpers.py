"""Helpers shared by the dataset tests (a module with a unique name, importable from tests)."""

from __future__ import annotations

from pathlib import Path

from biopsynav.config import load_config, save_config

N_TRAIN, N_TEST = 14, 2


def edit_config(case_dir: Path, **sections: dict) -> None:
    """Change case.toml values: ``edit_config(d, solver={"max_iterations": 8})``."""
    cfg = load_config(case_dir)
    for section, values in sections.items():
        for key, value in values.items():
            setattr(getattr(cfg, section), key, value)
    save_config(case_dir, cfg)
