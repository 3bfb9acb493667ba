"""Training of the surrogate: Adam, warm-up + cosine learning rate, masked loss, validation on
the held-out samples, best weights kept, resumable checkpoints, exports at the end.

Files in ``model_dir`` (``CASE_DIR/model`` by default), all written atomically:

* ``checkpoint.pt`` - everything to resume (weights, Adam state, history, best weights, timers);
* ``best.pt`` - the weights with the lowest mean validation error so far;
* ``model.ts`` - the exported inference model (frozen TorchScript, fp32, mm in and out);
* ``model.onnx`` - the same graph as ONNX (for ONNX Runtime / OpenVINO);
* ``meta.json`` - architecture, normalisation, grid, fingerprint, envelope, training figures;
* ``loss_curve.png`` - training loss and validation error against iterations (drawn at most
  once a minute while the training runs, and when it ends or stops).

Determinism: batches and learning rates are pure functions of (seed, iteration), so a run killed
at any point and restarted from its last checkpoint ends with the same weights as an
uninterrupted one (same machine, same thread count, each run in a process of its own: oneDNN
picks convolution kernels by what the process ran before, so two trainings in one process
after other convolutions may differ in the last bits).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import io
import math
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..case import Case, as_case
from ..config import NetworkSection
from ..contact.projection import BatchProjection, sample_projections
from ..errors import InputError, TrainingError
from ..fileio import remove_partial_writes, write_bytes_atomic
from ..inference.runtimes import ONNX, TORCHSCRIPT
from ..layout import BEST, CHECKPOINT, HISTORY, LOSS_CURVE, META, MODEL_DIR
from ..prior_registry import Prior, choose_prior
from ..threads import cpu_bf16_unit, set_threads
from ..timing import medians_in_turn
from .data import (
    Dataset,
    dataset_contact_input,
    envelope,
    load_dataset,
    normalisation_stats,
    quadratic_scale,
    require_complete,
    target_rms,
)
from .export import SurrogateNet
from .metrics import masked_loss, mean_norm_error
from .model_io import write_model
from .unet import UNet3d, UNetSpec, count_parameters, section_spec
from .warmstart import SourceModel, load_source, merged_envelope, resolve_source

if TYPE_CHECKING:
    from tqdm import tqdm

#: seconds between drawings of ``loss_curve.png`` while a training runs (drawn again when it
#: ends or stops); each drawing holds the training up
LOSS_CURVE_INTERVAL_S = 60.0
#: Every file training writes into the model folder (all atomically).
MODEL_FILES = (CHECKPOINT, BEST, LOSS_CURVE, TORCHSCRIPT, ONNX, META, HISTORY)


@dataclass
class TrainSummary:
    """Outcome of :func:`train`; times in seconds, errors in mm."""

    model_dir: Path
    iterations_done: int
    iterations: int
    best_val_e_mm: float
    best_iteration: int
    last_val_e_mm: float
    train_time_s: float
    resumed_from: int
    finished: bool
    spec: dict = field(default_factory=dict)
    n_parameters: int = 0


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is an InputError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda' requested but no CUDA GPU is available", "--device")
    return torch.device(name)


#: training steps that ``precision = "auto"`` times in each arithmetic on a CPU with bf16
#: arithmetic, in turn (their median)
PRECISION_PROBE_STEPS = 6
#: rounds of steps a timing runs first, untimed (oneDNN makes its kernels on first use)
PROBE_WARMUP = 2
#: ... and bf16 is chosen where its step takes less than this share of fp32's (a near tie
#: keeps fp32): AVX-512 BF16 trains 1.3x faster than fp32 on an AMD EPYC, 1.4x slower on an
#: Intel Xeon whose VM hides AMX (docs/network.md, "Arithmetic")
BF16_WIN = 0.9


@dataclass(frozen=True)
class Precision:
    """The training's forward arithmetic: bf16 autocast (``amp``) or fp32, and why (a
    measured step in each, ms, where ``auto`` timed them)."""

    amp: bool
    why: str = ""
    fp32_ms: float | None = None
    bf16_ms: float | None = None

    def record(self) -> dict:
        """What ``meta.json`` keeps of it."""
        timed = {} if self.fp32_ms is None else {"precision_step_ms": {
            "fp32": self.fp32_ms, "bf16": self.bf16_ms}}
        return {"precision": "bf16" if self.amp else "fp32", **timed}


def use_bf16(precision: str, dev: torch.device) -> bool:
    """Whether training may autocast its forward pass to bfloat16 on ``dev``: always for
    'bf16', never for 'fp32'; for 'auto' on CUDA and on a CPU with bf16 arithmetic, AMX-BF16
    or AVX-512 BF16 (:func:`cpu_bf16_unit`), where :func:`choose_precision` then times
    both; fp32 on other CPUs (docs/network.md, "Arithmetic")."""
    if precision != "auto":
        return precision == "bf16"
    return dev.type == "cuda" or (dev.type == "cpu" and cpu_bf16_unit() is not None)


def choose_precision(precision: str, dev: torch.device, spec: UNetSpec,
                     node_shape: tuple[int, int, int], batch: int,
                     resumed: bool | None = None) -> Precision:
    """The arithmetic of a training of the U-Net ``spec`` at ``batch`` on ``node_shape``
    nodes: as set ('fp32', 'bf16'); for 'auto', bf16 on CUDA, fp32 on a CPU without bf16
    arithmetic, the checkpoint's (``resumed``: its bf16, None: none), else the faster of the
    two by a timed step of each (:func:`timed_steps_ms`; bf16 only below :data:`BF16_WIN`
    of fp32's)."""
    amp = use_bf16(precision, dev)
    if precision != "auto" or not amp or dev.type != "cpu":
        return Precision(amp)
    if resumed is not None:
        return Precision(resumed, "as the checkpoint it resumes")
    fp32_ms, bf16_ms = timed_steps_ms(spec, tuple(node_shape), batch, torch.get_num_threads())
    return Precision(bf16_ms < BF16_WIN * fp32_ms,
                     f"a step timed {bf16_ms:.0f} ms in bf16 against {fp32_ms:.0f} in fp32",
                     fp32_ms, bf16_ms)


@functools.lru_cache(maxsize=8)
def timed_steps_ms(spec: UNetSpec, node_shape: tuple[int, int, int], batch: int,
                   threads: int) -> tuple[float, float]:
    """The median training step (ms) of the U-Net ``spec`` at ``batch`` on random inputs of
    ``node_shape`` nodes on the CPU, in fp32 and in bf16 autocast, timed in turn
    (:func:`step_times`, :data:`PRECISION_PROBE_STEPS` each); kept for the process
    (``threads``: the torch threads it was timed with)."""
    fp32_s, bf16_s = step_times(spec, node_shape, batch, (False, True), PRECISION_PROBE_STEPS)
    return 1e3 * fp32_s, 1e3 * bf16_s


def step_seconds(spec: UNetSpec, node_shape: tuple[int, int, int], batch: int, bf16: bool,
                 steps: int) -> float:
    """Median seconds of one training step of the U-Net ``spec`` with bf16 autocast or not
    (:func:`step_times`)."""
    return step_times(spec, node_shape, batch, (bf16,), steps)[0]


def step_times(spec: UNetSpec, node_shape: tuple[int, int, int], batch: int,
               arithmetics: tuple[bool, ...], steps: int) -> list[float]:
    """Median seconds of one training step (forward, backward, Adam) of a fresh U-Net
    ``spec`` on random inputs (``batch``, its feature channels, ``node_shape``) on the CPU in
    the training layout, for each of ``arithmetics`` (bf16 autocast or not): ``steps``
    rounds of one step in each, in turn (what slows the machine for a while slows both),
    after :data:`PROBE_WARMUP` such rounds. Leaves torch's random generator as it found
    it."""
    cpu = torch.device("cpu")
    layout = training_layout(cpu)
    with torch.random.fork_rng():
        net = UNet3d(spec).to(memory_format=layout)
        opt = torch.optim.Adam(net.parameters(), lr=1e-4)
        x = torch.randn(batch, spec.feature_channels(), *node_shape)
    x = x.contiguous(memory_format=layout)

    def step(bf16: bool) -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = net(x)
        loss = out.float().square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return medians_in_turn([lambda b=bf16: step(b) for bf16 in arithmetics], PROBE_WARMUP,
                           steps)


def precision_line(choice: Precision | bool, dev: torch.device) -> str:
    """The one line ``train`` prints of its arithmetic and why."""
    amp, why = (choice.amp, choice.why) if isinstance(choice, Precision) else (choice, "")
    unit = cpu_bf16_unit() if dev.type == "cpu" else dev.type
    why = f" ({why})" if why else ""
    if not amp:
        if unit is None:
            why = " (this CPU has neither AMX-BF16 nor AVX-512 BF16)"
        return f"[network] precision: fp32 on {dev.type}{why}"
    if unit is None:
        return ("[network] precision: bf16 autocast on a CPU without bf16 instructions "
                "(emulated, slower than fp32), fp32 weights and loss")
    return f"[network] precision: bf16 autocast on {unit}, fp32 weights and loss{why}"


def training_layout(dev: torch.device) -> torch.memory_format:
    """Memory layout of the training's convolutions: channels-last on the CPU (oneDNN trains
    it 1.4x faster on one thread, 2x on two, in fp32 and in bf16; ``benchmarks/bf16_cpu.py``,
    docs/network.md); GPUs keep their default. The random NaN losses once seen in bf16
    channels-last without AMX came from convolutions of inputs two nodes deep, which
    :class:`~biopsynav.network.unet.Conv3d` runs in fp32."""
    return torch.channels_last_3d if dev.type == "cpu" else torch.contiguous_format


def lr_at(it: int, s: NetworkSection) -> float:
    """Learning rate of iteration ``it``: linear warm-up, then cosine decay to 1 % of the peak."""
    peak = s.learning_rate
    if it < s.warmup_iterations:
        return peak * (it + 1) / s.warmup_iterations
    span = max(1, s.iterations - s.warmup_iterations)
    t = min(1.0, (it - s.warmup_iterations) / span)
    return peak * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))


