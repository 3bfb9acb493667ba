"""Real-time prediction with the exported model: :class:`Surrogate`.

``Surrogate.load(model_dir, expected_fingerprint)`` refuses a model trained for another anatomy
or grid (FingerprintError), checks the exported file against its checksum, picks the runtime
(:mod:`~biopsynav.inference.runtimes`: TorchScript, OpenVINO in fp32, or OpenVINO in bf16 on
a CPU with AMX-BF16 or AVX-512 BF16; ``precision`` says which), sets the thread count and
warms the runtime up, so that :meth:`Surrogate.predict` does nothing but the forward pass.

When the model was trained on top of the linear-elastic baseline (``meta.json`` ``baseline``
``kind = linear-elastic``), the exported network is the residual net and ``predict`` returns
``baseline(x) + net(x)``; the baseline's Green's functions are computed at load from the case
(``model_dir``'s parent folder, or ``case=``), whose fingerprint must match the model's.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..contact.baseline import LinearElasticBaseline
from ..contact.lesions import PointOperator, point_operator
from ..contact.projection import ContactProjection
from ..errors import InputError
from ..probe import ContactInputOperator
from ..threads import auto_threads, set_torch_threads
from .model_files import check_file, check_fingerprint, read_meta
from .runtimes import (  # noqa: F401  (re-exported)
    Runner,
    openvino_available,
    resolve_runtime,
    runtime_runner,
)

if TYPE_CHECKING:
    from ..case import Case
    from ..grid.embedding import Embedding



class Surrogate:
    """The trained surrogate of one case: contact input -> displacement of every grid node."""

    def __init__(self, runner: Runner, meta: dict, model_dir: Path,
                 baseline: LinearElasticBaseline | None = None, runtime_chosen: str = ""
                 ) -> None:
        self._run = runner
        self.baseline = baseline
        self.meta = meta
        self.model_dir = model_dir
        self.node_shape: tuple[int, int, int] = tuple(meta["node_shape"])  # type: ignore
        self.runtime: str = runner.name  # type: ignore[attr-defined]
        self.precision: str = getattr(runner, "precision", "fp32")
        #: why ``auto`` chose this runtime, in words (empty: named or ranked; runtime_runner)
        self.runtime_chosen = runtime_chosen

    @property
    def fingerprint(self) -> str:
        return self.meta["fingerprint"]

    @property
    def contact_input(self) -> str:
        """How the training inputs were built (``[dataset] contact_input``): 'elastic' or
        'average' (models from before the option)."""
        return str(self.meta.get("contact_input", "average"))

    @property
    def envelope(self) -> dict:
        """Training envelope (mm): ``max_contact_disp_mm``, ``max_target_disp_mm``, ..."""
        return self.meta["envelope"]

    @classmethod
    def load(cls, model_dir: str | Path, expected_fingerprint: str, *,
             runtime: str | None = None, threads: int = 0, warmup: int = 30,
             case: Case | None = None) -> Surrogate:
        """Load a model folder for a case whose fingerprint is ``expected_fingerprint``.

        Raises FingerprintError when the model was trained for another anatomy or grid, and
        InputError when files are missing or corrupt. ``runtime`` defaults to the one recorded
        at training ([network] runtime); ``threads`` 0 takes the idle cores
        (:func:`~biopsynav.threads.auto_threads`). ``case`` (a loaded
        :class:`~biopsynav.case.Case`) is needed by a model with a physics baseline; by default
        the case in ``model_dir``'s parent folder.
        """
        model_dir = Path(model_dir)
        meta = read_meta(model_dir)
        check_fingerprint(meta, expected_fingerprint, str(model_dir))
        n = threads if threads > 0 else auto_threads()
        spec, runner, chosen = runtime_runner(
            runtime or meta.get("inference", {}).get("runtime", "auto"),
            lambda s: check_file(model_dir, s.model_file, meta), n, tuple(meta["node_shape"]))
        baseline = _load_baseline(meta, model_dir, case)
        if baseline is not None:
            # the baseline's small BLAS calls run in torch's pool; beside a runtime with its
            # own pool one torch thread is faster (two spinning pools fight for the cores:
            # measured 3.6 ms against 5.0 ms per prediction on 2 cores, docs/network.md)
            set_torch_threads(1 if spec.own_threads else n)
        sur = cls(runner, meta, model_dir, baseline, chosen)
        sur.warm_up(warmup)
        return sur

    def warm_up(self, n: int) -> None:
        """Run ``n`` predictions on zeros (TorchScript optimises its graph on the first runs)."""
        x = np.zeros((4, *self.node_shape), np.float32)
        for _ in range(n):
            self.predict(x)

    @property
    def can_project(self) -> bool:
        """Whether :meth:`contact_projection` applies: a hard linear-elastic baseline on the
        elastic contact input."""
        return (self.baseline is not None and self.baseline.spring is None
                and self.contact_input == "elastic")

    @property
    def requires_projection(self) -> bool:
        """Whether the model was trained through the contact projection (``meta.json``
        ``baseline.projection``): its predictions are meant to be projected."""
        return bool((self.meta.get("baseline") or {}).get("projection", False))

    def projects(self, enabled: bool) -> bool:
        """Whether predictions are projected onto the contact, given the case's ``[network]
        contact_projection`` switch ``enabled``: when the model allows it, and always for a
        model trained through the projection; never for one that learnt elastic contact."""
        return ((enabled or self.requires_projection) and self.can_project
                and not self.learnt_elastic_contact)

    @property
    def learnt_elastic_contact(self) -> bool:
        """Whether the model learnt rigid pushes whose contact points were tied to the face
        by springs (``meta.json`` ``baseline.elastic_contact``): it predicts how far they lag
        the face, and is never projected onto the face."""
        return bool((self.meta.get("baseline") or {}).get("elastic_contact", False))

    def point_operator(self, points: Embedding, input_op: ContactInputOperator,
                       projection: ContactProjection | None = None) -> PointOperator | None:
        """The displacement of ``points`` for the contact set of ``input_op`` as the network's
        residual plus a linear map of the contact displacement
        (:class:`~biopsynav.contact.lesions.PointOperator`), projected with ``projection``
        when given; None for a model without a physics baseline (its prediction is the
        network's field alone)."""
        if self.baseline is None:
            return None
        return point_operator(self.baseline, input_op, points, projection)

    def contact_projection(self, contact: sp.spmatrix,
                           input_op: ContactInputOperator | None = None) -> ContactProjection:
        """The :class:`~biopsynav.contact.projection.ContactProjection` of the contact points
        of trilinear weights ``contact`` (n, n_nodes), for :meth:`predict`; InputError when
        this model has no hard baseline on the elastic input (retrain it)."""
        if not self.can_project:
            raise InputError("this model cannot honour the contact points exactly (it needs "
                             "the elastic contact input and the hard linear-elastic baseline); "
                             "retrain it", str(self.model_dir))
        return ContactProjection.build(self.baseline, contact, input_op)

    def predict(self, inputs: np.ndarray, contact: ContactProjection | None = None,
                contact_disp: np.ndarray | None = None) -> np.ndarray:
        """Displacement (3, nx, ny, nz) mm of input (4, nx, ny, nz); batched (B, ...) too.

        ``inputs`` float32, channels 0-2 the contact displacement (mm), channel 3 the weight sum
        (see the dataset contract). Zero-copy for C-contiguous float32 input.

        ``contact`` and ``contact_disp`` (one input only): the :meth:`contact_projection` of
        the input's contact points and their measured displacement (n, 3) mm, from which the
        input was built; the prediction then moves the points exactly by ``contact_disp``
        (docs/network.md).
        """
        x, single = self._checked(inputs)
        if (contact is None) != (contact_disp is None):
            raise InputError("give both the contact projection and the contact displacement, "
                             "or neither", "predict")
        if contact is not None:
            if x.shape[0] != 1:
                raise InputError("a contact projection applies to one input at a time, not a "
                                 f"batch of {x.shape[0]}", "predict")
            y = self._predict_projected(x, contact, contact_disp)
            return y[0] if single else y
        if self.baseline is None:
            y = self._run(x)
        elif hasattr(self._run, "start"):
            # the network on OpenVINO's threads while the baseline gathers its Green's
            # functions here: 0.3-1 ms less per prediction on 2 cores (docs/network.md)
            pending = self._run.start(x)
            base = self.baseline.predict(x)
            y = self._run.finish(pending) + base
        else:
            y = self._run(x) + self.baseline.predict(x)
        return y[0] if single else y

    def _predict_projected(self, x: np.ndarray, contact: ContactProjection,
                           contact_disp: np.ndarray) -> np.ndarray:
        """The projected prediction (1, 3, nx, ny, nz) of one checked input (1, 4, ...)."""
        if contact.baseline is not self.baseline:
            raise InputError("the contact projection was built for another model", "predict")
        if hasattr(self._run, "start"):
            pending = self._run.start(x)  # network on OpenVINO's threads meanwhile
            a0 = contact.input_forces(x[0], contact_disp)
            r = self._run.finish(pending)
        else:
            a0 = contact.input_forces(x[0], contact_disp)
            r = self._run(x)
        return (r[0] + contact.baseline_field(x[0], contact_disp, r[0], a0))[None]

    def predict_network(self, inputs: np.ndarray) -> np.ndarray:
        """The exported network's part of :meth:`predict` only (the residual on top of the
        physics baseline, or everything without one); same shapes and units."""
        x, single = self._checked(inputs)
        y = self._run(x)
        return y[0] if single else y

    def _checked(self, inputs: np.ndarray) -> tuple[np.ndarray, bool]:
        x = np.ascontiguousarray(inputs, dtype=np.float32)
        single = x.ndim == 4
        if single:
            x = x[None]
        if x.ndim != 5 or x.shape[1] != 4 or tuple(x.shape[2:]) != self.node_shape:
            raise InputError(f"input shape {tuple(inputs.shape)} is not (4, {self.node_shape}) "
                             f"or (B, 4, {self.node_shape})", "predict")
        return x, single


def _load_baseline(meta: dict, model_dir: Path,
                   case: Case | None) -> LinearElasticBaseline | None:
    """The physics baseline the model was trained with (None for ``kind = none``)."""
    info = meta.get("baseline") or {"kind": "none"}
    kind = info.get("kind", "none")
    if kind == "none":
        return None
    if kind != "linear-elastic":
        raise InputError(f"model needs an unknown baseline {kind!r}; retrain it", str(model_dir))
    from ..case import Case

    if case is None:
        try:
            case = Case.load(model_dir.parent)
        except (InputError, OSError, ValueError) as exc:
            raise InputError(f"this model adds a linear-elastic baseline, which needs its case "
                             f"(case.toml, anatomy.npz, grid.npz) in {model_dir.parent} or "
                             f"passed as case= ({exc})", str(model_dir)) from None
    check_fingerprint(meta, case.fingerprint(), str(case.dir))
    from ..contact.baseline import SPRING_POWER

    return LinearElasticBaseline.from_case(case, spring=info.get("spring"),
                                           power=float(info.get("spring_power", SPRING_POWER)))


def load_for_case(case: Case | str | Path, *, runtime: str | None = None,
                  threads: int | None = None) -> Surrogate:
    """Load the model of ``case`` (loaded, or its folder) checked against the case's
    anatomy+grid fingerprint, with its [network] runtime and threads unless given."""
    from ..case import as_case
    from ..refine import tracking_teacher_case

    case = as_case(case)
    net = case.cfg.network
    return Surrogate.load(case.tracking_model, case.fingerprint(),
                          case=tracking_teacher_case(case),
                          runtime=runtime or net.runtime,
                          threads=net.threads if threads is None else threads)


def case_fingerprint(case_dir: str | Path) -> str:
    """Anatomy+grid fingerprint of the case in ``case_dir`` (``biopsynav.case.Case``)."""
    from ..case import Case

    return Case.load(case_dir).fingerprint()
