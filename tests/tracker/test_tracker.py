"""Tracker with the FE engine on a coarse phantom: poses, contact, safety statuses, CSV I/O."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.errors import InputError
from biopsynav.tracker import Tracker, pose_problem
from biopsynav.tracker import result as st
from biopsynav.tracker.csvtrack import MATRIX_COLUMNS, read_poses, track_csv

TOP = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])


def pushed(depth: float) -> np.ndarray:
    pose = TOP.copy()
    pose[2, 3] -= depth
    return pose


@pytest.fixture(scope="module")
def coarse_case(tmp_path_factory):
    from biopsynav.case import make_phantom_case

    # [refine] off: the FE engine solves on [dataset] teacher_refine's grid in the tests below
    return make_phantom_case(tmp_path_factory.mktemp("trk") / "case", cell_size_mm=12.0,
                             overrides={"refine": {"samples": 0}})


@pytest.fixture(scope="module")
def fem_tracker(coarse_case):
    return Tracker.load(coarse_case.dir, engine="fem")


def test_pose_validation():
    assert pose_problem(TOP, 1e-3) == ""
    assert pose_problem(TOP[:3], 1e-3) == ""
    bad = TOP.copy()
    bad[0, 0] = np.nan
    assert "NaN" in pose_problem(bad, 1e-3)
    scaled = TOP.copy()
    scaled[:3, :3] *= 1.1
    assert "not rigid" in pose_problem(scaled, 1e-3)
    mirrored = TOP.copy()
    mirrored[:3, 0] *= -1
    assert "not rigid" in pose_problem(mirrored, 1e-3)
    assert "shape" in pose_problem(np.eye(3), 1e-3)
    projective = TOP.copy()
    projective[3, 2] = 0.01
    assert "last row" in pose_problem(projective, 1e-3)
    sheared = TOP.copy()
    sheared[0, 1] += 0.01  # a shear breaks orthonormality
    assert "not rigid" in pose_problem(sheared, 1e-3)
    inf = TOP.copy()
    inf[1, 3] = np.inf
    assert "NaN or infinite" in pose_problem(inf, 1e-3)
    turned = TOP.copy()
    c, s = np.cos(0.3), np.sin(0.3)
    turned[:3, :3] = turned[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert pose_problem(turned, 1e-6) == ""


def test_rest_pose_and_push(fem_tracker):
    r = fem_tracker.update(TOP)
    assert r.status == st.NO_REST_POSE and not r.reliable
    assert all(np.isnan(les.center).all() for les in r.lesions)
    n = fem_tracker.set_rest_pose(TOP)
    assert n > 5
    r0 = fem_tracker.update(TOP, with_field=True)
    assert r0.status == st.OK
    np.testing.assert_allclose([les.displacement for les in r0.lesions], 0.0, atol=1e-9)
    r = fem_tracker.update(pushed(10.0), with_surface=True, lesion_surfaces=True,
                           with_field=True)
    assert r.status == st.OK, r.reason
    assert r0.grid_displacement is None  # asked for, but at rest nothing is solved
    # each lesion moves as the grid's field at its centre, trilinear in its cell (SciPy's
    # interpolator on the node lattice, not the tracker's embedding)
    from scipy.interpolate import RegularGridInterpolator

    g = fem_tracker.case.grid
    axes = [g.origin[a] + g.spacing * np.arange(g.node_shape[a]) for a in range(3)]
    field = RegularGridInterpolator(axes, r.grid_displacement.reshape(*g.node_shape, 3))
    centres = [les.center for les in fem_tracker.case.anatomy.lesions]
    np.testing.assert_allclose(field(centres), [les.displacement for les in r.lesions],
                               atol=1e-9)
    central = {les.id: les for les in r.lesions}[3]  # lesion 3 at (0, 0, 45), under the probe
    assert -10.0 < central.displacement[2] < -1.0
    assert abs(central.displacement[0]) < 0.5 and abs(central.displacement[1]) < 0.5
    assert r.surface.shape == fem_tracker.case.anatomy.vertices.shape
    # the lesion's closed surface mesh moves with it, read off the same field
    rest_vertices, faces = fem_tracker.lesion_meshes[3]
    assert central.surface.shape == rest_vertices.shape and len(faces) == 2 * len(rest_vertices) - 4
    np.testing.assert_allclose((central.surface - rest_vertices).mean(axis=0),
                               central.displacement, atol=1.0)
    np.testing.assert_array_equal(r0.lesions[2].surface, rest_vertices)  # at rest: unmoved
    # skin at the probe centre moves with the probe
    top = np.argmax(fem_tracker.case.anatomy.vertices[:, 2])
    assert r.surface[top, 2] == pytest.approx(65.0, abs=1.0)


def test_prepare_surface_builds_the_skin_embedding_the_skin_answers_use(coarse_case,
                                                                        monkeypatch):
    """The service prepares the skin before the first pose: no skin answer builds it again
    (on a clinical skin the build held up a 100 Hz stream for a tenth of a second)."""
    import biopsynav.tracker.core as core

    tracker = Tracker.load(coarse_case.dir, engine="fem")
    tracker.prepare_surface()

    def rebuilt(*_):
        raise AssertionError("the skin embedding was built again")

    monkeypatch.setattr(core, "surface_embedding", rebuilt)
    tracker.set_rest_pose(TOP)
    r = tracker.update(pushed(5.0), with_surface=True)
    assert r.status == st.OK, r.reason
    top = np.argmax(coarse_case.anatomy.vertices[:, 2])
    assert r.surface[top, 2] == pytest.approx(70.0, abs=1.0)


def test_unreliable_poses_give_no_numbers(fem_tracker):
    fem_tracker.set_rest_pose(TOP)
    nan_pose = pushed(5.0)
    nan_pose[1, 3] = np.nan
    for pose, status in [(nan_pose, st.INVALID_POSE), (pushed(5.0) * 1.5, st.INVALID_POSE)]:
        r = fem_tracker.update(pose)
        assert r.status == status and r.reason
        assert all(np.isnan(les.center).all() for les in r.lesions)
    lifted = fem_tracker.update(pushed(-10.0))
    assert lifted.status == st.NO_CONTACT and "lifted" in lifted.reason
    np.testing.assert_allclose([les.displacement for les in lifted.lesions], 0.0)
    away = TOP.copy()
    away[:3, 3] = [0.0, 0.0, 200.0]
    fem_tracker.set_rest_pose(away)
    assert fem_tracker.n_contact == 0
    assert fem_tracker.update(away).status == st.NO_CONTACT
    with pytest.raises(InputError, match="rest pose"):
        fem_tracker.set_rest_pose(nan_pose)


def tilted_rest_pose(case) -> np.ndarray:
    """A Table 2 rest pose over the first lesion: a rotation whose inverse rounds."""
    from biopsynav.evaluate.placement import place_probe

    return place_probe(case.anatomy, 0).pose


@pytest.mark.parametrize("tilted", [False, True])
def test_rest_pose_answers_at_once_without_a_solve(fem_tracker, monkeypatch, tilted):
    import biopsynav.fem

    rest = tilted_rest_pose(fem_tracker.case) if tilted else TOP
    fem_tracker.set_rest_pose(rest)

    def no_solve(*args, **kwargs):
        raise AssertionError("a pose with zero displacement must not solve")

    monkeypatch.setattr(biopsynav.fem, "solve", no_solve)
    r = fem_tracker.update(rest.copy())
    assert r.status == st.OK and r.reliable
    np.testing.assert_array_equal([les.displacement for les in r.lesions], 0.0)
    np.testing.assert_array_equal([les.center for les in r.lesions],
                                  [les.center for les in fem_tracker.case.anatomy.lesions])


def test_every_clinical_push_over_every_lesion_converges(fem_tracker):
    """Table-2-like pushes (probe over each lesion, along its beam) up to the clinical 35 mm:
    the FE engine answers ok for each (benchmarks/fe_pushes.py runs the default grid)."""
    from biopsynav.evaluate.placement import place_probe

    anatomy = fem_tracker.case.anatomy
    failed = []
    for li in range(len(anatomy.lesions)):
        placement = place_probe(anatomy, li)
        fem_tracker.set_rest_pose(placement.pose)
        for depth in (12.0, 24.0, 35.0):
            r = fem_tracker.update(placement.pushed(depth))
            if r.status != st.OK:
                failed.append((anatomy.lesions[li].id, depth, r.status, r.reason))
    assert not failed


def test_solver_failure_is_solver_failed_not_out_of_envelope(fem_tracker, monkeypatch):
    import dataclasses

    fem_tracker.set_rest_pose(TOP)
    starved = dataclasses.replace(fem_tracker._fem_settings, max_total_iterations=1,
                                  max_iterations=1, initial_load_step=1.0, min_load_step=1.0)
    monkeypatch.setattr(fem_tracker, "_fem_settings", starved)
    r = fem_tracker.update(pushed(10.0))
    assert r.status == st.SOLVER_FAILED and not r.reliable
    assert "converge" in r.reason or "iteration" in r.reason
    assert all(np.isnan(les.center).all() for les in r.lesions)


def test_the_springs_as_asked_get_the_tracker_s_budget_then_their_fallback(coarse_case,
                                                                          monkeypatch):
    """The FE engine and Table 2's FE method give elastic contact's first attempt ``[tracker]
    spring_budget`` Newton iterations on the case grid (Table 2's ground truth, r times finer, r
    times as many); a push whose first attempt runs out of them is answered by the stiffer
    springs, with no limit of their own."""
    import dataclasses
    import math

    import biopsynav.fem.solver as solver_mod
    from biopsynav.evaluate.references import GridReference
    from biopsynav.evaluate.simulation import evaluation_solver_settings, setup_for
    from biopsynav.tracker.core import finer_grid_spring_budget

    budget = coarse_case.cfg.tracker.spring_budget
    settings = evaluation_solver_settings(coarse_case)
    assert budget > 0 and settings.first_attempt_budget == budget
    # a finer grid (Table 2's ground truth, 1.5 times finer in quick mode) gets a budget as
    # many times larger: converging solves there need more iterations
    setup = setup_for(coarse_case, quick=True)
    truth = GridReference(coarse_case, setup, settings)
    assert setup.refinement == 1.5
    assert truth.tracker._fem_settings.first_attempt_budget == math.ceil(1.5 * budget)
    assert finer_grid_spring_budget(settings, 1.0).first_attempt_budget == budget
    assert finer_grid_spring_budget(dataclasses.replace(settings, first_attempt_budget=0),
                                    2.0).first_attempt_budget == 0  # no budget stays none
    real, budgets = solver_mod.solve_once, []

    def first_runs_out(model, loads, settings=None, resume_from=None):
        budgets.append(settings.max_total_iterations)
        if len(budgets) == 1:
            raise solver_mod.SolverError("no convergence within max_total_iterations", "test")
        return real(model, loads, settings, resume_from)

    tracker = Tracker.load(coarse_case.dir, engine="fem")
    tracker.set_rest_pose(TOP)
    monkeypatch.setattr(solver_mod, "solve_once", first_runs_out)
    r = tracker.update(pushed(10.0))
    assert r.status == st.OK and budgets == [budget, 0]
    assert tracker.last_solve.spring_factor == 4.0
    # the answer says which springs gave it (`track`'s reason column, Table 2's records)
    assert r.reason == "answered with contact springs 4 times stiffer: those asked did not " \
                       "converge"
    monkeypatch.setattr(solver_mod, "solve_once", real)
    assert tracker.update(pushed(10.0)).reason == ""


def _poses_csv(path, poses):
    lines = ["frame,sequence," + ",".join(MATRIX_COLUMNS)]
    for i, (seq, pose) in enumerate(poses):
        lines.append(f"{i},{seq}," + ",".join(f"{v:.6f}" for v in pose[:3].ravel()))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_track_csv_fem(coarse_case, tmp_path):
    poses = _poses_csv(tmp_path / "poses.csv", [("a", TOP), ("a", pushed(8.0)),
                                                 ("b", TOP), ("b", pushed(4.0))])
    out = tmp_path / "lesions.csv"
    assert track_csv(coarse_case.dir, poses, out, engine="fem") == {"ok": 4}
    rows = out.read_text().splitlines()
    assert rows[0] == "frame,lesion_id,x,y,z,bound_mm,status,reason"
    assert len(rows) == 1 + 4 * len(coarse_case.anatomy.lesions)
    assert all(r.endswith(",ok,") for r in rows[1:])
    bound = {(r.split(",")[0], r.split(",")[1]): float(r.split(",")[5]) for r in rows[1:]}
    assert all(b == 0.0 for (frame, _), b in bound.items() if frame in ("0", "2"))  # at rest
    assert all(0.0 < b < 5.0 for (frame, _), b in bound.items() if frame in ("1", "3"))


def test_a_refused_rest_pose_names_the_poses_file_and_frame(coarse_case, tmp_path):
    """A NaN rest pose stops ``track`` before anything is written, naming the file and the
    frame; a NaN pose later in a sequence is that frame's status (a tracker's dropout)."""
    bad = TOP.copy()
    bad[2, 3] = np.nan
    out = tmp_path / "lesions.csv"
    poses = _poses_csv(tmp_path / "poses.csv", [("a", TOP), ("a", pushed(4.0)), ("b", bad)])
    with pytest.raises(InputError, match=r"poses\.csv: frame 2: rest pose of sequence 'b': "
                                         r"pose contains NaN"):
        track_csv(coarse_case.dir, poses, out, engine="fem")
    assert not out.exists()
    poses = _poses_csv(tmp_path / "poses.csv", [("a", TOP), ("a", bad), ("a", pushed(4.0))])
    assert track_csv(coarse_case.dir, poses, out, engine="fem") == {"ok": 2, "invalid_pose": 1}


def test_bad_poses_csv(tmp_path):
    bad = tmp_path / "p.csv"
    bad.write_text("frame,x\n1,2\n")
    with pytest.raises(InputError, match="lacks the columns"):
        read_poses(bad)
    (tmp_path / "q.csv").write_text("frame,sequence," + ",".join(MATRIX_COLUMNS) + "\n"
                                    + "1,a," + ",".join(["x"] * 12) + "\n")
    with pytest.raises(InputError, match="line 2"):
        read_poses(tmp_path / "q.csv")
    with pytest.raises(InputError, match="file not found"):
        read_poses(tmp_path / "none.csv")


def test_hot_path_input_matches_the_dataset_contract(fem_tracker):
    """The tracker's precomputed input operator gives the input the dataset stores."""
    fem_tracker.set_rest_pose(TOP)
    u_c = fem_tracker.contact_displacement(pushed(7.0))
    fem_tracker._set_input(u_c, fem_tracker.input_operator())
    expected = fem_tracker.network_input(u_c)
    assert fem_tracker.contact_input_kind == "elastic" and np.abs(expected[:3]).max() > 1.0
    np.testing.assert_allclose(fem_tracker._input, expected, atol=1e-5)


