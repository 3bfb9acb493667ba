"""How long ``run`` will take on this machine, and the run's stage table.

Each stage's expected time is a measured reference run's time (:data:`REFERENCE`) scaled to
the case and to this machine today, from three probes of ten U-Net training steps each
(:func:`probe_seconds`, about half a second each):

* **the machine's speed today**: the probe on the reference case's grid against the reference
  run's own probe, so that a slow day of a shared VM lengthens the estimate;
* **FE stages**: ``generate`` scales with its samples and with the active cells (a solve
  costs about ``cells^1.3``), times the machine's speed; rigid pushes (of the data set or of
  ``[refine]``) with their count and the teacher's refinement cubed, times the machine's
  speed, from the median of five breasts (:data:`REFINE_PUSH_MINUTES`), or the built-in
  phantom's own measured cost (:data:`PHANTOM_PUSH_MINUTES`): their cost is set by the
  share of deep pushes that need the 4x-spring fallback, which neither the cells nor the
  data stage predict;
* **training stages**: their iterations times the probe's step on the case's own grid at the
  stage's batch and arithmetic, times :data:`TRAINING_STEP_FACTOR` (what a training
  iteration costs beyond the bare step: data, validation, the best weights' checks);
* **FE processes**: the reference runs had one a core on 2 cores; ``run --workers`` fewer,
  or more cores, scale the FE stages by :data:`REFERENCE_WORKERS` over the processes;
* evaluation and report scale with Table 2's reference solves (lesions x pushes x the fine
  grid's cells^1.3, from a run of a fine-grid truth, :data:`FINE_GRID_TABLE2`, or of the
  reference run's for other truths) and the machine's speed, plus each lesion's self-check
  (:data:`LESION_CHECK`, by the lesions and the teacher grid's cells^1.3).

An estimate is a forecast: the run's stage table says what each stage took (docs/pipeline.md
compares the two).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .reference_registry import chosen_reference

FE_EXPONENT = 1.3
#: The reference run: ``biopsynav run`` with every default on the right breast of exam 01 of
#: the prone MRI collection of docs/anatomy.md (582 mL, 2,041 active cells, 14 x 21 x 20
#: nodes), alone on the 2-core machine, 2026-12-02: 45.5 min in all, stage minutes from the
#: outputs' times. ``probe_s``: :func:`probe_seconds` on that case, the median of 12 probes
#: in three processes just after (0.017-0.022 s; the VM's speed moves by that much).
REFERENCE = {"probe_s": 0.019, "node_shape": (14, 21, 20), "active_cells": 2041, "batch": 4,
             "samples": 1000, "table2_pushes": 8, "reference_refinement": 2.0,
             "minutes": {"generate": 2.68, "evaluate and report": 3.47}}
# its pushes: REFINE_PUSH_MINUTES; its trainings: TRAINING_STEP_FACTOR
PROBE_STEPS = 10  # steps timed after the warm-up (network.train.PROBE_WARMUP); their median
#: What a rigid push costs since the FE engine evaluates a tangent only where it factors one,
#: against before (the measurements below that predate it): 1.13 s against 1.30 on the
#: phantom's rigid pushes, one thread, the two codes interleaved in one process, AMD EPYC,
#: 2026-12-07 (docs/fem.md, "Newton strategy").
FE_SPEEDUP = 1.13 / 1.30
#: Minutes of 1,000 default ``[refine]`` rigid pushes on the 2-core machine: the median of
#: five breasts with ``[probe] max_chest_compression``, each alone, 2026-12-03
#: (time-to-model-phantom 11.0 min on 2,225 active cells, which the limit leaves alone; MRI
#: 13 right 4.6 on 2,524, 05 right 7.2 on 3,529, 05 left 6.5 on 3,656, 06 right 6.7 on
#: 4,068; docs/dataset.md). Not scaled by the cells: they do not predict it. 6.7 then, times
#: :data:`FE_SPEEDUP`.
REFINE_PUSH_MINUTES = 6.7 * FE_SPEEDUP
#: The same for the built-in phantom, a fixed anatomy whose own cost is measured: the
#: ``pushes`` demo's 450 rigid pushes took 5.47 min at a speed probe of 0.86x (Intel Xeon,
#: alone, 2026-12-06; ``time-to-model-phantom-pushes-amx.json``, its data set's summary):
#: 14.1 min per 1,000 at the reference machine's speed, on its 2,225 active cells of 7.3 mm,
#: times :data:`FE_SPEEDUP`. Its steep flank makes deep pushes that need the 4x springs.
PHANTOM_PUSH_MINUTES = 14.1 * FE_SPEEDUP
PHANTOM_ACTIVE_CELLS = 2225
#: How a rigid push's solve time grows with its depth (per mm): ``exp(rate depth)``, fitted on
#: the kept solves of the phantom's 450 uniform-depth pushes (Intel Xeon, 2026-12-08; it
#: forecasts 1.30x for ``[probe] train_depth_exponent`` 0.7, where the data stage took 1.28x).
RIGID_PUSH_DEPTH_RATE = 0.150
#: Seconds of a training iteration over :func:`probe_seconds`'s step at the same batch, grid
#: and arithmetic, at the day's speed: the median of five trainings, AMD EPYC, bf16,
#: 2026-12-04/05 (batch 16: the ``pushes`` runs of the phantom 1.12, UC Davis 1.23 and MRI
#: exam 13 right 1.23, the ``chain`` run's case network 1.29; batch 4: its refine training
#: 1.24), the probe taken on an idle machine on 2026-12-05 and rescaled by each run's own
#: speed probe. The reference run's batch-4 fp32 training of 2026-12-02 took 1.87 times its
#: probe (fp32 at batch 4, and the code of that day; not measured apart).
TRAINING_STEP_FACTOR = 1.23
#: The reference runs' FE processes (``run`` on the 2-core machine: one a core). With fewer
#: (``--workers``) or more cores the FE stages' times scale by this over the processes: the
#: pushes are independent (measured on 2 cores only).
REFERENCE_WORKERS = 2
#: A ``[refine] teacher = "p2"`` push (4 mm tetrahedra near the probe, the truth's sharp-edged
#: probe) in one single-threaded process at the reference machine's speed: about
#: ``P2_PUSH_S[0] exp(P2_PUSH_S[1] depth_mm)`` seconds, at most the push's time limit
#: (``[refine] teacher_push_limit_s``). Fitted on the phantom's pushes of a
#: stopped N = 50 refine (``benchmarks/p2_teacher.py --store``; result file
#: ``p2-teacher-phantom-depths.json``, its speed probe taken out); a larger breast's cost more.
P2_PUSH_S = (5.72, 0.179)


@dataclass
class Estimate:
    """Expected minutes per stage (stage name -> minutes) and the machine's speed factor
    (1: as fast as the reference machine; 2: half as fast)."""

    minutes: dict[str, float]
    slowness: float

    @property
    def total(self) -> float:
        return float(sum(self.minutes.values()))

    def line(self) -> str:
        parts = ", ".join(f"{k} {_minutes(v)}" for k, v in self.minutes.items())
        return (f"expected on this machine today: about {_minutes(self.total)} min ({parts} "
                f"min; speed probe {self.slowness:.2f}x the reference machine's time)")


def _minutes(value: float) -> str:
    """Minutes to two significant figures at most: 0.3, 4.7, 28."""
    return f"{value:.1f}" if value < 10 else f"{value:.0f}"


def probe_seconds(case, node_shape: tuple[int, int, int] | None = None, *,
                  as_reference: bool = False, batch: int | None = None) -> float:
    """Seconds per step of the case's U-Net training (forward, backward, Adam) at its batch
    size, arithmetic (``[network] precision``; ``auto`` timed as ``train`` times it:
    :func:`~biopsynav.network.train.choose_precision`) and layout on random inputs on a grid
    of ``node_shape`` (the case's when None), the median of :data:`PROBE_STEPS` after the
    warm-up. ``as_reference``: at the reference run's batch (``REFERENCE["batch"]``) in fp32,
    the machine's speed probe; ``batch``: at that batch instead of the case's."""
    import dataclasses

    import torch

    from .network.train import choose_precision, step_seconds
    from .network.unet import section_spec

    s, cpu = case.cfg.network, torch.device("cpu")
    if as_reference:
        s = dataclasses.replace(s, batch_size=REFERENCE["batch"], precision="fp32")
    elif batch is not None:
        s = dataclasses.replace(s, batch_size=batch)
    spec = section_spec(s)
    shape = tuple(node_shape or case.grid.node_shape)
    amp = choose_precision(s.precision, cpu, spec, shape, s.batch_size).amp
    return step_seconds(spec, shape, s.batch_size, amp, PROBE_STEPS)


def estimate_run(case, probes: tuple[float, ...] | None = None, workers: int = 0) -> Estimate:
    """Expected minutes of each stage of ``case`` on this machine with ``workers`` FE
    processes (``run --workers``; 0: one a core). ``probes``: seconds of
    :func:`probe_seconds` on the reference grid (the machine's speed), on the case's grid
    (its training step) and on the case's grid at ``[refine] batch_size`` (the refine
    training's step; the case's step when left out), measured when None (the third only when
    ``[refine]`` runs at another batch)."""
    ref = REFERENCE
    if probes is None:
        probes = (probe_seconds(case, ref["node_shape"], as_reference=True), probe_seconds(case))
        if case.cfg.refine.samples and case.cfg.refine.batch_size != case.cfg.network.batch_size:
            probes += (probe_seconds(case, batch=case.cfg.refine.batch_size),)
    slowness = probes[0] / ref["probe_s"]
    processes = fe_processes(workers)
    fe = fe_factor(slowness, processes)
    step, refine_step = probes[1], probes[-1]  # seconds of each training's step today
    cells = (float(case.grid.active_cells.sum()) / ref["active_cells"]) ** FE_EXPONENT
    cfg, m = case.cfg, ref["minutes"]
    samples = cfg.dataset.n_train + cfg.dataset.n_test
    per_1000 = push_minutes_per_1000(case)
    rigid = cfg.probe.rigid_share * samples  # rigid pushes cost what [refine]'s do
    deeper = depth_cost_factor(cfg.probe.train_depth_exponent, cfg.probe.max_push_mm)
    rigid_cost = cfg.probe.rigid_share * (cfg.dataset.n_train * deeper + cfg.dataset.n_test)
    minutes = {"generate": (m["generate"] * (samples - rigid) / ref["samples"] * cells * fe
                            + rigid_push_minutes(rigid_cost, cfg.dataset.teacher_refine, fe,
                                                 per_1000)),
               "train": training_minutes(cfg.network.iterations, step)}
    if cfg.refine.samples:
        minutes["refine pushes"] = refine_push_minutes(case, slowness, processes, per_1000)
        minutes["refine training"] = training_minutes(cfg.refine.iterations, refine_step)
    minutes["evaluate and report"] = (
        evaluation_minutes(case, processes) * slowness
        + lesion_check_minutes(case) * fe)
    return Estimate(minutes, slowness)


def depth_cost_factor(exponent: float, max_push_mm: float,
                      rate: float = RIGID_PUSH_DEPTH_RATE) -> float:
    """What a rigid push of depth ``max_push_mm u^exponent`` (mm, ``u`` uniform in [0, 1];
    ``[probe] train_depth_exponent``) costs on average over one of uniform depth, its solve
    time taken as ``exp(rate depth_mm)``; 1 for the uniform depth."""
    u = np.linspace(0.0, 1.0, 2001)
    cost = np.exp(rate * max_push_mm * u ** exponent)
    return float(np.trapezoid(cost, u) / np.trapezoid(np.exp(rate * max_push_mm * u), u))


def p2_push_seconds(max_push_mm: float, model: tuple[float, float] = P2_PUSH_S,
                    limit_s: float | None = None) -> float:
    """Expected seconds of a P2 teacher push of depth uniform in [0, ``max_push_mm``] mm in
    one process: ``model`` (a, b), ``a exp(b depth_mm)`` seconds (default
    :data:`P2_PUSH_S`, at the reference machine's speed), capped at the push's time limit
    ``limit_s`` (default :data:`biopsynav.dataset.converged.PUSH_LIMIT_S`; 0: none)."""
    from .dataset.converged import PUSH_LIMIT_S

    cap = PUSH_LIMIT_S if limit_s is None else (limit_s or np.inf)
    depths = np.linspace(0.0, max_push_mm, 201)
    seconds = np.minimum(model[0] * np.exp(model[1] * depths), cap)
    return float(np.trapezoid(seconds, depths) / max_push_mm)


def fe_processes(workers: int = 0) -> int:
    """The FE processes of a run given ``--workers workers`` (0: one a core), at most one a
    core."""
    cores = os.cpu_count() or 1
    return max(1, min(workers or cores, cores))


def fe_factor(slowness: float, processes: int) -> float:
    """The FE stages' time factor against the reference runs: the machine's ``slowness``
    times :data:`REFERENCE_WORKERS` over the FE ``processes``."""
    return slowness * REFERENCE_WORKERS / processes


def refine_push_minutes(case, slowness: float, processes: int, per_1000: float) -> float:
    """Expected minutes of ``[refine]``'s pushes on ``processes`` FE processes at the
    machine's ``slowness``: the grid teacher's (:func:`rigid_push_minutes`) or the P2
    teacher's (:func:`p2_push_seconds` each in this machine's seconds, capped at the push's
    time limit)."""
    r = case.cfg.refine
    if r.teacher == "p2":
        here = (P2_PUSH_S[0] * slowness, P2_PUSH_S[1])
        seconds = p2_push_seconds(r.max_push_mm, here, limit_s=r.teacher_push_limit_s)
        return r.samples * seconds / 60.0 / processes
    return rigid_push_minutes(r.samples, r.teacher_refine, fe_factor(slowness, processes),
                              per_1000)


def training_minutes(iterations: int, step_s: float) -> float:
    """Expected minutes of ``iterations`` training iterations whose bare step (the probe's)
    takes ``step_s`` seconds today."""
    return iterations * step_s * TRAINING_STEP_FACTOR / 60.0


def evaluation_minutes(case, cores: int | None = None) -> float:
    """Expected minutes of ``evaluate`` and ``report`` of ``case`` on the reference machine:
    with a fine-grid ground truth, :data:`FINE_GRID_TABLE2`'s run scaled by the rounds of
    lesions on ``cores`` processes (each lesion's pushes are one task: one lesion keeps one
    core busy; default this machine's cores), the pushes a lesion and the fine grid's
    cells^1.3; else the reference run's (:func:`table2_work`)."""
    ev, fine = case.cfg.evaluate, FINE_GRID_TABLE2
    if chosen_reference(case)[0] != "fine_grid":
        return REFERENCE["minutes"]["evaluate and report"] * table2_work(case)
    cells = (float(case.grid.active_cells.sum()) * ev.reference_refinement ** 3
             / (fine["active_cells"] * fine["reference_refinement"] ** 3)) ** FE_EXPONENT
    rounds = math.ceil(evaluated_lesions(case) / max(1, cores or os.cpu_count() or 1))
    return (fine["minutes"] * rounds / fine["rounds"] * ev.deformations_per_lesion
            / fine["pushes_per_lesion"] * cells)


#: each lesion's self-check (:mod:`biopsynav.evaluate.lesion_check`, three pushes of 15-35 mm
#: on the teacher's grid and the teacher gap's push on a finer one, in two processes): the
#: phantom's default model (10 lesions, 2,225 active cells), alone, AMD EPYC, 2026-12-07: 126 s
#: at a speed probe of 1.42x, 1.48 min at the reference machine's speed
LESION_CHECK = {"active_cells": PHANTOM_ACTIVE_CELLS, "lesions": 10, "minutes": 1.48}


def lesion_check_minutes(case) -> float:
    """Expected minutes of the lesion self-check of ``case`` on the reference machine:
    :data:`LESION_CHECK` scaled by the lesions and the teacher grid's cells^1.3."""
    cfg = case.cfg
    refine = cfg.refine.teacher_refine if cfg.refine.samples else cfg.dataset.teacher_refine
    cells = (float(case.grid.active_cells.sum()) * refine ** 3
             / LESION_CHECK["active_cells"]) ** FE_EXPONENT
    return LESION_CHECK["minutes"] * len(case.anatomy.lesions) / LESION_CHECK["lesions"] * cells


def evaluated_lesions(case) -> int:
    """How many lesions Table 2 evaluates (:func:`~biopsynav.evaluate.simulation.
    select_lesions`: all, or ``[evaluate] max_lesions`` of them)."""
    from .evaluate.simulation import select_lesions

    return len(select_lesions(len(case.anatomy.lesions), case.cfg.evaluate.max_lesions))


def rigid_push_minutes(pushes: float, teacher_refine: float, slowness: float,
                       per_1000: float) -> float:
    """Expected minutes of ``pushes`` rigid-probe pushes on cells ``teacher_refine`` times
    smaller than the case grid's, ``per_1000`` minutes per 1,000 on the case grid at the
    reference machine's speed (:func:`push_minutes_per_1000`), at the machine's
    ``slowness``."""
    return per_1000 * pushes / REFERENCE["samples"] * teacher_refine ** 3 * slowness


def push_minutes_per_1000(case) -> float:
    """Minutes of 1,000 rigid pushes of ``case`` at the reference machine's speed: the
    built-in phantom's own (:data:`PHANTOM_PUSH_MINUTES`, scaled by its grid's active
    cells^1.3: the same anatomy on other cells), else the breasts' median
    (:data:`REFINE_PUSH_MINUTES`)."""
    if case.cfg.anatomy.source != "phantom":
        return REFINE_PUSH_MINUTES
    cells = float(case.grid.active_cells.sum()) / PHANTOM_ACTIVE_CELLS
    return PHANTOM_PUSH_MINUTES * cells ** FE_EXPONENT


#: Table 2 with the fine-grid ground truth (each lesion's pushes in turn, the lesions in two
#: processes): ``time_to_model.py --case ucdavis`` (the ``pushes`` recipe), AMD EPYC,
#: 2026-12-05: evaluation and report 5.36 min at the run's speed probe of 1.15x, 4.66 at the
#: reference machine's speed; 5 lesions x 4 pushes on 1,920 active cells refined twice. Times
#: what the FE engine's change of 2026-12-07 took off the fine-grid truth, most of the stage
#: (391 s against 447 in the same case's runs that day).
FINE_GRID_TABLE2 = {"active_cells": 1920, "reference_refinement": 2.0, "pushes_per_lesion": 4,
                    "rounds": 3, "minutes": 4.66 * 391 / 447}  # 5 lesions on 2 cores: 3 rounds

#: pushes per lesion of a stored truth (benchmarks/truth.py's 10, 20 and 30 mm)
STORED_PUSHES = 3


def table2_work(case) -> float:
    """Table 2's reference solves of ``case`` against the reference run's: lesions evaluated
    x pushes each x the fine grid's cells^1.3 (its cells: the case's times the refinement
    cubed; a stored truth solves nothing, and the FE engine's solves on the case grid stand
    in for it)."""
    ref, e = REFERENCE, case.cfg.evaluate
    lesions = evaluated_lesions(case)
    stored = chosen_reference(case)[0] == "stored"  # no reference solve: the FE engine's
    refinement = 1.0 if stored else e.reference_refinement
    pushes = STORED_PUSHES if stored else e.deformations_per_lesion
    fine = (float(case.grid.active_cells.sum()) * refinement ** 3
            / (ref["active_cells"] * ref["reference_refinement"] ** 3)) ** FE_EXPONENT
    return lesions * pushes / ref["table2_pushes"] * fine


#: the estimate's stages of each of the run's stages (:func:`biopsynav.pipeline.run_case`)
RUN_STAGES = {"training data": ("generate",), "network training": ("train",),
              "refine": ("refine pushes", "refine training"),
              "evaluation": ("evaluate and report",)}
#: the run stage whose taken time rescales each estimated stage ahead (none: the rigid pushes)
RESCALED_BY = {"generate": "training data", "evaluate and report": "training data",
               "train": "network training", "refine training": "network training"}


def remaining_minutes(estimate: Estimate, done_s: dict[str, float]) -> float:
    """Expected minutes of the run's stages not in ``done_s`` (run stage -> seconds taken).
    Once a stage has run, what it took against its estimate rescales the stages of its kind
    still ahead (the evaluation's FE solves by the data stage, training by the network's;
    not the rigid pushes, whose cost the data stage does not predict): the estimate learns
    this case and this day as the run goes."""
    ratio = {"training data": _taken_ratio(estimate, done_s, "training data", "generate"),
             "network training": _taken_ratio(estimate, done_s, "network training", "train")}
    total = 0.0
    for stage, parts in RUN_STAGES.items():
        if stage in done_s:
            continue
        for part in parts:
            scale = ratio[RESCALED_BY[part]] if part in RESCALED_BY else 1.0
            total += estimate.minutes.get(part, 0.0) * scale
    return total


def _taken_ratio(estimate: Estimate, done_s: dict[str, float], stage: str, part: str) -> float:
    """Minutes ``stage`` took over its estimate; 1 while it has not run, or when it did
    (almost) nothing (its outputs were up to date)."""
    expected, taken = estimate.minutes.get(part, 0.0), done_s.get(stage, 0.0) / 60.0
    return taken / expected if expected > 0 and taken > 0.25 * expected else 1.0


def stage_table(timings_s: dict[str, float]) -> str:
    """The run's stage times as a table (minutes), the whole run last."""
    width = max(len(k) for k in timings_s) + 2
    lines = [f"{'stage':<{width}}minutes"]
    lines += [f"{k:<{width}}{v / 60:7.1f}" for k, v in timings_s.items()]
    lines.append(f"{'whole run':<{width}}{sum(timings_s.values()) / 60:7.1f}")
    return "\n".join(lines)
