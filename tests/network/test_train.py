"""Training: learns, resumes exactly, deterministic, survives kill -9."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import biopsynav.network.train as T
from biopsynav.errors import InputError, TrainingError
from biopsynav.network.data import load_dataset
from biopsynav.network.train import CHECKPOINT, batch_indices, lr_at, train, use_bf16

from .conftest import tiny_settings


def test_training_reduces_error(trained):
    case, summary = trained
    data = load_dataset(case)
    y = data.targets[data.test_idx]
    baseline = float(torch.linalg.vector_norm(y, dim=1)[:, data.active].mean())  # zero guess
    assert summary.finished and summary.iterations_done == 300
    assert summary.best_val_e_mm < 0.75 * baseline
    hist = json.loads((case / "model" / "history.json").read_text())
    assert hist[-1]["train_loss"] < 0.7 * hist[0]["train_loss"]
    for name in ("checkpoint.pt", "best.pt", "model.ts", "model.onnx", "meta.json",
                 "loss_curve.png"):
        assert (case / "model" / name).is_file(), name


def test_the_loss_curve_is_drawn_every_interval_and_when_the_training_stops(synth_case,
                                                                              tmp_path,
                                                                              monkeypatch):
    """Drawn at a validation only once ``LOSS_CURVE_INTERVAL_S`` has passed since the last
    drawing, and always when the run ends or stops, with the whole history so far."""
    import biopsynav.network.plots as plots
    import biopsynav.network.train as train_mod

    drawn = []
    monkeypatch.setattr(plots, "plot_loss_curve", lambda h, path: drawn.append(len(h)))
    s = tiny_settings(iterations=12, val_interval=4)
    monkeypatch.setattr(train_mod, "LOSS_CURVE_INTERVAL_S", 1e9)  # never due at a validation
    train(synth_case, settings=s, model_dir=tmp_path / "a", progress=False, stop_after=9)
    assert drawn == [2]  # validations at 4 and 8, drawn when the run stopped at 9
    drawn.clear()
    monkeypatch.setattr(train_mod, "LOSS_CURVE_INTERVAL_S", 0.0)
    train(synth_case, settings=s, model_dir=tmp_path / "b", progress=False, stop_after=11)
    assert drawn == [1, 2, 2]  # at every validation, then when the run stopped


def test_first_samples_trains_on_the_first_training_samples_only(synth_case, tmp_path):
    """A data-size study: the model records how many samples taught it, and a checkpoint of
    another count is not resumed."""
    import json

    from biopsynav.network.data import load_dataset

    total = int(load_dataset(synth_case).train_idx.numel())
    s = tiny_settings(iterations=4, val_interval=2)
    train(synth_case, settings=s, model_dir=tmp_path, progress=False, first_samples=3)
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["training"]["n_train"] == 3 < total
    summary = train(synth_case, settings=s, model_dir=tmp_path, progress=False)
    assert json.loads((tmp_path / "meta.json").read_text())["training"]["n_train"] == total
    assert summary.resumed_from is None or summary.resumed_from == 0
    before = (tmp_path / "meta.json").read_bytes()
    for bad in (0, -3):  # refused before any work; the model written stays
        with pytest.raises(InputError, match="first_samples must be >= 1"):
            train(synth_case, settings=s, model_dir=tmp_path, progress=False,
                  first_samples=bad)
    assert (tmp_path / "meta.json").read_bytes() == before


def test_schedule_and_batches_are_pure_functions():
    s = tiny_settings(iterations=100, warmup_iterations=10, learning_rate=1.0)
    assert lr_at(0, s) == 0.1 and lr_at(9, s) == 1.0
    assert abs(lr_at(99, s) - 0.01) < 0.01
    seen = torch.cat([batch_indices(i, 4, 10, 3) for i in range(5)])  # two epochs of 10
    assert sorted(seen[:10].tolist()) == list(range(10))
    assert sorted(seen[10:].tolist()) == list(range(10))
    assert torch.equal(batch_indices(3, 4, 10, 3), batch_indices(3, 4, 10, 3))


def _weights(model_dir: Path) -> dict:
    return torch.load(model_dir / CHECKPOINT, weights_only=False)["model"]


def test_resume_equals_uninterrupted_and_is_deterministic(synth_case, tmp_path):
    s = tiny_settings(iterations=50, val_interval=20)
    full = train(synth_case, settings=s, model_dir=tmp_path / "a", progress=False)
    again = train(synth_case, settings=s, model_dir=tmp_path / "b", progress=False)
    part = train(synth_case, settings=s, model_dir=tmp_path / "c", progress=False,
                 stop_after=27)
    assert not part.finished and part.iterations_done == 27
    assert not (tmp_path / "c" / "meta.json").exists()
    rest = train(synth_case, settings=s, model_dir=tmp_path / "c", progress=False)
    assert rest.resumed_from == 27 and rest.finished
    wa, wb, wc = (_weights(tmp_path / d) for d in "abc")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k  # deterministic for a seed
        assert torch.equal(wa[k], wc[k]), k  # resumed == uninterrupted
    assert rest.best_val_e_mm == full.best_val_e_mm == again.best_val_e_mm
    ha = json.loads((tmp_path / "a" / "history.json").read_text())
    hc = json.loads((tmp_path / "c" / "history.json").read_text())
    assert [h["train_loss"] for h in ha] == [h["train_loss"] for h in hc]


def test_changed_settings_train_afresh(synth_case, tmp_path):
    s = tiny_settings(iterations=20, val_interval=10)
    train(synth_case, settings=s, model_dir=tmp_path, progress=False, stop_after=10)
    r = train(synth_case, settings=tiny_settings(iterations=20, val_interval=10, seed=5),
              model_dir=tmp_path, progress=False)
    assert r.resumed_from == 0 and r.finished


SCRIPT = """
import sys
from biopsynav.network.train import train
from tests.network.conftest import tiny_settings
s = tiny_settings(iterations=int(sys.argv[3]), val_interval=5)
r = train(sys.argv[1], settings=s, model_dir=sys.argv[2], progress=False)
print("RESUMED", r.resumed_from, r.finished)
"""


def test_kill_9_then_rerun_continues(synth_case, tmp_path):
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(repo) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-c", SCRIPT, str(synth_case), str(tmp_path), "100000"]
    proc = subprocess.Popen(cmd, env=env, cwd=repo, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    ckpt = tmp_path / CHECKPOINT
    deadline = time.time() + 60
    while time.time() < deadline and not ckpt.exists():
        time.sleep(0.2)
    time.sleep(0.5)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert ckpt.exists(), "no checkpoint within 60 s"
    done = torch.load(ckpt, weights_only=False)["state"]["iteration"]
    assert done >= 5
    # a kill during an atomic write leaves its temporary file; the rerun removes it
    (tmp_path / f".{CHECKPOINT}.killed.tmp").write_bytes(b"half a checkpoint")
    # same run with the same settings would go on for 100000 iterations: check it resumes by
    # continuing the same signature for a few more steps through stop_after
    r = train(synth_case, settings=tiny_settings(iterations=100000, val_interval=5),
              model_dir=tmp_path, progress=False, stop_after=done + 5)
    assert r.resumed_from == done and r.iterations_done == done + 5
    assert not list(tmp_path.glob(".*.tmp")), "temporary files left behind"
    assert np.isfinite(r.best_val_e_mm)


def test_model_files_name_every_file_training_writes(trained):
    from biopsynav.network.train import MODEL_FILES

    case, _ = trained
    written = {p.name for p in (case / "model").iterdir()}
    assert written == set(MODEL_FILES)


@pytest.mark.skipif(not Path("/proc/stat").exists(), reason="needs Linux /proc/stat")
def test_auto_threads_sees_a_busy_core():
    from biopsynav.threads import _busy_cores, auto_threads

    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        busy = _busy_cores(0.5)
        threads = auto_threads(0.5)
    finally:
        spinner.kill()
        spinner.wait()
    cores = os.cpu_count() or 1
    assert busy is not None and 0.6 <= busy <= cores + 0.01
    assert 1 <= threads <= max(1, cores - 1 + (cores == 1))


THREADS_AFTER_FE = """
import sys, numba, torch
from biopsynav.fem.solver import compile_kernels
from biopsynav.threads import set_threads
torch.get_num_threads()  # torch's own pool started, as in a run that has used torch
if sys.argv[1] == "set_threads":
    set_threads(1)