def test_fe_engine_holds_skin_that_the_face_reaches(phantom_case):
    """``[tracker] contact_follows_pose`` (default grid, a 30 mm push over lesion 4, where the
    ends of the face reach skin not touched at rest): afterwards that skin lies on the face
    plane, and the lesions move differently from the rest-contact-only solve. With the points
    met (``points``; elastic contact holds that skin by springs too, off the plane by its
    gap)."""
    import copy

    from biopsynav.case import Case
    from biopsynav.evaluate.placement import place_probe

    met = copy.deepcopy(phantom_case.cfg)
    met.tracker.fem_contact = "points"
    cfg = copy.deepcopy(met)
    cfg.tracker.contact_follows_pose = True
    follow = Tracker.load(Case(phantom_case.dir, cfg, phantom_case.anatomy, phantom_case.grid),
                          engine="fem")
    plain = Tracker.load(Case(phantom_case.dir, met, phantom_case.anatomy, phantom_case.grid),
                         engine="fem")
    placement = place_probe(phantom_case.anatomy, 3)
    pose = placement.pushed(30.0)
    for tracker in (follow, plain):
        tracker.set_rest_pose(placement.pose)
    r_follow, r_plain = follow.update(pose, with_surface=True), plain.update(pose)
    assert r_follow.status == r_plain.status == st.OK, r_follow.reason
    held = follow.last_touched
    assert len(held) > 0 and not np.isin(held, follow._contact).any()
    depth = (r_follow.surface[held] - pose[:3, 3]) @ pose[:3, 2]
    assert np.abs(depth).max() < 0.05  # on the face plane
    moved = np.array([les.displacement for les in r_follow.lesions])
    rest_only = np.array([les.displacement for les in r_plain.lesions])
    assert np.abs(moved - rest_only).max() > 0.5


