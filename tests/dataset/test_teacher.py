"""A finer teacher grid (``[dataset] teacher_refine``): samples solved on cells half the size,
stored on the case grid, named in the protocol and in the model's record."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr
from dataset_helpers import N_TEST, N_TRAIN, edit_config

from biopsynav.case import Case
from biopsynav.dataset.generate import generate_case
from biopsynav.dataset.store import protocol_dict
from biopsynav.grid.index import tensor_to_field
from biopsynav.network.data import load_dataset
from biopsynav.network.model_io import teacher


@pytest.fixture(scope="module")
def refined(base_case, tmp_path_factory):
    """The coarse phantom taught by a grid of half its cell size, 3 samples."""
    dst = tmp_path_factory.mktemp("teacher") / "case"
    shutil.copytree(base_case, dst)
    edit_config(dst, dataset={"teacher_refine": 2, "n_train": 2, "n_test": 1})
    generate_case(dst, workers=1, progress=False)
    return dst


def test_the_protocol_names_the_teacher_only_when_refined(base_case, refined, reference):
    plain = Case.load(base_case).cfg
    assert "teacher_refine" not in protocol_dict(plain, N_TRAIN, N_TEST)["dataset"]
    assert teacher(load_dataset(reference))["teacher_refine"] == 1
    data = zarr.open_group(str(refined / "dataset.zarr"), mode="r")
    assert data.attrs["protocol"]["dataset"]["teacher_refine"] == 2
    assert data.attrs["protocol"]["dataset"]["teacher_min_fraction"] == 0.2
    assert teacher(load_dataset(refined))["teacher_refine"] == 2


def test_the_teacher_s_cells_have_their_own_weight_floor(refined):
    """[dataset] teacher_min_fraction floors the refined teacher's cell weights; the case
    grid keeps [grid] min_fraction."""
    from biopsynav.fem import FEModel
    from biopsynav.fem.teacher import build_teacher

    case = Case.load(refined)
    fraction = case.grid.active_fraction()
    assert fraction.min() < case.cfg.grid.min_fraction
    assert FEModel.from_case(case).weight.min() == pytest.approx(case.cfg.grid.min_fraction)
    case.cfg.dataset.teacher_min_fraction = 0.3
    weight = build_teacher(case).model.weight
    assert weight.min() == pytest.approx(0.3) and weight.max() == pytest.approx(1.0)


def test_refined_targets_live_on_the_case_grid(base_case, refined, reference):
    """Same draws as the case-grid data set (the protocol's draws do not depend on the
    teacher): the targets have the case grid's shape, zero on the chest wall, and move the
    tissue about as far as the case grid's teacher (on average over the nodes: the finer grid
    locks less, so a little further, never half as far or much further)."""
    case = Case.load(refined)
    fine = zarr.open_group(str(refined / "dataset.zarr"), mode="r")
    coarse = zarr.open_group(str(reference / "dataset.zarr"), mode="r")
    fixed = np.asarray(case.grid.fixed_nodes).ravel()
    compared = 0
    for i in range(3):
        if fine["attempt"][i] != coarse["attempt"][i]:  # one of them redrew a failed push
            continue
        if fine["force_n"][i] != coarse["force_n"][i]:  # a training sample in one set only
            continue
        u_f = tensor_to_field(fine["targets"][i])
        u_c = tensor_to_field(coarse["targets"][i])
        assert u_f.shape == u_c.shape
        assert np.all(u_f[fixed] == 0.0)
        active = np.asarray(case.grid.active_nodes).ravel()
        ratio = (np.linalg.norm(u_f[active], axis=1).mean()
                 / np.linalg.norm(u_c[active], axis=1).mean())
        assert 0.95 < ratio < 1.5, (i, ratio)
        assert not np.allclose(u_f, u_c, atol=1e-3)
        compared += 1
    assert compared >= 2


def test_training_rebuilds_a_refined_sample_s_input_from_its_target(refined):
    """The stored input comes from the stored (fitted) field at the contact points, so the
    projection's set-up, which rebuilds it from the target, accepts every sample."""
    from biopsynav.contact.baseline import LinearElasticBaseline
    from biopsynav.contact.projection import sample_projections
    from biopsynav.dataset.contacts import sample_contact_matrices

    case = Case.load(refined)
    data = zarr.open_group(str(refined / "dataset.zarr"), mode="r")
    samples = np.flatnonzero(data["done"][:])
    out = sample_projections(LinearElasticBaseline.from_case(case, spring=None),
                             sample_contact_matrices(case, refined, samples),
                             data["inputs"][:], data["targets"][:], samples, str(refined))
    assert len(out) == len(samples) == 3


def test_a_refined_rigid_push_moves_its_stored_contact_points_with_the_probe(base_case,
                                                                              tmp_path):
    """The fit of a rigid push holds its contact points: on the case grid every one moves by
    the same vector, along the push, as the probe face does (the input the tracker builds),
    when the fine teacher meets them (``points``; elastic contact holds them where its
    springs left them)."""
    from biopsynav.dataset.contacts import sample_contact_matrices

    dst = tmp_path / "case"
    shutil.copytree(base_case, dst)
    edit_config(dst, dataset={"teacher_refine": 2, "n_train": 1, "n_test": 1},
                probe={"rigid_share": 1.0}, tracker={"fem_contact": "points"})
    generate_case(dst, workers=1, progress=False)
    data = zarr.open_group(str(dst / "dataset.zarr"), mode="r")
    samples = np.flatnonzero(data["done"][:])
    assert data.attrs["protocol"]["dataset"]["teacher_fit"] == "holds-rigid-contact"
    for i, w in zip(samples, sample_contact_matrices(Case.load(dst), dst, samples),
                    strict=True):
        moved = w @ tensor_to_field(data["targets"][i])
        push = moved.mean(axis=0)
        assert np.linalg.norm(push) > 1.0
        assert np.abs(moved - push).max() < 0.01  # without the hold: 0.4-0.7 mm (phantom)
        assert push @ data["direction"][i] == pytest.approx(np.linalg.norm(push), rel=1e-3)
