"""Data generation: contract, determinism across workers and Dask, kills, failures, guards."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from dataset_helpers import N_TEST, N_TRAIN, edit_config, generate_through_local_cluster

from biopsynav.case import Case
from biopsynav.contact.greens import ContactCompliance
from biopsynav.dataset.generate import generate_case
from biopsynav.errors import BiopsynavError, FingerprintError, InputError
from biopsynav.grid.embedding import Embedding
from biopsynav.grid.index import tensor_to_field
from biopsynav.probe import contact_input, probe_patch, push_for_sample

N = N_TRAIN + N_TEST

SCRIPT = """
import faulthandler
import sys
from biopsynav.dataset.generate import generate_case

if __name__ == "__main__":
    # a run that hangs prints every thread's stack and exits: the test shows where it hung
    faulthandler.dump_traceback_later(100, exit=True)
    generate_case(sys.argv[1], workers=int(sys.argv[2]), progress=False)
"""


def open_data(case_dir: Path):
    return zarr.open_group(str(case_dir / "dataset.zarr"), mode="r")


def count_done(case_dir: Path) -> int:
    """Chunk files of the ``done`` array: a cheap progress signal while a run writes (a file
    a kill cuts short counts here but reads as not done)."""
    chunks = case_dir / "dataset.zarr" / "done" / "c"
    return len(list(chunks.iterdir())) if chunks.is_dir() else 0


def samples_done(case_dir: Path) -> int:
    """Samples marked done as a resuming run reads them (after a kill: what it keeps)."""
    return int(np.asarray(open_data(case_dir)["done"][:], dtype=bool).sum())


def child_pids(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(t) for t in text]
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def start_generate(case_dir: Path, tmp_path: Path, workers: int) -> subprocess.Popen:
    script = tmp_path / "gen.py"
    script.write_text(SCRIPT)
    return subprocess.Popen([sys.executable, str(script), str(case_dir), str(workers)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def wait_for_done(proc: subprocess.Popen, case_dir: Path, count: int) -> None:
    deadline = time.monotonic() + 120
    while count_done(case_dir) < count:
        if proc.poll() is not None:
            pytest.fail(f"generate exited early: {proc.stderr.read().decode()[-2000:]}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("no progress within 120 s")
        time.sleep(0.005)


def test_contract_of_the_stored_samples(reference):
    g = open_data(reference)
    case = Case.load(reference)
    shape = case.grid.node_shape
    assert g["inputs"].shape == (N, 4, *shape) and g["inputs"].dtype == np.float32
    assert g["targets"].shape == (N, 3, *shape) and g["targets"].dtype == np.float32
    assert g["done"].shape == (N,) and g["done"].chunks == (1,) and g["done"][:].all()
    assert g["inputs"].chunks[0] == 1
    assert np.array_equal(g["active_nodes"][:], case.grid.active_nodes)
    attrs = g.attrs
    assert (attrs["n_train"], attrs["n_test"]) == (N_TRAIN, N_TEST)
    assert attrs["fingerprint"] == case.fingerprint()
    assert list(attrs["node_shape"]) == list(shape)
    assert len(attrs["protocol_fingerprint"]) == 64
    for name in ("center", "long_axis", "direction"):
        assert g[name].shape == (N, 3)
    for name in ("vertex", "force_n", "tilt_deg", "n_contact", "attempt", "max_disp_mm",
                 "probe_disp_mm", "newton_iters", "residual", "solve_s"):
        assert g[name].shape == (N,)
    summary = json.loads((reference / "dataset_summary.json").read_text())
    assert summary["count"] == N and summary["failures"] == 0
    assert summary["max_disp_mm"] > 0 and summary["samples_per_min"] > 0
    assert (reference / "dataset.png").stat().st_size > 1000

    skin = Embedding.build(case.grid, case.anatomy.vertices).matrix
    inactive = ~case.grid.active_nodes
    probe = case.cfg.probe
    assert case.cfg.dataset.contact_input == "elastic"
    compliance = ContactCompliance.from_case(case)
    for i in (0, N - 1):
        u = tensor_to_field(g["targets"][i]).astype(np.float64)
        assert np.all(g["targets"][i][:, inactive] == 0)
        push = push_for_sample(case.anatomy, probe, case.cfg.dataset.seed, i,
                               int(g["attempt"][i]), training=i < N_TRAIN)
        assert int(g["vertex"][i]) == push.vertex and g["force_n"][i] == push.force_n
        contact = probe_patch(case.anatomy, push.vertex, push.long_axis, probe.footprint_mm,
                              probe.depth_tolerance_mm)
        assert g["n_contact"][i] == len(contact)
        w = skin[contact]
        expected = contact_input(w, w @ u, "elastic", compliance)
        got = tensor_to_field(g["inputs"][i])
        assert np.allclose(got, expected, rtol=1e-4, atol=1e-4)
        assert np.isclose(g["probe_disp_mm"][i], np.linalg.norm(w @ u, axis=1).mean(),
                          rtol=1e-4)
        assert np.isclose(g["max_disp_mm"][i], np.linalg.norm(u, axis=1).max(), rtol=1e-4)


def test_one_worker_gives_the_same_samples_as_two(fresh_case, reference, assert_same_dataset):
    summary = generate_case(fresh_case, workers=1, progress=False)
    assert summary["count"] == N
    assert_same_dataset(fresh_case, reference)


def test_dask_local_cluster_gives_the_same_samples(fresh_case, reference,
                                                  assert_same_dataset):
    summary = generate_through_local_cluster(fresh_case)
    assert summary["count"] == N
    assert_same_dataset(fresh_case, reference)


def test_resume_after_sigkill_of_the_main_process(fresh_case, reference, tmp_path,
                                                  assert_same_dataset):
    proc = start_generate(fresh_case, tmp_path, workers=1)
    wait_for_done(proc, fresh_case, 3)
    children = child_pids(proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    at_kill = samples_done(fresh_case)
    assert at_kill < N, "the kill came too late to interrupt the run"
    deadline = time.monotonic() + 30
    while any(alive(p) for p in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(p) for p in children), "orphaned worker processes"
    summary = generate_case(fresh_case, workers=2, progress=False)
    assert summary["count"] == N
    assert summary["computed_this_run"] == N - at_kill
    assert_same_dataset(fresh_case, reference)


def test_a_dead_worker_is_noticed_when_no_future_says_so(fresh_case, monkeypatch):
    """A worker killed at the wrong moment can leave the executor's futures pending for ever;
    the local runner's wait then notices the dead process itself (BrokenProcessPool, which
    the main loop answers by restarting the pool) instead of waiting for ever."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from biopsynav.dataset import generate, pool
    from biopsynav.dataset.worker import WorkerSpec

    monkeypatch.setattr(pool, "WORKER_WATCH_S", 0.2)
    runner = generate.LocalRunner(WorkerSpec(Case.load(fresh_case), "key"), 1)
    try:
        assert runner.submit(0, 0).result(timeout=120)["index"] == 0  # the worker is up
        never = Future()  # a future no worker will ever finish
        assert runner.wait_any([never, runner.submit(1, 0)])  # a live worker: its result
        pid = runner.processes.processes()[0].pid
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        outcome: list[BaseException] = []

        def wait_for_never() -> None:
            try:
                runner.wait_any([never])
            except BrokenProcessPool as exc:
                outcome.append(exc)

        waiter = threading.Thread(target=wait_for_never, daemon=True)
        waiter.start()
        waiter.join(60)
        assert not waiter.is_alive(), "the wait did not notice the dead worker"
        assert len(outcome) == 1 and str(pid) in str(outcome[0])
    finally:
        runner.close()


