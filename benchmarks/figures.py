"""The figures of README.md and BENCHMARKS.md, rendered from the result files of
``benchmarks/results/``.

    python benchmarks/figures.py            # print the blocks
    python benchmarks/figures.py --write    # rewrite them in README.md and BENCHMARKS.md

Each block sits between ``<!-- figures:NAME -->`` and ``<!-- /figures:NAME -->``; nothing
else in those files carries a measured figure. ``tests/test_figures.py`` fails when a block
differs from its rendering, so a figure cannot outlive the file it came from: re-measure
(the row's command), then ``--write``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from speedprobe import slowness

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = {"readme": ROOT / "README.md", "benchmarks": ROOT / "BENCHMARKS.md"}


def load(name: str) -> dict | None:
    """The result file ``benchmarks/results/<name>.json`` (None when absent)."""
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def fmt(value: float, digits: int = 2) -> str:
    """A figure to ``digits`` decimals; 'n/a' for a missing or non-finite one."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{value:.{digits}f}"


def depth_means(data: dict, method: str) -> list[float]:
    """A truth comparison's mean TRE (mm) at 10, 20 and 30 mm for ``method``."""
    out = []
    for depth in (10.0, 20.0, 30.0):
        v = [r["tre_mm"][method] for r in data["rows"]
             if r["depth_mm"] == depth and r.get("status", {}).get(method) == "ok"]
        out.append(sum(v) / len(v) if v else math.nan)
    return out


def tre(method: str) -> Callable[[dict], str]:
    """Renderer of a truth comparison's D10 / D20 / D30 for ``method``."""
    def render(data: dict) -> str:
        return " / ".join(fmt(v) for v in depth_means(data, method)) + " mm"
    return render


def ttm_tre(data: dict) -> str:
    f = data["figures"]
    if "tre_d10_mm" not in f:
        return "not measured (no P2 truth of three tissues)"
    return " / ".join(fmt(f[f"tre_d{d}_mm"]) for d in (10, 20, 30)) + " mm"


def ttm_total(data: dict) -> str:
    """The whole run's minutes and the day's speed: the U-Net probe against the reference
    machine's (``biopsynav.runtime.REFERENCE``), and the minutes at that machine's speed."""
    total, slow = data["figures"]["total_min"], slowness(data)
    return f"{fmt(total, 1)} min (speed probe {slow:.2f}x: {fmt(total / slow, 1)} at 1x)"


def with_speed(render: Callable[[dict], str]) -> Callable[[dict], str]:
    """``render``'s text, followed by the day's speed probe where the result holds one."""
    def rendered(data: dict) -> str:
        slow = slowness(data)
        return render(data) + ("" if slow is None else f" (speed probe {slow:.2f}x)")
    return rendered


def ttm_stages(data: dict) -> str:
    st = data["figures"]["stages_min"]
    return ", ".join(f"{k} {fmt(v, 1)}" for k, v in st.items()) + " min"


def ttm_table1(data: dict) -> str:
    f = data["figures"]
    return f"{fmt(f['table1_mean_e_mm'], 4)} / {fmt(f['table1_max_e_mm'], 3)} mm"


def ttm_summary(data: dict) -> str:
    """A whole run in one cell: its minutes, each stage, Table 1 and the TRE."""
    return (f"{ttm_total(data)}; {ttm_stages(data)}; Table 1 {ttm_table1(data)}; "
            f"TRE {ttm_tre(data)}")


def figure(key: str, digits: int = 2, unit: str = "") -> Callable[[dict], str]:
    """Renderer of one figure of a result file's ``figures``."""
    return lambda data: fmt(data["figures"][key], digits) + unit


def pair(a: str, b: str, digits: int = 2, unit: str = " ms") -> Callable[[dict], str]:
    return lambda data: (f"{fmt(data['figures'][a], digits)} / "
                         f"{fmt(data['figures'][b], digits)}{unit}")


def round_trip(data: dict) -> str:
    """A latency run's pose-to-POINT round trip, median / p99, and its poses lost."""
    return f"{pair('rtt_p50_ms', 'rtt_p99_ms')(data)}; {data['figures']['lost']} lost"


def p2_push_cost(data: dict) -> str:
    """The P2 truth's pushes in turn: seconds with single-precision factors and in double,
    and how far apart their answers are, per depth."""
    rows = data["figures"]["rows"]

    def joined(key: str, digits: int) -> str:
        return " / ".join(fmt(r[key], digits) for r in rows)

    apart = " / ".join(f"{r['diff_mm']:.1g}" for r in rows)
    return f"{joined('single_s', 0)} s against {joined('double_s', 0)} s; {apart} mm apart"


def p2_teacher_cost(data: dict) -> str:
    """The P2 teacher's pushes: seconds a push and the estimated minutes of 400 pushes on 16
    and 64 workers."""
    f = data["figures"]
    est = f["estimate_min"]
    return (f"a push {fmt(f['push_s_mean'], 0)} s (median {fmt(f['push_s_median'], 0)}, "
            f"{f['pushes']} pushes of {', '.join(fmt(d, 1) for d in f['probe_disp_mm'])} mm) "
            f"in {fmt(f['wall_s'] / 60, 1)} min on {f['workers']} workers; 400 pushes on 16 / "
            f"64 workers: {fmt(est['16w_400'], 0)} / {fmt(est['64w_400'], 0)} min")


def evaluate_again(data: dict) -> str:
    """A case evaluated twice: the truth solved, then kept (s), and whether the records
    agree."""
    f = data["figures"]
    same = "the same" if f["same_records"] else "NOT the same"
    return (f"{fmt(f['first_s'], 0)} s, then {fmt(f['again_s'], 0)} s; Table 2's "
            f"{f['records']} records {same}")


def p2_teacher_depths(data: dict) -> str:
    """The P2 teacher's push time against depth: the pushes' range, the deepest, the fit over
    the protocol's depths and the estimate of 400 pushes on 16 and 64 workers."""
    f = data["figures"]
    depth, seconds = f["probe_disp_mm"], f["push_s"]
    a, b = f["depth_model"]
    est = f["estimate_min"]
    deep = depth.index(max(depth))
    return (f"{f['pushes']} pushes of {fmt(min(depth), 1)}-{fmt(max(depth), 1)} mm: "
            f"{fmt(min(seconds), 0)}-{fmt(max(seconds), 0)} s (the {fmt(depth[deep], 1)} mm one "
            f"{fmt(seconds[deep], 0)} s; mean {fmt(f['push_s_mean'], 0)}); fitted "
            f"{a:.3g} exp({b:.3g} depth) s, {fmt(f['push_s_expected'], 0)} s a push over "
            f"0-{fmt(f['max_push_mm'], 0)} mm; 400 pushes on 16 / 64 workers: "
            f"{fmt(est['16w_400'], 0)} / {fmt(est['64w_400'], 0)} min")


