"""Reading ``CASE_DIR/dataset.zarr`` once into memory, and the normalisation statistics.

The data contract (written by the dataset stage): ``inputs`` (N, 4, nx, ny, nz) float32 (contact
displacement in mm on channels 0-2, trilinear weight sum on channel 3), ``targets`` (N, 3, nx, ny,
nz) float32 FE displacement in mm, ``done`` (N,) bool, ``active_nodes`` (nx, ny, nz) bool, attrs
``n_train``, ``n_test``, ``fingerprint``, ``node_shape``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..layout import DATASET_NAME
from .unet import QUADRATIC_PAIRS


@dataclass
class Dataset:
    """The whole data set in memory (CPU float32 tensors)."""

    inputs: torch.Tensor  # (N, 4, nx, ny, nz) mm / weight
    targets: torch.Tensor  # (N, 3, nx, ny, nz) mm
    active: torch.Tensor  # (nx, ny, nz) bool
    train_idx: torch.Tensor  # (n_train_done,) int64, complete training samples
    test_idx: torch.Tensor  # (n_test_done,) int64, complete held-out samples
    fingerprint: str
    node_shape: tuple[int, int, int]
    path: Path
    attrs: dict
    probe_disp_mm: np.ndarray | None = None  # (N,) mean contact-point displacement norm, mm

    @property
    def n_active(self) -> int:
        return int(self.active.sum())


def resolve_dataset_path(case_or_zarr: str | Path) -> Path:
    """``dataset.zarr`` of a case folder, or the given path when it already is a zarr group."""
    p = Path(case_or_zarr)
    return p if p.suffix == ".zarr" else p / DATASET_NAME


REGENERATE = "regenerate it with `biopsynav generate CASE --overwrite`"


def load_dataset(case_or_zarr: str | Path) -> Dataset:
    """Load the arrays once; only samples flagged ``done`` are kept in the index lists.

    Every failure (an unreadable group, a damaged or missing chunk, wrong attributes or
    shapes) is one InputError naming the store and the array."""
    import zarr

    path = resolve_dataset_path(case_or_zarr)
    where = str(path)
    if not path.exists():
        raise InputError("no training data; run `biopsynav generate` first", where)
    try:
        g = zarr.open_group(str(path), mode="r")
        attrs = dict(g.attrs)
        n_train, n_test = int(attrs["n_train"]), int(attrs["n_test"])
        node_shape = tuple(int(n) for n in attrs["node_shape"])
        fingerprint = str(attrs["fingerprint"])
    except Exception as exc:  # noqa: BLE001 - any failure here: the store is unusable
        raise InputError(f"not a readable dataset.zarr ({type(exc).__name__}: {exc}); "
                         f"{REGENERATE}", where) from None
    done = _read_array(g, "done", bool, where)
    inputs = _read_array(g, "inputs", np.float32, where)
    targets = _read_array(g, "targets", np.float32, where)
    active = _read_array(g, "active_nodes", bool, where)
    probe = _read_array(g, "probe_disp_mm", np.float64, where, optional=True)
    _check_shapes(inputs, targets, done, active, node_shape, where)
    _check_chunks_present(g, done, where)
    for name, values in (("inputs", inputs), ("targets", targets)):
        if not np.isfinite(values[done]).all():
            raise InputError(f"array {name!r} holds NaN or infinite values; {REGENERATE}", where)
    idx = np.flatnonzero(done)
    train = idx[idx < n_train]
    test = idx[(idx >= n_train) & (idx < n_train + n_test)]
    if train.size == 0 or test.size == 0:
        raise InputError(f"dataset has {train.size} complete training and {test.size} complete "
                         "test samples; both must be > 0", where)
    return Dataset(torch.from_numpy(inputs), torch.from_numpy(targets), torch.from_numpy(active),
                   torch.from_numpy(train), torch.from_numpy(test), fingerprint,
                   node_shape, path, attrs, probe)  # type: ignore[arg-type]


def _read_array(group, name: str, dtype: type, where: str,
                optional: bool = False) -> np.ndarray | None:
    """Array ``name`` of the store (None when ``optional`` and absent); damaged metadata, a
    missing array or a chunk that fails its checksum or does not decompress is an InputError
    naming it."""
    try:
        return np.asarray(group[name][:], dtype=dtype)
    except KeyError:
        if optional:
            return None
        raise InputError(f"array {name!r} is missing; {REGENERATE}", where) from None
    except Exception as exc:  # noqa: BLE001 - zarr, codecs and the OS raise many kinds
        raise InputError(f"array {name!r} is damaged or missing ({type(exc).__name__}: "
                         f"{str(exc)[:160]}); {REGENERATE}", where) from None


def _check_chunks_present(group, done: np.ndarray, where: str) -> None:
    """Refuse a store whose data chunks are missing for complete samples (Zarr reads a missing
    chunk as zeros: a deleted ``targets`` chunk would train on a zero field)."""
    sample_chunks = {name: len(np.unique(np.flatnonzero(done) // group[name].chunks[0]))
                     for name in ("inputs", "targets")}
    for name, expected in {**sample_chunks, "active_nodes": 1}.items():
        arr = group[name]
        if arr.nchunks_initialized < expected:
            raise InputError(f"array {name!r} lacks {expected - arr.nchunks_initialized} of its "
                             f"{expected} chunks; {REGENERATE}", where)


def require_complete(data: Dataset) -> None:
    """Refuse (InputError) to train on a data set with samples still to generate."""
    n = int(data.attrs["n_train"]) + int(data.attrs["n_test"])
    have = int(data.train_idx.numel() + data.test_idx.numel())
    if have < n:
        raise InputError(f"the data set is incomplete: {have} of {n} samples (was `generate` "
                         "stopped?); run `biopsynav generate CASE` to finish it before "
                         "training", str(data.path))


def _check_shapes(inputs: np.ndarray, targets: np.ndarray, done: np.ndarray,
                  active: np.ndarray, node_shape: tuple, where: str) -> None:
    n = inputs.shape[0]
    ok = (inputs.ndim == 5 and inputs.shape[1] == 4 and tuple(inputs.shape[2:]) == node_shape
          and targets.shape == (n, 3, *node_shape) and done.shape == (n,)
          and tuple(active.shape) == node_shape)
    if not ok:
        raise InputError(f"inconsistent shapes: inputs {inputs.shape}, targets {targets.shape}, "
                         f"done {done.shape}, active_nodes {active.shape}, node_shape "
                         f"{node_shape}", where)


def normalisation_stats(data: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel scales from the training samples, over active nodes only.

    Returns ``in_scale`` (4,) and ``out_scale`` (3,). ``in_scale`` is the root mean square of
    each input channel over the active nodes touched by the contact (weight sum > 0; the input
    is zero elsewhere by construction). ``out_scale`` equals ``in_scale[:3]``: displacement in
    and out share one unit per axis, so that the network maps the contact displacement to
    nearby nodal displacements of the same size. (The RMS of the targets over all active
    nodes is dominated by the many nodes far from the probe that barely move; scaling by it
    makes normalised targets of ~30 near the probe from inputs of ~1, which trains far
    slower.) Only scales, no shifts: a zero input stays zero.
    """
    xin = _contact_node_inputs(data)
    if xin.shape[1] == 0:
        x = data.inputs[data.train_idx]
        xin = x.permute(1, 0, 2, 3, 4)[:, :, data.active].reshape(4, -1)
    in_scale = _rms(xin)
    return in_scale, in_scale[:3].copy()