def batch_indices(it: int, batch: int, n: int, seed: int) -> torch.Tensor:
    """Positions (batch,) into the training list for iteration ``it``.

    Epochs are random permutations seeded by (seed, epoch); iteration ``it`` takes the positions
    ``it*batch ... it*batch+batch-1`` of their concatenation. Stateless, hence resumable.
    """
    start = it * batch
    out = []
    while len(out) < batch:
        epoch, pos = divmod(start + len(out), n)
        g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
        perm = torch.randperm(n, generator=g)
        out.extend(perm[pos:pos + batch - len(out)].tolist())
    return torch.tensor(out, dtype=torch.int64)


def build_optimizer(params: Iterable[torch.nn.Parameter],
                    s: NetworkSection) -> torch.optim.Optimizer:
    """AdamW with ``s.weight_decay`` when it is > 0 (decoupled decay), else plain Adam (the
    paper); peak learning rate ``s.learning_rate`` (:func:`lr_at` sets it per step). The
    fused kernel updates every parameter in one pass (the same update up to rounding; the
    default network's ~30 small tensors made the per-tensor loop a tenth of a CPU step). A
    checkpoint of an unfused optimiser resumes unfused."""
    if s.weight_decay > 0:
        return torch.optim.AdamW(params, lr=s.learning_rate, weight_decay=s.weight_decay,
                                 fused=True)
    return torch.optim.Adam(params, lr=s.learning_rate, fused=True)