@dataclass
class Cell:
    """One figure: the result file it comes from and how it is shown."""

    source: str
    render: Callable[[dict], str]
    command: str

    def text(self) -> str:
        data = load(self.source)
        if data is None:
            return f"not measured (`{self.command}`)"
        return self.render(data)

    def date(self) -> str:
        data = load(self.source)
        return (data or {}).get("date", "-")


def depth_series(rows: list[dict], key: str) -> str:
    """``key``'s distances of truth-agreement ``rows`` (one per depth), ``a / b / c``."""
    return " / ".join(fmt(r[key], 3) for r in rows)


def per_depth(*keys: str) -> Callable[[dict], str]:
    """Renderer of a truth-agreement result of one lesion: each of ``keys``' distances per
    row (depth), mm, the keys apart by semicolons."""
    return lambda data: "; ".join(depth_series(data["figures"]["rows"], key) + " mm"
                                  for key in keys)


def between_answers(a: str, b: str) -> Callable[[dict], str]:
    """Renderer of the distance per row (depth) between two answers ``a`` and ``b`` (lesion
    displacement vectors, mm) of a truth-agreement result of one lesion."""
    def render(data: dict) -> str:
        return " / ".join(fmt(math.dist(r[a], r[b]), 3)
                          for r in data["figures"]["rows"]) + " mm"
    return render


def every_lesion_cmd(truth: str, name: str) -> str:
    """The commands of a rounded-edge truth's refinement over every lesion at 10 mm, against
    the stored truth ``truth`` (its file name in ``src/biopsynav/data/truths``)."""
    return ("python benchmarks/truth.py CASE --lesions 0 --depths 10 20 --edge-radius 2.5 "
            "--reference-only --reference f4.json; the same with --depths 10 --tet-rim 2 "
            "--reference rim2.json; python benchmarks/truth_refinement.py f4=f4.json "
            f"rim2=rim2.json --stored src/biopsynav/data/truths/{truth}.json --result-name "
            f"{name}")


def h_lesions_cmd(ids: str, truth: str, name: str) -> str:
    """The commands of a rounded-edge truth's h refinement (4 against 2.8 mm tetrahedra near
    the probe) at lesions ``ids``, against the stored truth ``truth``."""
    return (f"python benchmarks/truth.py CASE --lesion-ids {ids} --depths 10 20 --edge-radius "
            "2.5 --tet-fine F --push-minutes 30 --reference-only --reference fF.json (F = 4, "
            "2.8); python benchmarks/truth_refinement.py f4=f4.json f28=f28.json --stored "
            f"src/biopsynav/data/truths/{truth}.json --result-name {name}")


def lesion_range(*keys: str) -> Callable[[dict], str]:
    """Renderer of a truth-refinement result of many lesions: each of ``keys``' smallest and
    largest distance over the lesions, per depth (``lo-hi / lo-hi mm``), the keys apart by
    semicolons."""
    def over_lesions(rows: list[dict], key: str) -> str:
        depths = sorted({r["depth_mm"] for r in rows})
        spans = []
        for depth in depths:
            vals = [r[key] for r in rows if r["depth_mm"] == depth and r[key] is not None]
            spans.append(f"{fmt(min(vals), 3)}-{fmt(max(vals), 3)}" if vals else "n/a")
        return " / ".join(spans) + " mm"
    return lambda data: "; ".join(over_lesions(data["figures"]["rows"], k) for k in keys)


def per_lesion_depth(*keys: str) -> Callable[[dict], str]:
    """Renderer of a truth-agreement result of several lesions: per lesion (numbered from 1),
    each of ``keys``' distances per depth, mm."""
    def render(data: dict) -> str:
        rows = data["figures"]["rows"]
        parts = []
        for lesion in dict.fromkeys(r["lesion"] for r in rows):
            mine = [r for r in rows if r["lesion"] == lesion]
            parts.append(f"lesion {lesion + 1}: "
                         + "; ".join(depth_series(mine, k) for k in keys) + " mm")
        return ", ".join(parts)
    return render


AGREE_CMD = ("python benchmarks/truth_agreement.py --lesion-ids 1 --stored "
             "src/biopsynav/data/truths/phantom.json")


def agreement_cmd(lesion_ids: str, result_name: str) -> str:
    """The command of a P2-against-NGSolve agreement on phantom lesions ``lesion_ids``
    (their ids, comma-separated), 20 minutes a push, written as ``result_name``."""
    return (f"python benchmarks/truth_agreement.py --lesion-ids {lesion_ids} --stored "
            "src/biopsynav/data/truths/phantom.json --orders 2 --push-minutes 20 "
            f"--result-name {result_name}")
TRUTH_CMD = ("python benchmarks/truth.py CASE --lesions 0 --reference "
             "src/biopsynav/data/truths/phantom.json")
UCD_TRUTH_CMD = ("python benchmarks/truth.py CASE --lesions 0 --reference "
                 "src/biopsynav/data/truths/ucdavis-homogeneous.json")
TTM = "python benchmarks/time_to_model.py --case {}"
TTM_CHAIN = TTM + " --recipe chain"
PUSHES_CMD = "python benchmarks/pushes_only.py CASE --reference src/biopsynav/data/truths/{}.json"


def pushes_only(data: dict) -> str:
    """A pushes-only training's TRE at 10 / 20 / 30 mm and its minutes."""
    f = data["figures"]
    return (" / ".join(fmt(f[f"tre_d{k}_mm"]) for k in (10, 20, 30))
            + f" mm; {fmt(f['train_min'], 1)} min")


def bf16_cells(d: dict) -> str:
    """The cells of a ``bf16_cpu.py`` result."""
    f = d["figures"]
    return (f"{fmt(f['fp32_cl_ms'], 1)} / {fmt(f['bf16_cl_ms'], 1)} / "
            f"{fmt(f['bf16_contig_ms'], 1)} ms; {fmt(f['fp32_cl_b16_ms'], 1)} / "
            f"{fmt(f['bf16_cl_b16_ms'], 1)} ms; {f['nan_cl']} / {f['nan_contig']}; "
            f"{' '.join(d['machine']['cpu_flags']) or 'none'}")


def ttm_kinds(data: dict) -> str:
    """Table 1 of a whole run of both kinds of held-out sample (the ``pushes-patches`` recipe): the
    force patches' and the rigid pushes' mean / max e and counts."""
    f = data["figures"]
    return "; ".join(
        f"{words} {fmt(f[f'table1_{kind}_mean_e_mm'], 4)} / "
        f"{fmt(f[f'table1_{kind}_max_e_mm'], 3)} mm ({f[f'table1_{kind}_samples']})"
        for kind, words in (("force_patches", "force patches"), ("rigid_pushes", "rigid pushes")))


