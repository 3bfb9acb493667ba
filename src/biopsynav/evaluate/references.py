"""The ground truths of Table 2 by simulation, registered in
:mod:`biopsynav.reference_registry` and chosen by ``[evaluate] reference``.

A reference answers like a tracker (``set_rest_pose(pose) -> contact count``, ``update(pose)
-> TrackingResult`` with every lesion's centre and displacement, mm) and describes itself
(``facts() -> dict``, kept in ``table2.json`` and shown by the report). Registered:

* ``fine_grid``: biopsynav's own FE on a grid ``[evaluate] reference_refinement`` times finer,
  the same contact constraints. Cheap, but it shares the training FE's formulation: it shows
  the network's learning error and the grid's discretisation error, not the formulation's.
  A lesion's deeper push continues from the equilibrium of the one before it (the same load
  path as from rest, its first part solved once).
* ``p2``: an independent FE (:mod:`biopsynav.evaluate.p2`: quadratic tetrahedra of a gmsh mesh
  of the same surface, refined under the probe, its own assembly and Newton), homogeneous
  neo-Hookean with the default tissue's E and nu, the chest-wall plane fixed, the skin under
  the face at rest moved rigidly with the probe. Minutes per push on two cores; its answers
  are kept in ``eval/`` after every push, so a stopped evaluation resumes. Needs gmsh (the
  ``reference`` extra) and a case of one material.

``stored`` (:mod:`biopsynav.evaluate.stored`) answers from the ``p2`` pushes computed once, and
``auto``, the default, is ``stored`` where a stored truth serves the case, else ``fine_grid``.
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

import numpy as np

from ..errors import InputError
from ..fem.teacher import teacher_refinement
from .kept import pose_key
from .p2 import chest_key, probe_key


class GridReference:
    """biopsynav's FE tracker on a finer grid (``fine_grid``)."""

    #: nothing is carried from one rest pose to the next: each rest pose's pushes (a lesion's,
    #: in the order asked: a deeper push continues from the last one's equilibrium) may be
    #: solved in other processes (:mod:`biopsynav.evaluate.parallel`)
    independent_rest_poses = True

    def __init__(self, case: Any, setup: Any, settings: Any) -> None:
        from ..tracker.core import fem_engine, finer_grid_spring_budget
        from .simulation import reference_case

        t0 = time.perf_counter()
        self.case = case
        self.check(case)
        self.fine = reference_case(case, setup.refinement)
        self.tracker = fem_engine(self.fine, finer_grid_spring_budget(settings, setup.refinement),
                                  on_teacher=False, continuation=True)
        self.refinement = setup.refinement
        self.build_s = time.perf_counter() - t0

    @staticmethod
    def check(case: Any) -> None:
        """InputError when the network has a refined teacher (``[dataset] teacher_refine``
        > 1, or ``[refine]``) and the reference grid is no finer than it: it would be the
        network's own teacher, not a truth."""
        from ..refine import tracking_teacher_config

        ev = case.cfg.evaluate
        taught_by = tracking_teacher_config(case.cfg)
        refine = teacher_refinement(taught_by)
        # an order-p extrapolation from cells h and h / r is taken to be as near the converged
        # answer as cells h / r^2 (docs/experiments.md, "An extrapolated teacher")
        extrapolating = taught_by.dataset.teacher_extrapolation > 0
        like = refine ** 2 if extrapolating else refine
        if refine > 1 and ev.reference_refinement <= like:
            teacher_words = (f"{refine:g} times finer, extrapolated from the case grid: about "
                             f"as fine as {like:.3g} times" if extrapolating else
                             f"{refine:g} times finer")
            raise InputError(f"the fine_grid reference ({ev.reference_refinement:g} times finer "
                             f"than the case grid) is no finer than the network's teacher "
                             f"({teacher_words}): raise [evaluate] reference_refinement or "
                             "use reference = \"p2\"", "[evaluate] reference")

    def set_rest_pose(self, pose: np.ndarray) -> int:
        return self.tracker.set_rest_pose(pose)

    def update(self, pose: np.ndarray) -> Any:
        return self.tracker.update(pose)

    def facts(self) -> dict:
        return {"kind": "fine_grid", "cell_size_mm": float(self.fine.grid.spacing),
                "training_cell_size_mm": float(self.case.grid.spacing),
                "refinement": self.refinement,
                "active_cells": int(self.fine.grid.active_cells.sum()),
                "training_active_cells": int(self.case.grid.active_cells.sum()),
                "n_equations": int(self.tracker._fem_model.n_eq)}

    def describe(self) -> str:
        f = self.facts()
        return (f"biopsynav's own FE (the teacher's code: not independent) on a "
                f"{f['cell_size_mm']:.2f} mm grid ({f['active_cells']} active cells, built in "
                f"{self.build_s:.1f} s)")


