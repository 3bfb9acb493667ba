"""Error measures of the paper (eq. 3), masked to active nodes.

``e`` of one sample is the mean over the ``n`` active nodes of the Euclidean norm of the nodal
displacement error, in mm. Inactive nodes neither count nor dilute it. The paper's eq. (3)
divides by "the number of degrees of freedom of the mesh", which reads as the mean over the
``3 n`` displacement components of their absolute error (:func:`mean_dof_error_np`): the
same errors weigh about half as much that way (docs/network.md, "What e is, and the
paper's").
"""

from __future__ import annotations

import numpy as np
import torch


def mean_norm_error(pred: torch.Tensor, target: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """Per-sample e (B,) in mm; ``pred``/``target`` (B, 3, nx, ny, nz), ``active`` (nx, ny, nz)."""
    norm = torch.linalg.vector_norm(pred - target, dim=1)  # (B, nx, ny, nz)
    return norm[:, active].mean(dim=1)


def mean_norm_error_np(pred: np.ndarray, target: np.ndarray, active: np.ndarray) -> np.ndarray:
    """NumPy twin of :func:`mean_norm_error`: (B, 3, nx, ny, nz) x2, (nx, ny, nz) bool -> (B,)."""
    norm = np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(target, np.float64), axis=1)
    return norm[:, active].mean(axis=1)


def mean_dof_error_np(pred: np.ndarray, target: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Per-sample mean absolute error (B,) mm over the ``3 n`` displacement components of the
    active nodes: the paper's eq. (3) read per degree of freedom. (B, 3, nx, ny, nz) x2,
    (nx, ny, nz) bool."""
    diff = np.asarray(pred, np.float64) - np.asarray(target, np.float64)
    return np.abs(diff[:, :, active]).mean(axis=(1, 2))


LOSSES = ("norm", "mse", "l1")


def masked_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                kind: str = "norm", scale: torch.Tensor | None = None) -> torch.Tensor:
    """Loss over active nodes only, on normalised displacements.

    ``pred``/``target`` (B, C, nx, ny, nz); ``mask`` (nx, ny, nz) float 0/1 or bool.

    * ``norm``: the batch mean of e (the paper's eq. 3, mm): the Euclidean norm of each node's
      error, back in mm through ``scale`` (C,) (mm per normalised unit; ones when None),
      averaged over B * n_active nodes;
    * ``mse`` / ``l1``: the mean squared / absolute normalised error over B * C * n_active
      values.

    Inactive nodes neither count nor dilute the mean.
    """
    diff = pred - target
    m = mask.to(diff.dtype)
    if kind == "norm":
        if scale is not None:
            diff = diff * scale.to(diff.dtype).view(1, -1, *([1] * (diff.dim() - 2)))
        # sqrt(|d|^2 + eps): the norm's gradient stays finite where a node's error is exactly 0
        err = torch.sqrt((diff * diff).sum(dim=1) + 1e-12)  # (B, nx, ny, nz) mm
        return (err * m).sum() / (m.sum() * pred.shape[0])
    if kind not in ("mse", "l1"):
        raise ValueError(f"unknown loss {kind!r}; known: {', '.join(LOSSES)}")
    err = diff * diff if kind == "mse" else diff.abs()
    denom = m.sum() * pred.shape[0] * pred.shape[1]
    return (err * m).sum() / denom


def error_summary(e: np.ndarray) -> dict:
    """Mean, standard deviation and maximum of per-sample errors e (mm), plus the worst index."""
    e = np.asarray(e, dtype=np.float64)
    return {"mean_e_mm": float(e.mean()), "std_e_mm": float(e.std()),
            "max_e_mm": float(e.max()), "worst_index": int(e.argmax()), "n_samples": int(e.size)}
