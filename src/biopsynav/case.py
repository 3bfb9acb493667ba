"""A case is a folder: ``case.toml`` plus what the pipeline writes into it.

Layout: ``inputs/`` (copies of the user's files), ``anatomy.npz``, ``grid.npz`` (written by
``init``), ``dataset.zarr`` (``generate``), ``model/`` (``train``), ``eval/`` (``evaluate``),
``report.html`` and ``report.md`` (``report``).
"""

from __future__ import annotations

import hashlib
import shutil
from dataclasses import dataclass
from pathlib import Path

from .anatomy.build import anatomy_source, build_anatomy
from .anatomy.model import Anatomy
from .anatomy.phantom import phantom_lesions_csv
from .config import CaseConfig, load_config, save_config
from .errors import BiopsynavError, InputError
from .fileio import write_json_atomic, write_text_atomic
from .grid.build import build_grid
from .grid.model import Grid
from .layout import (
    ANATOMY_FILE,
    DATASET_NAME,
    EVAL_DIR,
    GRID_FILE,
    META,
    MODEL_DIR,
    PHANTOM_LESIONS_FILE,
    REPORT_HTML,
    TABLE1_FILE,
    CasePaths,
)

STAGES = {
    "anatomy": ANATOMY_FILE,
    "grid": GRID_FILE,
    "dataset": f"{DATASET_NAME}/zarr.json",
    "model": f"{MODEL_DIR}/{META}",
    "evaluation": f"{EVAL_DIR}/{TABLE1_FILE}",
    "report": REPORT_HTML,
}


@dataclass
class Case:
    """A loaded case: its folder, validated configuration, anatomy and grid."""

    dir: Path
    cfg: CaseConfig
    anatomy: Anatomy
    grid: Grid

    @classmethod
    def load(cls, case_dir: str | Path, cfg: CaseConfig | None = None) -> Case:
        """Read ``case.toml`` (unless ``cfg`` is given), ``anatomy.npz`` and ``grid.npz``."""
        paths = CasePaths(case_dir)
        cfg = load_config(paths.dir) if cfg is None else cfg
        return cls(paths.dir, cfg, Anatomy.load(paths.anatomy), Grid.load(paths.grid))

    @property
    def paths(self) -> CasePaths:
        """The paths of this case's files."""
        return CasePaths(self.dir)

    def fingerprint(self) -> str:
        """SHA-256 of anatomy and grid: data and models carry it to refuse another patient's."""
        return hashlib.sha256((self.anatomy.fingerprint() + self.grid.fingerprint())
                              .encode()).hexdigest()

    @property
    def tracking_model(self) -> Path:
        """The model folder the tracker uses: the one trained further on the fine teacher's
        pushes (``CASE_DIR/refine/model``) when ``[refine] samples > 0``, else ``model``.
        InputError when that model has not been trained yet."""
        model = self.paths.tracking_model(bool(self.cfg.refine.samples))
        if self.cfg.refine.samples and not (model / META).is_file():
            raise InputError("[refine] samples > 0 but the model trained on the fine teacher's "
                             "pushes is missing: run `biopsynav refine CASE` (or `biopsynav run "
                             "CASE`)", str(model))
        return model

    def stages_done(self) -> dict[str, bool]:
        """Which pipeline outputs exist in the folder."""
        return {name: (self.dir / rel).exists() for name, rel in STAGES.items()}


def as_case(case: Case | str | Path) -> Case:
    """``case`` itself when loaded, else the case folder ``case`` loaded (public entry points
    take either; the stages below them pass the loaded :class:`Case` on)."""
    return case if isinstance(case, Case) else Case.load(case)


def build_case(case_dir: Path, cfg: CaseConfig) -> Case:
    """Build anatomy and grid from ``cfg`` and write ``case.toml``, ``anatomy.npz``,
    ``grid.npz`` (each atomically; nothing is written if the inputs are bad)."""
    from .fem.tissues import label_tissues

    anatomy, facts = build_anatomy(cfg, case_dir)
    grid = build_grid(anatomy, cfg.grid, cfg.anatomy.max_fixed_share,
                      cfg.anatomy.chest_wall_tolerance_mm)
    # every label mapped, or refused naming the user's anatomy file
    label_tissues(grid.label_values, cfg, anatomy, anatomy_source(cfg, case_dir))
    save_config(case_dir, cfg)
    paths = CasePaths(case_dir)
    anatomy.save(paths.anatomy)
    grid.save(paths.grid)
    write_json_atomic(paths.facts, facts)
    return Case(case_dir, cfg, anatomy, grid)


