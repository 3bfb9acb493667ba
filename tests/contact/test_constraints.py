"""Contact constraint kinds of the FE engine (biopsynav.contact.constraints)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from biopsynav.case import Case
from biopsynav.config import TrackerSection, field_choices
from biopsynav.contact.constraints import (
    constraint_rows,
    contact_constraint_names,
    point_stiffness,
    vertex_areas,
)
from biopsynav.tracker import Tracker

TOP = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])


def test_config_choices_come_from_the_registry():
    import dataclasses

    meta = {f.name: f.metadata for f in dataclasses.fields(TrackerSection)}["fem_contact"]
    assert field_choices(meta) == contact_constraint_names() == ("points", "cell_average",
                                                                 "elastic")
    from biopsynav.config import config_from_dict
    from biopsynav.errors import InputError

    with pytest.raises(InputError, match="fem_contact must be one of points, cell_average"):
        config_from_dict({"tracker": {"fem_contact": "glue"}}, "case.toml")
    with pytest.raises(InputError, match="contact_follows_pose"):
        config_from_dict({"tracker": {"contact_follows_pose": "yes"}}, "case.toml")


def test_cell_average_rows_average_each_cells_points():
    cells = np.array([7, 3, 7, 7, 3, 9])
    rows = constraint_rows("cell_average", cells).toarray()
    assert rows.shape == (3, 6)
    np.testing.assert_allclose(rows.sum(axis=1), 1.0)
    for r in rows:  # each row averages the points of one cell, equally
        assert len(set(cells[r > 0])) == 1 and np.ptp(r[r > 0]) == 0.0
    np.testing.assert_array_equal(constraint_rows("points", cells).toarray(), np.eye(6))


@pytest.fixture(scope="module")
def coarse(tmp_path_factory) -> Case:
    from biopsynav.case import make_phantom_case

    return make_phantom_case(tmp_path_factory.mktemp("cst") / "case", cell_size_mm=12.0)


def fem_tracker(case: Case, kind: str) -> Tracker:
    cfg = copy.deepcopy(case.cfg)
    cfg.tracker.fem_contact = kind
    return Tracker.load(Case(case.dir, cfg, case.anatomy, case.grid), engine="fem")


def test_cell_average_meets_each_cells_mean_and_lets_the_cell_deform(coarse):
    """With ``cell_average`` the mean displacement of each cell's contact points is the
    probe's (to the solver tolerance) while single points deviate; with ``points`` each one
    is met."""
    push = TOP.copy()
    push[2, 3] -= 10.0
    moved = {}
    for kind in ("points", "cell_average"):
        tracker = fem_tracker(coarse, kind)
        tracker.set_rest_pose(TOP)
        res = tracker.update(push, with_field=True)
        assert res.status == "ok", res.reason
        emb = tracker._contact_emb
        moved[kind] = emb.interpolate(res.grid_displacement)
        target = tracker.contact_displacement(push)
        rows = constraint_rows(kind, emb.cells)
        tol = tracker._fem_settings.constraint_tolerance_mm
        assert np.abs(rows @ (moved[kind] - target)).max() <= tol
    deviation = np.abs(moved["cell_average"] - tracker.contact_displacement(push)).max()
    assert deviation > 10 * tol


def test_vertex_areas_share_out_the_surface():
    """Each vertex stands for a third of its triangles: the areas sum to the surface's, and
    on a flat square of two triangles the shared corners hold twice the others'."""
    v = np.array([[0.0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(vertex_areas(v, f), [4 / 3, 2 / 3, 4 / 3, 2 / 3])


def test_point_stiffness_is_beta_e_a_over_h():
    k = point_stiffness(10.0, np.array([0.005, 0.01]), np.array([5.0, 5.0]), 7.3)
    np.testing.assert_allclose(k, 10.0 * np.array([0.005, 0.01]) * 5.0 / 7.3)


def test_elastic_contact_lets_the_points_lag_and_drags_less(coarse):
    """With ``elastic`` the probe's contact points follow the face through springs: they lag
    it (a gap, largest at the face's edge), move the same way, and the lesions move less
    than with every point met, in the same direction."""
    push = TOP.copy()
    push[2, 3] -= 10.0
    lesion, moved = {}, {}
    for kind in ("points", "elastic"):
        tracker = fem_tracker(coarse, kind)
        tracker.set_rest_pose(TOP)
        res = tracker.update(push, with_field=True)
        assert res.status == "ok", res.reason
        lesion[kind] = np.array([les.displacement for les in res.lesions])
        moved[kind] = tracker._contact_emb.interpolate(res.grid_displacement)
    target = tracker.contact_displacement(push)
    assert tracker.last_solve.spring_factor == 1.0
    gap = np.linalg.norm(moved["elastic"] - target, axis=1)
    assert 0.05 < gap.max() < 10.0 and gap.max() == pytest.approx(
        tracker.last_solve.constraint_error_mm, rel=1e-6)
    assert np.all(np.einsum("ij,ij->i", moved["elastic"], target) > 0)
    a, b = (np.linalg.norm(lesion[k], axis=1) for k in ("elastic", "points"))
    assert np.all(a < b)
    cos = np.einsum("ij,ij->i", lesion["elastic"], lesion["points"]) / (a * b)
    assert np.all(cos > 0.9)


def test_the_protocol_of_elastic_rigid_pushes_holds_its_stiffness():
    from biopsynav.config import config_from_dict
    from biopsynav.dataset.store import protocol_dict

    def fe_model(tracker):
        cfg = config_from_dict({"probe": {"rigid_share": 1.0}, "tracker": tracker}, "case.toml")
        return protocol_dict(cfg, 8, 2)["fe_model"]

    assert "contact_stiffness" not in fe_model({"fem_contact": "points"})
    assert fe_model({"fem_contact": "elastic", "contact_stiffness": 7.0})[
        "contact_stiffness"] == 7.0


def test_the_case_grid_moduli_are_its_fe_models(coarse):
    """The springs of the network input use the case grid's element moduli without building
    its FE model: the same values as the model's."""
    from biopsynav.contact.springs import case_young_moduli
    from biopsynav.fem import FEModel

    np.testing.assert_array_equal(case_young_moduli(coarse), FEModel.from_case(coarse).E_mpa)
