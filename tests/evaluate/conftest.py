"""A coarse phantom (15 mm cells: FE solves in well under a second) shared by these tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def coarse_phantom(tmp_path_factory):
    from biopsynav.case import make_phantom_case

    return make_phantom_case(tmp_path_factory.mktemp("eval") / "case", cell_size_mm=15)
