"""The paper's Table 1 of a case's network (``CASE/model``): its error on the paper's force
patches, solved by its own teacher's law.

    python benchmarks/table1_patches.py CASE [--samples 200] [--workdir DIR] [--keep]
                                        [--result-name NAME]

A `pushes` case (the default recipe) holds out rigid pushes, so its own Table 1 is not the
paper's protocol. This copies CASE's anatomy, grid, inputs and configuration into a scratch
case, sets the paper's training data there (force patches: ``[probe] rigid_share`` and
``calibrate_force`` at the configuration's defaults, which are the `chain` recipe's) and keeps
every other setting of CASE, the material law above all (the network's own teacher), then
``biopsynav generate`` solves ``--samples`` held-out force patches (and one training sample,
unused) and ``CASE/model``, copied there, is measured on them as ``biopsynav evaluate`` measures
Table 1 (the deployed runtime, projected onto the contact where the model projects). Run it
alone.

Writes ``benchmarks/results/table1-patches-<case name>.json`` (or ``NAME.json``); the last line
reads ``RESULT mean_e_mm=... max_e_mm=... samples=...``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from biopsynav.layout import CasePaths
from biopsynav.network.evaluate import baseline_words
from pushes_only import copy_case_files
from resultfile import write_result


def patches_config(case_dir: Path, out: Path, samples: int) -> None:
    """``out/case.toml``: ``case_dir``'s configuration with the paper's force patches as its
    data (the configuration's defaults of ``[probe] rigid_share`` and ``calibrate_force``), one
    training sample and ``samples`` held out."""
    from biopsynav.config import CaseConfig, load_config, save_config

    cfg, defaults = load_config(case_dir), CaseConfig().probe
    cfg.probe.rigid_share = defaults.rigid_share
    cfg.probe.calibrate_force = defaults.calibrate_force
    cfg.dataset.n_train, cfg.dataset.n_test = 1, samples
    save_config(out, cfg)


def measure(case_dir: Path, work: Path, samples: int) -> dict:
    """Table 1 of ``case_dir``'s model on ``samples`` force patches solved in ``work/case``:
    the model copied into that scratch case, whose configuration drew the patches (a
    projecting model redraws its contacts from it), and evaluated there as ``evaluate`` does
    (:func:`biopsynav.network.evaluate.evaluate_network_case`)."""
    from biopsynav.network.evaluate import evaluate_network_case

    out = work / "case"
    out.mkdir(parents=True)
    copy_case_files(case_dir, out)
    patches_config(case_dir, out, samples)
    subprocess.run([sys.executable, "-m", "biopsynav.cli", "generate", str(out)], check=True)
    shutil.copytree(CasePaths(case_dir).model, CasePaths(out).model)
    return evaluate_network_case(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case", type=Path)
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--keep", action="store_true", help="keep the scratch case")
    p.add_argument("--result-name", default=None)
    args = p.parse_args(argv)
    if args.samples < 1:
        p.error(f"--samples {args.samples}: at least 1 held-out force patch")
    if not CasePaths(args.case).model_meta.is_file():
        p.error(f"{args.case}: no trained model ({CasePaths(args.case).model_meta}) to "
                "measure; `biopsynav train` it first")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="table1-patches-"))
    try:
        r = measure(args.case.resolve(), work, args.samples)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    name = args.result_name or f"table1-patches-{args.case.resolve().name}"
    figures = {k: r[k] for k in ("mean_e_mm", "std_e_mm", "max_e_mm", "mean_e_dof_mm",
                                 "std_e_dof_mm", "max_e_dof_mm", "n_samples",
                                 "max_disp_mm", "contact_projection", "runtime", "precision",
                                 "inverted_samples")}
    figures.update({k: r[k] for k in ("baseline_mean_e_mm", "baseline_max_e_mm") if k in r})
    write_result(name, figures, case=str(args.case))
    print(f"Table 1 on {r['n_samples']} force patches of the case's own law: mean e "
          f"{r['mean_e_mm']:.4f} mm, max e {r['max_e_mm']:.3f} mm (largest nodal displacement "
          f"{r['max_disp_mm']:.1f} mm); read per degree of freedom (eq. 3 as written): mean "
          f"{r['mean_e_dof_mm']:.4f} mm, max {r['max_e_dof_mm']:.3f} mm"
          + (f"; {baseline_words(r)}" if "baseline_mean_e_mm" in r else ""))
    print(f"RESULT mean_e_mm={r['mean_e_mm']:.4f} max_e_mm={r['max_e_mm']:.4f} "
          f"mean_e_dof_mm={r['mean_e_dof_mm']:.4f} max_e_dof_mm={r['max_e_dof_mm']:.4f} "
          f"samples={r['n_samples']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
