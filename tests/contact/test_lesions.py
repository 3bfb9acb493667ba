"""The point operator: the lesions' displacement for a contact set without the full field."""

from __future__ import annotations

import numpy as np

from biopsynav.contact.lesions import point_operator
from biopsynav.grid.embedding import Embedding

from .test_projection import input_of, setup  # noqa: F401  (the fixture)


def _points(case) -> Embedding:
    """Five points inside the phantom: the lesion centres and a few more."""
    centres = np.array([les.center for les in case.anatomy.lesions])[:5]
    return Embedding.build(case.grid, centres, where="points")


def _full_field(base, proj, g, residual, projected: bool) -> np.ndarray:
    """The surrogate's whole prediction (n_nodes, 3): baseline plus residual, projected."""
    x = input_of(proj, g)
    u = proj.project(x, g, residual) if projected else base.predict(x) + residual
    return np.asarray(u).reshape(3, -1).T


def test_point_operator_equals_the_full_field_at_the_points(setup):  # noqa: F811
    case, base, proj = setup
    points = _points(case)
    rng = np.random.default_rng(3)
    g = rng.normal(size=(3, 3)) * 2.0
    residual = (rng.normal(size=(3, *base.node_shape)) * 0.3).astype(np.float32)
    for projection in (None, proj):
        op = point_operator(base, proj.input_op, points, projection)
        expect = points.interpolate(_full_field(base, proj, g, residual, projection is not None))
        got = op.displacement(residual, g)
        assert np.abs(got - expect).max() < 1e-3 * np.abs(expect).max(), projection
        first = op.first(2)
        assert np.allclose(first.displacement(residual, g), got[:2], atol=1e-9)
