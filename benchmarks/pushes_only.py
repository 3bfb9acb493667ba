"""The tracking network trained on a case's `[refine]` rigid pushes alone: no force patches, no
case network (docs/pipeline.md, "no force patches at all").

    python benchmarks/pushes_only.py CASE --reference TRUTH.json [--prior NAME]
                                     [--iterations 4000] [--batch 16] [--lr 2e-3]
                                     [--seed 0] [--train-samples N] [--workdir DIR]

CASE is a case whose ``refine/dataset.zarr`` is complete (e.g. the one ``make demo`` or
``time_to_model.py --keep`` leaves) and of which ``truth.py`` takes the truth as it is (its
anatomy, material, depths, mesh and probe; refused before any work otherwise, naming what
differs). A copy of it (the data set linked, not copied) gets one
training on those pushes, from scratch or from the packaged prior ``--prior``, with
``[network]``'s other settings, into ``WORKDIR/case/refine/model``; then ``truth.py``
compares that model with the stored P2 truth ``--reference`` over every lesion at 10 / 20 /
30 mm. Run it alone on the machine.

``--train-samples N`` trains on the first N training pushes only (the held-out ones stay).
Writes ``benchmarks/results/pushes-only-<case name>[-<prior>][-nN][-seed<n>].json``; the last
line reads ``RESULT tre_d10_mm=... tre_d20_mm=... tre_d30_mm=... train_min=...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
from pathlib import Path

from figures import depth_means
from resultfile import write_result
from time_to_model import net_against_truth
from truth import reference_differences

CASE_FILES = ("anatomy.npz", "grid.npz", "case.toml", "inputs")
REFINE_FILES = ("anatomy.npz", "grid.npz", "case.toml", "dataset_summary.json")


def copy_case_files(case_dir: Path, out: Path) -> None:
    """``case_dir``'s anatomy, grid, configuration and inputs (:data:`CASE_FILES`) into the
    existing folder ``out``."""
    for name in CASE_FILES:
        src = case_dir / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, out / name)


def copy_case(case_dir: Path, work: Path) -> Path:
    """``case_dir``'s anatomy, grid and configuration in ``work/case``, its refine case's too,
    with the refine data set linked; returns the copy's refine folder."""
    out = work / "case"
    (out / "refine").mkdir(parents=True)
    copy_case_files(case_dir, out)
    for name in REFINE_FILES:
        shutil.copy2(case_dir / "refine" / name, out / "refine" / name)
    (out / "refine" / "dataset.zarr").symlink_to((case_dir / "refine" / "dataset.zarr").resolve())
    return out / "refine"


def train_on_pushes(refine_dir: Path, args: argparse.Namespace) -> dict:
    """One training of the refine case's pushes (``args``: prior, iterations, batch, lr);
    its meta.json ``training``."""
    from biopsynav.case import as_case
    from biopsynav.network.train import train

    case = as_case(refine_dir)
    s = dataclasses.replace(case.cfg.network, init_from="", prior=args.prior,
                            iterations=args.iterations, batch_size=args.batch,
                            learning_rate=args.lr, warmup_iterations=300, val_interval=500,
                            seed=args.seed)
    train(case, settings=s, model_dir=refine_dir / "model", first_samples=args.train_samples)
    return json.loads((refine_dir / "model" / "meta.json").read_text())["training"]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case_dir", type=Path)
    p.add_argument("--reference", type=Path, required=True, help="stored P2 truth (JSON)")
    p.add_argument("--prior", default="none", help="[network] prior of the training")
    p.add_argument("--iterations", type=int, default=4000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0, help="[network] seed of the training")
    p.add_argument("--train-samples", type=int, default=None,
                   help="train on the first N training pushes only (default: all)")
    p.add_argument("--workdir", type=Path, default=None)
    return p


def check_reference(case_dir: Path, reference: Path) -> None:
    """Exit naming the file and what differs when ``reference`` is not a stored truth that
    ``truth.py`` would take as it is for ``case_dir`` at 10 / 20 / 30 mm (it would solve it
    again, for hours)."""
    from biopsynav.case import as_case
    from biopsynav.errors import BiopsynavError

    try:
        case = as_case(case_dir)
    except BiopsynavError as exc:
        sys.exit(f"pushes_only: {exc}")
    try:
        differs = reference_differences(case, reference, [10.0, 20.0, 30.0])
    except ValueError as exc:
        sys.exit(f"pushes_only: {reference}: {exc}")
    if differs:
        sys.exit(f"pushes_only: {reference} is no stored truth of {case_dir} as truth.py "
                 f"reads it: {', '.join(differs)} differ{'s' if len(differs) == 1 else ''}")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    check_reference(args.case_dir, args.reference)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="pushes-only-"))
    refine_dir = copy_case(args.case_dir, work)
    training = train_on_pushes(refine_dir, args)
    data = net_against_truth(refine_dir.parent, args.reference)
    tre = dict(zip(("tre_d10_mm", "tre_d20_mm", "tre_d30_mm"), depth_means(data, "net"),
                   strict=True))
    figures = {**tre, "train_min": training["train_time_s"] / 60,
               "held_out_mean_e_mm": training["best_val_e_mm"], "prior": args.prior,
               "iterations": args.iterations, "batch_size": args.batch,
               "learning_rate": args.lr, "seed": args.seed,
               "train_samples": training.get("n_train"), "rows": data["rows"]}
    name = (args.case_dir.resolve().name + ("" if args.prior == "none" else f"-{args.prior}")
            + (f"-n{args.train_samples}" if args.train_samples is not None else "")
            + (f"-seed{args.seed}" if args.seed else ""))
    write_result(f"pushes-only-{name}", figures)
    print(" ".join(["RESULT"] + [f"{k}={v:.3f}" for k, v in tre.items()]
                   + [f"train_min={figures['train_min']:.2f}"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