def test_fe_engine_lets_go_of_skin_its_springs_pull(fem_tracker):
    """Elastic contact holds reached skin by springs, which can pull: skin that a solve puts
    in front of the face plane (the tissue side) is let go, skin behind it stays held; with
    the points met nothing is let go (they lie on the plane)."""
    fem_tracker.set_rest_pose(TOP)
    skin = fem_tracker.case.anatomy.vertices
    near = np.flatnonzero(np.abs(skin[:, 2] - (75.0 - 8.0)) < 2.0)[:20]
    assert len(near) > 0
    moved = fem_tracker._moved_skin(np.zeros((fem_tracker._fem_model.n_nodes, 3)))
    np.testing.assert_array_equal(moved, skin)
    assert fem_tracker.case.cfg.tracker.fem_contact == "elastic"
    np.testing.assert_array_equal(fem_tracker._skin_pulled(moved, pushed(4.0), near), near)
    assert len(fem_tracker._skin_pulled(moved, pushed(12.0), near)) == 0
    assert len(fem_tracker._skin_pulled(moved, pushed(4.0), near[:0])) == 0
    fem_tracker.case.cfg.tracker.fem_contact = "points"
    try:
        assert len(fem_tracker._skin_pulled(moved, pushed(4.0), near)) == 0
    finally:
        fem_tracker.case.cfg.tracker.fem_contact = "elastic"