def quadratic_scale(data: Dataset, in_scale: np.ndarray) -> np.ndarray:
    """Scales (6,) of the quadratic input features: the RMS over the training samples' contact
    nodes (weight sum > 0, active) of each product ``(x_i / s_i) (x_j / s_j)`` of the scaled
    displacement channels, pairs in :data:`~biopsynav.network.unet.QUADRATIC_PAIRS` order."""
    u = _contact_node_inputs(data)[:3].double()  # (3, n_contact_nodes)
    u = u / torch.from_numpy(np.asarray(in_scale[:3], np.float64))[:, None]
    if u.shape[1] == 0:
        return np.ones(len(QUADRATIC_PAIRS), np.float32)
    return _rms(torch.stack([u[i] * u[j] for i, j in QUADRATIC_PAIRS]))


def _contact_node_inputs(data: Dataset) -> torch.Tensor:
    """Input channels (4, n) at the training samples' active nodes touched by the contact
    (weight sum > 0): the values the input scales are measured over."""
    x = data.inputs[data.train_idx]  # (n_samples, 4, nx, ny, nz)
    contact = (x[:, 3] > 0) & data.active
    return x.permute(1, 0, 2, 3, 4)[:, contact]


def target_rms(data: Dataset) -> np.ndarray:
    """Per-channel RMS (3,) in mm of the training targets over active nodes (for reports)."""
    y = data.targets[data.train_idx]
    return _rms(y.permute(1, 0, 2, 3, 4)[:, :, data.active].reshape(3, -1))


def _rms(values: torch.Tensor) -> np.ndarray:
    rms = values.double().pow(2).mean(dim=1).sqrt().numpy()
    return np.where(rms > 1e-12, rms, 1.0).astype(np.float32)


def envelope(data: Dataset) -> dict:
    """The training envelope in mm: largest contact input and target displacement norms, and
    (when the store has it) the deepest training push, ``max_probe_disp_mm`` (the mean norm
    of the contact points' displacement, ``[probe] max_push_mm``'s measure), and for rigid
    pushes drawn with it, ``max_chest_compression``."""
    x = data.inputs[data.train_idx]
    y = data.targets[data.train_idx]
    contact = torch.linalg.vector_norm(x[:, :3], dim=1)
    disp = torch.linalg.vector_norm(y, dim=1)
    out = {"max_contact_disp_mm": float(contact.max()), "max_target_disp_mm": float(disp.max()),
           "max_weight_sum": float(x[:, 3].max())}
    if data.probe_disp_mm is not None:
        out["max_probe_disp_mm"] = float(data.probe_disp_mm[data.train_idx.numpy()].max())
    share = rigid_chest_compression(data.attrs.get("protocol") or {})
    if share > 0.0:
        out["max_chest_compression"] = share
    return out


def rigid_chest_compression(protocol: dict) -> float:
    """The ``[probe] max_chest_compression`` a data set's rigid pushes were drawn with (0: no
    rigid pushes, or drawn before the limit existed)."""
    from ..dataset.store import recorded_probe_value

    if float(recorded_probe_value(protocol, "rigid_share")) <= 0.0:
        return 0.0
    return float(recorded_probe_value(protocol, "max_chest_compression"))


def dataset_contact_input(data: Dataset) -> str:
    """The contact-input kind the data set was generated with (``[dataset] contact_input``;
    data sets from before the option are 'average')."""
    protocol = data.attrs.get("protocol") or {}
    return str(protocol.get("dataset", {}).get("contact_input", "average"))
