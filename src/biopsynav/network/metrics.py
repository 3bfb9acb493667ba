"""Error measures of the paper (eq. 3), masked to active nodes.

``e`` of one sample is the mean over the ``n`` active nodes of the Euclidean norm of the nodal
displacement error, in mm. Inactive nodes neither count nor dilute it.
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


def masked_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                kind: str = "mse") -> torch.Tensor:
    """Loss over active nodes only: mean of the squared (``mse``) or absolute (``l1``) error.

    ``pred``/``target`` (B, C, nx, ny, nz); ``mask`` (nx, ny, nz) float 0/1 or bool. The mean is
    taken over B * C * n_active values, so inactive nodes do not dilute it.
    """
    diff = pred - target
    err = diff * diff if kind == "mse" else diff.abs()
    m = mask.to(err.dtype)
    denom = m.sum() * pred.shape[0] * pred.shape[1]
    return (err * m).sum() / denom


def summarize(e: np.ndarray) -> dict:
    """Mean, standard deviation and maximum of per-sample errors e (mm), plus the worst index."""
    e = np.asarray(e, dtype=np.float64)
    return {"mean_e_mm": float(e.mean()), "std_e_mm": float(e.std()),
            "max_e_mm": float(e.max()), "worst_index": int(e.argmax()), "n_samples": int(e.size)}