def _signature(s: NetworkSection, spec: UNetSpec, data: Dataset, bf16: bool) -> dict:
    """Settings that must match for a checkpoint to be resumed (``bf16``: the forward
    pass's arithmetic, :func:`use_bf16`)."""
    keys = ("iterations", "batch_size", "learning_rate", "warmup_iterations", "loss", "seed",
            "val_interval", "baseline")
    extra = {"weight_decay": s.weight_decay} if s.weight_decay > 0 else {}  # old checkpoints
    extra.update({"precision": "bf16"} if bf16 else {})
    return {"spec": spec.to_dict(), "fingerprint": data.fingerprint,
            "n_train": int(data.train_idx.numel()), "n_test": int(data.test_idx.numel()),
            **{k: getattr(s, k) for k in keys}, **extra}


def _save_torch(obj: dict, path: Path) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes_atomic(path, buf.getvalue())


def _read_checkpoint(path: Path) -> dict | None:
    """The training checkpoint at ``path`` if it exists and is readable (its signature not
    judged: :func:`_matching_checkpoint`).

    A damaged one is reported in one warning line (on stderr) naming it and why, and renamed
    to ``checkpoint.pt.damaged-<time>`` so that the restart never overwrites it; None is
    returned (train from iteration 0)."""
    if not path.is_file():
        return None
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
        if not isinstance(ckpt, dict) or not {"model", "optimizer", "state",
                                              "signature"} <= set(ckpt):
            raise ValueError("not a biopsynav training checkpoint")
    except Exception as exc:  # noqa: BLE001 - any unreadable file: report, keep, start afresh
        _set_aside(path, "damaged", f"unreadable ({type(exc).__name__}: {str(exc)[:120]})")
        return None
    return ckpt


def _ran_in_bf16(ckpt: dict | None) -> bool | None:
    """Whether the checkpoint ``ckpt`` (:func:`_read_checkpoint`) trained in bf16; None
    without one."""
    signature = None if ckpt is None else ckpt["signature"]
    return signature.get("precision") == "bf16" if isinstance(signature, dict) else None


def _matching_checkpoint(ckpt: dict | None, signature: dict, path: Path) -> dict | None:
    """``ckpt``, read from ``path``, where it matches ``signature``; an incompatible one is
    reported in one warning line, renamed to ``checkpoint.pt.incompatible-<time>`` and None
    returned (train from iteration 0)."""
    if ckpt is not None and ckpt.get("signature") != signature:
        _set_aside(path, "incompatible", "written with other settings or data")
        return None
    return ckpt


def _resume(ckpt: dict, net: SurrogateNet, opt: torch.optim.Optimizer, state: dict,
            path: Path) -> bool:
    """Load a checkpoint's weights, optimiser state and loop state; False (the checkpoint set
    aside, ``net``, ``opt`` and ``state`` as they were) when they do not fit."""
    before = (copy.deepcopy(net.state_dict()), copy.deepcopy(opt.state_dict()), dict(state))
    try:
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        if not isinstance(ckpt["state"], dict) or not set(state) <= set(ckpt["state"]):
            raise ValueError("its loop state lacks keys")
        state.update(ckpt["state"])
        return True
    except (RuntimeError, ValueError, KeyError, TypeError) as exc:
        net.load_state_dict(before[0])
        opt.load_state_dict(before[1])
        state.clear()
        state.update(before[2])
        _set_aside(path, "damaged", f"does not fit the network ({str(exc)[:120]})")
        return False