def test_the_fe_engine_solves_on_a_refined_teacher_grid(coarse_case):
    """With [dataset] teacher_refine = 2 the FE engine solves on the teacher's grid (about 8x
    the cells) and answers on the case grid: the central lesion moves the same way, by a
    similar amount (the two grids' discretisation errors differ)."""
    import copy

    from biopsynav.case import Case
    from biopsynav.fem import SolverSettings
    from biopsynav.tracker.core import fem_engine

    cfg = copy.deepcopy(coarse_case.cfg)
    cfg.dataset.teacher_refine = 2
    refined = Case(coarse_case.dir, cfg, coarse_case.anatomy, coarse_case.grid)
    settings = SolverSettings.from_config(cfg.solver)
    answers = {}
    for refine, case in ((1, coarse_case), (2, refined)):
        tracker = fem_engine(case, settings)
        assert (tracker._teacher is None) == (refine == 1)
        tracker.set_rest_pose(TOP)
        r = tracker.update(pushed(8.0))
        assert r.status == "ok", r.reason
        answers[refine] = np.array(r.lesions[0].displacement)
    assert len(tracker._fem_model.hexes) > 6 * coarse_case.grid.active_cells.sum()
    a, b = answers[1], answers[2]
    assert np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)) > 0.95
    assert 0.5 < np.linalg.norm(b) / np.linalg.norm(a) < 1.5