def mixed_summary(data: dict) -> str:
    """A whole run of the ``pushes-patches`` recipe in one cell: its minutes, each stage, Table 1 of
    each kind and the TRE."""
    return (f"{ttm_total(data)}; {ttm_stages(data)}; Table 1 {ttm_kinds(data)}; "
            f"TRE {ttm_tre(data)}")


MIXED_TAG = "amx"


def mixed_cell(case: str, render: Callable[[dict], str]) -> Cell:
    """The ``pushes-patches`` recipe's whole run of ``case`` (Intel Xeon with AMX-BF16)."""
    return Cell(f"time-to-model-{case}-pushes-patches-{MIXED_TAG}", render,
                TTM.format(case) + f" --recipe pushes-patches --tag {MIXED_TAG}")


def table1_cell(d: dict) -> str:
    """Mean / max e of a ``table1_patches.py`` result, and per degree of freedom and of the
    physics baseline alone where they were measured."""
    f = d["figures"]
    dof = (f"; per degree of freedom {fmt(f['mean_e_dof_mm'], 4)} / {fmt(f['max_e_dof_mm'], 3)}"
           " mm" if "mean_e_dof_mm" in f else "")
    base = (f"; the physics baseline alone {fmt(f['baseline_mean_e_mm'], 4)} / "
            f"{fmt(f['baseline_max_e_mm'], 3)} mm" if "baseline_mean_e_mm" in f else "")
    return f"{fmt(f['mean_e_mm'], 4)} / {fmt(f['max_e_mm'], 3)} mm{dof}{base}"


def sweep_cell(d: dict) -> str:
    """The figures of ``mri_breasts.py --all``."""
    rows = d["rows"]
    chosen = sum(not r["side_asked"] and not r["error"] for r in rows)
    asked = sum("--side" in r["error"] for r in rows)
    warned = sum(bool(r.get("warnings")) for r in rows if not r["error"])
    return (f"{chosen}; {asked}; {d['modelled']}, {d['tumours_found']}; {warned}; "
            f"{d['refused']}")


