"""From nothing to a served model: every stage's wall time, the machine, and the accuracy
reached.

    python benchmarks/time_to_model.py [--case phantom|ucdavis|ucdavis-homogeneous]
                                       [--workdir DIR] [--keep] [--no-truth]
                                       [--prior auto --iterations 4000]
                                       [--recipe pushes|pushes-patches|chain] [--tag TAG]

* ``phantom``: what ``make demo`` does (``biopsynav demo``: the built-in phantom, every
  default, Table 2 on 3 lesions);
* ``ucdavis``: what ``biopsynav run`` does for a patient: ``init`` of the UC Davis breast of
  three tissues (fat, gland, skin) with the example lesions, then ``run``;
* ``ucdavis-homogeneous``: the same breast as one material
  (``examples/ucdavis_breast3/homogeneous.toml``), the case the stored P2 truth is of.

Run it alone on the machine: two jobs at once on 2 cores take far longer than twice as long.
The machine is recorded with two short probes of the day's speed (a shared VM runs at
different speeds on different days): one U-Net training step on the phantom's grid
(``biopsynav.runtime.probe_seconds``) and a 1,024 x 1,024 float32 matmul.

Accuracy: Table 1 (``CASE/eval/table1.json``: mean and max e of the case network against its
own FE teacher on the held-out force patches), and, where a P2 truth of the case's anatomy and
material is stored in ``src/biopsynav/data/truths/`` (the phantom; UC Davis as one material), the
tracking network's lesion TRE against it at 10 / 20 / 30 mm over every lesion
(``benchmarks/truth.py CASE --lesions 0 --methods net``; a minute or two, the truth is not
solved again). The three-tissue breast has no such truth (the P2 reference is homogeneous), so
its TRE is not measured; its time and Table 1 are.

``--recipe`` chooses the new case's training data (:mod:`biopsynav.recipes`; ``init
--recipe``, ``demo --recipe``): with ``pushes`` Table 1 is the tracking network on its
held-out rigid pushes; with ``pushes-patches`` on its held-out pushes and force patches, each kind's
figures recorded too (``table1_force_patches_mean_e_mm``, ...). ``--prior`` and
``--iterations`` set ``[network]`` in the new case (docs/network.md, "Starting from a
prior"); the result is then
``time-to-model-<case>[-<recipe>]-prior.json`` (``-itN`` added with ``--iterations N``).

The run's own estimate, printed before its long stages (docs/pipeline.md, "The expected
time"), is recorded beside the time taken (``expected_min``).

Writes ``benchmarks/results/time-to-model-<case>.json``; the last line reads
``RESULT total_min=... train_min=... tre_d10_mm=... tre_d30_mm=...`` (nan where not measured).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from biopsynav.recipes import DEFAULT_RECIPE, RECIPES
from figures import depth_means
from resultfile import write_result
from speedprobe import speed_probes

ROOT = Path(__file__).resolve().parents[1]
UCDAVIS = ROOT.parent / "shared" / "data" / "ucdavis_breast3" / "volmesh3.vtk"
TRUTHS_DIR = ROOT / "src" / "biopsynav" / "data" / "truths"  # the stored P2 truths
TRUTHS = {"phantom": TRUTHS_DIR / "phantom.json",
          "ucdavis-homogeneous": TRUTHS_DIR / "ucdavis-homogeneous.json"}


def init_ucdavis(case_dir: Path, homogeneous: bool, recipe: str) -> None:
    """``biopsynav init --recipe RECIPE`` of the UC Davis breast, as the README says."""
    if not UCDAVIS.is_file():
        sys.exit(f"time_to_model: the UC Davis breast is not at {UCDAVIS}")
    labels = "1=fat,2=fat,3=fat" if homogeneous else "1=fat,2=gland,3=skin"
    cmd = [sys.executable, "-m", "biopsynav.cli", "init", str(case_dir), "--surface",
           str(UCDAVIS), "--tissue-labels", labels, "--lesions",
           str(ROOT / "examples" / "ucdavis_breast3" / "lesions.csv"), "--recipe", recipe]
    if homogeneous:
        cmd += ["--config", str(ROOT / "examples" / "ucdavis_breast3" / "homogeneous.toml")]
    subprocess.run(cmd, check=True)


def check_network(network: dict) -> None:
    """Exit naming the option when the ``[network]`` values asked are not valid case.toml
    values (before any work)."""
    from biopsynav.config import config_from_dict
    from biopsynav.errors import InputError

    try:
        config_from_dict({"network": network}, "time_to_model options")
    except InputError as exc:
        sys.exit(f"time_to_model: {exc}")


def build_and_run(kind: str, case_dir: Path, network: dict, recipe: str) -> tuple[dict, float]:
    """The pipeline from nothing with training data of ``recipe``, ``[network]`` values
    ``network`` set in the new case (none: the recipe's): what the run returns (its stage
    times ``timings_s``, s, and its estimate before the long stages ``expected_min``) and the
    init's time (s)."""
    from biopsynav.case import make_phantom_case
    from biopsynav.config import load_config, save_config
    from biopsynav.pipeline import demo_overrides, run_case, run_demo
    from biopsynav.recipes import merged

    if kind == "phantom":
        if network:  # what run_demo builds, with those values
            make_phantom_case(case_dir, overrides=merged(demo_overrides(recipe, False),
                                                         {"network": network}))
        return run_demo(case_dir, recipe=recipe), 0.0
    t = time.perf_counter()
    init_ucdavis(case_dir, homogeneous=kind == "ucdavis-homogeneous", recipe=recipe)
    if network:
        cfg = load_config(case_dir)
        save_config(case_dir, dataclasses.replace(
            cfg, network=dataclasses.replace(cfg.network, **network)))
    init_s = time.perf_counter() - t
    return run_case(case_dir), init_s