class P2Reference:
    """The independent P2 tetrahedral FE (``p2``), one mesh per rest pose (refined under the
    face), pushes solved in turn from the last equilibrium of the same rest pose with the
    probe a rigid face (:meth:`~biopsynav.evaluate.p2.TetReference.push` with its
    footprint), answers kept in ``cache`` (a JSON file) keyed by rest pose and pose."""

    def __init__(self, case: Any, setup: Any, settings: Any) -> None:
        self.check(case)
        self.case = case
        ev = case.cfg.evaluate
        self.size_mm, self.fine_mm = float(ev.p2_size_mm), float(ev.p2_fine_mm)
        self.rim_mm, self.friction = float(ev.p2_rim_mm), str(ev.p2_friction)
        self.edge_radius_mm = float(ev.p2_edge_radius_mm)
        self.e_mpa, self.nu = homogeneous_material(case)
        self.cache_path = case.paths.table2_reference_cache
        self.key = self._key()
        self.answers = self._read_cache()
        self.centres = np.array([les.center for les in case.anatomy.lesions]).reshape(-1, 3)
        self.ids = [les.id for les in case.anatomy.lesions]
        self.meshes: list[dict] = []
        self.build_s = 0.0
        self._rest: np.ndarray | None = None
        self._model = None
        self._contact = None
        self._last = None

    @staticmethod
    def check(case: Any) -> None:
        """InputError when gmsh is missing or the case has several tissues."""
        require_gmsh()
        homogeneous_material(case)

    def _key(self) -> str:
        what = {"anatomy": self.case.anatomy.fingerprint(), "E_mpa": self.e_mpa, "nu": self.nu,
                "size_mm": self.size_mm, "fine_mm": self.fine_mm,
                **probe_key(self.case.cfg.probe, self.friction, self.rim_mm,
                            self.edge_radius_mm), **chest_key(self.case.anatomy)}
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()

    def _read_cache(self) -> dict:
        if not self.cache_path.is_file():
            return {}
        try:
            stored = json.loads(self.cache_path.read_text())
        except (OSError, ValueError):
            return {}  # a damaged cache is solved again, never trusted
        return stored.get("answers", {}) if stored.get("key") == self.key else {}

    def set_rest_pose(self, pose: np.ndarray) -> int:
        from ..tracker.core import as_pose, contact_indices

        self._rest = as_pose(pose)
        self._model = self._contact = self._last = None
        probe = self.case.cfg.probe
        return len(contact_indices(self.case.anatomy, self._rest, probe.footprint,
                                   probe.contact_tolerance_mm))

    def update(self, pose: np.ndarray) -> Any:
        from ..tracker import result as st
        from ..tracker.core import as_pose

        start = time.perf_counter()
        pose = as_pose(pose)
        name = pose_key(self._rest, pose)
        if name not in self.answers:
            try:
                disp = self._solve(pose)
            except (FloatingPointError, RuntimeError) as exc:
                self._last = None  # the next push starts from rest
                return reference_result(self.ids, self.centres, None, st.SOLVER_FAILED,
                                        f"P2 reference: {exc}", start)
            self.answers[name] = {"displacement_mm": disp,
                                  "solve_ms": (time.perf_counter() - start) * 1e3,
                                  "tangled_elements": len(self._model.tangled(self._last))}
            self._write_cache()
        answer = self.answers[name]
        res = reference_result(self.ids, self.centres, np.asarray(answer["displacement_mm"]),
                               st.OK, "", start)
        res.latency_ms = float(answer["solve_ms"])  # the solve's, also when kept from before
        return res

    def _solve(self, pose: np.ndarray) -> list:
        """Every lesion centre's displacement (n, 3) mm at ``pose``, as a list."""
        if self._model is None:
            self._build()
        (disp,) = self._model.push(self._rest, [pose], self._contact, self.centres,
                                   start=self._last, footprint=self.case.cfg.probe.footprint,
                                   edge_radius_mm=self.edge_radius_mm)
        self._last = self._model.last
        return np.asarray(disp).tolist()

    def _build(self) -> None:
        from .p2 import TetReference, rim_at

        t0 = time.perf_counter()
        probe = self.case.cfg.probe
        self._model = TetReference.build(self.case.anatomy, self.size_mm, self.e_mpa,
                                         self.nu, fine_at=self._rest[:3, 3],
                                         fine_mm=self.fine_mm,
                                         rim=rim_at(self._rest, probe.footprint, self.rim_mm))
        self._contact = self._model.contact(self._rest, probe.footprint,
                                            probe.contact_tolerance_mm, self.friction)
        self.build_s += time.perf_counter() - t0
        self.meshes.append({"tets": len(self._model.elements), "dofs": self._model.n_dofs,
                            "contact_nodes": len(self._contact)})

    def _write_cache(self) -> None:
        from ..fileio import write_json_atomic

        write_json_atomic(self.cache_path, {"key": self.key, "answers": self.answers})

    def facts(self) -> dict:
        return {"kind": "p2", "E_mpa": self.e_mpa, "nu": self.nu, "size_mm": self.size_mm,
                "fine_mm": self.fine_mm, "rim_mm": self.rim_mm, "friction": self.friction,
                "edge_radius_mm": self.edge_radius_mm,
                "meshes": self.meshes,
                "answers_with_folded_elements": self._folded_answers(),
                "training_cell_size_mm": float(self.case.grid.spacing),
                "training_active_cells": int(self.case.grid.active_cells.sum())}

    def _folded_answers(self) -> int:
        """How many answers hold elements folded over at a node (:meth:`TetReference.tangled`:
        skin bent round the probe face's sharp edge)."""
        return sum(1 for a in self.answers.values() if a.get("tangled_elements"))

    def describe(self) -> str:
        tets = [m["tets"] for m in self.meshes]
        if tets:
            size = f"{min(tets)}-{max(tets)} tetrahedra"
        else:
            size = "answers of an earlier run" if self.answers else "one mesh per placement"
        folded = self._folded_answers()
        rim = f", {self.rim_mm:g} mm at its edge" if self.rim_mm else ""
        edges = (f"edges rounded by {self.edge_radius_mm:g} mm" if self.edge_radius_mm
                 else "sharp edges")
        return (f"independent P2 tetrahedral FE ({self.size_mm:g} mm, {self.fine_mm:g} mm under "
                f"the probe{rim}; {size}; a {self.friction} face with {edges}), homogeneous "
                f"{self.e_mpa * 1e3:g} kPa, nu {self.nu:g}"
                + (f"; {folded} of {len(self.answers)} answers with elements folded over at "
                   "the probe's edge" if folded else ""))


