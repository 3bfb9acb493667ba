"""Writing and checking the model folder: exports, ``meta.json``, checksums, fingerprint."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import FingerprintError, InputError
from ..fileio import write_json_atomic
from .data import Dataset
from .export import SurrogateNet, load_torchscript, save_onnx, save_torchscript
from .unet import UNetSpec, count_parameters

META = "meta.json"
TORCHSCRIPT = "model.ts"
ONNX = "model.onnx"
HISTORY = "history.json"
FORMAT = "biopsynav-unet/1"


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_model(out: Path, net: SurrogateNet, spec: UNetSpec, data: Dataset,
                in_scale: np.ndarray, out_scale: np.ndarray, envelope: dict, training: dict,
                runtime: str = "auto", baseline: dict | None = None,
                quad_scale: np.ndarray | None = None) -> dict:
    """Export ``net`` (TorchScript and ONNX), check the export against eager, write meta.json."""
    net = net.cpu().eval()
    save_torchscript(net, out / TORCHSCRIPT)
    save_onnx(net, out / ONNX, data.node_shape)
    parity = _export_parity(net, out / TORCHSCRIPT, data.inputs[data.test_idx[:4]])
    spacing = data.attrs.get("spacing_mm", data.attrs.get("cell_size_mm"))
    meta = {
        "format": FORMAT,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "fingerprint": data.fingerprint,
        "node_shape": list(data.node_shape),
        "spacing_mm": float(spacing) if spacing is not None else None,
        "n_active_nodes": data.n_active,
        "architecture": spec.to_dict(),
        "n_parameters": count_parameters(spec),
        "normalisation": {"in_scale": np.asarray(in_scale).tolist(),
                          "out_scale": np.asarray(out_scale).tolist(),
                          **({} if quad_scale is None else
                             {"quad_scale": np.asarray(quad_scale).tolist()}),
                          "kind": "per-channel RMS over active nodes of the training set "
                                  "(inputs: over contact nodes; outputs: of the residual when "
                                  "a baseline is used); x/in_scale in, "
                                  "y*out_scale*active out"},
        "envelope": envelope,
        "contact_input": _contact_input(data),
        "baseline": baseline or {"kind": "none"},
        "training": {k: v for k, v in training.items() if k != "history"},
        "inference": {"precision": "fp32", "runtime": runtime,
                      "export_max_abs_diff_mm": parity,
                      "files": {TORCHSCRIPT: sha256(out / TORCHSCRIPT),
                                ONNX: sha256(out / ONNX)}},
        "units": "inputs: mm (channels 0-2) and weight sum (channel 3); outputs: mm",
    }
    write_json_atomic(out / META, meta)
    write_json_atomic(out / HISTORY, training.get("history", []))
    return meta


def _contact_input(data: Dataset) -> str:
    from .train import dataset_contact_input  # local import: train imports this module

    return dataset_contact_input(data)


@torch.no_grad()
def _export_parity(net: SurrogateNet, ts_path: Path, x: torch.Tensor) -> float:
    """Largest |TorchScript - eager| (mm) on a few samples."""
    ts = load_torchscript(ts_path)
    with torch.inference_mode():
        y = ts(x)
    return float((y - net(x)).abs().max())


def read_meta(model_dir: str | Path) -> dict:
    """``meta.json`` of a model folder; InputError with the reason when missing or corrupt."""
    path = Path(model_dir) / META
    if not path.is_file():
        raise InputError("no trained model here (meta.json missing); run `biopsynav train`",
                         str(path))
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"meta.json is corrupt ({exc}); retrain with `biopsynav train`",
                         str(path)) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"meta.json is not a {FORMAT} model description", str(path))
    return meta


def check_fingerprint(meta: dict, expected: str, where: str) -> None:
    """Refuse a model trained for another anatomy or grid than ``expected``."""
    stored = meta.get("fingerprint")
    if stored != expected:
        raise FingerprintError(
            f"this model was trained for another anatomy or grid (model fingerprint "
            f"{str(stored)[:16]}..., case fingerprint {str(expected)[:16]}...); a model must "
            f"never run on another patient: retrain it for this case with `biopsynav train`",
            where)


def check_file(model_dir: Path, name: str, meta: dict) -> Path:
    """Path of an exported file after checking that it exists and matches its checksum."""
    path = Path(model_dir) / name
    if not path.is_file():
        raise InputError(f"exported model {name} is missing; retrain with `biopsynav train`",
                         str(path))
    expected = meta.get("inference", {}).get("files", {}).get(name)
    if expected is not None and sha256(path) != expected:
        raise InputError(f"exported model {name} is corrupt (checksum mismatch); retrain with "
                         "`biopsynav train`", str(path))
    return path
