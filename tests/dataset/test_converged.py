"""The P2 teacher (``[dataset] teacher = "p2"``): its samples are the P2 answer on the case grid,
the same through local workers, a Dask cluster and a resume after a kill; what it cannot
teach is refused before any work."""

from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import zarr
from dataset_helpers import edit_config, generate_through_local_cluster
from test_generate import samples_done, start_generate, wait_for_done

from biopsynav.case import Case
from biopsynav.config import load_config
from biopsynav.dataset.converged import face_rest_pose
from biopsynav.dataset.generate import generate_case
from biopsynav.dataset.worker import SampleContext, input_springs
from biopsynav.errors import InputError
from biopsynav.evaluate.p2 import PushTimeout, TetReference
from biopsynav.evaluate.references import default_tissue_material
from biopsynav.grid.index import tensor_to_field
from biopsynav.probe import contact_input, push_for_sample

pytest.importorskip("gmsh")

N_TRAIN, N_TEST = 5, 1
N = N_TRAIN + N_TEST


def p2_settings(case_dir: Path) -> None:
    """Every push rigid, solved by the P2 teacher on coarse tetrahedra (seconds a push)."""
    edit_config(case_dir, probe={"rigid_share": 1.0},
                dataset={"teacher": "p2", "teacher_size_mm": 25.0, "teacher_fine_mm": 12.0,
                         "n_train": N_TRAIN, "n_test": N_TEST})


@pytest.fixture(scope="module")
def p2_base(base_case: Path, tmp_path_factory) -> Path:
    dst = tmp_path_factory.mktemp("p2") / "base"
    shutil.copytree(base_case, dst)
    p2_settings(dst)
    return dst


@pytest.fixture(scope="module")
def p2_reference(p2_base: Path, tmp_path_factory) -> Path:
    """The P2-taught data set made by two local workers, uninterrupted."""
    dst = tmp_path_factory.mktemp("p2ref") / "case"
    shutil.copytree(p2_base, dst)
    summary = generate_case(dst, workers=2, progress=False)
    assert summary["count"] == N
    return dst


