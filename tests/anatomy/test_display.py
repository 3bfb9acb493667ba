"""Display meshes: closed outward lesion hulls, skin decimation by vertex clustering."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from biopsynav.anatomy.display import decimate, lesion_mesh


def test_lesion_mesh_is_closed_outward_and_bounded_in_size():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3))
    pts = 4.0 * pts / np.linalg.norm(pts, axis=1, keepdims=True) + [10, 20, 30]
    vertices, faces = lesion_mesh(pts, max_vertices=162)
    assert len(vertices) <= 162
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 4.0**3, rel=0.1)


def test_flat_lesion_points_are_refused():
    with pytest.raises(ValueError, match="no volume"):
        lesion_mesh(np.c_[np.random.default_rng(1).normal(size=(50, 2)), np.zeros(50)])


def test_decimation_keeps_the_shape_within_the_triangle_budget():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=50.0)  # 20,480 triangles
    keep, faces = decimate(np.asarray(sphere.vertices), np.asarray(sphere.faces), 2000)
    assert 500 < len(faces) <= 2000 and faces.max() < len(keep)
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices[keep], axis=1), 50.0)
    small = trimesh.Trimesh(sphere.vertices[keep], faces, process=False)
    assert small.area == pytest.approx(sphere.area, rel=0.1)
    same_keep, same = decimate(np.asarray(sphere.vertices), np.asarray(sphere.faces), 10**6)
    assert len(same) == len(sphere.faces) and len(same_keep) == len(sphere.vertices)