def init_case(case_dir: str | Path, cfg: CaseConfig, inputs: dict[str, Path | None],
              overwrite: bool = False) -> Case:
    """Create a case folder: copy the inputs into ``inputs/``, point case.toml at them, build.

    ``inputs`` maps ``"anatomy"`` and ``"lesions"`` to user files (or None). A half-built case is
    never left behind: on error the new folder is removed.
    """
    case_dir = Path(case_dir)
    if CasePaths(case_dir).config.exists() and not overwrite:
        raise InputError("a case already exists here; use --overwrite to rebuild it",
                         str(case_dir))
    created = not case_dir.exists()
    copies: dict[str, str] = {}  # the copy inside the case -> the user's own file
    try:
        CasePaths(case_dir).inputs.mkdir(parents=True, exist_ok=True)
        for key, src in inputs.items():
            if src is None:
                continue
            src = Path(src)
            if not src.exists():
                raise InputError("file not found", str(src))
            dst = CasePaths(case_dir).inputs / src.name
            if src.is_dir():
                shutil.copytree(src, dst, dirs_exist_ok=True)
            elif src.resolve() != dst.resolve():
                shutil.copy2(src, dst)
            copies[str(dst)] = str(src)
            rel = str(dst.relative_to(case_dir))
            if key == "anatomy":
                cfg.anatomy.path = rel
            else:
                cfg.anatomy.lesions = rel
        if cfg.anatomy.source == "phantom" and not cfg.anatomy.lesions:
            write_text_atomic(CasePaths(case_dir).inputs / PHANTOM_LESIONS_FILE,
                              phantom_lesions_csv())
            cfg.anatomy.lesions = "inputs/phantom_lesions.csv"
            copies[str(CasePaths(case_dir).inputs / PHANTOM_LESIONS_FILE)] = \
                "the built-in phantom lesions"
        return build_case(case_dir, cfg)
    except BaseException as exc:
        if created:
            shutil.rmtree(case_dir, ignore_errors=True)
        if isinstance(exc, BiopsynavError):
            _name_user_files(exc, copies)
        raise


def _name_user_files(exc: BiopsynavError, copies: dict[str, str]) -> None:
    """Name the user's own files in ``exc`` (its ``what`` and ``where``) instead of their
    copies inside the case folder."""
    what, where = exc.what, exc.where
    for copy, original in copies.items():
        what = what.replace(copy, original)
        where = where.replace(copy, original) if where else where
    BiopsynavError.__init__(exc, what, where)


def surface_kind(path: Path) -> str:
    """'labelmap', 'volume' or 'surface' from a file name (volume meshes: checked on read)."""
    from .anatomy.io import LABELMAP_SUFFIXES, _suffix

    if _suffix(path) in LABELMAP_SUFFIXES:
        return "labelmap"
    return "surface"


def make_phantom_case(case_dir, overwrite: bool = False, cell_size_mm: float | None = None,
                      overrides: dict | None = None):
    """Create the built-in phantom case in ``case_dir`` and return the loaded :class:`Case`.

    ``overrides`` holds case.toml sections to set (validated like case.toml).
    """
    from .anatomy.phantom import PHANTOM_DESCRIPTION
    from .config import config_from_dict

    data: dict = {section: dict(values) for section, values in (overrides or {}).items()}
    data.setdefault("case", {}).setdefault("name", "phantom")
    data["case"].setdefault("description", PHANTOM_DESCRIPTION)
    data.setdefault("anatomy", {})["source"] = "phantom"
    if cell_size_mm is not None:
        data.setdefault("grid", {})["cell_size_mm"] = float(cell_size_mm)
    cfg = config_from_dict(data, "phantom settings")
    return init_case(case_dir, cfg, {}, overwrite=overwrite)
