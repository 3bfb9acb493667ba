"""The P2 teacher (``[dataset] teacher = "p2"``, set by ``[refine] teacher``): rigid pushes
solved by the P2 tetrahedral FE of Table 2's truth, brought to the case grid.

Each push gets its own gmsh mesh, ``[dataset] teacher_fine_mm`` tetrahedra within 35 mm of
the push's centre and ``teacher_size_mm`` elsewhere (:meth:`biopsynav.evaluate.p2.
TetReference.build`, as the truth meshes each probe placement), the probe the truth's (a
rigid face holding the skin it touches at rest; ``[evaluate] p2_friction``, ``p2_rim_mm``,
``p2_edge_radius_mm``), the material the case's default tissue (one material). The push's
rest pose is the face of the grid teacher's draw (its long axis, the centre's outward normal)
and it moves by the draw's displacement without turning, as the grid teacher's contact
points do.

The answer reaches the case grid as the grid teacher's finer grids do
(:class:`biopsynav.grid.transfer.PointFit`): the case-grid field whose trilinear
interpolation is nearest, in the least-squares sense, the P2 field at the centres of the
cells of a grid :data:`FIT_REFINE` times finer that lie in the tetrahedra (weighted by their
tissue), with the penalty :data:`FIT_SMOOTHING` on neighbouring nodes' differences, and, unlike
theirs, no contact points held (the network's input, with elastic contact the face's own
motion, does not read them). Measured on phantom lesions 1 and 4, 10 / 20 / 30 mm pushes of the
P2 FE (8 mm tetrahedra near the probe): the case grid's trilinear interpolation at the lesion
0.01-0.03 / 0.05-0.10 / 0.20 mm from the P2 answer; the P2 values at the case grid's nodes
instead (with a harmonic extension to the nodes outside the tetrahedra) 0.07-0.08 / 0.23-0.24
/ 0.55-0.66 mm; the fit holding the contact points flung the nodes of nearly empty cells to
2-4 times the push. A push that has taken :data:`PUSH_LIMIT_S` seconds of its worker's CPU
time is given up and redrawn like a push that did not converge (``[dataset]
teacher_push_limit_s``; 0: never): CPU time, so that what else the machine runs does not
decide which pushes a set keeps (its speed still does; sets made before 2026-12-07 counted
wall time).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InputError

#: How an answer reaches the case grid (in the data set's protocol)
TO_CASE_GRID = "least-squares fit at the cell centres of a finer grid, no held points"
#: The fit's points: cell centres of a grid this many times finer than the case grid
FIT_REFINE = 2
#: The fit's neighbour-difference penalty (:class:`biopsynav.grid.transfer.PointFit`),
#: ten times the grid teacher's: nodes of nearly empty cells stay near the push's depth
FIT_SMOOTHING = 1e-2
#: The default ``[dataset] teacher_push_limit_s``: a push that has taken this many seconds of
#: its worker's CPU time is given up (recorded as not converged)
PUSH_LIMIT_S = 1800.0


class P2Teacher:
    """Rigid pushes of one case solved by the P2 truth's FE (module docstring)."""

    def __init__(self, case: Any) -> None:
        from ..evaluate.references import default_tissue_material
        from ..grid.transfer import fine_cell_samples, refined_grid

        self.check(case)
        self.case = case
        self.e_mpa, self.nu = default_tissue_material(case)
        fine = refined_grid(case.anatomy, case.cfg.grid, FIT_REFINE, 1.0,
                            case.cfg.anatomy.chest_wall_tolerance_mm)
        self.points, self.weights, _ = fine_cell_samples(fine)

    @staticmethod
    def check(case: Any) -> None:
        """InputError when gmsh does not import or the case has several materials."""
        from ..evaluate.references import require_gmsh

        require_gmsh()
        _one_material(case)

    @staticmethod
    def protocol(cfg: Any, anatomy: Any) -> dict:
        """What its answers depend on beside the case's anatomy, grid and material: the
        truth's mesh sizes and probe (:func:`biopsynav.evaluate.p2.probe_key`), how it holds
        ``anatomy``'s chest wall (:func:`biopsynav.evaluate.p2.chest_key`: named for a curved
        wall only, which the truth held as a plane before), the fit."""
        from ..evaluate.p2 import chest_key, probe_key

        ev, data = cfg.evaluate, cfg.dataset
        return {"size_mm": float(data.teacher_size_mm), "fine_mm": float(data.teacher_fine_mm),
                **probe_key(cfg.probe, str(ev.p2_friction), float(ev.p2_rim_mm),
                            float(ev.p2_edge_radius_mm)), **chest_key(anatomy),
                "to_case_grid": TO_CASE_GRID, "fit_refine": FIT_REFINE,
                "fit_smoothing": FIT_SMOOTHING,
                "push_limit_s": push_limit_s(cfg)}

    def solve(self, push: Any) -> np.ndarray:
        """``push`` (a rigid :class:`biopsynav.probe.ProbePush`) on its own P2 mesh, fitted
        to the case grid (:meth:`_on_case_grid`): (n_nodes, 3) mm; SolverError when it is
        not answered (an element inverted, Newton failed, or ``[dataset]
        teacher_push_limit_s`` passed)."""
        from ..errors import SolverError
        from ..evaluate.p2 import PushTimeout

        model, rest = self._model(push)
        ev, probe = self.case.cfg.evaluate, self.case.cfg.probe
        contact = model.contact(rest, probe.footprint, probe.contact_tolerance_mm,
                                str(ev.p2_friction))
        pose = rest.copy()
        pose[:3, 3] += push.displacement
        try:
            model.push(rest, [pose], contact, np.zeros((0, 3)), footprint=probe.footprint,
                       edge_radius_mm=float(ev.p2_edge_radius_mm),
                       time_limit_s=push_limit_s(self.case.cfg), cpu_time=True)
        except (FloatingPointError, RuntimeError, PushTimeout) as exc:
            raise SolverError(f"P2 teacher: {exc or type(exc).__name__}",
                              "[dataset] teacher") from None
        return self._on_case_grid(model)

    def _on_case_grid(self, model: Any) -> np.ndarray:
        """The last push of ``model`` on the case grid (n_nodes, 3) mm: the
        :class:`~biopsynav.grid.transfer.PointFit` of its values at the fit's points that
        lie in its tetrahedra (:attr:`points`, :attr:`weights`), smoothing
        :data:`FIT_SMOOTHING`."""
        from ..grid.transfer import PointFit

        matrix, inside = model.interpolation(self.points)
        fit = PointFit(self.case.grid, self.points[inside], self.weights[inside],
                       smoothing=FIT_SMOOTHING, where="P2 teacher")
        return fit(matrix[inside] @ model.last)

    def _model(self, push: Any) -> tuple[Any, np.ndarray]:
        """The P2 model meshed for ``push`` and the face's rest pose (4, 4): axes the push's
        long axis and the centre's inward normal (the beam), origin the centre."""
        from ..evaluate.p2 import TetReference, rim_at

        ev, probe = self.case.cfg.evaluate, self.case.cfg.probe
        rest = face_rest_pose(push)
        data = self.case.cfg.dataset
        model = TetReference.build(self.case.anatomy, float(data.teacher_size_mm), self.e_mpa,
                                   self.nu, fine_at=rest[:3, 3],
                                   fine_mm=float(data.teacher_fine_mm),
                                   rim=rim_at(rest, probe.footprint, float(ev.p2_rim_mm)))
        return model, rest


def push_limit_s(cfg: Any) -> float | None:
    """Seconds after which a push is given up (``[dataset] teacher_push_limit_s``); None for
    no limit (0)."""
    return float(cfg.dataset.teacher_push_limit_s) or None


def face_rest_pose(push: Any) -> np.ndarray:
    """The probe pose (4, 4) of a drawn push at rest: x the face's long axis, z the beam
    (into the tissue, against the centre's outward normal), origin the centre (mm)."""
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([push.long_axis, -push.short_axis, -push.normal])
    pose[:3, 3] = push.center
    return pose


def _one_material(case: Any) -> None:
    """InputError when the case's grid mixes tissues of other materials than its default
    tissue's (the P2 FE has one)."""
    from ..evaluate.references import other_materials

    others = other_materials(case)
    if others:
        raise InputError("the P2 teacher has one material, and this case's grid mixes tissues "
                         f"of other materials ({', '.join(others)} beside "
                         f"{case.cfg.material.default_tissue}); use teacher = \"grid\"",
                         "[dataset] teacher")
