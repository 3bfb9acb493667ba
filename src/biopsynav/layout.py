"""The layout of a case folder: every file and folder a case holds, named here and only here.

:class:`CasePaths` gives each as a path; the stages import the names they write from here.
Nothing else in the package spells a case file's name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

CASE_FILE = "case.toml"
ANATOMY_FILE = "anatomy.npz"
GRID_FILE = "grid.npz"
INPUTS_DIR = "inputs"
FACTS_FILE = "facts.json"
PHANTOM_LESIONS_FILE = "phantom_lesions.csv"
ANATOMY_PICTURE = "anatomy.png"
DATASET_NAME = "dataset.zarr"
DATASET_SUMMARY = "dataset_summary.json"
DATASET_PLOT = "dataset.png"
MODEL_DIR = "model"
REFINE_DIR = "refine"  # the multi-fidelity case folder inside a case ([refine] samples > 0)
META = "meta.json"
HISTORY = "history.json"
CHECKPOINT = "checkpoint.pt"
BEST = "best.pt"
TORCHSCRIPT = "model.ts"
ONNX = "model.onnx"
LESION_CHECK = "lesion_check.json"  # in the tracking model's folder: each lesion's self-check
LOSS_CURVE = "loss_curve.png"
EVAL_DIR = "eval"
TABLE1_FILE = "table1.json"
TABLE2 = "table2"  # by simulation: eval/table2.json and eval/table2.md
TABLE2_MEASURED = "table2_measured"  # from user data: eval/table2_measured.json and .md
TABLE2_REFERENCE_CACHE = "table2_p2_answers.json"  # the P2 reference's answers, by push
TABLE2_FINE_GRID_CACHE = "table2_fine_grid_answers.json"  # the fine-grid truth, by lesion
CONVERGENCE_FILE = "convergence.json"  # benchmarks/convergence.py's study of this case
REPORT_HTML = "report.html"
REPORT_MD = "report.md"
REPORT_FILES = "report_files"  # figures the report makes, beside report.html
LOCK_NAME = ".biopsynav.lock"
#: computed arrays kept between processes, named by a hash of what they are computed from
#: (``contact_compliance-<sha256>.npz``: :mod:`biopsynav.contact.greens`); deleting it costs
#: only their computation again
CACHE_DIR = "cache"
COMPLIANCE_CACHE = "contact_compliance"  # cache/contact_compliance-<sha256>.npz


@dataclass(frozen=True)
class CasePaths:
    """Paths of the files of the case folder ``dir``."""

    dir: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "dir", Path(self.dir))

    @property
    def config(self) -> Path:
        return self.dir / CASE_FILE

    @property
    def anatomy(self) -> Path:
        return self.dir / ANATOMY_FILE

    @property
    def grid(self) -> Path:
        return self.dir / GRID_FILE

    @property
    def inputs(self) -> Path:
        return self.dir / INPUTS_DIR

    @property
    def facts(self) -> Path:
        return self.inputs / FACTS_FILE

    @property
    def dataset(self) -> Path:
        return self.dir / DATASET_NAME

    @property
    def dataset_summary(self) -> Path:
        return self.dir / DATASET_SUMMARY

    @property
    def model(self) -> Path:
        return self.dir / MODEL_DIR

    @property
    def model_meta(self) -> Path:
        return self.model / META

    @property
    def refine(self) -> Path:
        """The case folder of the fine teacher's pushes and the model trained further on them
        (``[refine] samples > 0``): a case of its own, same anatomy and grid."""
        return self.dir / REFINE_DIR

    def tracking_model(self, refined: bool) -> Path:
        """The folder of the model the tracker uses: ``refine/model`` when ``refined``
        (``[refine] samples > 0``), else ``model``."""
        return CasePaths(self.refine).model if refined else self.model

    @property
    def eval(self) -> Path:
        return self.dir / EVAL_DIR

    @property
    def table1(self) -> Path:
        return self.eval / TABLE1_FILE

    def table2(self, stem: str = TABLE2) -> Path:
        """``eval/<stem>.json`` (``table2`` by simulation, ``table2_measured``)."""
        return self.eval / f"{stem}.json"

    @property
    def table2_reference_cache(self) -> Path:
        """The P2 reference's answers by push (``[evaluate] reference = "p2"``)."""
        return self.eval / TABLE2_REFERENCE_CACHE

    @property
    def table2_fine_grid_cache(self) -> Path:
        """The fine-grid truth's answers by lesion (:mod:`biopsynav.evaluate.kept`)."""
        return self.eval / TABLE2_FINE_GRID_CACHE

    @property
    def convergence(self) -> Path:
        """The convergence study of the FE against the P2 reference
        (``benchmarks/convergence.py CASE``), which the report shows."""
        return self.eval / CONVERGENCE_FILE

    @property
    def report_html(self) -> Path:
        return self.dir / REPORT_HTML

    @property
    def report_md(self) -> Path:
        return self.dir / REPORT_MD

    @property
    def report_files(self) -> Path:
        return self.dir / REPORT_FILES

    @property
    def lock(self) -> Path:
        return self.dir / LOCK_NAME

    @property
    def cache(self) -> Path:
        return self.dir / CACHE_DIR

    def outputs(self) -> list[Path]:
        """The pipeline outputs the folder holds (data set, model, refined case, evaluation)."""
        return [p for p in (self.dataset, self.model, self.refine, self.eval) if p.exists()]