def _set_aside(path: Path, kind: str, why: str) -> Path:
    """Rename a checkpoint that cannot be resumed out of the way, with a warning line."""
    aside = path.with_name(f"{path.name}.{kind}-{time.strftime('%Y%m%dT%H%M%S')}")
    path.replace(aside)
    print(f"biopsynav: warning: {path}: {why}; the training progress it held is not used and "
          f"training restarts from iteration 0; the file is kept as {aside.name}",
          file=sys.stderr)
    return aside


@torch.no_grad()
def validate(net: SurrogateNet, x: torch.Tensor, y: torch.Tensor, active: torch.Tensor,
             batch: int = 8, memory_format: torch.memory_format = torch.contiguous_format,
             projection: BatchProjection | None = None) -> torch.Tensor:
    """Per-sample e (n,) in mm of the eager fp32 model on inputs ``x`` against targets ``y``
    (batches passed in ``memory_format``, the layout of the network's weights); with
    ``projection`` (of these samples, in order) the projected residual is compared."""
    was_training = net.training
    net.eval()
    errs = []
    for i in range(0, x.shape[0], batch):
        pred = net(x[i:i + batch].contiguous(memory_format=memory_format)).float()
        if projection is not None:
            idx = torch.arange(i, i + pred.shape[0], device=pred.device)
            pred = pred - projection.seen(pred, idx)
        errs.append(mean_norm_error(pred, y[i:i + batch], active))
    net.train(was_training)
    return torch.cat(errs).cpu()


def train(case: Case | str | Path, preset: str | None = None, iterations: int | None = None,
          device: str | None = None, *, settings: NetworkSection | None = None,
          dataset: str | Path | None = None, model_dir: str | Path | None = None,
          progress: bool = True, stop_after: int | None = None,
          first_samples: int | None = None) -> TrainSummary:
    """Train (or resume training of) the surrogate of ``case`` (a loaded case, or its folder).

    ``settings`` is the [network] section (defaults when None); ``preset``, ``iterations`` and
    ``device`` override it. Data come from ``dataset`` (default ``CASE_DIR/dataset.zarr``) and
    files go to ``model_dir`` (default ``CASE_DIR/model``). ``stop_after`` stops after that many
    iterations in total, checkpoint written, as an interruption would (for tests).
    ``first_samples`` trains on the first that many training samples of the complete data set
    only (a study of how many samples a case needs; the held-out ones stay).
    """
    s = overridden_settings(settings, preset, iterations, device)
    case_dir = case.dir if isinstance(case, Case) else Path(case)
    out = Path(model_dir) if model_dir is not None else case_dir / MODEL_DIR
    spec = section_spec(s)
    dev = resolve_device(s.device)
    threads = set_threads(s.threads)
    full = training_samples(dataset if dataset is not None else case_dir, first_samples)
    stored = _read_checkpoint(out / CHECKPOINT)
    precision = choose_precision(s.precision, dev, spec, full.node_shape, s.batch_size,
                                 _ran_in_bf16(stored))
    amp = precision.amp
    if progress:
        print(precision_line(precision, dev), flush=True)
    source = source_model(case_dir, s, spec, full)  # checked before the baselines' work
    prior, start_line = starting_point(case, s, spec, source)
    if progress:
        print(f"[network] {start_line}; {s.iterations} iterations", flush=True)
    data, baseline_meta, projections = residual_dataset(full, s.baseline, case,
                                                        s.contact_projection)
    in_scale, out_scale, quad_scale = network_scales(data, spec, baseline_meta["kind"], source)
    prior_summary = None if prior is None else prior.summary()  # its file hashed once
    signature = training_signature(s, spec, data, amp, baseline_meta, source, prior_summary)
    if projections is not None:
        projections = tuple(p.to(dev) for p in projections)

    torch.manual_seed(s.seed)
    net = SurrogateNet(spec, in_scale, out_scale, data.active.numpy(), quad_scale).to(dev)
    starts_from_a_model = initial_weights(net, source, prior, baseline_meta["kind"])
    opt = build_optimizer(net.unet.parameters(), s)
    state = {"iteration": 0, "history": [], "best_val": math.inf, "best_iteration": 0,
             "best_state": None, "elapsed_s": 0.0, "loss_sum": 0.0, "loss_n": 0}
    remove_partial_writes(out, MODEL_FILES)  # debris of a run killed mid-write
    ckpt = _matching_checkpoint(stored, signature, out / CHECKPOINT)
    if ckpt is not None and not _resume(ckpt, net, opt, state, out / CHECKPOINT):
        ckpt = None
    resumed_from = state["iteration"]

    runner = TrainingLoop(net, opt, data, s, dev, out, signature, state, projections, amp)
    if ckpt is None and starts_from_a_model:
        runner.keep_initial()  # the source model, prior or baseline alone: the one to beat
    with deterministic_algorithms():
        runner.run(progress=progress, stop_after=stop_after)
    finished = state["iteration"] >= s.iterations
    if finished:
        if state["best_state"] is not None:
            net.unet.load_state_dict(state["best_state"])
        net.to(memory_format=torch.contiguous_format)
        record = training_record(s, state, full, dev.type, threads, precision, baseline_meta,
                                 source, prior_summary)
        write_model(out, net.cpu(), spec, data, in_scale, out_scale,
                    merged_envelope(envelope(full), source), quad_scale=quad_scale,
                    training=record, runtime=s.runtime, baseline=baseline_meta)
    last = state["history"][-1]["val_mean_e_mm"] if state["history"] else math.nan
    return TrainSummary(out, state["iteration"], s.iterations, state["best_val"],
                        state["best_iteration"], last, state["elapsed_s"], resumed_from,
                        finished, spec.to_dict(), count_parameters(spec))


