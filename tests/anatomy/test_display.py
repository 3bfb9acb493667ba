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


def test_decimation_stays_closed_within_the_budget_and_follows_the_deformation():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=50.0)  # 20,480 triangles
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    weights, faces = decimate(v, f, 2000)
    assert 1500 < len(faces) <= 2000 and faces.max() < weights.shape[0]
    small = trimesh.Trimesh(weights @ v, faces, process=False)
    assert small.is_watertight and small.is_winding_consistent
    np.testing.assert_allclose(np.linalg.norm(weights @ v, axis=1), 50.0, rtol=2e-3)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    stretched = v * [1.0, 1.0, 2.0]  # a deformation of the full surface...
    np.testing.assert_allclose((weights @ stretched)[:, 2], 2 * (weights @ v)[:, 2])  # ...follows
    same, same_faces = decimate(v, f, 10**6)
    assert same.shape == (len(v), len(v)) and len(same_faces) == len(f)
