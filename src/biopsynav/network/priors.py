"""Export of a case network trained from scratch as a packaged prior
(:mod:`biopsynav.prior_registry`; docs/network.md, "Starting from a prior").

    python -m biopsynav.network.priors CASE_DIR NAME DESCRIPTION
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..prior_registry import PRIOR_DIR, surface_fingerprint


def export_prior(model_dir: Path, name: str, description: str, surface: str,
                 case_name: str, out_dir: Path = PRIOR_DIR) -> Path:
    """Write the best weights of the trained model in ``model_dir`` (trained from scratch on
    the case ``case_name``, whose :func:`surface_fingerprint` is ``surface``) as the prior
    ``name`` in ``out_dir``: ``NAME.npz`` and ``NAME.json``, each written atomically. Returns
    the .npz path; InputError when that model was itself trained from another network."""
    import torch

    from ..fileio import write_json_atomic
    from ..inference.model_files import read_meta
    from ..layout import BEST

    meta = read_meta(model_dir)
    training = meta.get("training") or {}
    if training.get("prior") or training.get("init_from"):
        raise InputError(f"{model_dir} was trained from another network; a prior is trained "
                         "from scratch", "export_prior")
    best = torch.load(model_dir / BEST, map_location="cpu", weights_only=True)["model"]
    out_dir.mkdir(parents=True, exist_ok=True)
    weights, tmp = out_dir / f"{name}.npz", out_dir / f".{name}.tmp.npz"
    np.savez_compressed(tmp, **{k: v.float().numpy().astype(np.float16) for k, v in best.items()})
    tmp.replace(weights)
    write_json_atomic(out_dir / f"{name}.json", {
        "architecture": meta["architecture"], "surface_fingerprint": surface,
        "description": description,
        "source": {"case": case_name, "node_shape": meta.get("node_shape"),
                   "best_val_e_mm": training.get("best_val_e_mm"),
                   **{k: training.get(k) for k in ("iterations", "batch_size", "precision")},
                   "teacher": meta.get("teacher")}})
    return weights


def export_command(argv: list[str] | None = None) -> int:
    """``python -m biopsynav.network.priors CASE_DIR NAME DESCRIPTION``: export the case's
    trained network (``CASE_DIR/model``) as a packaged prior."""
    import sys

    from ..case import as_case
    from ..layout import MODEL_DIR

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3:
        print(export_command.__doc__)
        return 2
    case = as_case(args[0])
    print(export_prior(case.dir / MODEL_DIR, args[1], args[2], surface_fingerprint(case.anatomy),
                       case.cfg.case.name))
    return 0


if __name__ == "__main__":
    raise SystemExit(export_command())
