"""Fixtures of the dataset tests (the coarse phantom ``base_case`` and its generated
``reference`` are in tests/conftest.py: the network tests train on them too)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest


@pytest.fixture
def fresh_case(base_case: Path, tmp_path: Path) -> Path:
    """A private copy of the base case."""
    dst = tmp_path / "case"
    shutil.copytree(base_case, dst)
    return dst


def _assert_same_dataset(a: Path, b: Path) -> None:
    import numpy as np
    import zarr

    ga = zarr.open_group(str(a / "dataset.zarr"), mode="r")
    gb = zarr.open_group(str(b / "dataset.zarr"), mode="r")
    names = sorted(name for name, _ in ga.arrays())
    assert names == sorted(name for name, _ in gb.arrays())
    for name in names:
        if name == "solve_s":  # wall-clock time
            continue
        xa, xb = ga[name][...], gb[name][...]
        assert xa.dtype == xb.dtype, name
        assert np.array_equal(xa, xb), f"array {name!r} differs"
    for key in ("fingerprint", "protocol_fingerprint", "n_train", "n_test", "node_shape"):
        assert ga.attrs[key] == gb.attrs[key]
    strip = lambda fs: sorted((f["index"], f["attempt"], f["error"]) for f in fs)  # noqa: E731
    assert strip(ga.attrs["failures"]) == strip(gb.attrs["failures"])


@pytest.fixture
def assert_same_dataset():
    """``assert_same_dataset(case_a, case_b)``: bit-identical arrays and failure logs."""
    return _assert_same_dataset
