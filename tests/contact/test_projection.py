"""The contact projection: predictions that move the contact points as measured."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from biopsynav.contact.baseline import LinearElasticBaseline
from biopsynav.contact.projection import ContactProjection
from biopsynav.errors import InputError
from biopsynav.grid.embedding import Embedding
from biopsynav.grid.index import field_to_tensor


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The phantom at 24 mm cells, its hard baseline and three skin points on the top."""
    from biopsynav.case import make_phantom_case

    case = make_phantom_case(tmp_path_factory.mktemp("proj") / "case", cell_size_mm=24.0)
    base = LinearElasticBaseline.from_case(case, spring=None, dtype=np.float64)
    a = case.anatomy
    top = np.argsort(a.vertices[:, 2])[-400:]
    pick = top[[0, 150, 399]]
    contact = Embedding.build(case.grid, a.vertices[pick], where="contact").matrix
    return case, base, ContactProjection.build(base, contact)


def input_of(proj: ContactProjection, g: np.ndarray) -> np.ndarray:
    return field_to_tensor(proj.input_op.field(g), proj.baseline.node_shape).astype(np.float32)


def test_zero_residual_gives_the_baseline(setup):
    _, base, proj = setup
    g = np.array([[0.0, 0, -3], [0.5, 0, -4], [0, 0.2, -3.5]])
    x = input_of(proj, g)
    zero = np.zeros((3, *base.node_shape), np.float32)
    assert np.allclose(proj.project(x, g, zero), base.predict(x), atol=1e-3)


def test_projected_field_moves_the_points_by_the_measurement(setup):
    """Any residual: the points move by g (3 points, fewer constraints than contact dofs);
    unprojected they do not."""
    case, base, proj = setup
    rng = np.random.default_rng(0)
    g = rng.normal(size=(3, 3)) * 2.0
    x = input_of(proj, g)
    r = (rng.normal(size=(3, *base.node_shape)) * 0.3).astype(np.float32)
    u = proj.project(x, g, r)
    assert np.abs(proj.point_displacement(base.predict(x) + r) - g).max() > 0.05
    assert np.abs(proj.point_displacement(u) - g).max() < 1e-3 * np.abs(g).max()


def test_a_residual_the_points_do_not_see_passes_unchanged(setup):
    _, base, proj = setup
    g = np.array([[0.0, 0, -3], [0.5, 0, -4], [0, 0.2, -3.5]])
    x = input_of(proj, g)
    r = np.zeros((3, *base.node_shape), np.float32)
    r[:, :2] = 0.7  # the two node planes at the lowest x: far from the top points
    assert np.allclose(proj.point_displacement(r), 0.0)
    assert np.allclose(proj.project(x, g, r) - r, base.predict(x), atol=1e-3)


def test_lesion_operator_is_the_field_at_the_rows(setup):
    _, base, proj = setup
    rng = np.random.default_rng(1)
    rows = sp.random(4, 3 * base.n_nodes, density=0.01, random_state=2, format="csr")
    d = rng.normal(size=(3, 3))
    r = np.zeros((3, *base.node_shape), np.float32)
    field = proj.project(np.zeros((4, *base.node_shape), np.float32), d, r)
    assert np.allclose(proj.lesion_operator(rows) @ d.ravel(), rows @ field.ravel(), atol=1e-6)


def test_bad_arguments_are_named(setup):
    case, base, proj = setup
    x = np.zeros((4, *base.node_shape), np.float32)
    with pytest.raises(InputError, match=r"contact displacement of shape \(2, 3\)"):
        proj.input_forces(x, np.zeros((2, 3)))
    with pytest.raises(InputError, match="is not"):
        ContactProjection.build(base, sp.csr_matrix((2, 7)))
    soft = LinearElasticBaseline(base.compliance, spring=0.3)
    with pytest.raises(InputError, match="hard linear-elastic baseline"):
        ContactProjection.build(soft, proj.contact)


def test_batch_projection_matches_the_per_sample_projection(setup):
    """Training's padded, batched ``u_lin(W_P r)`` equals each contact set's own projection
    (two sets of different sizes)."""
    import torch

    from biopsynav.contact.projection import BatchProjection

    case, base, proj = setup
    a = case.anatomy
    top = np.argsort(a.vertices[:, 2])[-400:]
    other = ContactProjection.build(base, Embedding.build(case.grid, a.vertices[top[::40]],
                                                          where="contact").matrix)
    batch = BatchProjection(base, [proj, other])
    rng = np.random.default_rng(3)
    r = (rng.normal(size=(3, 3, *base.node_shape)) * 0.3).astype(np.float32)
    seen = batch.seen(torch.from_numpy(r), torch.tensor([1, 0, 1])).numpy()
    zeros = np.zeros((4, *base.node_shape), np.float32)
    for row, (p, i) in enumerate(((other, 0), (proj, 1), (other, 2))):
        g = np.zeros((p.n_points, 3))
        expect = -(p.project(zeros, g, r[i]) - r[i])  # u_lin(W_P r)
        assert np.abs(seen[row] - expect).max() < 1e-4 * max(1.0, np.abs(expect).max())


def test_one_thread_limits_blas_and_torch_and_restores_them():
    """The set-up's small solves run on one thread; the caller's thread counts come back, also
    after an error inside."""
    import torch
    from threadpoolctl import threadpool_info

    from biopsynav.threads import one_thread

    before_torch = torch.get_num_threads()
    # torch.set_num_threads also sets MKL's pool: what must come back is the state on entry
    torch.set_num_threads(2)
    before = sorted((i["prefix"], i["num_threads"]) for i in threadpool_info())
    try:
        with pytest.raises(RuntimeError, match="inside"):
            with one_thread():
                assert torch.get_num_threads() == 1
                assert all(i["num_threads"] == 1 for i in threadpool_info())
                raise RuntimeError("inside")
        assert torch.get_num_threads() == 2
        assert sorted((i["prefix"], i["num_threads"]) for i in threadpool_info()) == before
    finally:
        torch.set_num_threads(before_torch)
