"""Training that starts from another trained model of the same case (``[network] init_from``).

Multi-fidelity training: a network trained on many samples of a cheap teacher (the case grid)
is trained further on a few samples of a costly one (``[dataset] teacher_refine``, rigid-probe
pushes). The new training keeps the source model's architecture, grid and normalisation, and
starts from its best weights; everything else (learning rate, iterations, data) is its own.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..inference.model_files import read_meta
from ..layout import BEST

WHERE = "[network] init_from"


@dataclass
class SourceModel:
    """A trained model training starts from.

    Attributes:
        path: its model folder.
        weights: the U-Net state dict of its best weights.
        in_scale: (C_in,) its input normalisation (mm, weight sum).
        out_scale: (3,) its output normalisation, mm.
        quad_scale: its quadratic-feature normalisation, or None.
        envelope: its training envelope (mm; see :func:`biopsynav.network.data.envelope`).
        checksum: its meta.json checksum (part of the checkpoint signature).
        teacher: what taught it (meta.json ``teacher``).
    """

    path: Path
    weights: dict
    in_scale: np.ndarray
    out_scale: np.ndarray
    quad_scale: np.ndarray | None
    envelope: dict
    checksum: str
    teacher: dict

    def summary(self) -> dict:
        """What meta.json records of the source."""
        return {"path": str(self.path), "checksum": self.checksum, "teacher": self.teacher}


def resolve_source(case_dir: Path, init_from: str) -> Path | None:
    """The model folder named by ``init_from`` (relative to the case folder, ``..`` folded
    away: ``CASE/refine`` names ``../model`` as ``CASE/model``), or None."""
    if not init_from:
        return None
    path = Path(init_from).expanduser()
    return Path(os.path.normpath(path if path.is_absolute() else case_dir / path))


def load_source(path: Path, spec: dict, node_shape: tuple, baseline: str,
                contact_input: str) -> SourceModel:
    """The model in ``path``, checked against the new training's architecture ``spec``, grid
    ``node_shape``, baseline kind and contact input; InputError naming what differs."""
    try:
        meta = read_meta(path)
    except InputError as exc:  # its advice is for the case's own model: name this option
        raise InputError(f"{path} is not a usable trained model: {exc.what}", WHERE) from None
    expected = {"architecture": spec, "node_shape": list(node_shape),
                "baseline kind": baseline, "contact input": contact_input}
    found = {"architecture": meta.get("architecture"), "node_shape": meta.get("node_shape"),
             "baseline kind": (meta.get("baseline") or {}).get("kind", "none"),
             "contact input": meta.get("contact_input", "average")}
    for key, value in expected.items():
        if found[key] != value:
            raise InputError(f"{path}: its {key} is {found[key]}, this training's is {value}; "
                             "a training can start only from a model of the same network and "
                             "grid", WHERE)
    norm = meta["normalisation"]
    quad = norm.get("quad_scale")
    return SourceModel(path, read_weights(path), np.asarray(norm["in_scale"], np.float32),
                       np.asarray(norm["out_scale"], np.float32),
                       None if quad is None else np.asarray(quad, np.float32),
                       dict(meta.get("envelope") or {}), str(meta.get("checksum")),
                       dict(meta.get("teacher") or {}))


def read_weights(path: Path) -> dict:
    """The best weights (U-Net state dict) in the model folder ``path``."""
    try:
        best = torch.load(path / BEST, map_location="cpu", weights_only=True)
        return dict(best["model"])
    except Exception as exc:  # noqa: BLE001 - any unreadable file: one line naming it
        raise InputError(f"{path / BEST}: cannot read the model's weights "
                         f"({type(exc).__name__}: {str(exc)[:120]})", WHERE) from None


def merged_envelope(own: dict, source: SourceModel | None) -> dict:
    """The envelope of a model trained on its own data after ``source``'s: each figure the
    larger of the two (both data sets taught it)."""
    if source is None:
        return own
    keys = set(own) | set(source.envelope)
    return {k: max(float(own.get(k, 0.0)), float(source.envelope.get(k, 0.0))) for k in keys}