def test_an_extrapolating_teacher_s_fe_engine_answers_richardson_s_extrapolation(coarse_case):
    """With [dataset] teacher_extrapolation the FE engine solves on the teacher's grid and on
    the case grid and answers ``fit + w (fit - case)``: for the central lesion (in full
    cells) exactly that combination of the two engines' own answers."""
    import copy

    from biopsynav.case import Case
    from biopsynav.fem import SolverSettings
    from biopsynav.fem.teacher import extrapolation_weight
    from biopsynav.tracker.core import fem_engine

    answers = {}
    for order in (None, 0.0, 2.0):
        cfg = copy.deepcopy(coarse_case.cfg)
        if order is not None:
            cfg.dataset.teacher_refine, cfg.dataset.teacher_extrapolation = 1.5, order
        tracker = fem_engine(Case(coarse_case.dir, cfg, coarse_case.anatomy, coarse_case.grid),
                             SolverSettings.from_config(cfg.solver))
        tracker.set_rest_pose(TOP)
        r = tracker.update(pushed(8.0))
        assert r.status == "ok", r.reason
        answers[order] = np.array(r.lesions[0].displacement)
    case_grid, fit, extrapolated = answers[None], answers[0.0], answers[2.0]
    expected = fit + extrapolation_weight(1.5, 2.0) * (fit - case_grid)
    assert np.linalg.norm(fit - case_grid) > 0.01
    assert np.abs(extrapolated - expected).max() < 1e-6