def test_a_killed_worker_is_replaced(fresh_case, reference, tmp_path, assert_same_dataset):
    proc = start_generate(fresh_case, tmp_path, workers=2)
    wait_for_done(proc, fresh_case, 2)
    workers = [p for p in child_pids(proc.pid)
               if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
    assert workers
    at_kill = count_done(fresh_case)  # the run goes on writing: files, not their contents
    os.kill(workers[0], signal.SIGKILL)
    assert proc.wait(timeout=120) == 0, proc.stderr.read().decode()  # whole: a stack dump
    summary = json.loads((fresh_case / "dataset_summary.json").read_text())
    assert summary["count"] == N
    if at_kill < N:
        assert summary["pool_restarts"] >= 1
    assert_same_dataset(fresh_case, reference)


def test_failed_solves_are_logged_and_replaced(fresh_case):
    # no load stepping and few Newton iterations: the harder pushes fail
    edit_config(fresh_case, solver={"max_iterations": 8, "min_load_step": 1.0},
                dataset={"max_failure_share": 1.0})
    summary = generate_case(fresh_case, workers=2, progress=False)
    assert summary["count"] == N
    assert summary["failures"] >= 1 and summary["failures"] == summary["failures_total"]
    g = open_data(fresh_case)
    attempts = g["attempt"][:]
    failed = {(f["index"], f["attempt"]) for f in g.attrs["failures"]}
    assert len(failed) == summary["failures"]
    for f in g.attrs["failures"]:
        assert f["kind"] == "not_converged"
        assert "converge" in f["error"] or "Newton" in f["error"]
        assert f["last_iterations"] and f["newton_iters"] >= 1
    for i in range(N):  # every earlier attempt of a sample failed; the kept one is its own
        assert {(i, a) for a in range(attempts[i])} <= failed
    case = Case.load(fresh_case)
    replaced = np.flatnonzero(attempts > 0)
    assert replaced.size
    for i in replaced:
        push = push_for_sample(case.anatomy, case.cfg.probe, case.cfg.dataset.seed, i,
                               int(attempts[i]), training=i < N_TRAIN)
        assert g["force_n"][i] == push.force_n


def generate_with_half_the_pushes_too_deep(fresh_case, reference, redraw: str):
    """``fresh_case`` generated with the reference's median probe displacement as the depth
    limit and ``[probe] too_deep_redraw = redraw``: (summary, store, reference store, limit)."""
    ref = open_data(reference)
    limit = float(np.median(ref["probe_disp_mm"][:]))  # about half the pushes go deeper
    edit_config(fresh_case, probe={"max_push_mm": limit, "too_deep_redraw": redraw},
                dataset={"max_failure_share": 1.0})
    summary = generate_case(fresh_case, workers=2, progress=False)
    return summary, open_data(fresh_case), ref, limit


def check_too_deep_log(summary, g, ref, limit) -> set:
    """Every kept push within ``limit``, every earlier draw logged as what it was; the logged
    draws' keys (index, attempt, redraw)."""
    disp, attempts = g["probe_disp_mm"][:], g["attempt"][:]
    ref_disp = ref["probe_disp_mm"][:]
    assert summary["count"] == N and disp.max() <= limit
    deep = [f for f in g.attrs["failures"] if f["kind"] == "too_deep"]
    assert len(deep) == summary["too_deep"] == summary["too_deep_total"] >= (ref_disp > limit).sum()
    assert all(f["probe_disp_mm"] > limit and "max_push_mm" in f["error"] for f in deep)
    logged = {(f["index"], f["attempt"]) for f in g.attrs["failures"]}
    for i in range(N):  # every earlier draw of a sample is logged; a kept shallow push unchanged
        assert {(i, a) for a in range(attempts[i])} <= logged
        if ref_disp[i] <= limit:
            assert attempts[i] == ref["attempt"][i]
            assert np.array_equal(g["targets"][i], ref["targets"][i])
    # the summary's max probe displacement, and the histogram, are of the kept pushes
    assert summary["max_probe_disp_mm"] <= round(limit, 4) + 1e-4
    return {(f["index"], f["attempt"], f.get("redraw", 0)) for f in g.attrs["failures"]}


def test_pushes_deeper_than_the_limit_are_redrawn_elsewhere(fresh_case, reference):
    summary, g, ref, limit = generate_with_half_the_pushes_too_deep(fresh_case, reference,
                                                                    "elsewhere")
    logged = check_too_deep_log(summary, g, ref, limit)
    assert all(redraw == 0 for _, _, redraw in logged)
    deep = ref["probe_disp_mm"][:] > limit
    assert (g["attempt"][:][deep] > ref["attempt"][:][deep]).all()  # each moved to a new draw


def test_training_pushes_deeper_than_the_limit_are_redrawn_weaker_at_the_same_place(
        fresh_case, reference):
    """[probe] too_deep_redraw = "same-place": a too-deep training push keeps its patch and gets
    a weaker force, logged redraw by redraw; held-out pushes move elsewhere."""
    from biopsynav.probe import weaker_push

    summary, g, ref, limit = generate_with_half_the_pushes_too_deep(fresh_case, reference,
                                                                    "same-place")
    logged = check_too_deep_log(summary, g, ref, limit)
    case = Case.load(fresh_case)
    deep = np.flatnonzero(ref["probe_disp_mm"][:] > limit)
    kept_in_place = [i for i in deep if i < N_TRAIN and g["attempt"][i] == ref["attempt"][i]]
    assert kept_in_place and all(g["attempt"][i] > ref["attempt"][i] for i in deep
                                 if i >= N_TRAIN)
    for i in kept_in_place:  # the same patch, a force the logged redraws reproduce
        a = int(g["attempt"][i])
        redraws = max(r for j, att, r in logged if (j, att) == (i, a)) + 1
        push = push_for_sample(case.anatomy, case.cfg.probe, case.cfg.dataset.seed, i, a,
                               training=True)
        for k in range(1, redraws + 1):
            push = weaker_push(push, case.cfg.probe, case.cfg.dataset.seed, i, k)
        assert g["vertex"][i] == ref["vertex"][i] and g["n_contact"][i] == ref["n_contact"][i]
        assert g["force_n"][i] == push.force_n < ref["force_n"][i]


def test_too_many_deep_pushes_stop_the_job(fresh_case):
    edit_config(fresh_case, probe={"max_push_mm": 0.5}, dataset={"max_failure_share": 0.25})
    with pytest.raises(BiopsynavError, match=r"deeper than \[probe\] max_push_mm.*lower f_max_n"):
        generate_case(fresh_case, workers=1, progress=False)


def test_too_many_failures_stop_the_job(fresh_case):
    edit_config(fresh_case, solver={"max_iterations": 1, "min_load_step": 1.0},
                dataset={"max_failure_share": 0.25})
    with pytest.raises(BiopsynavError, match="did not converge"):
        generate_case(fresh_case, workers=1, progress=False)
    assert len(open_data(fresh_case).attrs["failures"]) > 0.25 * N


def _edge_stretches(case_dir: Path) -> np.ndarray:
    """The largest cell-edge stretch of every stored sample (n,)."""
    from biopsynav.fem import FEModel, largest_edge_stretch

    model = FEModel.from_case(Case.load(case_dir))
    targets = open_data(case_dir)["targets"]
    return np.array([largest_edge_stretch(model, tensor_to_field(np.asarray(t, np.float64)))
                     for t in targets])


def test_implausible_solutions_are_logged_and_redrawn(fresh_case, reference):
    """With [dataset] max_edge_stretch below half the reference's samples, those draws are
    logged as 'implausible' with the stretch named, redrawn, and no kept sample exceeds it;
    the limit is part of the protocol (the default is not, as before the check)."""
    from biopsynav.dataset.store import protocol_dict

    stretch = _edge_stretches(reference)
    limit = float(np.median(stretch))
    edit_config(fresh_case, dataset={"max_edge_stretch": limit, "max_failure_share": 1.0})
    summary = generate_case(fresh_case, workers=2, progress=False)
    bad = [f for f in open_data(fresh_case).attrs["failures"] if f["kind"] == "implausible"]
    assert len(bad) == summary["implausible"] == summary["implausible_total"]
    assert len(bad) >= (stretch > limit + 1e-4).sum() > 0
    assert all("max_edge_stretch" in f["error"] and "times its rest length" in f["error"]
               for f in bad)
    assert _edge_stretches(fresh_case).max() <= limit + 1e-4
    cfg = Case.load(fresh_case).cfg
    assert protocol_dict(cfg, N_TRAIN, N_TEST)["dataset"]["max_edge_stretch"] == limit
    cfg.dataset.max_edge_stretch = 8.0
    assert "max_edge_stretch" not in protocol_dict(cfg, N_TRAIN, N_TEST)["dataset"]


def test_too_many_implausible_solutions_stop_the_job(fresh_case):
    edit_config(fresh_case, dataset={"max_edge_stretch": 1.0, "max_failure_share": 0.25})
    with pytest.raises(BiopsynavError, match="states no tissue reaches.*max_edge_stretch"):
        generate_case(fresh_case, workers=1, progress=False)


def test_guard_against_mixing(reference, tmp_path):
    case_dir = tmp_path / "case"
    shutil.copytree(reference, case_dir)
    # a tracker-only setting does not invalidate the data
    edit_config(case_dir, probe={"contact_tolerance_mm": 3.0})
    assert generate_case(case_dir, workers=1, progress=False)["computed_this_run"] == 0
    edit_config(case_dir, probe={"f_max_n": 2.0})
    with pytest.raises(FingerprintError, match=r"another protocol.*f_max_n \(data set [\d.]+, "
                       r"case 2\.0\).*--overwrite.*in case\.toml to keep it"):
        generate_case(case_dir, workers=1, progress=False)
    with pytest.raises(FingerprintError, match="n_train"):  # growing is tests/dataset/test_grow.py
        generate_case(case_dir, workers=1, progress=False, n_train=N_TRAIN - 1)
    summary = generate_case(case_dir, workers=1, progress=False, overwrite=True, n_train=2,
                            n_test=1)
    assert summary["count"] == 3 and open_data(case_dir).attrs["n_train"] == 2
    group = zarr.open_group(str(case_dir / "dataset.zarr"), mode="r+")
    group.attrs["fingerprint"] = "0" * 64
    with pytest.raises(FingerprintError, match="another anatomy or grid"):
        generate_case(case_dir, workers=1, progress=False, n_train=2, n_test=1)


@pytest.mark.parametrize("damage", ["garbage", "foreign", "file", "missing_array"])
def test_corrupt_or_foreign_store_is_refused(reference, tmp_path, damage):
    case_dir = tmp_path / "case"
    shutil.copytree(reference, case_dir)
    path = case_dir / "dataset.zarr"
    if damage == "garbage":
        (path / "zarr.json").write_text("{not json")
    elif damage == "foreign":
        shutil.rmtree(path)
        zarr.open_group(str(path), mode="w").attrs["made_by"] = "someone else"
    elif damage == "file":
        shutil.rmtree(path)
        path.write_text("hello")
    else:
        shutil.rmtree(path / "targets")
    with pytest.raises(InputError, match="--overwrite"):
        generate_case(case_dir, workers=1, progress=False)


def test_training_samples_draw_their_force_by_the_exponent_and_scale(fresh_case):
    """With [probe] train_force_exponent and train_force_scale the training samples (below the
    data set's own n_train, here a generate override) draw s f_max u^e, the held-out ones the
    uniform force in [0, f_max]; both are part of the protocol, and their former values (1,
    the paper's uniform force) are not (as before the keys)."""
    from biopsynav.dataset.store import protocol_dict

    edit_config(fresh_case, probe={"train_force_exponent": 0.5, "train_force_scale": 1.5},
                dataset={"max_failure_share": 1.0})
    generate_case(fresh_case, workers=1, progress=False, n_train=3, n_test=2)
    g = open_data(fresh_case)
    case = Case.load(fresh_case)
    probe, seed = case.cfg.probe, case.cfg.dataset.seed
    for i in range(5):
        attempt = int(g["attempt"][i])
        push = push_for_sample(case.anatomy, probe, seed, i, attempt, training=i < 3)
        uniform = push_for_sample(case.anatomy, probe, seed, i, attempt)
        assert g["force_n"][i] == push.force_n
        assert (push.force_n > uniform.force_n) == (i < 3)
    assert g.attrs["protocol"]["probe"]["train_force_exponent"] == 0.5
    assert g.attrs["protocol"]["probe"]["train_force_scale"] == 1.5
    case.cfg.probe.train_force_exponent = case.cfg.probe.train_force_scale = 1.0
    assert not {"train_force_exponent", "train_force_scale"} & set(
        protocol_dict(case.cfg, 3, 2)["probe"])
    edit_config(fresh_case, probe={"train_force_exponent": 1.0})  # left out: read as 1.0
    with pytest.raises(FingerprintError, match=r"train_force_exponent \(data set 0\.5, case "
                       r"1\.0\)"):
        generate_case(fresh_case, workers=1, progress=False, n_train=3, n_test=2)
    edit_config(fresh_case, probe={"train_force_exponent": 0.5, "train_force_scale": 1.0})
    with pytest.raises(FingerprintError, match=r"train_force_scale \(data set 1\.5, case "
                       r"1\.0\)"):
        generate_case(fresh_case, workers=1, progress=False, n_train=3, n_test=2)