def overridden_settings(settings: NetworkSection | None, preset: str | None,
                        iterations: int | None, device: str | None) -> NetworkSection:
    """A copy of the [network] section ``settings`` (defaults when None) with ``preset``,
    ``iterations`` and ``device`` in place of its own where given; InputError for fewer than
    one iteration (before anything is read or written: the model stays)."""
    s = dataclasses.replace(settings or NetworkSection())
    if preset is not None:
        s.preset = preset
    if iterations is not None:
        if int(iterations) < 1:
            raise InputError(f"must be >= 1, got {iterations}", "--iterations")
        s.iterations = int(iterations)
    if device is not None:
        s.device = device
    return s


def training_samples(path: str | Path, first_samples: int | None) -> Dataset:
    """The complete data set at ``path`` (a case folder or a ``dataset.zarr``), its training
    samples cut to the first ``first_samples`` when given (InputError below 1)."""
    if first_samples is not None and first_samples < 1:
        raise InputError(f"first_samples must be >= 1, got {first_samples}", "train")
    full = load_dataset(path)
    require_complete(full)
    if first_samples is not None:
        full.train_idx = full.train_idx[:first_samples]
    return full


def training_signature(s: NetworkSection, spec: UNetSpec, data: Dataset, amp: bool,
                       baseline_meta: dict, source: SourceModel | None,
                       prior_summary: dict | None) -> dict:
    """What a checkpoint must match to be resumed: the settings and data
    (:func:`_signature`), the baseline (not its timings), the model trained from and the
    prior started from."""
    signature = _signature(s, spec, data, amp)
    signature["baseline_meta"] = {k: v for k, v in baseline_meta.items()
                                  if not k.endswith("_s")}
    if source is not None:
        signature["init_from"] = source.checksum
    if prior_summary is not None:
        signature["prior"] = prior_summary["checksum"]
    return signature


def initial_weights(net: SurrogateNet, source: SourceModel | None, prior: Prior | None,
                    baseline_kind: str) -> bool:
    """Give ``net`` its first weights: the source model's (``[network] init_from``), else the
    prior's, else, with a physics baseline, a head at zero (the model starts as the baseline);
    True when the net so starts as a model worth keeping if training does not beat it."""
    if source is not None:
        net.unet.load_state_dict(source.weights)
    elif prior is not None:
        prior.load_into(net.unet)
    elif baseline_kind != "none":
        torch.nn.init.zeros_(net.unet.head.weight)
        torch.nn.init.zeros_(net.unet.head.bias)
    else:
        return False
    return True