def test_track_says_when_a_case_has_no_lesions_to_write():
    from biopsynav.tracker.csvtrack import track_summary

    with_lesions = track_summary({"ok": 9, "out_of_envelope": 2}, 3, "out.csv")
    assert with_lesions.startswith("11 poses tracked (9 ok, 2 out_of_envelope)")
    assert "lesion positions" in with_lesions and "no lesions" not in with_lesions
    healthy = track_summary({"ok": 11}, 0, "out.csv")
    assert "no lesions" in healthy and "out.csv holds the header alone" in healthy


def test_a_deeper_push_continues_from_the_last_equilibrium_to_the_answer_from_rest(coarse_case):
    """With ``continuation`` a push further along the line of the last one starts at its load
    factor from its equilibrium and lands where a solve from rest does; a push off that line
    (tilted), or one over another rest pose, starts from rest."""
    from biopsynav.fem import SolverSettings
    from biopsynav.tracker.core import fem_engine

    settings = SolverSettings.from_config(coarse_case.cfg.solver)
    settings.constraint_tolerance_mm = 1e-4
    from_rest = fem_engine(coarse_case, settings)
    continuing = fem_engine(coarse_case, settings, continuation=True)
    for tracker in (from_rest, continuing):
        tracker.set_rest_pose(TOP)
    for depth in (6.0, 12.0, 18.0):
        a, b = from_rest.update(pushed(depth)), continuing.update(pushed(depth))
        assert a.status == b.status == "ok", (a.reason, b.reason)
        first_load = continuing.last_solve.log[0]["load"] - continuing.last_solve.log[0]["step"]
        assert first_load == pytest.approx(0.0 if depth == 6.0 else (depth - 6.0) / depth)
        for la, lb in zip(a.lesions, b.lesions, strict=True):
            assert np.abs(la.center - lb.center).max() < 1e-4
    tilted = pushed(24.0)
    c, s = np.cos(0.1), np.sin(0.1)
    tilted[:3, :3] = tilted[:3, :3] @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    assert continuing.update(tilted).status == "ok"
    assert continuing.last_solve.log[0]["load"] == continuing.last_solve.log[0]["step"]
    continuing.set_rest_pose(TOP)  # the same rest pose again: nothing kept
    assert continuing.update(pushed(12.0)).status == "ok"
    assert continuing.last_solve.log[0]["load"] == continuing.last_solve.log[0]["step"]


def test_a_stiffer_spring_answer_is_not_continued_from(coarse_case):
    """An answer of elastic contact's stiffer-spring fallback is of other loads: the next
    deeper push starts from rest."""
    from biopsynav.fem.solver import SolveReport
    from biopsynav.tracker.core import fem_engine

    tracker = fem_engine(coarse_case, None, continuation=True)
    g = np.ones((4, 3))
    state = (1.0, np.zeros(7))
    tracker._keep_for_continuation(g, SolveReport(spring_factor=1.0, reached=state))
    assert tracker._continuation_start(2.0 * g)[0] == pytest.approx(0.5)
    assert tracker._continuation_start(0.5 * g) is None  # shallower: from rest
    tracker._keep_for_continuation(g, SolveReport(spring_factor=4.0, reached=state))
    assert tracker._continuation_start(2.0 * g) is None