#: BENCHMARKS.md: (what, cell, target, paper)
BENCH_ROWS: list[tuple[str, Cell, str, str]] = [
    ("`make demo` from nothing, phantom, the default recipe `pushes` (450 rigid pushes, one "
     "network; Intel Xeon with AMX-BF16; the evaluation with each lesion's self-check; uniform "
     "depths, the recipe before 2026-12-08): whole; "
     "each stage; Table 1 on its 50 held-out rigid pushes; the TRE against the P2 truth, "
     "10 / 20 / 30 mm",
     Cell("time-to-model-phantom-pushes-amx", ttm_summary,
          TTM.format("phantom") + " --recipe pushes --tag amx"), "<= 15 min", "-"),
    ("the same on an AMD EPYC with AVX-512 BF16 and no AMX, with the teacher gap in each "
     "lesion's self-check and the FE engine's tangents evaluated only where factored (the "
     "Intel row above was measured before both): whole; each stage; Table 1; the TRE",
     Cell("time-to-model-phantom-pushes-avx512-gap", ttm_summary,
          TTM.format("phantom") + " --recipe pushes --tag avx512-gap"), "<= 15 min", "-"),
    ("the same on an Intel Xeon whose VM shows AVX-512 BF16 and hides AMX, the arithmetic of "
     "training and inference chosen by timing both (fp32 there: bf16 trains 1.4 times slower), "
     "today's recipe (training pushes drawn deep more often, `train_depth_exponent` 0.7; the "
     "rows above: uniform depths): whole; each stage; Table 1; the TRE",
     Cell("time-to-model-phantom-pushes-xeon", ttm_summary,
          TTM.format("phantom") + " --recipe pushes --tag xeon"), "<= 15 min", "-"),
    ("that AMD EPYC network: the paper's Table 1, mean / max e on 200 force patches solved by "
     "its own teacher's law; the same errors read per degree of freedom (the paper's eq. 3 as "
     "written); the network's physics baseline alone (its head at zero)",
     Cell("table1-patches-phantom-pushes-avx512-gap", table1_cell,
          "python benchmarks/table1_patches.py CASE --result-name "
          "table1-patches-phantom-pushes-avx512-gap"),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("the Intel network: the paper's Table 1, mean / max e on 200 force patches (the paper's "
     "data) solved by its own teacher's law",
     Cell("table1-patches-phantom-pushes-amx", table1_cell,
          "python benchmarks/table1_patches.py CASE --result-name "
          "table1-patches-phantom-pushes-amx"),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("`run` from nothing, UC Davis of three tissues, the default recipe `pushes` (Intel Xeon; "
     "uniform depths, the recipe before 2026-12-08, as the next row): whole; each stage; "
     "Table 1 on its held-out rigid pushes",
     Cell("time-to-model-ucdavis-pushes-amx", ttm_summary,
          TTM.format("ucdavis") + " --recipe pushes --tag amx"), "<= 15 min", "-"),
    ("the same on an AMD EPYC with AVX-512 BF16 and no AMX, with the teacher gap in each "
     "lesion's self-check and the FE engine's tangents evaluated only where factored (Table 2 "
     "against the fine-grid truth, 391 s of the evaluation): whole; each stage; Table 1",
     Cell("time-to-model-ucdavis-pushes-avx512-gap", ttm_summary,
          TTM.format("ucdavis") + " --recipe pushes --tag avx512-gap"), "<= 15 min", "-"),
    ("the same on an Intel Xeon whose VM shows AVX-512 BF16 and hides AMX, the arithmetic "
     "chosen by timing (fp32 there; Table 2 against the fine-grid truth, said so), today's "
     "recipe (training pushes drawn deep more often): whole; each stage; Table 1",
     Cell("time-to-model-ucdavis-pushes-xeon", ttm_summary,
          TTM.format("ucdavis") + " --recipe pushes --tag xeon"), "<= 15 min", "-"),
    ("the same network: the paper's Table 1 on 200 force patches of its own teacher's law",
     Cell("table1-patches-ucdavis-pushes-amx", table1_cell,
          "python benchmarks/table1_patches.py CASE --result-name "
          "table1-patches-ucdavis-pushes-amx"),
     "-", "-"),
    ("`demo --recipe pushes-patches` from nothing, phantom (the `pushes` recipe's 450 rigid "
     "pushes and 270 force patches of their law, one network; Intel Xeon with AMX-BF16): "
     "whole; each stage; Table 1 "
     "on its held-out force patches and rigid pushes; the TRE against the P2 truth, 10 / 20 "
     "/ 30 mm", mixed_cell("phantom", mixed_summary), "<= 15 min", "-"),
    ("the same network: the paper's Table 1, mean / max e on 200 force patches (the paper's "
     "data) solved by its own teacher's law",
     Cell("table1-patches-phantom-pushes-patches", table1_cell,
          "python benchmarks/table1_patches.py CASE --result-name "
          "table1-patches-phantom-pushes-patches"),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("the same recipe's phantom network made on the AMD EPYC (`time_to_model.py --case phantom "
     "--recipe pushes-patches --tag avx512`, 21.5 min on 2026-12-06): the paper's Table 1 on "
     "200 force patches; read per degree of freedom",
     Cell("table1-patches-phantom-pushes-patches-avx512", table1_cell,
          "python benchmarks/table1_patches.py CASE --result-name "
          "table1-patches-phantom-pushes-patches-avx512"),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("`run --recipe pushes-patches` from nothing, UC Davis of three tissues (the same machine): "
     "whole; each stage; Table 1 of each kind", mixed_cell("ucdavis", mixed_summary),
     "<= 15 min", "-"),
    ("`run --recipe pushes-patches` from nothing, UC Davis as one material (Table 2 against the P2 "
     "truth): whole; each stage; Table 1 of each kind; the TRE against the P2 truth, 10 / 20 "
     "/ 30 mm", mixed_cell("ucdavis-homogeneous", mixed_summary),
     "<= 15 min; D10 <= 0.209, D30 <= 1.44 mm", "-"),
    ("`demo --recipe chain` from nothing, phantom (force patches, case network, `[refine]`; "
     "Intel Xeon with AMX-BF16): whole pipeline",
     Cell("time-to-model-phantom", ttm_total, TTM_CHAIN.format("phantom")), "<= 15 min",
     "278 min (GPU)"),
    ("the same, each stage", Cell("time-to-model-phantom", ttm_stages,
                                  TTM_CHAIN.format("phantom")), "-", "-"),
    ("the same: Table 1, mean / max e against its own FE teacher (200 held-out force patches)",
     Cell("time-to-model-phantom", ttm_table1, TTM_CHAIN.format("phantom")),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("the same: the tracking network's lesion TRE against the P2 truth, 10 / 20 / 30 mm",
     Cell("time-to-model-phantom", ttm_tre, TTM_CHAIN.format("phantom")),
     "D10 <= 0.5, D30 <= 1.5 mm", "-"),
    ("the same on an AMD EPYC with AVX-512 BF16 and no AMX (bf16 training): whole; each "
     "stage; Table 1; the TRE against the P2 truth, 10 / 20 / 30 mm",
     Cell("time-to-model-phantom-avx512", ttm_summary,
          TTM_CHAIN.format("phantom") + " --tag avx512"), "<= 15 min", "-"),
    ("`init --recipe chain` and `run` from nothing, UC Davis of three tissues: whole pipeline",
     Cell("time-to-model-ucdavis", ttm_total, TTM_CHAIN.format("ucdavis")), "<= 15 min", "-"),
    ("the same, each stage", Cell("time-to-model-ucdavis", ttm_stages,
                                  TTM_CHAIN.format("ucdavis")), "-", "-"),
    ("the same: Table 1", Cell("time-to-model-ucdavis", ttm_table1, TTM_CHAIN.format("ucdavis")),
     "<= 0.05 / 0.27 mm", "0.052 / 0.266 mm"),
    ("lesion TRE against the P2 truth, every phantom lesion, 10 / 20 / 30 mm: the chain's "
     "network of 2026-12-02 (`--recipe chain`)",
     Cell("phantom-default-truth", tre("net"), TRUTH_CMD), "D10 <= 0.5, D30 <= 1.5 mm", "-"),
    ("the same, one network trained on the demo's 1,000 rigid pushes alone (no force patches, "
     "no case network; from scratch, 4,000 iterations at batch 16); its training minutes",
     Cell("pushes-only-phantom", pushes_only, PUSHES_CMD.format("phantom")),
     "D10 <= 0.5, D30 <= 1.5 mm", "-"),
    ("the same, the default recipe's data: the first 400 of the AMD EPYC demo's pushes, "
     "training seed 1 (seed 0 is the `pushes` demo's own network, the first row)",
     Cell("pushes-only-phantom-n400-seed1", pushes_only,
          PUSHES_CMD.format("phantom") + " --train-samples 400 --seed 1"),
     "D10 <= 0.5, D30 <= 1.5 mm", "-"),
    ("Table 1 of that case, mean / max e; one prediction, median / p99",
     Cell("train-and-predict", with_speed(lambda d: (
         f"{fmt(d['figures']['mean_e_mm'], 4)} / {fmt(d['figures']['max_e_mm'], 3)} mm; "
         f"{fmt(d['figures']['predict_p50_ms'])} / {fmt(d['figures']['predict_p99_ms'])} ms")),
          "python benchmarks/train_and_predict.py CASE --no-train"),
     "<= 0.05 / 0.27 mm; <= 3 / 6 ms", "0.052 / 0.266 mm; 3.14 ms (GPU)"),
    ("the same: its FE teacher (7.3 mm hexahedra, elastic contact)",
     Cell("phantom-default-mixed-d30-all-truth", tre("fem"), TRUTH_CMD),
     "within 0.3 mm of converged at 30 mm", "-"),
    ("the same: the rigid assumption",
     Cell("phantom-default-mixed-d30-all-truth", tre("rigid"), TRUTH_CMD), "-", "-"),
    ("the P2 truth against a second FE code (NGSolve, the same tetrahedra, the face glued), "
     "phantom lesion 1 at 10 / 20 / 30 mm: distance between their lesion displacements",
     Cell("truth-agreement-phantom", per_depth("codes_mm"), AGREE_CMD + " --orders 2"),
     "<= 0.2 mm at 30 mm", "-"),
    ("the same: what the probe body changes (the stored truth, reached skin sliding on the "
     "face, against the glued face)",
     Cell("truth-agreement-phantom", per_depth("contact_mm"), AGREE_CMD + " --orders 2"),
     "-", "-"),
    ("the same, phantom lesion 2 at 10 / 20 / 30 mm: between the two codes; what the probe "
     "body changes",
     Cell("truth-agreement-phantom-lesion1", per_depth("codes_mm", "contact_mm"),
          agreement_cmd("2", "truth-agreement-phantom-lesion1")), "<= 0.2 mm at 30 mm", "-"),
    ("the same, phantom lesions 3 and 4 at 10 / 20 / 30 mm: between the two codes; what the "
     "probe body changes",
     Cell("truth-agreement-phantom-lesions2-3", per_lesion_depth("codes_mm", "contact_mm"),
          agreement_cmd("3,4", "truth-agreement-phantom-lesions2-3")), "<= 0.2 mm at 30 mm",
     "-"),
    ("the same, phantom lesion 4 with one quadrature rule in both codes (24 points): between "
     "the two codes (degree 5 in each: 0.003 / 0.018 / 0.261 mm, the rows above)",
     Cell("truth-agreement-phantom-lesion3-q7", per_depth("codes_mm"),
          agreement_cmd("4", "truth-agreement-phantom-lesion3-q7")
          + " --quadrature-degree 7 --intorder 6"), "<= 0.2 mm at 30 mm", "-"),
    ("the same at 10 mm: NGSolve's P3 against its P2 on the same mesh",
     Cell("truth-agreement-phantom-p3", per_depth("p3_mm"), AGREE_CMD + " --depths 10 "
          "--orders 2 3 --result-name truth-agreement-phantom-p3"), "<= 0.1 mm", "-"),
    ("the P2 truth's h refinement, phantom lesion 1, the face glued: its lesion displacement "
     "with 4 mm tetrahedra near the probe (55,446 unknowns) against 2.8 mm (112,761), 10 / 20 "
     "/ 30 mm",
     Cell("truth-agreement-phantom-h", per_depth("h2.8_mm"), AGREE_CMD + " --orders "
          "--h-fine 2.8 --push-minutes 50 --result-name truth-agreement-phantom-h"),
     "<= 0.1 mm", "-"),
    ("the same at 10 / 20 mm with 2 mm tetrahedra near the probe (247,341 unknowns): 4 mm "
     "against 2 mm; 2.8 mm against 2 mm",
     Cell("truth-agreement-phantom-h2", lambda d: per_depth("h2_mm")(d) + "; "
          + between_answers("p2_h2.8", "p2_h2")(d), AGREE_CMD + " --orders --h-fine 2.8 2.0 "
          "--depths 10 20 --push-minutes 60 --result-name truth-agreement-phantom-h2"),
     "<= 0.1 mm", "-"),
    ("the same with tetrahedra of 1 mm along the face's edge at rest in every mesh (the glued "
     "outline resolved: 428 held nodes on 4 mm, 456 on 2.8 mm), 10 mm: 4 mm against 2.8 mm "
     "(the h refinement); the 1 mm rim against 0.5 mm (273,288 unknowns; the rim refinement)",
     Cell("truth-agreement-phantom-rim-d10", per_depth("h2.8_mm", "r0.5_mm"), AGREE_CMD
          + " --orders --depths 10 --rim 1 --h-fine 2.8 --rim-fine 0.5 --push-minutes 40 "
          "--result-name truth-agreement-phantom-rim-d10"), "<= 0.1 mm", "-"),
    ("the same 1 mm rim mesh (4 mm near the probe, 106,518 unknowns), 10 mm: between the two "
     "codes (NGSolve's P2 on the same tetrahedra, the same held nodes)",
     Cell("truth-agreement-phantom-rim-ng-d10", per_depth("codes_mm"), AGREE_CMD
          + " --depths 10 --rim 1 --orders 2 --result-name truth-agreement-phantom-rim-ng-d10"),
     "<= 0.2 mm at 30 mm", "-"),
    ("the truth's own contact model (the probe body, a sticking face) with its edges rounded "
     "by 2.5 mm, phantom lesion 1, 10 mm: a 2 mm rim against 1 mm (62,598 and 106,518 "
     "unknowns; 20 mm answered by the 2 mm rim alone, 30 mm by neither); the stored truth "
     "(sharp edges, no rim) against the 1 mm rim's answer",
     Cell("truth-refinement-phantom-edge25-stick",
          per_depth("step_rim2_rim1_mm", "stored_truth_to_finest_mm"),
          "python benchmarks/truth.py CASE --lesion-ids 1 --depths 10 20 30 --edge-radius 2.5 "
          "--tet-rim R --reference-only --reference rimR.json (R = 2, 1); python "
          "benchmarks/truth_refinement.py rim2=rim2.json rim1=rim1.json --stored "
          "src/biopsynav/data/truths/phantom.json --result-name "
          "truth-refinement-phantom-edge25-stick"), "<= 0.1 mm", "-"),
    ("the same rounded-edge truth without a rim, phantom lesion 1, at the depths both answer: "
     "4 mm tetrahedra near the probe (55,446 unknowns) against 2.8 mm (112,761; the h "
     "refinement); the stored truth (sharp edges, 4 mm) against the 2.8 mm answer",
     Cell("truth-refinement-phantom-edge25-norim",
          per_depth("step_f4_f28_mm", "stored_truth_to_finest_mm"),
          "python benchmarks/truth.py CASE --lesion-ids 1 --depths 10 20 30 --edge-radius 2.5 "
          "--tet-fine F --reference-only --reference fF.json (F = 4, 2.8); python "
          "benchmarks/truth_refinement.py f4=f4.json f28=f28.json --stored "
          "src/biopsynav/data/truths/phantom.json --result-name "
          "truth-refinement-phantom-edge25-norim"), "<= 0.1 mm", "-"),
    ("the rounded-edge truth (the probe body, a sticking face, edges rounded by 2.5 mm) at "
     "every phantom lesion (10), 10 mm: 4 mm tetrahedra near the probe (no rim) against a 2 mm "
     "rim (smallest-largest over the lesions); the stored truth (sharp edges, 4 mm) against the "
     "rim's answer",
     Cell("truth-refinement-phantom-every-lesion-d10",
          lesion_range("step_f4_rim2_mm", "stored_truth_to_finest_mm"),
          every_lesion_cmd("phantom", "truth-refinement-phantom-every-lesion-d10")),
     "<= 0.1 mm", "-"),
    ("the next step at the two phantom lesions whose step to the 2 mm rim exceeded 0.1 mm "
     "(lesions 9 and 10), 10 mm: the 2 mm rim against a 1 mm rim; the stored truth against the "
     "1 mm rim's answer",
     Cell("truth-refinement-phantom-lesions-9-10-rim1-d10",
          lesion_range("step_rim2_rim1_mm", "stored_truth_to_finest_mm"),
          "python benchmarks/truth.py CASE --lesion-ids 9,10 --depths 10 --edge-radius 2.5 "
          "--tet-rim 1 --reference-only --reference rim1.json; python "
          "benchmarks/truth_refinement.py f4=f4.json rim2=rim2.json rim1=rim1.json --stored "
          "src/biopsynav/data/truths/phantom.json --result-name "
          "truth-refinement-phantom-lesions-9-10-rim1-d10"),
     "<= 0.1 mm", "-"),
    ("the same at every UC Davis lesion (5; one material)",
     Cell("truth-refinement-ucdavis-every-lesion-d10",
          lesion_range("step_f4_rim2_mm", "stored_truth_to_finest_mm"),
          every_lesion_cmd("ucdavis-homogeneous", "truth-refinement-ucdavis-every-lesion-d10")),
     "<= 0.1 mm", "-"),
    ("the same rounded-edge truth without a rim, more lesions at 10 / 20 mm "
     "(smallest-largest): 4 mm tetrahedra near the probe against 2.8 mm (the h refinement); "
     "the stored truth against the 2.8 mm answer; phantom lesions 4 and 8",
     Cell("truth-refinement-phantom-edge25-h-lesions",
          lesion_range("step_f4_f28_mm", "stored_truth_to_finest_mm"),
          h_lesions_cmd("4,8", "phantom", "truth-refinement-phantom-edge25-h-lesions")),
     "<= 0.1 mm", "-"),
    ("the same, UC Davis lesions 1, 3 and 4",
     Cell("truth-refinement-ucdavis-edge25-h-lesions",
          lesion_range("step_f4_f28_mm", "stored_truth_to_finest_mm"),
          h_lesions_cmd("1,3,4", "ucdavis-homogeneous",
                        "truth-refinement-ucdavis-edge25-h-lesions")),
     "<= 0.1 mm", "-"),
    ("the same h refinement with a 2 mm rim in both meshes (the face's outline resolved), "
     "phantom lesion 4, 10 / 20 mm (66,471 and 122,628 unknowns; without the rim 0.238 mm "
     "at 20 mm, two rows above): 4 against 2.8 mm; the stored truth against the 2.8 mm answer",
     Cell("truth-refinement-phantom-lesion4-rim2-h",
          per_depth("step_rim2f4_rim2f28_mm", "stored_truth_to_finest_mm"),
          "python benchmarks/truth.py CASE --lesion-ids 4 --depths 10 20 --edge-radius 2.5 "
          "--tet-rim 2 --tet-fine F --reference-only --reference rim2fF.json (F = 4, 2.8); "
          "python benchmarks/truth_refinement.py rim2f4=rim2f4.json rim2f28=rim2f28.json "
          "--stored src/biopsynav/data/truths/phantom.json --result-name "
          "truth-refinement-phantom-lesion4-rim2-h"), "<= 0.1 mm", "-"),
    ("the same, UC Davis (one material) lesion 5 at 10 / 20 / 30 mm (108,300 unknowns): "
     "between the two codes; what the probe body changes",
     Cell("truth-agreement-ucdavis-lesion4", per_depth("codes_mm", "contact_mm"),
          "python benchmarks/truth_agreement.py CASE --lesion-ids 5 --stored "
          "src/biopsynav/data/truths/ucdavis-homogeneous.json --orders 2 --push-minutes 30 "
          "--result-name truth-agreement-ucdavis-lesion4"), "<= 0.2 mm at 30 mm", "-"),
    ("one push of the P2 truth (10 mm tetrahedra, 4 mm near the probe, the face's edges rounded "
     "by 2.5 mm), phantom lesion 1 at 10 / 20 / 30 mm in turn: Newton's tangents factored in "
     "single precision (the default) against double; the distance between their lesion "
     "displacements",
     Cell("p2-push-phantom-lesion1", with_speed(p2_push_cost),
          "python benchmarks/p2_push.py --lesion-ids 1 --depths 10 20 30 --push-minutes 20"),
     "a 30 mm UC Davis push <= 10 s, within 0.05 mm of the full solve", "-"),
    ("the same, UC Davis (one material) lesion 5 at 10 mm (108,300 unknowns)",
     Cell("p2-push-ucdavis-homogeneous-lesion5", with_speed(p2_push_cost),
          "python benchmarks/p2_push.py CASE --lesion-ids 5 --depths 10 --result-name "
          "p2-push-ucdavis-homogeneous-lesion5"),
     "a 30 mm UC Davis push <= 10 s, within 0.05 mm of the full solve", "-"),
    ("the P2 teacher (`[refine] teacher = \"p2\"`, the truth's 4 mm tetrahedra), phantom: its "
     "rigid pushes through a Dask LocalCluster (one thread a worker), and the estimate for "
     "larger clusters (`N (push + overhead) / workers`; the first pushes of the draw order, "
     "shallower than the uniform 0-35 mm, so a low estimate)",
     Cell("p2-teacher-phantom", with_speed(p2_teacher_cost),
          "python benchmarks/p2_teacher.py --samples 4"), "-", "-"),
    ("the P2 teacher's push time against the push's depth (phantom, one thread, the pushes a "
     "stopped `refine` of N = 50 + 6 had solved, in the draw order), fitted `a exp(b depth)` and "
     "averaged over the protocol's depths (uniform to 35 mm, capped at the 30 min limit): the "
     "estimate `biopsynav.runtime` prices the P2 teacher with",
     Cell("p2-teacher-phantom-depths", with_speed(p2_teacher_depths),
          "biopsynav refine CASE (a phantom case, [refine] teacher = \"p2\", samples = 56, "
          "held_out = 6; stopped); python benchmarks/p2_teacher.py --store CASE/refine "
          "--result-name p2-teacher-phantom-depths"), "-", "-"),
    ("`evaluate` of a trained UC Davis case of three tissues (the `pushes` network of "
     "`time_to_model.py --case ucdavis`; Table 2 against the fine-grid truth), twice: the "
     "truth solved and kept, then served (`biopsynav.evaluate.kept`), as after training again",
     Cell("evaluate-again-ucdavis", with_speed(evaluate_again),
          "python benchmarks/evaluate_again.py CASE --result-name evaluate-again-ucdavis"),
     "-", "-"),
    ("`run` from nothing, UC Davis as one material, the default recipe `pushes` (Intel Xeon; "
     "uniform depths, the recipe before 2026-12-08; Table 2 against the shipped P2 truth, "
     "`examples/ucdavis_breast3/homogeneous.toml`): "
     "whole; each stage; Table 1 on its held-out rigid pushes; the tracking network's TRE "
     "against the P2 truth over every lesion, 10 / 20 / 30 mm",
     Cell("time-to-model-ucdavis-homogeneous-pushes-amx", ttm_summary,
          TTM.format("ucdavis-homogeneous") + " --recipe pushes --tag amx"),
     "<= 15 min; D10 <= 0.209, D30 <= 1.44 mm", "-"),
    ("the same breast: the chain's network (defaults of 2026-11-30)",
     Cell("ucdavis-default-mixed-d30-all-truth", tre("net"), UCD_TRUTH_CMD), "-", "-"),
    ("the same: its FE teacher",
     Cell("ucdavis-default-mixed-d30-all-truth", tre("fem"), UCD_TRUTH_CMD), "-", "-"),
    ("the same breast: one network trained on 1,000 `[refine]` rigid pushes alone (as the "
     "phantom's above); its training minutes",
     Cell("pushes-only-ucdh", pushes_only, PUSHES_CMD.format("ucdavis-homogeneous")), "-", "-"),
    ("the same breast, the default recipe's data: the first 400 of a second set of 1,000 "
     "pushes, training seed 0",
     Cell("pushes-only-ucdh2-n400", pushes_only,
          PUSHES_CMD.format("ucdavis-homogeneous") + " --train-samples 400"), "-", "-"),
    ("the same, training seed 1",
     Cell("pushes-only-ucdh2-n400-seed1", pushes_only,
          PUSHES_CMD.format("ucdavis-homogeneous") + " --train-samples 400 --seed 1"), "-", "-"),
    ("one FE solve, phantom grid, 3.0 N push: biopsynav / scikit-fem",
     Cell("fem-solve", with_speed(pair("fem_ms", "peer_ms", 0)),
          "python benchmarks/fem_solve.py"),
     "<= 250 ms", "407.7 ms (SOFA)"),
    ("force patches per minute, 2 workers",
     Cell("generate", figure("per_min_2w", 0), "python benchmarks/generate.py"), "-", "-"),
    ("rigid pushes per minute (the `pushes` recipe's, elastic contact), 1 / 2 workers",
     Cell("generate-pushes", pair("per_min_1w", "per_min_2w", 1, ""),
          "python benchmarks/generate.py --recipe pushes --samples 40"), "-", "-"),
    ("tracker update, median / p99 (the phantom's default `pushes` network)",
     Cell("tracking-latency", with_speed(pair("update_p50_ms", "update_p99_ms")),
          "python benchmarks/tracking_latency.py CASE"), "<= 3 / 6 ms", "-"),
    ("pose to lesions in Slicer's connector at 100 Hz, median / p99; poses without an answer",
     Cell("tracking-latency", with_speed(round_trip), "python benchmarks/tracking_latency.py "
          "CASE"), "<= 5 / 10 ms", "-"),
    ("the same two on the Intel Xeon without AMX (the phantom's default `pushes` network of "
     "its `time_to_model.py --tag xeon` run, OpenVINO fp32)",
     Cell("tracking-latency-xeon",
          with_speed(lambda d: f"{pair('update_p50_ms', 'update_p99_ms')(d)}; "
                               f"{round_trip(d)}"),
          "python benchmarks/tracking_latency.py CASE --duration 30 --result-name "
          "tracking-latency-xeon"), "<= 3 / 6 ms; <= 5 / 10 ms", "-"),
    ("the same two on a large clinical breast (MRI exam 31 left, 1,189 mL, 3,986 cells, a skin "
     "of 95,642 vertices; docs/igtl.md, 'Latency')",
     Cell("tracking-latency-mri31-left",
          with_speed(lambda d: f"{pair('update_p50_ms', 'update_p99_ms')(d)}; "
                               f"{round_trip(d)}"),
          "python benchmarks/tracking_latency.py CASE --result-name "
          "tracking-latency-mri31-left"), "<= 3 / 6 ms; <= 5 / 10 ms", "-"),
    ("each lesion's 95 % error bound with its self-check (the network against its teacher, the "
     "teacher against a finer grid), fitted on UC Davis (4 networks): share of the phantom's "
     "TREs within it (7 networks); "
     "worst ratio of mean bound to mean TRE over 10 / 20 / 30 mm; the same bound without "
     "the self-check",
     Cell("error-bound", lambda d: (f"{d['figures']['coverage']:.0%}; "
                                    f"{d['figures']['worst_ratio']:.1f}x; without: "
                                    f"{d['figures']['unchecked_coverage']:.0%}; "
                                    f"{d['figures']['unchecked_worst_ratio']:.1f}x"),
          "python benchmarks/error_bound.py"), "90-97 %; <= 3x", "-"),
    ("the same bound on two MRI breasts made one material (exams 01 and 05, right; 10 pushes "
     "the truth answered), left out of the fit: share within it; worst ratio of mean bound to "
     "mean TRE; the same without the check",
     Cell("error-bound-mri", lambda d: (f"{d['figures']['coverage']:.0%}; "
                                        f"{d['figures']['worst_ratio']:.1f}x; without: "
                                        f"{d['figures']['unchecked_coverage']:.0%}"),
          "python benchmarks/error_bound.py --check "
          "benchmarks/results/bound-rows-mri01r-homogeneous-pushes.json "
          "benchmarks/results/bound-rows-mri05r-homogeneous-pushes.json --result-name "
          "error-bound-mri"), "90-97 %; <= 3x", "-"),
    ("the same bound on the networks of today's `pushes` recipe (training pushes drawn deep "
     "more often; phantom and UC Davis as one material, seeds 0 and 1; fitted before on "
     "networks of uniform depths): share within it; worst ratio; the same without the check",
     Cell("error-bound-deep", lambda d: (f"{d['figures']['coverage']:.0%}; "
                                         f"{d['figures']['worst_ratio']:.1f}x; without: "
                                         f"{d['figures']['unchecked_coverage']:.0%}"),
          "python benchmarks/error_bound.py --check "
          "benchmarks/results/bound-rows-phantom-pushes-deep.json "
          "benchmarks/results/bound-rows-phantom-pushes-deep-seed1.json "
          "benchmarks/results/bound-rows-ucdavis-homogeneous-pushes-deep.json "
          "benchmarks/results/bound-rows-ucdavis-homogeneous-pushes-deep-seed1.json "
          "--result-name error-bound-deep"), "90-97 %; <= 3x", "-"),
    *[(f"one training step on the CPU ({unit}), batch 4: fp32 / bf16 channels-last / bf16 "
       "contiguous; batch 16 channels-last: fp32 / bf16; bf16 trainings whose loss turned NaN, "
       "channels-last / contiguous; the CPU's bf16 flags",
       Cell(f"bf16-cpu-{kind}", bf16_cells, "python benchmarks/bf16_cpu.py"
            + (" --tag xeon" if kind.endswith("xeon") else "")), "-", "-")
      for kind, unit in (("amx", "AMX-BF16"), ("avx512", "AVX-512 BF16, no AMX; AMD EPYC"),
                         ("avx512-xeon", "AVX-512 BF16; an Intel Xeon whose VM hides AMX"))],
    ("`make test`", Cell("suite-time", figure("minutes", 1, " min"),
                         "python benchmarks/suite_time.py"), "<= 10 min", "-"),
    ("clinical MRI breasts found by label flags alone, within 15 % of a hand crop",
     Cell("mri-breasts", lambda d: f"{d['within15']} of {len(d['rows'])}",
          "python benchmarks/mri_breasts.py --exams DIR"),
     "-", "-"),
    ("`init` on every exam of that MRI collection as a new user runs it (the label flags, both "
     "tumour labels, no `--side`; each side where `init` asks for one): exams whose breast the "
     "tumours chose; exams asked for a side; breasts modelled, of which with the tumour count "
     "the collection's README lists; breasts warned about; exams refused otherwise",
     Cell("mri-breasts-all", sweep_cell, "python benchmarks/mri_breasts.py --exams DIR --all"),
     "-", "-"),
    ("the same on the collection's graded maps (fibroglandular 1-3 and transition 4 as gland, "
     "fat 5-7, by a table file)",
     Cell("mri-breasts-all-detailed", sweep_cell,
          "python benchmarks/mri_breasts.py --exams DIR --all --detailed"), "-", "-"),
]


def bench_block() -> str:
    lines = ["| what | figures | target | paper | command | result file | date |",
             "|---|---|---|---|---|---|---|"]
    for what, cell, target, paper in BENCH_ROWS:
        lines.append(f"| {what} | {cell.text()} | {target} | {paper} | `{cell.command}` | "
                     f"`{cell.source}.json` | {cell.date()} |")
    return "\n".join(lines)


def pushes_cells(render: Callable[[dict], str]) -> tuple[Cell, Cell]:
    """The phantom's and UC Davis's cells of the default recipe's whole runs (Intel Xeon)."""
    return tuple(Cell(f"time-to-model-{case}-pushes-amx", render,
                      TTM.format(case) + " --recipe pushes --tag amx")
                 for case in ("phantom", "ucdavis"))


#: README.md's headline: (what, phantom cell, UC Davis cell, paper)
README_ROWS: list[tuple[str, Cell | None, Cell | None, str]] = [
    ("from nothing to a served model, 2 cores (`make demo`; `run`), the default recipe "
     "`pushes` (Intel Xeon with AMX-BF16; uniform depths, the recipe before 2026-12-08)",
     *pushes_cells(ttm_total), "278 min with a GPU"),
    ("the same, today's `pushes` (training pushes drawn deep more often), phantom on an Intel "
     "Xeon whose VM hides AMX (fp32)",
     Cell("time-to-model-phantom-pushes-xeon", ttm_total,
          TTM.format("phantom") + " --recipe pushes --tag xeon"), None, "-"),
    ("the same, `--recipe pushes-patches` (rigid pushes and force patches; Intel Xeon with "
     "AMX-BF16)",
     mixed_cell("phantom", ttm_total), mixed_cell("ucdavis", ttm_total), "-"),
    ("the same, `--recipe chain` (force patches, case network, `[refine]`; Intel Xeon with "
     "AMX-BF16)",
     Cell("time-to-model-phantom", ttm_total, TTM_CHAIN.format("phantom")),
     Cell("time-to-model-ucdavis", ttm_total, TTM_CHAIN.format("ucdavis")), "-"),
    ("Table 1 of the default recipe: mean / max e of the tracking network against its FE "
     "teacher, held-out rigid pushes up to 35 mm (uniform depths, Intel Xeon with AMX-BF16)",
     *pushes_cells(ttm_table1), "-"),
    ("Table 1, `--recipe pushes-patches`: the tracking network on its held-out force patches (the "
     "paper's test) and rigid pushes", mixed_cell("phantom", ttm_kinds),
     mixed_cell("ucdavis", ttm_kinds), "0.052 / 0.266 mm (force patches)"),
    ("Table 1, `--recipe chain`: the case network on held-out force patches (the paper's test)",
     Cell("time-to-model-phantom", ttm_table1, TTM_CHAIN.format("phantom")),
     Cell("time-to-model-ucdavis", ttm_table1, TTM_CHAIN.format("ucdavis")), "0.052 / 0.266 mm"),
    ("lesion TRE against an independent FE (P2 tetrahedra), every lesion, 10 / 20 / 30 mm "
     "pushes: the tracking network of the default recipe (phantom: today's, Intel Xeon "
     "without AMX; UC Davis as one material: uniform depths, before 2026-12-08)",
     Cell("time-to-model-phantom-pushes-xeon", ttm_tre,
          TTM.format("phantom") + " --recipe pushes --tag xeon"),
     Cell("time-to-model-ucdavis-homogeneous-pushes-amx", ttm_tre,
          TTM.format("ucdavis-homogeneous") + " --recipe pushes --tag amx"), "-"),
    ("the same: its FE teacher",
     Cell("phantom-default-mixed-d30-all-truth", tre("fem"), TRUTH_CMD),
     Cell("ucdavis-default-mixed-d30-all-truth", tre("fem"), UCD_TRUTH_CMD), "-"),
    ("the same: no deformation (rigid)",
     Cell("phantom-default-mixed-d30-all-truth", tre("rigid"), TRUTH_CMD),
     Cell("ucdavis-default-mixed-d30-all-truth", tre("rigid"), UCD_TRUTH_CMD), "-"),
    ("the tracking network of `--recipe pushes-patches`, the same truth",
     mixed_cell("phantom", ttm_tre), mixed_cell("ucdavis-homogeneous", ttm_tre), "-"),
    ("tracker update, median / p99",
     Cell("tracking-latency", pair("update_p50_ms", "update_p99_ms"),
          "python benchmarks/tracking_latency.py CASE"), None, "3.14 ms per prediction (GPU)"),
    ("`make test`", Cell("suite-time", figure("minutes", 1, " min"),
                         "python benchmarks/suite_time.py"), None, "-"),
]


def readme_block() -> str:
    lines = ["| | phantom | UC Davis breast | paper |", "|---|---|---|---|"]
    for what, ph, ucd, paper in README_ROWS:
        cells = [c.text() if c else "-" for c in (ph, ucd)]
        lines.append(f"| {what} | {cells[0]} | {cells[1]} | {paper} |")
    return "\n".join(lines)


BLOCKS = {"readme": ("headline", readme_block), "benchmarks": ("today", bench_block)}


def block_pattern(name: str) -> re.Pattern:
    return re.compile(rf"(<!-- figures:{name} -->\n)(.*?)\n?(<!-- /figures:{name} -->)", re.S)


def current_block(doc: str) -> str | None:
    """The block of ``doc`` ('readme' or 'benchmarks') as the file holds it."""
    name, _ = BLOCKS[doc]
    m = block_pattern(name).search(DOCS[doc].read_text())
    return m.group(2) if m else None


def rendered_block(doc: str) -> str:
    return BLOCKS[doc][1]()


def write_blocks() -> None:
    for doc, path in DOCS.items():
        name, render = BLOCKS[doc]
        block = render()
        new, n = block_pattern(name).subn(lambda m, b=block: m.group(1) + b + "\n" + m.group(3),
                                          path.read_text())
        if n != 1:
            sys.exit(f"figures: {path.name} has no block <!-- figures:{name} -->")
        path.write_text(new)
        print(f"wrote {path.name}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--write", action="store_true")
    args = p.parse_args(argv)
    if args.write:
        write_blocks()
    else:
        for doc in DOCS:
            print(rendered_block(doc), end="\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
