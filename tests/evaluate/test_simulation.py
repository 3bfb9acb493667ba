"""Probe placement, push schedule and the simulated ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from biopsynav.anatomy.model import Lesion
from biopsynav.evaluate.placement import place_probe, push_depths
from biopsynav.evaluate.simulation import (
    evaluation_solver_settings,
    push_records,
    reference_case,
    select_lesions,
)
from biopsynav.evaluate.table import BIN_NAMES, bin_name
from biopsynav.tracker.core import contact_indices, fem_engine
from biopsynav.tracker.result import LesionResult, TrackingResult


def test_placement_puts_each_lesion_in_the_image_plane_below_the_face(coarse_phantom):
    a, probe = coarse_phantom.anatomy, coarse_phantom.cfg.probe
    for i, les in enumerate(a.lesions):
        pl = place_probe(a, i)
        r, t = pl.pose[:3, :3], pl.pose[:3, 3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        local = (les.center - t) @ r  # lesion in the probe frame
        assert abs(local[1]) < 1e-9, "lesion off the image (x-z) plane"
        assert abs(local[0]) < probe.footprint_mm[0] / 2, "lesion beside the probe face"
        assert local[2] > les.radius_mm, "lesion not below the face"
        assert pl.depth_mm == pytest.approx(local[2])
        assert not a.fixed_vertices[pl.vertex]
        np.testing.assert_allclose(t, a.vertices[pl.vertex])
        assert r[:, 2] @ a.normals[pl.vertex] < -0.8  # the beam enters the skin
        assert abs(r[:, 0] @ a.chest_normal) < 1e-9 or abs(r[:, 2] @ a.chest_normal) > 0.95
        assert len(contact_indices(a, pl.pose, tuple(probe.footprint_mm),
                                   probe.contact_tolerance_mm)) >= 3


def test_a_lesion_against_the_chest_wall_is_pushed_from_skin_a_training_push_may_centre_on(
        coarse_phantom):
    """The nearest pushable skin vertex of a lesion at the back of the breast lies within
    [probe] min_chest_distance_mm of the wall: the probe goes to the nearest one in front of
    that instead, and pushes into the breast."""
    a = coarse_phantom.anatomy
    depth = a.chest_depth(a.vertices)
    low = np.flatnonzero(a.pushable & (depth < 4.0))
    assert low.size, "the phantom has pushable skin next to its chest wall"
    v = int(low[np.argmax(np.linalg.norm(a.vertices[low] - a.vertices.mean(0), axis=1))])
    along_wall = a.normals[v] - (a.normals[v] @ a.chest_normal) * a.chest_normal
    centre = a.vertices[v] - 3.0 * along_wall / np.linalg.norm(along_wall)  # inside, at the wall
    lesion = Lesion(99, centre, 2.0, centre + 2.0 * np.eye(3))
    at_wall = dataclasses.replace(a, lesions=[lesion])
    assert depth[at_wall.nearest_pushable_vertex(centre)] < 5.0  # the old rule's skin point
    for floor in (5.0, 12.0):
        pl = place_probe(at_wall, 0, floor)
        assert depth[pl.vertex] >= floor
        ok = at_wall.pushable & (depth >= floor)
        nearest = np.linalg.norm(a.vertices[ok] - centre, axis=1).min()
        assert np.linalg.norm(a.vertices[pl.vertex] - centre) == pytest.approx(nearest)
        assert pl.pose[:3, 2] @ a.normals[pl.vertex] < 0  # into the breast


def test_push_depths_increase_and_fill_every_bin_across_lesions():
    seen = set()
    for k in range(5):
        d = push_depths(k, 4, 32.0)
        assert d.shape == (4,) and np.all(np.diff(d) > 0) and d.max() <= 32.0 and d.min() > 0
        bins = [bin_name(v) for v in d]
        assert len(set(bins)) == 4  # one push per bin, one bin skipped
        seen |= set(bins)
    assert seen == set(BIN_NAMES)
    assert select_lesions(10, 3) == [0, 4, 9]
    assert select_lesions(4, 0) == [0, 1, 2, 3]


class _StubTracker:
    """Reference stand-in: every lesion moves by ``shift`` (mm)."""

    def __init__(self, centres: np.ndarray, shift: np.ndarray, status: str = "ok") -> None:
        self.centres, self.shift, self.status = centres, shift, status

    def update(self, pose) -> TrackingResult:
        les = [LesionResult(i, c + self.shift, self.shift.copy(), self.status)
               for i, c in enumerate(self.centres)]
        return TrackingResult(les, self.status, "" if self.status == "ok" else "solver failed")


def test_rigid_tre_is_the_ground_truth_displacement_norm(coarse_phantom):
    a = coarse_phantom.anatomy
    centres = np.array([les.center for les in a.lesions])
    shift = np.array([1.0, -2.0, 2.0])
    pl = place_probe(a, 0)
    recs = push_records(pl, 0, 0, 14.0, _StubTracker(centres, shift), {}, ("rigid",))
    rigid = [r for r in recs if r.method == "rigid"][0]
    assert rigid.tre_mm == pytest.approx(3.0) and rigid.bin == "D15"
    assert rigid.displacement_mm == pytest.approx(14.0)
    failed = push_records(pl, 0, 1, 20.0, _StubTracker(centres, shift, "out_of_envelope"), {},
                          ("rigid",))
    assert failed[0].tre_mm is None and "solver failed" in failed[0].reason


def test_network_against_fe_agreement_is_the_distance_of_their_centres(coarse_phantom):
    a = coarse_phantom.anatomy
    centres = np.array([les.center for les in a.lesions])
    pl = place_probe(a, 0)
    truth = _StubTracker(centres, np.array([0.0, 0.0, -5.0]))
    net = _StubTracker(centres, np.array([0.0, 0.3, -5.4]))
    fem = _StubTracker(centres, np.array([0.0, 0.0, -5.0]))
    recs = {r.method: r for r in push_records(pl, 0, 0, 14.0, truth, {"net": net, "fem": fem},
                                              ("net", "fem"))}
    assert recs["net_vs_fem"].tre_mm == pytest.approx(0.5)
    assert recs["net"].tre_mm == pytest.approx(0.5) and recs["fem"].tre_mm == pytest.approx(0)
    broken = _StubTracker(centres, np.zeros(3), "out_of_envelope")
    recs = push_records(pl, 0, 0, 14.0, truth, {"net": broken, "fem": fem}, ("net", "fem"))
    assert "net_vs_fem" not in {r.method for r in recs}


def test_fine_reference_moves_the_lesion_and_fem_tracks_it(coarse_phantom):
    settings = evaluation_solver_settings(coarse_phantom)
    ref = reference_case(coarse_phantom, 1.5)
    assert ref.grid.spacing == pytest.approx(10.0)
    assert ref.grid.active_cells.sum() > coarse_phantom.grid.active_cells.sum()
    reference = fem_engine(ref, settings, on_teacher=False)
    fem = fem_engine(coarse_phantom, settings)
    pl = place_probe(coarse_phantom.anatomy, 2)
    n_ref = reference.set_rest_pose(pl.pose)
    assert fem.set_rest_pose(pl.pose) == n_ref > 0  # same skin vertices on both grids
    recs = {r.method: r for r in push_records(pl, 2, 0, 10.0, reference, {"fem": fem},
                                              ("fem", "rigid"))}
    assert recs["rigid"].tre_mm > 2.0  # the lesion moved
    assert recs["fem"].tre_mm < recs["rigid"].tre_mm  # the coarse FE follows it
    assert recs["reference"].time_ms > 0


def test_a_case_without_lesions_says_table_2_has_nothing_to_track(coarse_phantom, tmp_path):
    """A healthy breast (no lesions) gets Table 2's note, written and printed, with no
    reference built and no push solved; the report shows the note, not empty tables."""
    from biopsynav.case import Case
    from biopsynav.evaluate.run import table2_markdown, table2_text, write_table2
    from biopsynav.evaluate.simulation import NO_LESIONS, run_simulation
    from biopsynav.report.sections import table2_blocks, timing_section

    healthy = Case(coarse_phantom.dir, coarse_phantom.cfg,
                   dataclasses.replace(coarse_phantom.anatomy, lesions=[]), coarse_phantom.grid)
    said: list[str] = []
    result = run_simulation(healthy, log=said.append)
    assert result["note"] == NO_LESIONS and not result["records"] and not result["tables"]
    assert said == [f"Table 2: {NO_LESIONS}"]
    write_table2(tmp_path, result, "table2", log=said.append)
    assert NO_LESIONS[1:] in (tmp_path / "eval" / "table2.md").read_text()
    assert NO_LESIONS in table2_text(result) and "nothing to track" in table2_markdown(result)
    (block,) = table2_blocks(result, "by simulation", tmp_path / "t2.png")
    assert NO_LESIONS in block.text and not (tmp_path / "t2.png").exists()
    timing = timing_section(tmp_path, tmp_path)  # the report's timing, no reference built
    assert any("Table 2 by simulation took" in getattr(b, "text", "") for b in timing.blocks)
