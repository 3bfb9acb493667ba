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


def generate_through_local_cluster(case_dir: Path) -> dict:
    """``generate`` of ``case_dir`` through a Dask LocalCluster of two single-threaded worker
    processes (as ``generate --scheduler tcp://...``); its summary."""
    from distributed import LocalCluster

    from biopsynav.dataset.generate import generate_case

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        return generate_case(case_dir, scheduler=cluster.scheduler_address, progress=False)
