"""Writing the model folder at the end of training: the exports (checked against eager),
``meta.json`` with its checksum, the history."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from ..fileio import json_default, write_json_atomic
from ..inference.model_files import FORMAT, meta_checksum, sha256
from ..inference.runtimes import ONNX, TORCHSCRIPT, load_torchscript
from ..layout import HISTORY, META
from .data import Dataset
from .export import SurrogateNet, save_onnx, save_torchscript
from .unet import UNetSpec, count_parameters


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
        "teacher": teacher(data),
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


def teacher(data: Dataset) -> dict:
    """What taught the model: the data set's protocol fingerprint, its material law and
    fictitious stiffness, its
    share of rigid-probe pushes (0: the paper's force patches only) with their contact
    constraints (and the springs' beta of elastic contact, else None), the teacher grid's
    refinement (1: the case grid) and the order of its extrapolation from the case grid
    (0: none), and the FE code (``[dataset] teacher``; with another than the grid's, what
    its answers depend on)."""
    from ..fem.teacher import whole_or_float
    from ..teacher_registry import GRID_TEACHER

    protocol = data.attrs.get("protocol") or {}
    probe, dataset = protocol.get("probe", {}), protocol.get("dataset", {})
    return {"protocol_fingerprint": data.attrs.get("protocol_fingerprint"),
            "material_model": protocol.get("material", {}).get("model"),
            "fictitious_stiffness": float(protocol.get("material", {})
                                          .get("fictitious_stiffness", 0.0)),
            "rigid_share": float(probe.get("rigid_share", 0.0)),
            "fem_contact": protocol.get("fe_model", {}).get("fem_contact"),
            "contact_stiffness": protocol.get("fe_model", {}).get("contact_stiffness"),
            "teacher_refine": whole_or_float(dataset.get("teacher_refine", 1)),
            "teacher_extrapolation": float(dataset.get("teacher_extrapolation", 0.0)),
            "teacher": dataset.get("teacher", GRID_TEACHER),
            **({"teacher_protocol": dataset["teacher_protocol"]}
               if "teacher_protocol" in dataset else {})}


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
