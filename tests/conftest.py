"""Shared fixtures: small anatomy files made on the fly, the phantom case, the UC Davis breast."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

UCDAVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ucdavis_breast3"


def dome_surface(radius: float = 40.0, height: float = 30.0, step: float = 2.5):
    """Closed dome (half-ellipsoid on a flat base at z = 0) by marching cubes, mm."""
    from skimage.measure import marching_cubes

    xs = np.arange(-radius - 2 * step, radius + 2 * step + 1e-9, step)
    zs = np.arange(-2 * step, height + 2 * step + 1e-9, step)
    x, y, z = np.meshgrid(xs, xs, zs, indexing="ij")
    field = np.minimum(radius * (1 - np.sqrt((x / radius) ** 2 + (y / radius) ** 2
                                             + (z / height) ** 2)), z)
    v, f, _, _ = marching_cubes(field, 0.0, spacing=(step, step, step))
    v += np.array([xs[0], xs[0], zs[0]])
    return v, f[:, ::-1].astype(np.int64)  # outward


@pytest.fixture(scope="session")
def dome_stl(tmp_path_factory) -> Path:
    import trimesh

    v, f = dome_surface()
    path = tmp_path_factory.mktemp("dome") / "dome.stl"
    trimesh.Trimesh(v, f).export(path)
    return path


@pytest.fixture(scope="session")
def dome_lesions_csv(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("lesions") / "lesions.csv"
    path.write_text("id,x,y,z,radius_mm\n1,0,0,10,4\n2,10,-5,15,3\n")
    return path


@pytest.fixture(scope="session")
def phantom_case(tmp_path_factory):
    from biopsynav.anatomy.phantom import make_phantom_case

    return make_phantom_case(tmp_path_factory.mktemp("phantom") / "case")


@pytest.fixture(scope="session")
def ucdavis_dir() -> Path:
    if not (UCDAVIS / "volmesh3.vtk").is_file():
        pytest.skip("UC Davis breast not found beside the repository (../shared/data)")
    return UCDAVIS