@pytest.fixture
def p2_fresh(p2_base: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "case"
    shutil.copytree(p2_base, dst)
    return dst


def test_a_sample_is_the_p2_answer_fitted_to_the_case_grid(p2_reference):
    """The stored target is the fit of the P2 push (the same push solved again here) to the
    case grid, with no node flung far beyond the push, and the input is the face's motion."""
    case = Case.load(p2_reference)
    cfg = case.cfg
    g = zarr.open_group(str(p2_reference / "dataset.zarr"), mode="r")
    i = 0
    ctx = SampleContext(case)
    push = push_for_sample(case.anatomy, cfg.probe, cfg.dataset.seed, i, int(g["attempt"][i]),
                           ctx.centers, pinned=ctx.pinned, training=True)
    rest = face_rest_pose(push)
    e_mpa, nu = default_tissue_material(case)
    model = TetReference.build(case.anatomy, 25.0, e_mpa, nu, fine_at=rest[:3, 3], fine_mm=12.0)
    contact = model.contact(rest, cfg.probe.footprint, cfg.probe.contact_tolerance_mm)
    pose = rest.copy()
    pose[:3, 3] += push.displacement
    model.push(rest, [pose], contact, np.zeros((0, 3)), footprint=cfg.probe.footprint)
    stored = tensor_to_field(g["targets"][i]).astype(np.float64)
    np.testing.assert_allclose(stored, ctx.converged._on_case_grid(model), atol=1e-4)
    assert np.linalg.norm(stored, axis=1).max() < 2.0 * push.push_mm
    assert g["probe_disp_mm"][i] == pytest.approx(push.push_mm, rel=1e-6)
    assert np.all(g["targets"][i][:, ~case.grid.active_nodes] == 0)
    face = np.broadcast_to(push.displacement, (len(push.contact), 3))
    expected = contact_input(ctx.skin[push.contact], face, "elastic", ctx.compliance,
                             input_springs(ctx, push))
    np.testing.assert_allclose(tensor_to_field(g["inputs"][i]), expected, rtol=1e-4, atol=1e-4)


def test_local_workers_and_a_local_cluster_give_the_same_samples(p2_fresh, p2_reference,
                                                                 assert_same_dataset):
    summary = generate_through_local_cluster(p2_fresh)
    assert summary["count"] == N
    assert_same_dataset(p2_fresh, p2_reference)


def test_a_killed_run_resumes_to_the_same_samples(p2_fresh, p2_reference, tmp_path,
                                                  assert_same_dataset):
    proc = start_generate(p2_fresh, tmp_path, workers=1)
    wait_for_done(proc, p2_fresh, 1)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    at_kill = samples_done(p2_fresh)
    assert at_kill < N, "the kill came too late to interrupt the run"
    summary = generate_case(p2_fresh, workers=2, progress=False)
    assert summary["computed_this_run"] == N - at_kill
    assert_same_dataset(p2_fresh, p2_reference)


def test_the_teacher_is_part_of_the_protocol(p2_reference, tmp_path):
    """A P2-taught data set is another data set: the grid teacher's run refuses it."""
    from biopsynav.errors import FingerprintError

    dst = tmp_path / "case"
    shutil.copytree(p2_reference, dst)
    edit_config(dst, dataset={"teacher": "grid"})
    with pytest.raises(FingerprintError):
        generate_case(dst, workers=1, progress=False)


def test_the_protocol_names_a_curved_chest_wall_and_leaves_a_flat_ones_as_it_was(p2_base):
    """The P2 teacher held a label map's curved wall as a plane before it held what the grid
    holds: a data set of a curved wall records the rule (so one made before is refused), one of
    a flat wall keeps its former protocol."""
    from types import SimpleNamespace

    from biopsynav.dataset.store import protocol_dict

    cfg = load_config(p2_base)
    flat = protocol_dict(cfg, 5, 1, SimpleNamespace(chest_curved=False))
    curved = protocol_dict(cfg, 5, 1, SimpleNamespace(chest_curved=True))
    assert "chest_wall" not in flat["dataset"]["teacher_protocol"]
    assert curved["dataset"]["teacher_protocol"]["chest_wall"] == "curved"
    assert {**curved["dataset"]["teacher_protocol"], "chest_wall": None} \
        == {**flat["dataset"]["teacher_protocol"], "chest_wall": None}
    with pytest.raises(ValueError, match="anatomy"):
        protocol_dict(cfg, 5, 1)


@pytest.mark.parametrize("edit, words", [
    ({"dataset": {"teacher_refine": 2.0}}, "teacher_refine"),
    ({"probe": {"rigid_share": 0.5}}, "rigid_share = 1"),
])
def test_what_the_p2_teacher_does_not_solve_is_refused_in_the_config(p2_fresh, edit, words):
    with pytest.raises(InputError, match=words):
        edit_config(p2_fresh, **edit)
        load_config(p2_fresh)


def test_a_case_of_several_materials_is_refused_before_any_work(ucdavis_dir, tmp_path):
    """The P2 FE has one material: a case of fat and gland is refused by `generate`, naming
    the teacher, before a worker starts."""
    from biopsynav.cli import main

    case_dir = tmp_path / "ud"
    assert main(["init", str(case_dir), "--surface", str(ucdavis_dir / "volmesh3.vtk"),
                 "--tissue-labels", "1=fat,2=gland,3=fat", "--cell-size", "15"]) == 0
    edit_config(case_dir, probe={"rigid_share": 1.0}, dataset={"teacher": "p2"})
    with pytest.raises(InputError, match="one material") as err:
        generate_case(case_dir, workers=1, progress=False)
    assert "[dataset] teacher" in str(err.value)
    assert not (case_dir / "dataset.zarr").exists()


def test_the_cost_benchmark_times_a_local_cluster_and_extrapolates(base_case, tmp_path):
    """``benchmarks/p2_teacher.py`` on the coarse phantom: its pushes solved through a
    LocalCluster, per-push figures, and the larger clusters' wall times from them
    (``N (solve + overhead) / workers``)."""
    import subprocess
    import sys

    from tests.runs import BENCHMARKS, run_benchmark

    out, values = run_benchmark("p2_teacher.py", [str(base_case), "--samples", "3", "--workers",
                                                "1", "--fine", "12", "--size", "25",
                                                "--no-result-file"], tmp_path)
    assert "push_s_mean" in values
    push, overhead = float(values["push_s_expected"]), float(values["overhead_s"])
    assert push > 0 and overhead >= 0
    assert float(values["est_16w_400_min"]) == pytest.approx(
        400 * (push + overhead) / 16 / 60, rel=0.02, abs=0.1)
    assert "3 pushes" in out
    bad = subprocess.run([sys.executable, str(BENCHMARKS / "p2_teacher.py"), "--fine", "20",
                          "--size", "10"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--fine <= --size" in bad.stderr


def test_the_cost_benchmark_reads_a_stored_p2_data_set(p2_reference, base_case, tmp_path):
    """``p2_teacher.py --store``: the pushes a P2 data set holds, none solved; the estimate
    from their fit over the protocol's depths (a push's time grows with its depth); a data
    set of another teacher refused."""
    import subprocess
    import sys

    import numpy as np
    import zarr
    from tests.runs import BENCHMARKS, run_benchmark

    from biopsynav.config import load_config
    from biopsynav.runtime import p2_push_seconds

    out, values = run_benchmark("p2_teacher.py", ["--store", str(p2_reference),
                                                "--no-result-file"], tmp_path)
    assert f"{N} pushes" in out and "read from" in out
    g = zarr.open_group(str(p2_reference / "dataset.zarr"), mode="r")
    seconds, depth = np.asarray(g["solve_s"][...]), np.asarray(g["probe_disp_mm"][...])
    assert float(values["push_s_mean"]) == pytest.approx(seconds.mean(), abs=0.05)
    b, ln_a = np.polyfit(depth, np.log(seconds), 1)
    expected = p2_push_seconds(load_config(p2_reference).probe.max_push_mm,
                               (float(np.exp(ln_a)), float(b)))
    assert float(values["push_s_expected"]) == pytest.approx(expected, rel=0.01, abs=0.05)
    assert float(values["est_64w_400_min"]) == pytest.approx(400 * expected / 64 / 60,
                                                             rel=0.02, abs=0.1)
    bad = subprocess.run([sys.executable, str(BENCHMARKS / "p2_teacher.py"), "--store",
                          str(base_case), "--no-result-file"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 1 and "not a P2 teacher's data set" in bad.stderr


def test_a_push_the_p2_teacher_does_not_answer_is_recorded_as_not_converged(p2_base,
                                                                            monkeypatch):
    """An element inverting (or the time limit passing) in the P2 push is a draw that did
    not converge, named after the teacher, which the run then redraws; its record keeps the
    push's depth."""
    from biopsynav.dataset import worker

    def inverted(*args, **kwargs):
        raise FloatingPointError("an element inverted")

    from biopsynav.dataset.generate import _failure_record

    monkeypatch.setattr(TetReference, "push", inverted)
    case = Case.load(p2_base)
    ctx = SampleContext(case)
    result = worker.compute_sample(ctx, 0, 0)
    assert not result["ok"] and result["kind"] == worker.NOT_CONVERGED
    assert result["error"] == "P2 teacher: an element inverted"
    # the failures log says how deep the push was: what sets a rigid push's cost
    push = push_for_sample(case.anatomy, case.cfg.probe, case.cfg.dataset.seed, 0, 0,
                           ctx.centers, pinned=ctx.pinned, training=True)
    assert _failure_record(result)["push_mm"] == pytest.approx(push.push_mm, abs=1e-3)


@pytest.mark.parametrize("limit, given", [(1800.0, 1800.0), (90.0, 90.0), (0.0, None)])
def test_the_p2_push_limit_is_the_configs_and_part_of_the_protocol(p2_fresh, monkeypatch,
                                                                    limit, given):
    """``[dataset] teacher_push_limit_s`` bounds each P2 push (0: no limit) and is recorded in
    the data set's protocol (the default's as before); ``[refine]``'s reaches the refine case."""
    from biopsynav.dataset import worker
    from biopsynav.dataset.converged import P2Teacher
    from biopsynav.refine import refined_config

    edit_config(p2_fresh, dataset={"teacher_push_limit_s": limit})
    case = Case.load(p2_fresh)
    assert P2Teacher.protocol(case.cfg, case.anatomy)["push_limit_s"] == given
    seen = []

    def timed_out(self, *args, time_limit_s=None, cpu_time=False, **kwargs):
        seen.append(time_limit_s)
        assert cpu_time  # the worker's CPU time: what else the machine runs does not count
        raise PushTimeout("the push ran past its time limit")

    monkeypatch.setattr(TetReference, "push", timed_out)
    result = worker.compute_sample(SampleContext(case), 0, 0)
    assert seen == [given] and result["kind"] == worker.NOT_CONVERGED
    edit_config(p2_fresh, refine={"teacher_push_limit_s": limit, "teacher": "p2"})
    refined = refined_config(load_config(p2_fresh))
    assert refined.dataset.teacher_push_limit_s == limit
