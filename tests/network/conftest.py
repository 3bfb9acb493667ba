"""Fixtures of the network tests: a tiny synthetic data set and one trained tiny model."""

from __future__ import annotations

from pathlib import Path

import pytest

from biopsynav.config import NetworkSection

from .synth import write_synthetic_dataset

SHAPE = (16, 8, 8)


def tiny_settings(**kw) -> NetworkSection:
    """The default architecture (width 8, SiLU, quadratic features) with a short schedule
    (seconds on one CPU thread)."""
    base = dict(preset="custom", base_channels=8, levels=3, activation="silu",
                features="quadratic", iterations=300, val_interval=100,
                warmup_iterations=20, learning_rate=3e-3, batch_size=4, threads=1, seed=0,
                baseline="none")  # synthetic data have no case (FE model)
    base.update(kw)
    return NetworkSection(**base)


@pytest.fixture(scope="session")
def synth_case(tmp_path_factory) -> Path:
    case = tmp_path_factory.mktemp("synth") / "case"
    write_synthetic_dataset(case, shape=SHAPE, n_train=40, n_test=10, seed=1)
    return case


@pytest.fixture(scope="session")
def trained(synth_case):
    from biopsynav.network.train import train

    summary = train(synth_case, settings=tiny_settings(), progress=False)
    return synth_case, summary