def training_record(s: NetworkSection, state: dict, full: Dataset, device: str, threads: int,
                    precision: Precision, baseline_meta: dict, source: SourceModel | None,
                    prior_summary: dict | None) -> dict:
    """``meta.json``'s ``training``: the schedule, where and how it ran (the arithmetic and,
    where ``auto`` timed them, the steps it chose by: :meth:`Precision.record`), its time (s), the
    training samples, the best held-out e (mm) and when, the history, and what it started
    from."""
    return {"iterations": s.iterations, "batch_size": s.batch_size,
            "learning_rate": s.learning_rate, "loss": s.loss, "seed": s.seed,
            "device": device, "threads": threads, **precision.record(),
            "train_time_s": state["elapsed_s"], "n_train": int(full.train_idx.numel()),
            # the baseline and projections of every sample, before the loop
            "setup_s": float(baseline_meta.get("setup_s", 0.0)
                             + baseline_meta.get("all_samples_s", 0.0)),
            "best_val_e_mm": state["best_val"], "best_iteration": state["best_iteration"],
            "history": state["history"],
            **({} if source is None else {"init_from": source.summary()}),
            **({} if prior_summary is None else {"prior": prior_summary})}


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Deterministic kernels within the block (the same seed, data, threads and precision
    give the same model), without filling every new tensor with NaN first: that fill only
    exposes reads of uninitialised memory, which deterministic kernels do not make, and
    costs a few per cent of a CPU training step."""
    fill = torch.utils.deterministic
    was = torch.are_deterministic_algorithms_enabled(), fill.fill_uninitialized_memory
    torch.use_deterministic_algorithms(True, warn_only=True)
    fill.fill_uninitialized_memory = False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was[0])
        fill.fill_uninitialized_memory = was[1]


def starting_point(case: Case | str | Path, s: NetworkSection, spec: UNetSpec,
                   source: SourceModel | None) -> tuple[Prior | None, str]:
    """The prior the training starts from (``[network] prior``; none when ``init_from``
    names a source model) and one line saying where it starts."""
    if source is not None:
        return None, f"from the trained model {source.path} ([network] init_from)"
    return choose_prior(s.prior, lambda: as_case(case).anatomy, spec.to_dict())


def source_model(case_dir: Path, s: NetworkSection, spec: UNetSpec, full: Dataset
                 ) -> SourceModel | None:
    """The model ``[network] init_from`` names, checked against this training (``s``,
    ``spec``, the data set ``full``), or None."""
    path = resolve_source(case_dir, s.init_from)
    if path is None:
        return None
    return load_source(path, spec.to_dict(), tuple(full.node_shape), s.baseline,
                       dataset_contact_input(full))


def network_scales(data: Dataset, spec: UNetSpec, baseline: str, source: SourceModel | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Input, output and quadratic-feature scales: the source model's when training starts
    from one (its weights expect them), else from the training samples."""
    if source is not None:
        return source.in_scale, source.out_scale, source.quad_scale
    in_scale, out_scale = normalisation_stats(data)
    if baseline != "none":
        out_scale = target_rms(data)  # the residual's RMS over active nodes
    quad = quadratic_scale(data, in_scale) if spec.features == "quadratic" else None
    return in_scale, out_scale, quad


def residual_dataset(data: Dataset, kind: str, case: Case | str | Path,
                     contact_projection: bool = False
                     ) -> tuple[Dataset, dict, tuple[BatchProjection, BatchProjection] | None]:
    """The data set the network trains on, the ``baseline`` entry of meta.json and, when it
    trains through the contact projection, the (training, held-out) :class:`BatchProjection`.

    ``kind`` 'none': ``data`` itself. 'linear-elastic': targets replaced by the residual
    ``target - baseline(input)`` of :class:`~biopsynav.contact.baseline.LinearElasticBaseline`
    of ``case`` (computed once for every sample); the case must be the one the
    data were generated for (fingerprint). With ``contact_projection`` (and the elastic contact
    input) the network is trained on what the tracker deploys, the projected prediction
    (:mod:`~biopsynav.contact.projection`): the target is ``target - u_lin(x) - u_lin(g -
    W_P x)``, ``g = W_P target`` the contact points' displacement (their weights redrawn from
    the data set's protocol), and the loss sees ``r - u_lin(W_P r)``.
    """
    if kind == "none":
        return data, {"kind": "none"}, None
    if kind != "linear-elastic":
        raise InputError(f"unknown baseline {kind!r}; use linear-elastic or none",
                         "[network] baseline")
    from ..contact.baseline import SPRING_SCALE, LinearElasticBaseline
    from ..errors import FingerprintError

    case = as_case(case)
    if case.fingerprint() != data.fingerprint:
        raise FingerprintError("the data set was generated for another anatomy or grid than "
                               "this case; the linear-elastic baseline needs the case's own "
                               "FE model", str(data.path))
    contact = dataset_contact_input(data)
    start = time.perf_counter()
    # elastic input: hard constraints reproduce the point-constrained linear solution exactly;
    # averaged input: soft springs (docs/network.md)
    base = LinearElasticBaseline.from_case(case, spring=None if contact == "elastic"
                                           else SPRING_SCALE)
    setup_s = time.perf_counter() - start
    idx = torch.cat([data.train_idx, data.test_idx])
    targets = data.targets.clone()
    projections = None
    project = contact_projection and contact == "elastic"
    if project and not _has_pushes(data):
        print("[network] the data set records no probe pushes (probe protocol): training "
              "without the contact projection")
        project = False
    springs = elastic_rigid_pushes(data)
    if project and springs:
        print("[network] rigid pushes with elastic contact ([tracker] fem_contact): their "
              "contact points lag the face, so the model trains and predicts without the "
              "contact projection")
        project = False
    if project:
        baseline, projections = _projected_baselines(base, case, data, idx)
        targets[idx] -= torch.from_numpy(baseline)
    else:
        targets[idx] -= torch.from_numpy(base.predict(data.inputs[idx].numpy()))
    meta = {"kind": kind, "contact_input": contact, "spring": base.spring,
            "spring_power": base.power,
            **({"projection": True} if projections is not None else {}),
            **({"elastic_contact": True} if springs else {}),
            "n_candidate_dofs": base.n_candidate_dofs, "setup_s": setup_s,
            "all_samples_s": time.perf_counter() - start - setup_s}
    return dataclasses.replace(data, targets=targets), meta, projections


