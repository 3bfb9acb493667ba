"""An extrapolated teacher (``[dataset] teacher_extrapolation``): every sample solved on a
finer grid and on the case grid, stored as their Richardson extrapolation."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr
from dataset_helpers import edit_config

from biopsynav.case import Case
from biopsynav.dataset.generate import generate_case
from biopsynav.fem.teacher import build_teacher, extrapolation_weight, whole_or_float
from biopsynav.grid.index import tensor_to_field
from biopsynav.network.data import load_dataset
from biopsynav.network.model_io import teacher

REFINE, ORDER = 1.5, 2.0  # 15 mm cells -> 10 mm; error of order 2 in the cell size


@pytest.fixture(scope="module")
def teachers(base_case, tmp_path_factory):
    """The coarse phantom taught by 10 mm cells, fitted ("fit") and extrapolated from the
    case grid ("extrapolated"), 3 samples each."""
    out = {}
    for name, order in (("fit", 0.0), ("extrapolated", ORDER)):
        dst = tmp_path_factory.mktemp(name) / "case"
        shutil.copytree(base_case, dst)
        edit_config(dst, dataset={"teacher_refine": REFINE, "teacher_extrapolation": order,
                                  "n_train": 2, "n_test": 1})
        generate_case(dst, workers=1, progress=False)
        out[name] = dst
    return out


def test_richardson_weight():
    assert extrapolation_weight(2, 2) == pytest.approx(1 / 3)
    assert extrapolation_weight(1.46, 2) == pytest.approx(5.0**2 / (7.3**2 - 5.0**2), rel=1e-3)
    assert whole_or_float(2.0) == 2 and isinstance(whole_or_float(2.0), int)
    assert whole_or_float(1.46) == 1.46


def test_the_protocol_and_the_model_record_name_the_extrapolation(teachers):
    for name, order in (("fit", 0.0), ("extrapolated", ORDER)):
        data = zarr.open_group(str(teachers[name] / "dataset.zarr"), mode="r")
        dataset = data.attrs["protocol"]["dataset"]
        assert dataset["teacher_refine"] == REFINE
        assert dataset.get("teacher_extrapolation", 0.0) == order
        record = teacher(load_dataset(teachers[name]))
        assert record["teacher_extrapolation"] == order and record["teacher_refine"] == REFINE


def test_extrapolated_targets_are_richardson_s_from_the_fit_and_the_case_grid(teachers,
                                                                               reference):
    """Same draws in the three data sets: the extrapolated target is ``fit + w (fit - case)``
    at the nodes of cells at least half full, the fit itself elsewhere."""
    ex, fit, case_grid = (zarr.open_group(str(d / "dataset.zarr"), mode="r")
                          for d in (teachers["extrapolated"], teachers["fit"], reference))
    mask = build_teacher(Case.load(teachers["extrapolated"])).extrapolated
    assert 0 < mask.sum() < len(mask)
    w = extrapolation_weight(REFINE, ORDER)
    compared = 0
    for i in range(3):
        if not (ex["attempt"][i] == fit["attempt"][i] == case_grid["attempt"][i]):
            continue  # one of them redrew a failed push
        if ex["force_n"][i] != case_grid["force_n"][i]:  # a training sample in one set only
            continue
        u_e, u_f, u_c = (tensor_to_field(g["targets"][i]) for g in (ex, fit, case_grid))
        expected = u_f + w * mask[:, None] * (u_f - u_c)
        assert np.abs(u_e - expected).max() < 1e-3
        assert np.abs(u_e - u_f).max() > 0.1  # the case grid's answer differs
        compared += 1
    assert compared >= 2


def test_cells_the_extrapolation_stretches_beyond_the_limit_keep_the_fitted_field(teachers):
    """One node far apart in the two grids (as under the probe's edge at a deep push): the
    cells it would stretch beyond the limit get the fitted field back, every other node
    keeps the extrapolation, and no extrapolated cell is left beyond the limit."""
    from biopsynav.fem.solver import edge_stretches

    teacher = build_teacher(Case.load(teachers["extrapolated"]))
    nodes = teacher.coarse.nodes
    fitted = 0.02 * nodes  # a smooth field, mm
    u_case = fitted - np.array([1.0, 0.0, 0.0])
    flung = int(np.flatnonzero(teacher.extrapolated)[0])
    u_case[flung] -= [200.0, 0.0, 0.0]
    raw = teacher.extrapolate(fitted, u_case)
    assert raw[flung, 0] - fitted[flung, 0] == pytest.approx(201.0 * teacher.weight)
    limited = teacher.extrapolate(fitted, u_case, max_stretch=8.0)
    stretched = teacher.extrapolated_cells & (edge_stretches(teacher.coarse, raw) > 8.0)
    back = np.zeros(len(nodes), dtype=bool)
    back[teacher.coarse.hexes[stretched].ravel()] = True
    assert back[flung] and back.sum() < teacher.extrapolated.sum() / 4
    np.testing.assert_allclose(limited[back], fitted[back])
    kept = teacher.extrapolated & ~back
    np.testing.assert_allclose(limited[kept], raw[kept])
    assert edge_stretches(teacher.coarse, limited)[teacher.extrapolated_cells].max() <= 8.0


def test_a_draw_the_case_grid_rejects_costs_no_fine_solve(teachers, monkeypatch):
    """The case grid solves first: a draw whose case-grid solve fails is redrawn before the
    teacher's fine grid is solved."""
    from biopsynav.dataset import worker
    from biopsynav.errors import SolverError

    ctx = worker.SampleContext(Case.load(teachers["extrapolated"]))

    def case_grid_fails(ctx, push):
        raise SolverError("case grid: no convergence (forced)", "fem.solve")

    def fine_solve(ctx, push):
        raise AssertionError("the fine grid was solved after the case grid failed")

    monkeypatch.setattr(worker, "case_grid_solution", case_grid_fails)
    monkeypatch.setattr(worker, "teacher_solution", fine_solve)
    result = worker.compute_sample(ctx, 0, 0)
    assert not result["ok"] and result["kind"] == worker.NOT_CONVERGED
    assert result["error"].startswith("case grid:")