else:
    torch.set_num_threads(1)
compile_kernels()  # the process's first parallel numba kernel: one FE solve
print(torch.get_num_threads(), numba.threading_layer())
"""


def threads_after_fe_kernels(how: str) -> tuple[int, str]:
    """(torch's thread count, numba's threading layer) in a fresh process that set one
    thread ``how`` ('set_threads' or 'torch') and then ran the FE kernels."""
    out = subprocess.run([sys.executable, "-c", THREADS_AFTER_FE, how], capture_output=True,
                         text=True, timeout=300, check=True).stdout.split()
    return int(out[-2]), out[-1]


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs 2 cores")
def test_one_training_thread_stays_one_after_the_fe_kernels_start_their_pool():
    """numba's OpenMP pool, started by the first FE kernel, sets the OpenMP thread count
    that PyTorch reads to every core (the hazard, shown on torch's own setter); a count set
    by ``set_threads`` survives it (a training beside a busy core ran 25 times slower)."""
    raw, layer = threads_after_fe_kernels("torch")
    if layer == "omp":
        assert raw > 1, raw  # the hazard that set_threads guards against
    assert threads_after_fe_kernels("set_threads")[0] == 1


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_auto_threads_does_not_count_its_own_process():
    """A thread of this process spinning while the cores are sampled is this process's
    CPU time, not another process's: it is not counted as a busy core."""
    import threading

    from biopsynav.threads import _cpu_split

    stop = threading.Event()

    def spin():
        while not stop.is_set():
            pass

    spinner = threading.Thread(target=spin)
    spinner.start()
    try:
        time.sleep(0.1)
        split = _cpu_split(0.5)
    finally:
        stop.set()
        spinner.join()
    assert split is not None
    everything, own = split
    assert own >= 0.3 and own <= everything + 0.05


def test_validation_is_the_same_in_either_memory_layout():
    from biopsynav.network.export import SurrogateNet
    from biopsynav.network.train import validate
    from biopsynav.network.unet import UNetSpec

    torch.manual_seed(0)
    shape = (8, 8, 8)
    active = torch.rand(shape) > 0.3
    net = SurrogateNet(UNetSpec(base_channels=4, levels=2), np.ones(4), np.ones(3),
                       active.numpy())
    x, y = torch.randn(5, 4, *shape), torch.randn(5, 3, *shape)
    plain = validate(net, x, y, active, batch=2)
    net.to(memory_format=torch.channels_last_3d)
    last = validate(net, x, y, active, batch=2, memory_format=torch.channels_last_3d)
    assert plain.shape == (5,) and torch.allclose(plain, last, rtol=1e-5, atol=1e-6)


def test_weight_decay_shrinks_the_weights_and_is_part_of_the_signature(synth_case, tmp_path):
    """``weight_decay`` > 0 trains with AdamW (decoupled decay): the same run ends with
    smaller weights, and a checkpoint made with another decay is not resumed."""
    def norm_after(decay: float, out: Path):
        s = tiny_settings(iterations=30, val_interval=10, weight_decay=decay)
        r = train(synth_case, settings=s, model_dir=out, progress=False)
        state = torch.load(out / CHECKPOINT, weights_only=False)["model"]
        weights = [v for k, v in state.items() if k.startswith("unet.") and k.endswith("weight")]
        return r, float(torch.sqrt(sum((w ** 2).sum() for w in weights)))

    plain, n_plain = norm_after(0.0, tmp_path / "adam")
    decayed, n_decayed = norm_after(5.0, tmp_path / "adamw")
    assert plain.finished and decayed.finished and n_decayed < 0.98 * n_plain
    s = tiny_settings(iterations=30, val_interval=10, weight_decay=0.0)
    train(synth_case, settings=s, model_dir=tmp_path / "x", progress=False, stop_after=10)
    again = train(synth_case, settings=tiny_settings(iterations=30, val_interval=10,
                                                     weight_decay=5.0),
                  model_dir=tmp_path / "x", progress=False)
    assert again.resumed_from == 0


_TRAIN_IN_A_PROCESS = """
import json, sys
from biopsynav.config import NetworkSection
from biopsynav.network.train import train
case, out, stop, kw = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), json.loads(sys.argv[4])
r = train(case, settings=NetworkSection(**kw), model_dir=out, progress=False, stop_after=stop)
print(json.dumps({"finished": r.finished, "iterations_done": r.iterations_done,
                  "resumed_from": r.resumed_from, "best_val_e_mm": r.best_val_e_mm}))
"""


def _train_in_a_process(case: Path, out: Path, settings, stop_after: int | None = None):
    """:func:`train` in a new Python process, as a user's run and its resumption are (oneDNN
    picks its convolution kernels by what the process ran before, so two trainings in one
    process that ran other convolutions first need not agree to the last bit)."""
    from types import SimpleNamespace

    args = [str(case), str(out), json.dumps(stop_after), json.dumps(dataclasses.asdict(settings))]
    done = subprocess.run([sys.executable, "-c", _TRAIN_IN_A_PROCESS, *args],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return SimpleNamespace(**json.loads(done.stdout.strip().splitlines()[-1]))


def test_training_through_the_projection_resumes_exactly(reference, tmp_path):
    """A run through the contact projection (real pushes of the generated coarse phantom),
    stopped and run again in a new process, continues from its checkpoint and ends with the
    weights of an uninterrupted run; validation is the projected e, and meta.json says it."""
    s = tiny_settings(levels=2, iterations=12, val_interval=4, warmup_iterations=2,
                      baseline="linear-elastic", contact_projection=True)
    full = _train_in_a_process(reference, tmp_path / "a", s)
    part = _train_in_a_process(reference, tmp_path / "b", s, stop_after=5)
    assert not part.finished and part.iterations_done == 5
    rest = _train_in_a_process(reference, tmp_path / "b", s)
    assert rest.resumed_from == 5 and rest.finished
    wa, wb = _weights(tmp_path / "a"), _weights(tmp_path / "b")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert rest.best_val_e_mm == full.best_val_e_mm
    meta = json.loads((tmp_path / "b" / "meta.json").read_text())
    assert meta["baseline"]["projection"] is True
    # the envelope records the deepest training push (not a held-out one)
    import zarr

    g = zarr.open_group(str(reference / "dataset.zarr"), mode="r")
    n_train = int(g.attrs["n_train"])
    assert meta["envelope"]["max_probe_disp_mm"] == float(g["probe_disp_mm"][:n_train].max())


def test_precision_setting_picks_the_forward_arithmetic(monkeypatch):
    """'auto' is bf16 on CUDA, fp32 on a CPU without AMX-BF16 or AVX-512 BF16, and on one
    with them the faster of the two by a timed step (bf16 only when clearly faster), or the
    arithmetic of the checkpoint it resumes; the CPU trains channels-last in either; the
    first line names the unit and why."""
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    spec = T.UNetSpec()
    for unit in ("AMX-BF16 tiles", "AVX-512 BF16", None):
        monkeypatch.setattr(T, "cpu_bf16_unit", lambda unit=unit: unit)
        assert use_bf16("bf16", cpu) and not use_bf16("fp32", cpu) and not use_bf16("fp32", cuda)
        assert use_bf16("auto", cuda) and use_bf16("auto", cpu) == (unit is not None)
        assert T.training_layout(cpu) == torch.channels_last_3d
        assert T.training_layout(cuda) == torch.contiguous_format
        line = T.precision_line(True, cpu)
        assert (f"bf16 autocast on {unit}," in line) if unit else "emulated" in line
        assert ("neither AMX-BF16 nor AVX-512 BF16" in T.precision_line(False, cpu)) == \
            (unit is None)
        for fp32_ms, bf16_ms, amp in ((80.0, 110.0, False), (80.0, 60.0, True),
                                      (80.0, 75.0, False)):  # a near tie keeps fp32
            monkeypatch.setattr(T, "timed_steps_ms", lambda *a, t=(fp32_ms, bf16_ms): t)
            choice = T.choose_precision("auto", cpu, spec, (8, 8, 8), 4)
            assert choice.amp == (amp and unit is not None)
            if unit is not None:
                assert choice.record() == {"precision": "bf16" if amp else "fp32",
                                           "precision_step_ms": {"fp32": fp32_ms,
                                                                 "bf16": bf16_ms}}
                assert f"{bf16_ms:.0f} ms in bf16 against {fp32_ms:.0f} in fp32" in \
                    T.precision_line(choice, cpu)
            for resumed in (True, False):
                kept = T.choose_precision("auto", cpu, spec, (8, 8, 8), 4, resumed)
                assert kept.amp == (resumed and unit is not None)
        assert T.choose_precision("bf16", cpu, spec, (8, 8, 8), 4).amp
        assert not T.choose_precision("fp32", cpu, spec, (8, 8, 8), 4).amp
        assert T.choose_precision("auto", cuda, spec, (8, 8, 8), 4).amp


def test_the_timed_step_is_finite_and_leaves_the_random_stream_alone():
    """The step ``auto`` times runs in both arithmetics and does not move torch's random
    generator (the training's seed decides its draws, timed or not)."""
    state = torch.random.get_rng_state()
    spec = T.UNetSpec()
    for bf16 in (False, True):
        assert 0.0 < T.step_seconds(spec, (8, 8, 8), 2, bf16, 1) < 30.0
    assert torch.equal(torch.random.get_rng_state(), state)


def test_train_says_its_arithmetic_in_its_first_line(synth_case, tmp_path, capsys):
    s = tiny_settings(iterations=2, val_interval=1, warmup_iterations=1, precision="auto")
    summary = train(synth_case, settings=s, model_dir=tmp_path, progress=True)
    first = capsys.readouterr().out.splitlines()[0]
    meta = json.loads((tmp_path / "meta.json").read_text())
    precision = meta["training"]["precision"]
    assert first.startswith(f"[network] precision: {precision}")
    assert summary.finished and precision == first.split()[2]
    timed = meta["training"].get("precision_step_ms")
    assert (timed is not None) == (s.precision == "auto" and T.cpu_bf16_unit() is not None)


def test_the_bf16_unit_is_read_from_the_cpu_flags():
    from biopsynav.threads import cpu_bf16_unit, cpu_has_amx_bf16

    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    assert cpu_has_amx_bf16() == (" amx_bf16" in flags)
    expected = ("AMX-BF16 tiles" if " amx_bf16" in flags
                else "AVX-512 BF16" if " avx512_bf16" in flags else None)
    assert cpu_bf16_unit() == expected


def test_bf16_and_fp32_train_on_the_cpu_and_the_bf16_model_predicts_in_fp32(synth_case,
                                                                           tmp_path):
    """bf16 autocast trains on this CPU (whatever its bf16 support; the synthetic grid is two
    nodes deep at its bottleneck, where oneDNN once made losses NaN at random) as
    fp32 does: finite losses, the held-out error within 1.5x of fp32's after 40 iterations,
    the arithmetic recorded in meta.json; the exported model is fp32 and, loaded by the
    tracker's runtime, predicts within 0.01 mm (mean over nodes) of the model trained in fp32
    from the same seed, and not identically (the autocast was on); another arithmetic
    trains afresh."""
    from biopsynav.inference import Surrogate

    runs = {p: _train_in_a_process(synth_case, tmp_path / p,
                                   tiny_settings(iterations=40, val_interval=20, precision=p,
                                                 device="cpu"))
            for p in ("fp32", "bf16")}
    assert all(r.finished for r in runs.values())
    assert runs["bf16"].best_val_e_mm < 1.5 * runs["fp32"].best_val_e_mm
    for p in runs:
        meta = json.loads((tmp_path / p / "meta.json").read_text())
        assert meta["training"]["precision"] == p
        state = torch.load(tmp_path / p / CHECKPOINT, weights_only=False)["model"]
        assert {v.dtype for v in state.values() if v.is_floating_point()} == {torch.float32}
    data = load_dataset(synth_case)
    x = data.inputs[data.test_idx][:4].numpy()
    fingerprint = json.loads((tmp_path / "fp32" / "meta.json").read_text())["fingerprint"]
    pred = {p: Surrogate.load(tmp_path / p, fingerprint, runtime="torchscript",
                              threads=1).predict(x) for p in runs}
    gap = float(np.linalg.norm(pred["bf16"] - pred["fp32"], axis=1).mean())
    assert 0.0 < gap < 0.01  # mm: bf16 rounding alone (0.001 mm measured; e is 1.6 mm here)
    s = tiny_settings(iterations=40, val_interval=20, precision="fp32", device="cpu")
    train(synth_case, settings=s, model_dir=tmp_path / "x", progress=False, stop_after=20)
    again = train(synth_case, settings=dataclasses.replace(s, precision="bf16"),
                  model_dir=tmp_path / "x", progress=False)
    assert again.resumed_from == 0  # another arithmetic trains afresh


def test_a_diverging_training_stops_with_an_error_naming_the_iteration(synth_case, tmp_path):
    """A learning rate far too large makes the loss NaN: training stops at once with one
    error naming the iteration and the model folder, and writes no model."""
    s = tiny_settings(iterations=30, val_interval=10, learning_rate=1e6, warmup_iterations=0)
    with pytest.raises(TrainingError, match=r"loss became nan at iteration 2: .*diverged; "
                                            r"no checkpoint was written; .*lower .*learning_rate"):
        train(synth_case, settings=s, model_dir=tmp_path, progress=False)
    assert not (tmp_path / "meta.json").exists() and not (tmp_path / CHECKPOINT).exists()


def test_a_divergence_after_a_checkpoint_leaves_it_as_it_was(synth_case, tmp_path):
    """Weights that overflow after iteration 10 (one set to 1e30 in the checkpoint): the
    resumed run stops at iteration 11 naming the checkpoint's iteration, and the checkpoint's
    bytes are untouched."""
    s = tiny_settings(iterations=30, val_interval=10)
    train(synth_case, settings=s, model_dir=tmp_path, progress=False, stop_after=10)
    ckpt = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    name = next(k for k, v in ckpt["model"].items() if v.is_floating_point() and v.ndim == 5)
    ckpt["model"][name].fill_(1e30)
    torch.save(ckpt, tmp_path / CHECKPOINT)
    before = (tmp_path / CHECKPOINT).read_bytes()
    with pytest.raises(TrainingError, match=rf"at iteration 11: .*{CHECKPOINT} keeps "
                                            r"iteration 10") as err:
        train(synth_case, settings=s, model_dir=tmp_path, progress=False)
    assert err.value.where == str(tmp_path)
    assert (tmp_path / CHECKPOINT).read_bytes() == before
    assert not (tmp_path / "meta.json").exists()