def elastic_rigid_pushes(data: Dataset) -> bool:
    """Whether the data set holds rigid pushes whose contact points were tied to the face by
    springs (``[tracker] fem_contact = 'elastic'``): their fields do not move the points
    exactly with the face, which the contact projection would impose."""
    from ..contact.constraints import contact_constraint_names, is_elastic
    from ..dataset.store import recorded_probe_value

    protocol = data.attrs.get("protocol") or {}
    kind = (protocol.get("fe_model") or {}).get("fem_contact")
    rigid = float(recorded_probe_value(protocol, "rigid_share")) > 0.0
    return rigid and kind in contact_constraint_names() and is_elastic(kind)


def _has_pushes(data: Dataset) -> bool:
    """Whether the data set records its probe protocol (to redraw the contact points)."""
    return "probe" in (data.attrs.get("protocol") or {})


def _projected_baselines(base, case, data: Dataset, idx: torch.Tensor
                         ) -> tuple[np.ndarray, tuple[BatchProjection, BatchProjection]]:
    """``u_lin(x) + u_lin(g - W_P x)`` (n, 3, nx, ny, nz) of the samples ``idx`` (training
    then held-out) and their batch projections (training, held-out)."""
    from ..dataset.contacts import sample_contact_matrices

    samples = idx.numpy()
    x = data.inputs.numpy()
    contacts = sample_projections(base, sample_contact_matrices(case, data.path, samples), x,
                                  data.targets.numpy(), samples, str(data.path))
    zero = np.zeros((3, *data.node_shape), np.float32)
    fields = [proj.baseline_field(x[i], g, zero)
              for i, (proj, g) in zip(samples, contacts, strict=True)]
    projections = [proj for proj, _ in contacts]
    n_train = int(data.train_idx.numel())
    return np.stack(fields), (BatchProjection(base, projections[:n_train]),
                              BatchProjection(base, projections[n_train:]))


