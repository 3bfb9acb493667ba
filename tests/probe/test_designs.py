"""Designs of the training force patches (biopsynav.designs, ``[probe] train_design``)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from biopsynav.case import make_phantom_case
from biopsynav.config import CaseConfig
from biopsynav.dataset.store import protocol_dict
from biopsynav.designs import (
    DRAW_DIMENSIONS,
    design_names,
    hilbert_keys,
    hilbert_order,
    sobol_design,
)
from biopsynav.probe import (
    PATCH_DRAWS,
    designed_centre,
    eligible_centers,
    push_for_draw,
)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return make_phantom_case(tmp_path_factory.mktemp("designs") / "case", cell_size_mm=15.0)


def test_hilbert_order_walks_a_grid_one_face_at_a_time():
    cells = np.array(list(itertools.product(range(8), repeat=3)), dtype=float)
    shuffled = cells[np.random.default_rng(3).permutation(len(cells))]
    walk = shuffled[hilbert_order(shuffled)]
    steps = np.abs(np.diff(walk, axis=0)).sum(axis=1)
    assert np.all(steps == 1.0)
    assert len(np.unique(hilbert_keys(shuffled))) == len(cells)


def test_sobol_points_are_a_prefix_of_one_sequence_per_seed():
    first = np.array([sobol_design(0, k) for k in range(8)])
    assert first.shape == (8, DRAW_DIMENSIONS)
    assert np.all((first >= 0.0) & (first < 1.0))
    assert np.array_equal(sobol_design(0, 3000)[None], sobol_design(0, 3000)[None])
    assert np.array_equal(first[5], sobol_design(0, 5))
    assert not np.allclose(sobol_design(1, 5), first[5])


@pytest.mark.parametrize("pair", [(3, 4), (0, 3), (1, 2)])
def test_sobol_fills_every_cell_of_each_pair_of_numbers_evenly(pair):
    """The first 256 points put exactly 16 in each of 4 x 4 cells of any two of the five
    numbers (a net); 256 independent draws would not."""
    points = np.array([sobol_design(7, k) for k in range(256)])[:, list(pair)]
    counts = np.histogram2d(points[:, 0], points[:, 1], bins=4, range=[[0, 1], [0, 1]])[0]
    assert np.all(counts == 16)


def test_designed_centre_picks_every_vertex_once_over_the_unit_interval(case):
    centers = eligible_centers(case.anatomy, case.cfg.probe.min_chest_distance_mm)
    n = len(centers)
    picked = [designed_centre(case.anatomy, centers, (i + 0.5) / n) for i in range(n)]
    assert sorted(picked) == sorted(int(c) for c in centers)
    assert designed_centre(case.anatomy, centers, 1.0 - 1e-12) in centers


def test_sobol_sets_only_the_first_attempt_of_training_patches(case):
    probe = dataclasses.replace(case.cfg.probe, train_design="sobol", train_force_exponent=0.5)
    plain = dataclasses.replace(probe, train_design="random")
    anatomy, seed = case.anatomy, 5
    centers = eligible_centers(anatomy, probe.min_chest_distance_mm)
    for k in range(6):
        u = sobol_design(seed, k)
        push = push_for_draw(anatomy, probe, seed, PATCH_DRAWS + k, 0, centers, training=True)
        assert push.force_n == pytest.approx(probe.f_max_n * u[4] ** 0.5)
        assert push.tilt_deg == pytest.approx(probe.max_tilt_deg * (2 * u[3] - 1))
        assert push.vertex == designed_centre(anatomy, centers, u[0])
        assert push_for_draw(anatomy, probe, seed, k, 0, centers, training=True).force_n \
            == pytest.approx(probe.f_max_n * u[4] ** 0.5)  # a data set of patches alone
        for args in ((PATCH_DRAWS + k, 1, centers, False, None, True),  # a redraw
                     (PATCH_DRAWS + k, 0, centers, False, None, False),  # held out
                     (k, 0, centers, True, None, True)):  # a rigid push
            designed = push_for_draw(anatomy, probe, seed, *args)
            drawn = push_for_draw(anatomy, plain, seed, *args)
            assert (designed.vertex, designed.force_n, designed.push_mm) == \
                (drawn.vertex, drawn.force_n, drawn.push_mm)


def test_the_design_enters_the_protocol_only_where_it_acts():
    cfg = CaseConfig()
    assert set(design_names()) >= {"random", "sobol"}
    assert "train_design" not in protocol_dict(cfg, 10, 2)["probe"]  # former data sets' protocol
    cfg.probe.train_design = "sobol"
    assert protocol_dict(cfg, 10, 2)["probe"]["train_design"] == "sobol"
    cfg.probe.rigid_share = 1.0  # rigid pushes alone: no force patch to design
    assert "train_design" not in protocol_dict(cfg, 10, 2)["probe"]