def stage_minutes(case_dir: Path, timings: dict, init_s: float) -> dict:
    """Stage minutes: the pipeline's timings, with ``[refine]`` split into its pushes and its
    training (from the refine data set's summary and model)."""
    minutes = {k: v / 60 for k, v in timings.items()}
    if init_s:
        minutes["init"] = init_s / 60
    summary = case_dir / "refine" / "dataset_summary.json"
    meta = case_dir / "refine" / "model" / "meta.json"
    if summary.is_file() and meta.is_file():
        minutes["refine pushes"] = json.loads(summary.read_text())["minutes"]
        minutes["refine training"] = json.loads(meta.read_text())["training"]["train_time_s"] / 60
    return minutes


def net_against_truth(case_dir: Path, truth: Path) -> dict:
    """``truth.py``'s comparison of the case's tracking network with the stored P2 truth
    ``truth`` over every lesion at 10 / 20 / 30 mm (its ``--out`` JSON); the truth is read
    from a copy (truth.py may rewrite it; the stored one stays)."""
    with tempfile.TemporaryDirectory() as tmp:
        reference = Path(tmp) / "p2.json"
        shutil.copy(truth, reference)
        out = Path(tmp) / "truth.json"
        subprocess.run([sys.executable, str(ROOT / "benchmarks" / "truth.py"), str(case_dir),
                        "--lesions", "0", "--depths", "10", "20", "30", "--methods", "net",
                        "--reference", str(reference), "--out", str(out)], check=True)
        return json.loads(out.read_text())


def table1_figures(table1: dict) -> dict:
    """A run's ``eval/table1.json`` as result-file figures: mean and max e, on the node norm
    and per degree of freedom (docs/network.md, "What e is, and the paper's"), mm."""
    return {f"table1_{key}": table1.get(key)
            for key in ("mean_e_mm", "max_e_mm", "mean_e_dof_mm", "max_e_dof_mm")}


def kind_table1(table1: dict) -> dict:
    """Table 1 of each kind of held-out sample of a data set of both (the ``pushes-patches``
    recipe): ``table1_<kind>_mean_e_mm``, ``_max_e_mm`` and ``_samples``; {} for one kind."""
    return {f"table1_{kind}_{key}": v[key if key != "samples" else "n_samples"]
            for kind, v in table1.get("by_kind", {}).items()
            for key in ("mean_e_mm", "max_e_mm", "samples")}