class TrainingLoop:
    """The optimisation loop with validation, checkpoints and the progress bar."""

    def __init__(self, net: SurrogateNet, opt: torch.optim.Optimizer, data: Dataset,
                 s: NetworkSection, dev: torch.device, out: Path, signature: dict,
                 state: dict,
                 projections: tuple[BatchProjection, BatchProjection] | None,
                 amp: bool) -> None:
        self.net, self.opt, self.s, self.dev, self.out = net, opt, s, dev, out
        self.train_proj, self.test_proj = projections or (None, None)
        self.signature, self.state = signature, state
        self.active = data.active.to(dev)
        self.mask = self.active.to(torch.float32)
        scale = net.out_scale.to(dev)
        self.out_scale = scale.reshape(-1)  # (3,) mm per normalised unit, for the norm loss
        self.x_train = data.inputs[data.train_idx].to(dev)
        self.y_train = data.targets[data.train_idx].to(dev) / scale  # normalised targets
        self.x_test = data.inputs[data.test_idx].to(dev)
        self.y_test = data.targets[data.test_idx].to(dev)
        self.amp = amp  # bf16 autocast (choose_precision)
        self.saved_at = state["iteration"]  # the iteration the checkpoint on disk holds
        self.drawn_at = time.perf_counter()  # when loss_curve.png was last drawn
        self.memory_format = training_layout(dev)
        net.to(memory_format=self.memory_format)

    def step(self, it: int) -> float:
        s = self.s
        idx = batch_indices(it, s.batch_size, self.x_train.shape[0], s.seed).to(self.dev)
        for group in self.opt.param_groups:
            group["lr"] = lr_at(it, s)
        x = self.x_train[idx].contiguous(memory_format=self.memory_format)
        with torch.autocast(self.dev.type, dtype=torch.bfloat16, enabled=self.amp):
            pred = self.net.forward_normalised(x)
        pred = pred.float()
        if self.train_proj is not None:  # the loss sees the projected residual
            scale = self.out_scale.view(1, 3, 1, 1, 1)
            pred = pred - self.train_proj.seen(pred * scale, idx) / scale
        loss = masked_loss(pred, self.y_train[idx], self.mask, s.loss, self.out_scale)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return float(loss.detach())

    def run(self, progress: bool, stop_after: int | None) -> None:
        from ..progress import progress_bar

        st, s = self.state, self.s
        end = s.iterations if stop_after is None else min(s.iterations, stop_after)
        bar = progress_bar(total=s.iterations, initial=st["iteration"], disable=not progress,
                           desc="train", unit="it", dynamic_ncols=True)
        t0 = time.perf_counter() - st["elapsed_s"]
        try:
            self.iterate(end, t0, bar)
        finally:
            bar.close()  # an error's message then starts a line of its own
        self.draw_loss_curve()

    def iterate(self, end: int, t0: float, bar: tqdm) -> None:
        """Train up to iteration ``end`` (``t0``: the clock's start, less the time already
        trained), validating and saving every ``val_interval``; ``bar`` shows the progress."""
        st, s = self.state, self.s
        self.net.train()
        while st["iteration"] < end:
            it = st["iteration"]
            loss = self.step(it)
            if not math.isfinite(loss):
                raise self.diverged(f"the training loss became {loss}", it + 1)
            st["loss_sum"] += loss
            st["loss_n"] += 1
            st["iteration"] = it + 1
            bar.update(1)
            if st["iteration"] % s.val_interval == 0 or st["iteration"] == s.iterations:
                st["elapsed_s"] = time.perf_counter() - t0
                self.validate_and_log()
                bar.set_postfix(loss=f"{st['history'][-1]['train_loss']:.3g}",
                                val_e=f"{st['history'][-1]['val_mean_e_mm']:.4f}mm",
                                best=f"{st['best_val']:.4f}mm")
                self.save_checkpoint()
        st["elapsed_s"] = time.perf_counter() - t0
        if st["iteration"] < s.iterations and st["iteration"] % s.val_interval:
            self.save_checkpoint()

    def keep_initial(self) -> None:
        """Take the initial weights as the best so far (validated, not logged)."""
        st = self.state
        e = validate(self.net, self.x_test, self.y_test, self.active,
                     memory_format=self.memory_format, projection=self.test_proj)
        st["best_val"], st["best_iteration"] = float(e.mean()), 0
        st["best_state"] = copy.deepcopy({k: v.cpu() for k, v in
                                          self.net.unet.state_dict().items()})

    def validate_and_log(self) -> None:
        st = self.state
        e = validate(self.net, self.x_test, self.y_test, self.active,
                     memory_format=self.memory_format, projection=self.test_proj)
        mean_e = float(e.mean())
        if not math.isfinite(mean_e):
            raise self.diverged(f"the held-out error became {mean_e} mm", st["iteration"])
        st["history"].append({"iteration": st["iteration"],
                              "train_loss": st["loss_sum"] / max(1, st["loss_n"]),
                              "val_mean_e_mm": mean_e, "val_max_e_mm": float(e.max()),
                              "lr": lr_at(st["iteration"] - 1, self.s),
                              "elapsed_s": st["elapsed_s"]})
        st["loss_sum"], st["loss_n"] = 0.0, 0
        if mean_e < st["best_val"]:
            st["best_val"], st["best_iteration"] = mean_e, st["iteration"]
            st["best_state"] = copy.deepcopy({k: v.cpu() for k, v in
                                              self.net.unet.state_dict().items()})
            _save_torch({"model": st["best_state"], "iteration": st["iteration"],
                         "val_mean_e_mm": mean_e}, self.out / BEST)
        if time.perf_counter() - self.drawn_at >= LOSS_CURVE_INTERVAL_S:
            self.draw_loss_curve()

    def draw_loss_curve(self) -> None:
        """Write ``loss_curve.png`` from the history so far (when it has any validation)."""
        from .plots import plot_loss_curve

        if self.state["history"]:
            plot_loss_curve(self.state["history"], self.out / LOSS_CURVE)
        self.drawn_at = time.perf_counter()

    def diverged(self, what: str, iteration: int) -> TrainingError:
        """The error that stops a diverged training at 1-based ``iteration``: nothing of it is
        written, the checkpoint (if any) keeps the last finite state."""
        kept = (f"{CHECKPOINT} keeps iteration {self.saved_at}, from which the same settings "
                "diverge again" if self.saved_at else "no checkpoint was written")
        cure = "set [network] precision = \"fp32\" or lower" if self.amp else "lower"
        return TrainingError(f"{what} at iteration {iteration}: the network diverged; {kept}; "
                             f"{cure} [network] learning_rate and train again", str(self.out))

    def save_checkpoint(self) -> None:
        self.saved_at = self.state["iteration"]
        _save_torch({"model": self.net.state_dict(), "optimizer": self.opt.state_dict(),
                     "state": self.state, "signature": self.signature}, self.out / CHECKPOINT)


def train_case(case: Case | str | Path, preset: str | None = None, iterations: int | None = None,
               device: str | None = None, *, progress: bool = True) -> TrainSummary:
    """CLI entry: train with the [network] section of the case's ``case.toml``, with
    overrides (``case``: a loaded case, or its folder)."""
    case = as_case(case)
    return train(case, preset, iterations, device, settings=case.cfg.network, progress=progress)


__all__ = ["TrainSummary", "train", "train_case", "lr_at", "batch_indices", "validate",
           "resolve_device", "set_threads", "build_optimizer", "use_bf16", "training_layout",
           "cpu_bf16_unit", "precision_line"]
