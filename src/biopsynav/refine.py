"""Multi-fidelity training (``[refine] samples > 0``): the case-grid network trained further on
a few rigid-probe pushes of a finer teacher.

The case-grid network learns from many cheap pushes solved on the case grid, whose cells
drag the tissue under a 10 mm probe face (docs/fem.md). A few pushes solved on cells
``[refine] teacher_refine`` times smaller, the rigid probe holding the skin it touches, and
fitted to the case grid (:mod:`biopsynav.grid.transfer`), then teach it the finer answer
(docs/experiments.md, "Trained further on a finer teacher"). They live in a case folder of their
own inside the case, ``CASE_DIR/refine``: the same anatomy and grid (so the same fingerprint),
a configuration derived from the case's (:func:`refined_config`), its own ``dataset.zarr``
and ``model``; generation and training there resume like any case's. The tracker then loads
that model (:attr:`biopsynav.case.Case.tracking_model`).
"""

from __future__ import annotations

import copy

from .case import Case
from .config import CaseConfig, RefineSection, load_config, save_config
from .errors import BiopsynavError
from .fileio import write_bytes_atomic
from .layout import MODEL_DIR, CasePaths

#: Warm-up steps and validation interval of the training on the fine pushes (the case-grid
#: network's defaults, 300 and 500, are sized for 50,000 iterations).
REFINE_WARMUP = 100
REFINE_VAL_INTERVAL = 250


def refined_config(cfg: CaseConfig) -> CaseConfig:
    """The refine case's configuration: ``cfg`` with the law ``[refine] material_model``
    and ``[refine] fictitious_stiffness``, every push a rigid-probe push (depth uniform up to
    ``[refine] max_push_mm`` and ``[probe] max_chest_compression``, no force calibration,
    ``[refine] lesion_share`` of them centred near a lesion), ``[refine] samples`` samples of
    which ``held_out`` held out, solved on the finer teacher, and the training starting from
    the case's model (``../model``) with the ``[refine]`` schedule."""
    r, out = cfg.refine, copy.deepcopy(cfg)
    # the refine case does not refine again; its pushes are solved with the refine law
    out.refine = RefineSection(samples=0, material_model=r.material_model,
                               fictitious_stiffness=r.fictitious_stiffness,
                               batch_size=r.batch_size)
    out.material.model = r.material_model
    out.material.fictitious_stiffness = r.fictitious_stiffness
    out.case.name = f"{cfg.case.name}-refine"
    out.case.description = (f"the fine teacher's rigid pushes of case {cfg.case.name!r} "
                            "([refine], docs/dataset.md)")
    out.probe.rigid_share = 1.0
    out.probe.max_push_mm = r.max_push_mm
    out.probe.calibrate_force = False
    out.probe.lesion_share = r.lesion_share
    out.dataset.n_train = r.samples - r.held_out
    out.dataset.n_test = r.held_out
    out.dataset.teacher = r.teacher
    out.dataset.teacher_size_mm, out.dataset.teacher_fine_mm = r.teacher_size_mm, r.teacher_fine_mm
    out.dataset.teacher_push_limit_s = r.teacher_push_limit_s
    out.dataset.teacher_refine = r.teacher_refine
    out.dataset.teacher_extrapolation = r.extrapolation
    net = out.network
    net.init_from = f"../{MODEL_DIR}"
    net.iterations, net.learning_rate, net.batch_size = r.iterations, r.learning_rate, r.batch_size
    net.warmup_iterations = min(REFINE_WARMUP, r.iterations)
    net.val_interval = min(REFINE_VAL_INTERVAL, r.iterations)
    return out


def refine_case(case: Case) -> Case:
    """The refine case of ``case`` (``CASE_DIR/refine``), its ``case.toml`` written when
    missing or different from :func:`refined_config`, and anatomy and grid copied from the
    case when they differ (each write atomic; a data set made with another protocol or
    anatomy is then refused by ``generate``, never overwritten)."""
    cfg = refined_config(case.cfg)
    paths = CasePaths(case.paths.refine)
    paths.dir.mkdir(exist_ok=True)
    if _stored_config(paths) != cfg:
        save_config(paths.dir, cfg)
    for source, copy_ in ((case.paths.anatomy, paths.anatomy), (case.paths.grid, paths.grid)):
        data = source.read_bytes()
        if not copy_.is_file() or copy_.read_bytes() != data:
            write_bytes_atomic(copy_, data)
    return Case(paths.dir, cfg, case.anatomy, case.grid)


def fine_case(case: Case) -> Case:
    """The refine case of ``case`` as it stands on disk (nothing written)."""
    return Case(case.paths.refine, refined_config(case.cfg), case.anatomy, case.grid)


def tracking_teacher_config(cfg: CaseConfig) -> CaseConfig:
    """The configuration of the data that taught the model the tracker uses: the refine
    case's with ``[refine] samples > 0``, else ``cfg`` (see :func:`tracking_teacher_case`)."""
    return refined_config(cfg) if cfg.refine.samples else cfg


def tracking_teacher_case(case: Case) -> Case:
    """The case whose data taught the model the tracker uses: the refine case with
    ``[refine] samples > 0``, else ``case`` (its ``[dataset] teacher_refine`` is that
    teacher's grid: the FE engine solves there, and a fine-grid truth must be finer; its
    ``[material] model`` is the law of the FE engine and of the tracker's contact
    compliance). Same anatomy and grid as ``case``."""
    return fine_case(case) if case.cfg.refine.samples else case


def _stored_config(paths: CasePaths) -> CaseConfig | None:
    """The refine case's stored configuration, None when missing or unreadable."""
    if not paths.config.is_file():
        return None
    try:
        return load_config(paths.dir)
    except BiopsynavError:
        return None