def require_gmsh() -> None:
    """InputError unless gmsh (the P2 reference's mesher) imports."""
    try:
        import gmsh  # noqa: F401
    except ImportError as exc:
        raise InputError(f"the P2 reference meshes with gmsh, which does not import ({exc}); "
                         "install it with pip install 'biopsynav[reference]', or use "
                         "[evaluate] reference = \"fine_grid\"", "[evaluate] reference") from None


def homogeneous_material(case: Any) -> tuple[float, float]:
    """E (MPa) and nu of the case's default tissue; InputError when a labelled tissue of the
    grid has another material (the P2 reference has one material)."""
    others = other_materials(case)
    if others:
        raise InputError("the P2 reference has one material, and this case's grid mixes "
                         f"tissues of other materials ({', '.join(others)} beside "
                         f"{case.cfg.material.default_tissue}); use [evaluate] reference = "
                         "\"fine_grid\"", "[evaluate] reference")
    return default_tissue_material(case)


def other_materials(case: Any) -> list[str]:
    """The tissues of the grid's labels whose material ([material.tissues] entry) is not the
    default tissue's, in label order without repeats; empty for a case of one material (no
    labels, or every label mapped to a tissue of the default's parameters)."""
    from ..fem.tissues import label_tissues

    mat = case.cfg.material
    names = label_tissues(case.grid.label_values, case.cfg, case.anatomy)
    default = mat.tissues[mat.default_tissue]
    return list(dict.fromkeys(n for n in names if mat.tissues[n] != default))


def default_tissue_material(case: Any) -> tuple[float, float]:
    """E (MPa) and nu of the case's default tissue: the material of the homogeneous P2
    reference."""
    mat = case.cfg.material
    tissue = mat.tissues[mat.default_tissue]
    return float(tissue["E_mpa"]), float(tissue["nu"])


def reference_result(ids: list[int], centres: np.ndarray, disp: np.ndarray | None,
                     status: str, reason: str, start: float) -> Any:
    """A TrackingResult of lesion ``ids`` at rest ``centres`` (n, 3) moved by ``disp`` (n, 3)
    mm (None: not answered, NaN)."""
    from ..tracker.result import LesionResult, TrackingResult

    if disp is None:
        disp = np.full_like(centres, np.nan)
        centres = disp
    lesions = [LesionResult(i, c + d, d, status) for i, c, d in
               zip(ids, centres, disp, strict=True)]
    return TrackingResult(lesions, status, reason, (time.perf_counter() - start) * 1e3)

