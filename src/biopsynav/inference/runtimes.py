"""Inference runtimes of the exported model: one registry (``register_runtime``).

A runtime runs the exported network on a batch ``x`` (b, 4, nx, ny, nz) float32 and returns
(b, 3, nx, ny, nz) float32, computed in fp32 or, by ``openvino-bf16``, in bfloat16 (its
``precision``). Each is a :class:`RuntimeSpec`: the exported file it runs
(``model.ts`` or ``model.onnx`` in the model folder), how to build its runner, whether it is
installed, whether it keeps its own thread pool, and its rank for ``auto`` (the installed
runtime of highest rank; measured fastest first, docs/network.md). ``[network] runtime``
takes its choices from this registry. Nothing heavy is imported until a runner is built.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..errors import InputError
from ..layout import ONNX, TORCHSCRIPT
from ..threads import cpu_bf16_unit, set_torch_threads
from ..timing import medians_in_turn

if TYPE_CHECKING:
    import torch


class Runner(Protocol):
    name: str
    precision: str  # the arithmetic of the network's layers: 'fp32' or 'bf16'

    def __call__(self, x: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class RuntimeSpec:
    """One runtime: ``make(model_path, threads, node_shape) -> Runner``; ``needs``: what
    ``available`` checks, said when a runtime asked for by name is not available."""

    name: str
    model_file: str
    make: Callable[[Path, int, tuple[int, int, int]], Runner]
    available: Callable[[], bool] = lambda: True
    own_threads: bool = False
    auto_rank: int = 0
    needs: str = "its package installed"


RUNTIMES: dict[str, RuntimeSpec] = {}


def register_runtime(spec: RuntimeSpec) -> None:
    """Add (or replace) a runtime; ``[network] runtime`` accepts its name."""
    RUNTIMES[spec.name] = spec


def runtime_choices() -> tuple[str, ...]:
    """``auto`` and every registered runtime: the allowed ``[network] runtime`` values."""
    return ("auto", *RUNTIMES)


def resolve_runtime(name: str) -> RuntimeSpec:
    """The runtime called ``name``; ``auto``: the installed one of highest rank."""
    if name == "auto":
        return max((s for s in RUNTIMES.values() if s.available()), key=lambda s: s.auto_rank)
    spec = RUNTIMES.get(name)
    if spec is None:
        raise InputError(f"unknown runtime {name!r}; known: {', '.join(runtime_choices())}",
                         "runtime")
    if not spec.available():
        raise InputError(f"runtime {name!r} requested but not available here: it needs "
                         f"{spec.needs}", "runtime")
    return spec


#: predictions timed per arithmetic (after as many again to warm up) where ``auto`` chooses
#: between OpenVINO in bf16 and in fp32 (:func:`runtime_runner`)
AUTO_TIMED = 40
#: ... bf16 is kept where its median prediction takes less than this share of fp32's: on an
#: Intel Xeon whose VM hides AMX, bf16 predicted the phantom 1.4x slower than fp32
#: (docs/network.md, "Inference runtimes")
BF16_WIN = 0.9


#: ``auto``'s timed choices in this process: (model files with their sizes and times, threads,
#: nodes) -> (the runtime chosen, why); see :func:`runtime_runner`
AUTO_CHOICES: dict[tuple, tuple[str, str]] = {}


def runtime_runner(name: str, model_path: Callable[[RuntimeSpec], Path], threads: int,
                   node_shape: tuple[int, int, int]) -> tuple[RuntimeSpec, Runner, str]:
    """The runtime called ``name`` (:func:`resolve_runtime`), its runner of the model file
    ``model_path(spec)`` on ``threads`` threads for a grid of ``node_shape`` nodes, and why it
    was chosen, in words: for ``auto`` where OpenVINO runs in bf16, the faster of bf16 and fp32
    by :data:`AUTO_TIMED` predictions each, timed in turn (bf16 only below :data:`BF16_WIN` of
    fp32's median), the choice kept for the process (:data:`AUTO_CHOICES`: a later load of
    the same model files on as many threads takes it untimed, so that an evaluation's tables
    predict in one arithmetic); otherwise as named or ranked (no words)."""
    spec = resolve_runtime(name)
    if name != "auto" or spec.name != "openvino-bf16":
        return spec, spec.make(model_path(spec), threads, node_shape), ""
    fp32_spec = RUNTIMES["openvino"]
    paths = {s.name: model_path(s) for s in (spec, fp32_spec)}  # each file checked once
    key = (*(model_identity(path) for path in paths.values()), threads, node_shape)
    if key in AUTO_CHOICES:
        chosen, why = AUTO_CHOICES[key]
        kept = RUNTIMES[chosen]
        return kept, kept.make(paths[chosen], threads, node_shape), why
    runner, fp32 = (s.make(paths[s.name], threads, node_shape) for s in (spec, fp32_spec))
    bf16_ms, fp32_ms = timed_predictions_ms((runner, fp32), node_shape)
    why = f"a prediction timed {bf16_ms:.2f} ms in bf16 against {fp32_ms:.2f} in fp32"
    chosen = (spec, runner) if bf16_ms < BF16_WIN * fp32_ms else (fp32_spec, fp32)
    AUTO_CHOICES[key] = chosen[0].name, why
    return *chosen, why


def model_identity(path: Path) -> tuple[str, int, int]:
    """A model file as the process last saw it: (resolved path, size in bytes, modification
    time in ns); a model trained again since is another."""
    st = Path(path).stat()
    return str(Path(path).resolve()), st.st_size, st.st_mtime_ns


def timed_predictions_ms(runners: tuple[Runner, ...], node_shape: tuple[int, int, int]
                         ) -> list[float]:
    """The median (ms) of :data:`AUTO_TIMED` batch-1 predictions on zeros of each of
    ``runners``, one prediction of each in turn, after as many rounds to warm up
    (:func:`~biopsynav.timing.medians_in_turn`)."""
    x = np.zeros((1, 4, *node_shape), np.float32)
    calls = [lambda r=runner: r(x) for runner in runners]
    return [1e3 * t for t in medians_in_turn(calls, AUTO_TIMED, AUTO_TIMED)]


class TorchScriptRunner:
    """Frozen TorchScript on the CPU, fp32, run under ``torch.inference_mode``."""

    name = "torchscript"
    precision = "fp32"

    def __init__(self, path: Path, threads: int) -> None:
        import torch

        self._torch = torch
        set_torch_threads(threads)
        try:
            self.module = load_torchscript(path)
        except RuntimeError as exc:
            raise InputError(f"cannot load the TorchScript model ({str(exc)[:200]}); retrain "
                             "with `biopsynav train`", str(path)) from None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        with self._torch.inference_mode():
            return self.module(self._torch.from_numpy(x)).numpy()


class OpenVinoRunner:
    """OpenVINO on the CPU at the runner's ``precision``, forced: fp32 here (OpenVINO would
    pick bf16 on AMX by itself); :class:`OpenVinoBf16Runner` asks for bf16."""

    name = "openvino"
    precision = "fp32"
    _HINTS = {"fp32": "f32", "bf16": "bf16"}  # OpenVINO's INFERENCE_PRECISION_HINT

    def __init__(self, path: Path, threads: int, node_shape: tuple[int, int, int]) -> None:
        import openvino as ov

        self.node_shape = tuple(node_shape)
        self.core = ov.Core()
        self.model = self.core.read_model(str(path))
        self.threads = threads
        self.compiled: dict[int, object] = {}
        self._request(1)

    def _request(self, batch: int):
        req = self.compiled.get(batch)
        if req is None:
            model = self.model.clone()
            model.reshape({0: [batch, 4, *self.node_shape]})
            cm = self.core.compile_model(model, "CPU", {
                "INFERENCE_PRECISION_HINT": self._HINTS[self.precision],
                "INFERENCE_NUM_THREADS": self.threads, "PERFORMANCE_HINT": "LATENCY"})
            picked = str(cm.get_property("INFERENCE_PRECISION_HINT"))
            if ("32" in picked) != (self.precision == "fp32"):
                raise InputError(f"OpenVINO picked precision {picked}, not {self.precision}",
                                 "runtime")
            req = cm.create_infer_request()
            self.compiled[batch] = req
        return req

    def __call__(self, x: np.ndarray) -> np.ndarray:
        req = self._request(x.shape[0])
        return req.infer({0: x}, share_inputs=True)[0]

    def start(self, x: np.ndarray):
        """Start an inference on ``x`` (kept alive by the caller) and return at once; OpenVINO
        runs it on its own threads, without the GIL. Finish with :meth:`finish`."""
        req = self._request(x.shape[0])
        req.start_async({0: x}, share_inputs=True)
        return req

    @staticmethod
    def finish(req) -> np.ndarray:
        """The output of a started inference (a copy: the request reuses its buffer)."""
        req.wait()
        return np.array(req.get_output_tensor(0).data)


class OpenVinoBf16Runner(OpenVinoRunner):
    """OpenVINO on the CPU in bfloat16: its layers on the AMX-BF16 tiles or in AVX-512 BF16
    dot products, accumulating in fp32; input and output fp32 (what it costs in accuracy and
    buys in time: docs/network.md, "Inference runtimes")."""

    name = "openvino-bf16"
    precision = "bf16"


def openvino_bf16_available() -> bool:
    """Whether OpenVINO imports and the CPU has bf16 arithmetic: AMX-BF16 tiles or AVX-512
    BF16 (:func:`~biopsynav.threads.cpu_bf16_unit`; elsewhere bf16 is emulated, slower than
    fp32)."""
    return cpu_bf16_unit() is not None and openvino_available()


def openvino_available() -> bool:
    """Whether the ``openvino`` package can be imported."""
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True


register_runtime(RuntimeSpec("torchscript", TORCHSCRIPT,
                             lambda path, threads, shape: TorchScriptRunner(path, threads)))
register_runtime(RuntimeSpec("openvino", ONNX, OpenVinoRunner, openvino_available,
                             own_threads=True, auto_rank=1, needs="the openvino package"))
register_runtime(RuntimeSpec("openvino-bf16", ONNX, OpenVinoBf16Runner, openvino_bf16_available,
                             own_threads=True, auto_rank=2,
                             needs="the openvino package and a CPU with AMX-BF16 or "
                                   "AVX-512 BF16"))


def load_torchscript(path: str | Path) -> torch.jit.ScriptModule:
    """Load a saved module, then freeze it and optimise it for CPU inference."""
    import torch

    module = torch.jit.load(str(path), map_location="cpu").eval()
    with torch.no_grad():
        return torch.jit.optimize_for_inference(torch.jit.freeze(module))
