"""Settings that make a whole `run` of a test case take seconds."""

from __future__ import annotations

from biopsynav.config import CaseConfig


def small_run_settings(cfg: CaseConfig) -> None:
    """Set ``cfg`` (in place) to a few training iterations on one thread, 10 timed
    predictions and one Table 2 push over one lesion on a grid no finer than the case's."""
    cfg.network.iterations, cfg.network.val_interval = 6, 3
    cfg.network.warmup_iterations, cfg.network.threads = 2, 1
    cfg.evaluate.timed_predictions = 10
    cfg.evaluate.max_lesions, cfg.evaluate.deformations_per_lesion = 1, 1
    cfg.evaluate.reference_refinement = 1.0
