"""Writing and checking the model folder: exports, ``meta.json``, checksums, fingerprint."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from ..config import is_finite_number
from ..errors import FingerprintError, InputError
from ..fileio import json_default, write_json_atomic
from ..layout import HISTORY, META
from .data import Dataset
from .export import SurrogateNet, load_torchscript, save_onnx, save_torchscript
from .runtimes import ONNX, TORCHSCRIPT
from .unet import UNetSpec, count_parameters

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
    meta = json.loads(json.dumps(meta, default=json_default))  # plain JSON values, as read
    meta["checksum"] = meta_checksum(meta)
    write_json_atomic(out / META, meta)
    write_json_atomic(out / HISTORY, training.get("history", []))
    return meta


def meta_checksum(meta: dict) -> str:
    """``sha256:`` + SHA-256 of the canonical JSON of ``meta`` without its ``checksum`` key."""
    body = {k: v for k, v in meta.items() if k != "checksum"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _contact_input(data: Dataset) -> str:
    from .data import dataset_contact_input

    return dataset_contact_input(data)


@torch.no_grad()
def _export_parity(net: SurrogateNet, ts_path: Path, x: torch.Tensor) -> float:
    """Largest |TorchScript - eager| (mm) on a few samples."""
    ts = load_torchscript(ts_path)
    with torch.inference_mode():
        y = ts(x)
    return float((y - net(x)).abs().max())


RETRAIN = "retrain with `biopsynav train CASE` (after removing the model folder)"


def read_meta(model_dir: str | Path) -> dict:
    """``meta.json`` of a model folder, checked: its checksum (models written before it have
    none and are read unchecked) and the type and finiteness of every value the inference and
    the tracker use. InputError naming the file and what is wrong otherwise."""
    path = Path(model_dir) / META
    where = str(path)
    if not path.is_file():
        raise InputError("no trained model here (meta.json missing); run `biopsynav train`",
                         where)
    try:
        meta = json.loads(path.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"meta.json is corrupt ({exc}); {RETRAIN}", where) from None
    except OSError as exc:
        raise InputError(f"cannot read meta.json: {exc.strerror}", where) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"meta.json is not a {FORMAT} model description; {RETRAIN}", where)
    if "checksum" in meta and meta["checksum"] != meta_checksum(meta):
        raise InputError(f"meta.json does not match its checksum (damaged or edited by hand: "
                         f"the safety envelope it holds cannot be trusted); {RETRAIN}", where)
    problem = _meta_problem(meta)
    if problem:
        raise InputError(f"meta.json is damaged: {problem}; {RETRAIN}", where)
    return meta


def _finite(value: object, positive: bool = False) -> bool:
    return is_finite_number(value) and (not positive or value > 0)


def _meta_problem(meta: dict) -> str:
    """What is wrong with the values of ``meta`` ("" when nothing)."""
    shape = meta.get("node_shape")
    if not (isinstance(shape, list) and len(shape) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 1 for n in shape)):
        return f"node_shape must be three node counts > 1, got {shape!r}"
    if not isinstance(meta.get("fingerprint"), str):
        return "fingerprint is missing"
    env = meta.get("envelope")
    if not isinstance(env, dict) or not env:
        return "the safety envelope is missing"
    bad = [k for k, v in env.items() if not _finite(v, positive=True)]
    if bad or "max_contact_disp_mm" not in env:
        return f"envelope values must be finite positive numbers ({', '.join(bad) or env})"
    norm = meta.get("normalisation")
    if not isinstance(norm, dict):
        return "normalisation is missing"
    for key, size in (("in_scale", 4), ("out_scale", 3)):
        values = norm.get(key)
        if not (isinstance(values, list) and len(values) == size
                and all(_finite(v, positive=True) for v in values)):
            return f"normalisation {key} must be {size} finite positive numbers"
    for key in ("architecture", "inference", "training", "baseline"):
        if not isinstance(meta.get(key, {}), dict):
            return f"{key} must be a table"
    return ""


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
