"""Redrawing the contact points of stored samples (for the contact projection of Table 1)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr

from biopsynav.case import Case
from biopsynav.contact.greens import ContactCompliance
from biopsynav.dataset.contacts import sample_contact_matrices
from biopsynav.errors import InputError
from biopsynav.grid.index import tensor_to_field
from biopsynav.probe import contact_input


def test_redrawn_contacts_rebuild_the_stored_inputs(reference):
    """Each redrawn contact matrix, applied to the stored FE field, gives the contact
    displacement from which the stored input was built."""
    case = Case.load(reference)
    g = zarr.open_group(str(reference / "dataset.zarr"), mode="r")
    done = np.flatnonzero(g["done"][:])
    matrices = sample_contact_matrices(case, reference, done)
    compliance = ContactCompliance.from_case(case)
    for i, w in zip(done, matrices, strict=True):
        assert w.shape == (int(g["n_contact"][i]), case.grid.n_nodes)
        u = tensor_to_field(g["targets"][i]).astype(np.float64)
        rebuilt = contact_input(w, w @ u, "elastic", compliance)
        stored = tensor_to_field(g["inputs"][i])
        assert np.allclose(rebuilt, stored, atol=1e-4 + 1e-5 * np.abs(stored).max())


def test_a_store_drawn_otherwise_is_refused(reference, tmp_path):
    case = Case.load(reference)
    other = tmp_path / "dataset.zarr"
    shutil.copytree(reference / "dataset.zarr", other)
    g = zarr.open_group(str(other), mode="r+")
    vertex = g["vertex"][:]
    vertex[1] += 1
    g["vertex"][:] = vertex
    with pytest.raises(InputError, match="sample 1: the redrawn push"):
        sample_contact_matrices(case, other, np.array([0, 1]))
    del g.attrs["protocol"]
    with pytest.raises(InputError, match="no readable probe protocol"):
        sample_contact_matrices(case, other, np.array([0]))


def test_projections_refuse_an_input_their_points_do_not_rebuild(reference):
    """The redrawn points' displacement must rebuild the stored input (training and Table 1
    check it before projecting)."""
    from biopsynav.contact.baseline import LinearElasticBaseline
    from biopsynav.contact.projection import sample_projections

    case = Case.load(reference)
    g = zarr.open_group(str(reference / "dataset.zarr"), mode="r")
    x, y = np.asarray(g["inputs"][:2]), np.asarray(g["targets"][:2])
    samples = np.array([0, 1])
    matrices = sample_contact_matrices(case, reference, samples)
    base = LinearElasticBaseline.from_case(case, spring=None)
    pairs = sample_projections(base, matrices, x, y, samples, "here")
    assert [p.n_points for p, _ in pairs] == [m.shape[0] for m in matrices]
    assert np.allclose(pairs[1][1], matrices[1] @ y[1].reshape(3, -1).T)
    x[1, :3] += np.float32(0.5) * (x[1, 3] > 0)  # every contact node moved by 0.5 mm
    with pytest.raises(InputError, match="sample 1: its redrawn contact points give an input"):
        sample_projections(base, matrices, x, y, samples, "here")
