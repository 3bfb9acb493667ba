"""The immersed grid: volume fractions, padding, chest wall, trilinear mapping."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from biopsynav.grid import index
from biopsynav.grid.build import inside_lattice
from biopsynav.grid.embedding import Embedding, trilinear_weights


def _fraction_volume(v, f, h, n=5):
    lo = v.min(axis=0) - h
    cshape = tuple(int(c) for c in np.ceil((v.max(axis=0) + h - lo) / h))
    inside, _ = inside_lattice(v, f, lo, h, cshape, n)
    frac = inside.reshape(cshape[0], n, cshape[1], n, cshape[2], n).mean(axis=(1, 3, 5))
    return frac.sum() * h ** 3


def test_sphere_volume_fraction_sum_matches_and_converges():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=50.0)
    exact = sphere.volume  # the polyhedron's volume
    errors = []
    for h in (7.3, 3.65, 1.825):
        vol = _fraction_volume(np.asarray(sphere.vertices), np.asarray(sphere.faces), h)
        errors.append(abs(vol - exact) / exact)
    assert errors[0] < 0.02
    assert errors[2] < errors[0]
    assert abs(exact - 4 / 3 * np.pi * 50 ** 3) / exact < 0.01


def test_box_volume_fraction_is_exact():
    box = trimesh.creation.box(extents=(37.0, 21.0, 14.6))
    vol = _fraction_volume(np.asarray(box.vertices), np.asarray(box.faces), 7.3, n=10)
    assert vol == pytest.approx(37.0 * 21.0 * 14.6, rel=0.02)


def test_phantom_grid(phantom_case):
    g, a = phantom_case.grid, phantom_case.anatomy
    # the anatomy's box (150 x 120 x 75 mm) in 7.3 mm cells plus one empty cell around it,
    # none behind the chest wall; no padding for the network
    assert g.node_shape == (24, 20, 13)
    coords = g.node_coords().reshape(*g.node_shape, 3)
    lo, hi = a.bounds
    assert np.all(coords[0, 0, 0, :2] <= lo[:2] - g.spacing + 1e-9)
    assert coords[0, 0, 0, 2] == pytest.approx(0.0)  # a node plane on the chest wall
    assert np.all(coords[-1, -1, -1] >= hi + g.spacing - 1e-9)
    assert 2000 <= g.active_cells.sum() <= 2400
    assert g.fraction.sum() * g.spacing ** 3 == pytest.approx(abs(a.volume_ml()) * 1000,
                                                              rel=0.01)
    # fixed nodes: exactly the active nodes on the z = 0 chest-wall plane
    z = g.node_coords()[:, 2].reshape(g.node_shape)
    assert g.fixed_nodes.any()
    np.testing.assert_allclose(z[g.fixed_nodes], 0.0, atol=1e-9)
    assert np.array_equal(g.fixed_nodes, g.active_nodes & (np.abs(z) < 1e-9))
    assert set(np.unique(g.status)) <= {0, 1, 2}
    assert np.all(g.fraction[g.status == 2] == 1.0)


def test_trilinear_mapping_is_exact_for_linear_fields(phantom_case):
    g, a = phantom_case.grid, phantom_case.anatomy
    emb = Embedding.build(g, a.vertices)
    assert np.allclose(emb.weights.sum(axis=1), 1.0)
    coeffs = np.array([[0.3, -1.2, 2.0], [0.5, 0.1, -0.7], [1.5, 0.0, 0.25]])
    field = g.node_coords() @ coeffs + np.array([1.0, 2.0, 3.0])
    expected = a.vertices @ coeffs + np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(emb.interpolate(field), expected, atol=1e-9)
    np.testing.assert_allclose(emb.matrix @ field, expected, atol=1e-9)
    # a few points gather their nodes, many use the sparse matrix: both exact
    assert 8 * 5 < len(field) < 8 * len(a.vertices)
    np.testing.assert_allclose(emb.subset(np.arange(5)).interpolate(field),
                               expected[:5], atol=1e-9)
    np.testing.assert_allclose(emb.subset(np.arange(5)).interpolate(field.T.copy().T),
                               expected[:5], atol=1e-9)  # a strided (transposed) field
    # spreading is the adjoint of interpolation
    rng = np.random.default_rng(1)
    vals, node_vals = rng.standard_normal((len(a.vertices), 3)), rng.standard_normal(field.shape)
    assert np.sum(emb.spread(vals) * node_vals) == pytest.approx(
        np.sum(vals * emb.interpolate(node_vals)))


def test_embedding_rejects_points_outside(phantom_case):
    from biopsynav.errors import InputError

    g = phantom_case.grid
    with pytest.raises(InputError, match="1 of 2 points lie outside the active grid cells"):
        Embedding.build(g, np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 500.0]]))
    with pytest.raises(InputError, match="NaN"):
        Embedding.build(g, np.array([[np.nan, 0.0, 10.0]]))


def test_index_convention_round_trips():
    shape = (4, 3, 2)
    ijk = index.unflat_index(np.arange(24), shape)
    assert np.array_equal(index.flat_index(ijk, shape), np.arange(24))
    assert np.array_equal(ijk[1], [0, 0, 1])  # z fastest
    field = np.arange(24 * 3, dtype=float).reshape(24, 3)
    t = index.field_to_tensor(field, shape)
    assert t.shape == (3, 4, 3, 2) and t[0, 1, 2, 1] == field[index.flat_index([1, 2, 1], shape), 0]
    assert np.array_equal(index.tensor_to_field(t), field)
    zyx = np.zeros((2, 3, 4))
    assert index.image_array_to_xyz(zyx).shape == (4, 3, 2)


def test_trilinear_weights_corners():
    w = trilinear_weights(index.HEX_CORNERS.astype(float))
    np.testing.assert_allclose(w, np.eye(8))


def test_unlabelled_grids_keep_their_fingerprint_from_before_label_shares(phantom_case):
    """Grids held one label per cell (-1: none) before label shares; an unlabelled grid (the
    phantom) must keep its fingerprint so that models trained on it still load."""
    import hashlib
    from dataclasses import fields

    g = phantom_case.grid
    assert len(g.label_values) == 0
    h = hashlib.sha256()
    for f in fields(g):
        if f.name == "label_share":
            continue
        name, value = f.name, np.ascontiguousarray(getattr(g, f.name))
        if name == "label_values":
            name, value = "label", np.full(g.cell_shape, -1, np.int32)
        h.update(name.encode() + str(value.dtype).encode() + str(value.shape).encode()
                 + value.tobytes())
    assert g.fingerprint() == h.hexdigest()
