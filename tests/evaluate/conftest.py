"""A coarse phantom (15 mm cells: FE solves in well under a second) shared by these tests."""

from __future__ import annotations

import pytest


def cube_reference(size_mm: float, **build):
    """The P2 reference of a 30 mm cube of ``size_mm`` tetrahedra, its bottom face
    (z = -15) the chest wall, E 5 kPa, nu 0.45 (``build``: more of TetReference.build's options)."""
    from types import SimpleNamespace

    import numpy as np
    import trimesh

    from biopsynav.evaluate.p2 import TetReference

    box = trimesh.creation.box(extents=(30.0, 30.0, 30.0))
    anatomy = SimpleNamespace(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces),
                              normals=np.asarray(box.vertex_normals),
                              chest_point=np.array([0.0, 0.0, -15.0]),
                              chest_normal=np.array([0.0, 0.0, -1.0]))
    return TetReference.build(anatomy, size_mm, 5e-3, 0.45, **build)


@pytest.fixture(scope="session")
def coarse_phantom(tmp_path_factory):
    from biopsynav.case import make_phantom_case

    return make_phantom_case(tmp_path_factory.mktemp("eval") / "case", cell_size_mm=15)