def truth_tre(kind: str, case_dir: Path) -> dict:
    """The tracking network's TRE against the stored P2 truth, mean per depth (mm); {} where
    none is stored for this case."""
    if kind not in TRUTHS:
        return {}
    data = net_against_truth(case_dir, TRUTHS[kind])
    tre = {f"tre_d{depth}_mm": mean
           for depth, mean in zip((10, 20, 30), depth_means(data, "net"), strict=True)}
    rows = data["rows"]
    tre["answered"] = f"{sum(r['status'].get('net') == 'ok' for r in rows)}/{len(rows)}"
    return tre


def result_name(case: str, prior: str | None, iterations: int | None) -> str:
    """The result file's name: ``time-to-model-<case>``, with ``-prior`` when a prior was
    set and ``-itN`` when ``[network] iterations`` was, so that no variant overwrites the
    defaults' figures."""
    return (f"time-to-model-{case}" + ("-prior" if prior not in (None, "none") else "")
            + (f"-it{iterations}" if iterations is not None else ""))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--case", choices=("phantom", "ucdavis", "ucdavis-homogeneous"),
                   default="phantom")
    p.add_argument("--workdir", type=Path, default=None,
                   help="where the case is built (default: a temporary folder)")
    p.add_argument("--keep", action="store_true", help="keep the case folder")
    p.add_argument("--no-truth", action="store_true", help="skip the TRE against the truth")
    p.add_argument("--prior", default=None, help="[network] prior of the new case (default: "
                   "the case's default); the result file is then time-to-model-CASE-prior")
    p.add_argument("--iterations", type=int, default=None,
                   help="[network] iterations of the new case (default: the case's default); the "
                   "result file is then time-to-model-CASE[-prior]-itN")
    p.add_argument("--recipe", default=DEFAULT_RECIPE, choices=sorted(RECIPES),
                   help="the new case's training data (biopsynav.recipes; default "
                   f"{DEFAULT_RECIPE}); the result file is time-to-model-CASE-RECIPE, "
                   "time-to-model-CASE for chain (its name before recipes)")
    p.add_argument("--tag", default=None, help="appended to the result file's name (another "
                   "machine's run, say, that should not replace the reference's figures)")
    args = p.parse_args(argv)
    network = {k: v for k, v in (("prior", args.prior), ("iterations", args.iterations))
               if v is not None}
    check_network(network)
    sys.stdout.reconfigure(line_buffering=True)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="ttm-"))
    case_dir = work / args.case
    if case_dir.exists():
        sys.exit(f"time_to_model: {case_dir} exists; the benchmark starts from nothing")
    probes = speed_probes()
    start = time.perf_counter()
    run, init_s = build_and_run(args.case, case_dir, network, args.recipe)
    total_min = (time.perf_counter() - start) / 60
    minutes = stage_minutes(case_dir, run["timings_s"], init_s)
    table1 = json.loads((case_dir / "eval" / "table1.json").read_text())
    tre = {} if args.no_truth else truth_tre(args.case, case_dir)
    meta = json.loads((case_dir / "model" / "meta.json").read_text())["training"]
    figures = {"total_min": total_min, "stages_min": minutes,
               "expected_min": run.get("expected_min"),  # the run's own estimate
               "train_min": minutes.get("network training", math.nan),
               **table1_figures(table1), "precision": meta.get("precision"),
               "train_iterations": meta.get("iterations"),
               "prior": (meta.get("prior") or {}).get("name", "none"), "recipe": args.recipe,
               "table1_samples": table1.get("n_samples"), **kind_table1(table1), **tre}
    name = result_name(args.case + ("" if args.recipe == "chain" else f"-{args.recipe}"),
                       args.prior, args.iterations)
    write_result(name + (f"-{args.tag}" if args.tag else ""), figures,
                 speed_probes=probes)
    if not args.keep and args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)
    print("\n".join(f"  {k:<22} {v:6.2f} min" for k, v in minutes.items()))
    if run.get("expected_min") is not None:
        print(f"  the run expected about {run['expected_min']:.1f} min before its long stages")
    print(f"RESULT total_min={total_min:.2f} train_min={figures['train_min']:.2f} "
          f"tre_d10_mm={tre.get('tre_d10_mm', math.nan):.3f} "
          f"tre_d30_mm={tre.get('tre_d30_mm', math.nan):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
