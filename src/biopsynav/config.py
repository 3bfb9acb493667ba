"""``case.toml``: every parameter of a case, with its documented default and validation.

Units everywhere: millimetres (mm), newtons (N), megapascals (MPa; 1 kPa = 1e-3 MPa), seconds.
Each section is a dataclass; each field carries its documentation and its allowed range in the
field metadata, so that validation, defaults and the reference in ``docs/case_toml.md`` come from
one place (:func:`reference_markdown`).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w
import tomllib

from .contact.constraints import contact_constraint_names
from .errors import InputError
from .fileio import write_text_atomic
from .footprint import Footprint, footprint_names, make_footprint
from .inference.runtimes import runtime_choices
from .layout import CASE_FILE
from .materials import MATERIAL_LAWS, material_law_names
from .prior_registry import prior_choices
from .reference_registry import P2_FRICTIONS, reference_names
from .teacher_registry import GRID_TEACHER, teacher_names


def opt(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
        choices: tuple | Any = None, factory: Any = None) -> Any:
    """A documented case.toml field with optional numeric range or choices (a tuple, or a
    function returning one: the names of a registry, read when a value is checked)."""
    meta = {"doc": doc, "lo": lo, "hi": hi, "choices": choices}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


def field_choices(meta: dict) -> tuple:
    """The allowed values of a field (its registry's names when ``choices`` is a function)."""
    choices = meta.get("choices") or ()
    return tuple(choices()) if callable(choices) else tuple(choices)


@dataclass
class CaseSection:
    name: str = opt("case", "Free-text name of the case (patient or phantom).")
    description: str = opt("", "Free-text description.")


@dataclass
class AnatomySection:
    source: str = opt("surface", "Kind of anatomy input.",
                      choices=("phantom", "surface", "volume", "labelmap"))
    path: str = opt("", "Anatomy file relative to the case folder (STL/OBJ/PLY/VTK/VTU surface, "
                        "tetrahedral VTK/VTU volume, or NRRD/NIfTI/MHA label map).")
    lesions: str = opt("", "Lesions: a CSV (id,x,y,z,radius_mm) or a folder of lesion surface "
                           "meshes, relative to the case folder; empty when lesions come from "
                           "label values or the phantom.")
    breast_labels: list = opt(None, "Label-map values (any integer, negative included) or "
                                    "segment names of a Slicer .seg.nrrd that are breast "
                                    "tissue.", factory=list)
    lesion_labels: list = opt(None, "Label-map values or segment names that are lesions (one "
                                    "lesion per connected component; their cells get the "
                                    "tissue 'lesion' unless tissue_labels says otherwise).",
                              factory=list)
    chest_labels: list = opt(None, "Label-map values or segment names of the pectoral muscle "
                                   "(or chest): when given, the chest wall is the curved "
                                   "interface between breast tissue and these labels, not a "
                                   "plane.", factory=list)
    side: str = opt("", "Which breast of a bilateral label map: 'left' or 'right' (the "
                        "patient's; RAS -x is left). Empty: the only breast, or the one "
                        "holding the lesions.", choices=("", "left", "right"))
    breast_protrusion_mm: float = opt(25.0, "A label map of the whole anterior torso is cut "
                                            "to its breasts: the columns (along the anterior "
                                            "axis) whose tissue stands more than this off the "
                                            "torso layer (docs/anatomy.md, 'The breast of a "
                                            "torso'). 0: no cut. A map of one breast alone "
                                            "(no torso layer around it) is never cut.",
                                      lo=0.0, hi=100.0)
    torso_disc_mm: float = opt(200.0, "Diameter of the disc that rolls under the tissue "
                                      "thickness map to find the torso layer: wider than a "
                                      "breast, narrower than the torso.", lo=50.0, hi=500.0)
    crop_faces: str = opt("free", "Where a label map's image or the torso cut ends the breast "
                                  "(crop faces; never pushed): 'free' (traction-free) or "
                                  "'held' (fixed like the chest wall); with --chest-labels. "
                                  "docs/anatomy.md, 'Crop faces: held or free'.",
                          choices=("free", "held"))
    labelmap_spacing_mm: float = opt(0.0, "Isotropic voxel size a label map is resampled to "
                                          "before its surface is made; 0 takes the image's "
                                          "finest spacing.", lo=0.0, hi=10.0)
    labelmap_smoothing_mm: float = opt(1.0, "Standard deviation of the Gaussian that smooths "
                                            "the breast mask before marching cubes (0: none). "
                                            "The surface volume is checked against the "
                                            "labelled volume (within 10 %).", lo=0.0, hi=10.0)
    input_frame: str = opt("ras", "Frame of surface/volume meshes and lesion CSVs given by the "
                                  "user: 'ras' (3D Slicer's display frame) or 'lps' (DICOM/ITK). "
                                  "A case, its tracker and OpenIGTLink are in RAS; label maps "
                                  "(LPS in the file) and Slicer markups (their own "
                                  "coordinateSystem) are converted whatever this says.",
                           choices=("ras", "lps"))
    lesion_radius_mm: float = opt(5.0, "Radius of a lesion given as a markups point (.mrk.json "
                                       "has no size).", lo=0.1, hi=100.0)
    tissue_labels: dict = opt(None, "Map from a label value (as a string key, negative "
                                    "included) or a segment name to a tissue name of "
                                    "[material]. A label without an entry takes the tissue "
                                    "its segment is named after (fat, gland, fibroglandular, "
                                    "skin, tumour, lesion), lesion labels take 'lesion'; any "
                                    "other is refused at init.", factory=dict)
    label_field: str = opt("", "Name of the cell-data array that holds tissue labels in a volume "
                               "mesh; empty picks the first integer cell array.")
    chest_wall: str = opt("auto", "Chest wall (fixed, Dirichlet) definition: 'auto' (the flat "
                                  "posterior face), 'z-min', 'x-min', ... or "
                                  "'plane:px,py,pz,nx,ny,nz' (point and outward normal; nodes "
                                  "on or behind the plane are fixed).")
    chest_wall_tolerance_mm: float = opt(1.0, "Distance from the chest-wall plane within which "
                                              "surface vertices and grid nodes count as on it.",
                                         lo=0.0, hi=50.0)
    max_fixed_share: float = opt(0.4, "Largest share of the grid's active nodes the chest wall "
                                      "may fix. A chest wall holds the breast's base (about 12 "
                                      "% of the nodes on the phantom and the UC Davis breast); "
                                      "more usually means a plane whose normal points into the "
                                      "breast, and init refuses it with the numbers.",
                                 lo=0.0, hi=1.0)
    lesion_points: int = opt(42, "Surface points kept per spherical lesion.", lo=6, hi=2000)


@dataclass
class GridSection:
    cell_size_mm: float = opt(7.3, "Edge of the cubic hexahedral cells. The default gives the "
                                   "built-in phantom 2,225 active cells on 24 x 20 x 13 nodes "
                                   "(the paper: 2,174).",
                              lo=0.5, hi=100.0)
    margin_cells: int = opt(1, "Empty cells kept around the anatomy (on the chest wall's axis, on "
                                  "the far side only).", lo=0, hi=8)
    samples_per_axis: int = opt(5, "Sub-cell sample points per axis for the tissue volume "
                                   "fraction (n^3 per cell).", lo=1, hi=16)
    fraction_threshold: float = opt(0.01, "Cells with a tissue volume fraction above this are "
                                          "active; cells holding a surface vertex or lesion "
                                          "point are active too.", lo=0.0, hi=1.0)
    min_fraction: float = opt(0.05, "Lower bound of the fraction used to scale the integration "
                                    "weights of an active cell (keeps nearly empty cells from "
                                    "making the stiffness singular).", lo=0.0, hi=1.0)


@dataclass
class MaterialSection:
    model: str = opt("neo-hookean",
                     "Hyperelastic law (biopsynav.materials registry) of the case grid's force "
                     "patches (the case network's teacher, Table 1, the force calibration, "
                     "`simulate`); the tracking model's teacher has its own, [refine] "
                     "material_model, which the FE engine, Table 2's FE method and the tracker's "
                     "contact compliance follow. 'neo-hookean' (the default: compressible, full "
                     "2x2x2 integration; it answers more of the deep force patches, so the "
                     "case network sees deeper pushes, docs/fem.md 'Two laws: the mixed "
                     "recipe'), 'neo-hookean-split-sri-inner' (the decoupled neo-Hookean "
                     "energy, isochoric part at 2x2x2 points and volumetric part at the "
                     "centre, in the cells wholly inside the tissue, 'neo-hookean' in the "
                     "cells the surface cuts: nearer the independent P2 truth; the default of "
                     "cases made on 2026-11-30), "
                     "'neo-hookean-sri' (that energy, its volumetric term integrated at the "
                     "cell centre), 'neo-hookean-split-sri' (the decoupled law in every cell) "
                     "or 'svk' (Saint Venant-Kirchhoff, the paper's; collapses under large "
                     "pushes on soft tissue).",
                     choices=material_law_names)
    fictitious_stiffness: float = opt(0.0, "Share of its small-strain stiffness that the "
                                           "empty part of each cut cell keeps, linear in the "
                                           "displacement (the finite cell method's fictitious "
                                           "domain, docs/fem.md 'The fictitious domain'): a "
                                           "nearly empty cell holding contact points then "
                                           "cannot turn over under a deep push. 0 "
                                           "(default): none, every cell as before; the "
                                           "tracking model's teacher has its own, [refine] "
                                           "fictitious_stiffness.", lo=0.0, hi=1.0)
    default_tissue: str = opt("phantom", "Tissue of cells without a label.")
    tissues: dict = opt(None, "Per-tissue Young's modulus E_mpa (MPa) and Poisson ratio nu. "
                              "Defaults: fat 4.46 kPa, gland 15.1 kPa, skin 20 kPa (UC Davis / "
                              "Awwad et al. 2024, after Wellman 1999 and Samani 2007), lesion "
                              "30 kPa (Samani 2007, IDC), phantom 5 kPa; nu 0.45.",
                    factory=lambda: {
                        "fat": {"E_mpa": 4.46e-3, "nu": 0.45},
                        "gland": {"E_mpa": 15.1e-3, "nu": 0.45},
                        "skin": {"E_mpa": 20.0e-3, "nu": 0.45},
                        "lesion": {"E_mpa": 30.0e-3, "nu": 0.45},
                        "phantom": {"E_mpa": 5.0e-3, "nu": 0.45},
                    })


@dataclass
class SolverSection:
    tol_residual: float = opt(1e-8, "Newton stops when |R| <= tol_residual * |R0| (R0: the "
                                    "residual of the undeformed state under the full load; "
                                    "prescribed displacements count by the reactions they need "
                                    "in the linearised problem) ...",
                              lo=1e-14, hi=1e-1)
    tol_displacement: float = opt(1e-8, "... and |du| <= tol_displacement * |u| (du: the last "
                                        "Newton correction).",
                                  lo=1e-14, hi=1e-1)
    intermediate_tolerance: float = opt(1e-3, "Looser relative tolerance (residual and "
                                              "displacement) of load increments before the "
                                              "last one.", lo=1e-14, hi=1e-1)
    max_iterations: int = opt(30, "Newton iterations per load increment.", lo=1, hi=500)
    initial_load_step: float = opt(1.0, "First load increment as a fraction of the full load "
                                        "(cut in half on divergence or inverted elements, "
                                        "doubled after an increment converging in <= 4 "
                                        "iterations).", lo=1e-4, hi=1.0)
    min_load_step: float = opt(1.0 / 256, "Smallest load increment before the solve fails.",
                               lo=1e-8, hi=1.0)
    line_search: bool = opt(True, "Line search on the energy slope along the Newton step "
                                  "(steps that invert an element are always shortened).")
    reuse_factorization: bool = opt(True, "Once Newton is in its quadratic regime, reuse the "
                                          "last factorisation while it cuts |R| four-fold per "
                                          "iteration (modified Newton; far fewer "
                                          "factorisations).")
    backend: str = opt("auto", "Sparse direct solver: auto (fastest installed: pardiso, then "
                               "cholmod, then superlu), pardiso (MKL, pip install pypardiso), "
                               "cholmod (scikit-sparse), superlu (SciPy, always there, ~10x "
                               "slower).",
                       choices=("auto", "pardiso", "cholmod", "superlu"))
    single_precision: bool = opt(True, "Pardiso factors the tangent in single precision "
                                       "(about a third faster; residuals and convergence "
                                       "stay double precision). Not used with prescribed "
                                       "displacements, except for a data set's rigid pushes "
                                       "with elastic contact (docs/contact.md, 'Elastic "
                                       "contact').")
    threads: int = opt(0, "Pardiso threads (0: all cores).", lo=0, hi=1024)
    indefinite_tangent: str = opt("ldlt", "A Newton iteration whose tangent is not positive "
                                          "definite (deep pushes past a limit point): 'ldlt' "
                                          "factors it as it is (Pardiso's indefinite LDL^T); "
                                          "'shift' factors K + s diag|K| with the smallest s of "
                                          "0.01, 0.1, ... that makes it positive definite (a "
                                          "descent step on the energy) and lets a solve still "
                                          "converging at its iteration limits finish: 1,000 "
                                          "refine pushes in 6.7 instead of 11.0 min, 3 instead "
                                          "of 22 failed, but the network they teach lands "
                                          "further from the truth at 30 mm (docs/fem.md). "
                                          "SuperLU cannot tell and always factors as it is.",
                                  choices=("shift", "ldlt"))
    penalty: float = opt(1e6, "Penalty of prescribed displacements, relative to the mean "
                              "diagonal of the reference stiffness.", lo=1.0, hi=1e12)
    constraint_tolerance_mm: float = opt(1e-2, "Largest error of a prescribed displacement "
                                               "(mm); augmented-Lagrangian updates run until "
                                               "it is met. Far below the discretisation "
                                               "error of lesion displacements (docs/fem.md).",
                                         lo=1e-10, hi=1.0)


@dataclass
class ProbeSection:
    shape: str = opt("rectangle", "Shape of the probe face (biopsynav.footprint registry): "
                                  "'rectangle' (a linear array) or 'ellipse' (inscribed in "
                                  "footprint_mm).", choices=footprint_names)
    footprint_mm: list = opt(None, "Probe face, long side x short side.",
                             factory=lambda: [50.0, 10.0])
    depth_tolerance_mm: float = opt(5.0, "Half-depth of the oriented selection box along the "
                                         "surface normal.", lo=0.1, hi=100.0)
    max_tilt_deg: float = opt(45.0, "Largest angle between the force and the inward normal.",
                              lo=0.0, hi=89.0)
    f_max_n: float = opt(4.0, "Largest total probe force (N), shared equally by the contact "
                              "points; drawn uniformly in [0, f_max_n]. A total force keeps the "
                              "load independent of the skin-mesh density; the default pushes the "
                              "5 kPa phantom up to ~46 mm probe displacement, of which [probe] "
                              "max_push_mm keeps up to 35 mm (docs/dataset.md).",
                         lo=0.0, hi=1e4)
    train_force_exponent: float = opt(0.5, "Training pushes (samples below [dataset] n_train) "
                                           "draw the total force as f_max_n * u^e, u uniform "
                                           "in [0, 1]: e = 1 is the paper's uniform force, e < "
                                           "1 draws strong pushes more often (force density "
                                           "proportional to F^(1/e - 1)), where the network "
                                           "errs most. Held-out pushes keep the paper's "
                                           "uniform force, so Table 1 measures on its protocol "
                                           "(docs/experiments.md, 'Strong pushes drawn more "
                                           "often').", lo=0.05, hi=1.0)
    train_force_scale: float = opt(1.0, "Training pushes draw their force up to this multiple "
                                        "of f_max_n (s f_max_n u^e); draws deeper than "
                                        "max_push_mm are redrawn. Held-out pushes keep [0, "
                                        "f_max_n]. Above 1 it was measured worse on the UC "
                                        "Davis breast (1.5: Table 1 max e 0.46 against 0.25 mm "
                                        "on the same held-out pushes; docs/experiments.md, "
                                        "'A steadier force calibration, and training "
                                        "forces beyond the held-out range').",
                                   lo=1.0, hi=4.0)
    too_deep_redraw: str = opt("elsewhere", "How a training push that goes deeper than "
                                            "max_push_mm is redrawn: 'elsewhere' draws a whole "
                                            "new push (held-out pushes always do); 'same-place' "
                                            "keeps its patch and tilt and draws a weaker force "
                                            "(its u times a new uniform number), so each place "
                                            "keeps its share of the training pushes. Measured on "
                                            "the UC Davis breast, same-place was no better "
                                            "(Table 1 max e 0.362 against 0.355 mm on the same "
                                            "held-out pushes; docs/experiments.md, 'Too-deep "
                                            "training pushes redrawn at the same place'), so "
                                            "the default keeps the former protocol "
                                            "(docs/dataset.md, protocol step 6).",
                               choices=("elsewhere", "same-place"))
    calibrate_force: bool = opt(True, "Before generation, set the data set's force range "
                                      "for the breast at hand: f_max_n is searched (from the "
                                      "value above) until 90 % of calibration_pushes "
                                      "pushes at f_max_n reach max_push_mm, and recorded in "
                                      "the data set (docs/dataset.md). false: f_max_n as "
                                      "given.")
    calibration_pushes: int = opt(48, "Probe pushes of the force calibration (each solved in "
                                      "every round of the search). Fewer are faster but leave "
                                      "the force range to chance: with 12, the UC Davis "
                                      "breast's range moved from 3.1 to 5.5 N with the seed "
                                      "(docs/network.md). Not part of the data set's "
                                      "protocol: the calibration it found is recorded in it.",
                                  lo=4, hi=100000)
    max_push_mm: float = opt(35.0, "Deepest training push (mm of probe displacement, the mean "
                                   "norm of the contact points' displacement): a draw that "
                                   "goes deeper is recorded and redrawn, like a failed solve, so "
                                   "the data set stays in the clinical range the paper trains "
                                   "for ('up to about 35 mm') whatever the breast's local "
                                   "compliance. 0: keep every push (docs/dataset.md).",
                             lo=0.0, hi=1000.0)
    min_chest_distance_mm: float = opt(5.0, "Training pushes are centred on skin vertices at "
                                            "least this far in front of the chest-wall plane.",
                                       lo=0.0, hi=1000.0)
    min_contact_points: int = opt(4, "A training push needs at least this many skin vertices "
                                     "under the footprint (else centre and angle are redrawn).",
                                  lo=1, hi=100000)
    contact_tolerance_mm: float = opt(2.0, "Tracker rest pose: skin points within this distance "
                                           "of the probe face plane (and under the footprint) "
                                           "are in contact.", lo=0.0, hi=50.0)
    rigid_share: float = opt(0.0, "Share of the training samples pushed by the rigid probe "
                                  "face instead of a force patch: the skin under the face at "
                                  "rest (within contact_tolerance_mm, as the tracker takes it) "
                                  "moves with the face by a depth drawn uniformly in [0, "
                                  "max_push_mm] (less by max_chest_compression; a training "
                                  "push's skewed by train_depth_exponent) along a "
                                  "direction tilted as the force is, held "
                                  "by [tracker] fem_contact constraints (docs/dataset.md). 0: "
                                  "the paper's force patches only; 1: rigid pushes only; "
                                  "between, the kinds interleave evenly (any first n samples "
                                  "hold floor(n rigid_share) rigid pushes).",
                             lo=0.0, hi=1.0)
    lesion_share: float = opt(0.0, "Share of the training samples centred near a lesion "
                                   "instead of anywhere on the skin: a lesion drawn uniformly, "
                                   "then a centre among the eligible skin vertices within "
                                   "lesion_reach_mm of the skin vertex nearest it; angle, tilt "
                                   "and load drawn as for any push (docs/experiments.md, "
                                   "'Pushes near the lesions'). 0: the whole skin alike.",
                              lo=0.0, hi=1.0)
    lesion_reach_mm: float = opt(20.0, "With lesion_share > 0: how far from the skin vertex "
                                       "nearest a lesion a lesion-centred push may be centred.",
                                 lo=0.0, hi=1000.0)
    max_chest_compression: float = opt(0.6, "A rigid push moves the face towards the chest "
                                            "wall by at most this share of the tissue in front "
                                            "of it under the face (the median chest-wall "
                                            "distance of the skin the face holds at rest): a "
                                            "deeper draw is drawn shallower along the same line, "
                                            "and the tracking network answers out_of_envelope "
                                            "beyond it. Chosen on the solves that failed: on the "
                                            "MRI breasts nearly all pressed further "
                                            "(docs/dataset.md). 0: no such limit.",
                                       lo=0.0, hi=1.0)
    train_depth_exponent: float = opt(1.0, "Training rigid pushes (samples below [dataset] "
                                           "n_train) draw their depth as d_max * u^e, u "
                                           "uniform in [0, 1] and d_max the push's deepest "
                                           "(max_push_mm, less by max_chest_compression): e = "
                                           "1 is uniform, e < 1 draws deep pushes more often "
                                           "(depth density proportional to d^(1/e - 1)). "
                                           "Held-out pushes keep the uniform depth, so Table 1 "
                                           "measures on its protocol (docs/experiments.md, "
                                           "'Deep rigid pushes drawn more often').",
                                      lo=0.05, hi=1.0)
    rigid_max_tilt_deg: float = opt(15.0, "Largest angle between a rigid push and the inward "
                                          "normal. The skin sticks to the face, so a steeper "
                                          "push drags it across the face by the push's "
                                          "tangential part, which the grid does not follow "
                                          "(docs/dataset.md).", lo=0.0, hi=89.0)

    @property
    def footprint(self) -> Footprint:
        """The probe face: ``shape`` of ``footprint_mm``."""
        return make_footprint(self.shape, self.footprint_mm)


@dataclass
class DatasetSection:
    n_train: int = opt(800, "Training samples. Raising it (or n_test) later grows a stored "
                            "data set in place; lowering either is refused (docs/dataset.md, "
                            "'Growing a data set').", lo=1, hi=10**7)
    n_test: int = opt(200, "Held-out test samples.", lo=1, hi=10**7)
    seed: int = opt(0, "Seed: the same seed gives the same samples whatever the worker count.",
                    lo=0, hi=2**63 - 1)
    max_failure_share: float = opt(0.25, "Stop the job when more than this share of the draws "
                                         "fails to converge, or goes deeper than [probe] "
                                         "max_push_mm (each judged on its own, once 20 draws, "
                                         "or all requested if fewer, have been made).",
                                   lo=0.0, hi=1.0)
    contact_input: str = opt("elastic", "How the contact displacement becomes the network "
                                        "input on the contact nodes: 'elastic' (the nodal "
                                        "values of the linear-elastic field that moves the "
                                        "contact points as given; exact point constraints for "
                                        "the physics baseline) or 'average' (trilinear-weighted "
                                        "average of the contact points; docs/dataset.md).",
                             choices=("elastic", "average"))
    newton_budget: int = opt(40, "Newton iterations (all load increments together) after "
                                 "which a draw's solve gives up: it is recorded as failed and "
                                 "redrawn. Draws near the push's limit load need hundreds of "
                                 "iterations and then mostly fail anyway; the budget keeps them "
                                 "from costing most of the compute (docs/dataset.md). 0: no "
                                 "limit.", lo=0, hi=100000)
    max_edge_stretch: float = opt(8.0, "A solved push is not kept when it stretches an edge "
                                        "of a cell more than this many times its rest length: "
                                        "a state no tissue reaches (in practice the lone node "
                                        "of a nearly empty cell flung by the push). It is "
                                        "logged as 'implausible' and redrawn, and counts "
                                        "against max_failure_share on its own (docs/dataset.md)."
                                        " 0: no check.", lo=0.0, hi=1e6)
    teacher: str = opt(GRID_TEACHER, "The FE code that solves the samples: 'grid' (default), "
                                     "the immersed hexahedral FE on the case grid or a finer "
                                     "one (teacher_refine); 'p2', the P2 tetrahedral FE of "
                                     "Table 2's truth with its probe (a rigid face holding "
                                     "the skin it touches at rest; [evaluate] p2_friction, "
                                     "p2_rim_mm, p2_edge_radius_mm), a gmsh mesh of "
                                     "teacher_size_mm refined to teacher_fine_mm under each "
                                     "push, its answer fitted to the case grid: rigid pushes "
                                     "of one material only (docs/dataset.md, "
                                     "'The P2 teacher'). [refine] teacher sets it in the refine "
                                     "case.", choices=teacher_names)
    teacher_size_mm: float = opt(10.0, "With teacher = 'p2': tetrahedron size away from the "
                                       "push (mm; [evaluate] p2_size_mm is the truth's).",
                                 lo=0.5, hi=200.0)
    teacher_fine_mm: float = opt(4.0, "With teacher = 'p2': tetrahedron size within 35 mm of "
                                      "the push (mm). 4 (default): the truth's ([evaluate] "
                                      "p2_fine_mm): on one core of the 2-core machine, about "
                                      "20 s for a 5 mm push, 3-16 min at 19-21 mm, 19-24 min "
                                      "at 26-29 mm (the phantom; teacher_push_limit_s); 8 "
                                      "solves a push "
                                      "in 5-100 s but lies 0.15 / 0.38 / 1.17 mm from the 4 mm "
                                      "answers at 10 / 20 / 30 mm pushes on the phantom, as far "
                                      "as the grid teacher's network (docs/dataset.md, 'The P2 "
                                      "teacher').", lo=0.5, hi=200.0)
    teacher_push_limit_s: float = opt(1800.0, "With teacher = 'p2': a push that has taken "
                                              "this many seconds of its worker's CPU time "
                                              "(not wall time: what else the machine runs "
                                              "does not count) is given up and "
                                              "redrawn, like one that did not converge (0: no "
                                              "limit). A push's time grows about exponentially "
                                              "with its depth: on one core of the 2-core "
                                              "machine the phantom's pushes deeper than about "
                                              "30 mm take longer than the default 1,800 s, so "
                                              "a set made there holds none of them (their "
                                              "redraws are other pushes); raise it where the "
                                              "deep pushes matter and the workers have the "
                                              "time (docs/dataset.md, 'The P2 teacher').",
                                      lo=0.0, hi=1e6)
    teacher_refine: float = opt(1.0, "The teacher's grid: each sample is solved on cells this "
                                     "many times smaller than [grid] cell_size_mm (any factor "
                                     "from 1 to 4: 1.46 turns 7.3 mm cells into 5 mm) and "
                                     "brought to the case grid by a least-squares fit over the "
                                     "tissue (biopsynav.grid.transfer); the network still "
                                     "predicts on the case grid. 1: solve on the case grid "
                                     "itself. 2 halves the cells (8x the unknowns): nearer the "
                                     "converged answer under the probe, each solve 10-35x "
                                     "slower on the phantom (docs/dataset.md).",
                                lo=1.0, hi=4.0)
    teacher_extrapolation: float = opt(0.0, "With teacher_refine > 1: Richardson "
                                            "extrapolation of order p. Each sample is solved on "
                                            "the case grid too, and the stored field is "
                                            "u_fine + (u_fine - u_case) h_fine^p / (h_case^p - "
                                            "h_fine^p), both on the case grid "
                                            "(docs/experiments.md, "
                                            "'An extrapolated teacher'). 0: off, the fine "
                                            "solution itself.", lo=0.0, hi=8.0)
    teacher_min_fraction: float = opt(0.2, "With teacher_refine > 1: the lower bound of the "
                                           "fraction that scales the integration weights of "
                                           "the teacher's cells ([grid] min_fraction is the "
                                           "case grid's). On the phantom's 3.65 mm cells 0.2 "
                                           "keeps the nearly empty skin cells under a rigid "
                                           "face from buckling (an unstable equilibrium at "
                                           "0.05) and changes the FE's mean lesion error "
                                           "against the P2 truth by 0.01 mm "
                                           "(docs/dataset.md).", lo=0.0, hi=1.0)
    chunk_samples: int = opt(1, "Samples per storage chunk of inputs and targets (1: a chunk "
                                "per sample; 'done' always has one chunk per sample).",
                             lo=1, hi=4096)


@dataclass
class NetworkSection:
    preset: str = opt("default", "Architecture preset: 'default' (8 first-level channels, 3 "
                                 "levels, SiLU, quadratic input features, 0.35 M parameters: "
                                 "sized for real-time CPU inference, see docs/network.md), "
                                 "'paper' (128 first-level channels, 1024 in the bottleneck, "
                                 "ReLU, ~90 M parameters) or 'custom' (levels, base_channels, "
                                 "norm, activation, features below).",
                     choices=("default", "paper", "custom"))
    levels: int = opt(3, "U-Net levels k of the custom preset (any grid node counts: an odd "
                         "count's last pooling window is partial).", lo=1, hi=6)
    base_channels: int = opt(16, "Channels of the first level (custom preset); they double "
                                 "per level.", lo=1, hi=512)
    norm: str = opt("none", "Normalisation layer (custom preset).",
                    choices=("none", "batch", "instance", "group"))
    activation: str = opt("relu", "Activation (custom preset; the default preset uses SiLU).",
                          choices=("relu", "leaky_relu", "gelu", "silu"))
    features: str = opt("linear", "Network input features (custom preset): 'linear' (the 4 "
                                  "input channels, as in the paper) or 'quadratic' (plus the 6 "
                                  "products of the displacement channels; the default preset "
                                  "uses them, docs/network.md).",
                        choices=("linear", "quadratic"))
    iterations: int = opt(12500, "Training iterations (optimizer steps). 12,500 at batch 16 "
                                 "(the samples of the paper's 50,000 at batch 4) and "
                                 "learning_rate 2e-3: Table 1 and the tracking network's "
                                 "distance from the independent truth at 10-30 mm pushes as "
                                 "the 50,000 at batch 4, in half the time; 12,000 at batch 4 "
                                 "left the deep pushes 16 % further from it "
                                 "(docs/experiments.md, 'Cost and settings of the chain'). "
                                 "From a prior (prior), 4,000 reach the "
                                 "same mean held-out error, not its largest (docs/network.md, "
                                 "'Starting from a prior'). The time on this machine: "
                                 "benchmarks/time_to_model.py.",
                          lo=1, hi=10**8)
    batch_size: int = opt(16, "Batch size (the paper: 4). 16: a bf16 step on AMX costs 2.8 "
                              "times a batch of 4, not 4 times (benchmarks/bf16_cpu.py).",
                          lo=1, hi=1024)
    learning_rate: float = opt(2e-3, "Peak Adam learning rate (linear warm-up, then cosine "
                                     "decay to 1 % of it).", lo=1e-7, hi=1.0)
    warmup_iterations: int = opt(300, "Linear learning-rate warm-up steps.", lo=0, hi=10**7)
    weight_decay: float = opt(0.2, "Decoupled weight decay (AdamW) per unit learning rate; "
                                   "0: plain Adam (the paper). Measured on the phantom with the "
                                   "default network: mean e 0.0509 and 0.0503 mm (two seeds) "
                                   "with 0.2 against 0.0521 and 0.0540 with 0.05 "
                                   "(docs/network.md).",
                              lo=0.0, hi=10.0)
    loss: str = opt("norm", "Training loss over active nodes: 'norm' (the batch mean of the "
                            "paper's e, eq. 3, in mm; measured on the phantom: mean e 0.0599 "
                            "against 0.0697 mm with 'mse'), 'mse' (the paper's eq. 1) or 'l1' "
                            "on the normalised displacement.", choices=("norm", "mse", "l1"))
    val_interval: int = opt(500, "Validate on the held-out samples (and write a resumable "
                                 "checkpoint) every this many iterations.", lo=1, hi=10**7)
    seed: int = opt(0, "Training seed: the same seed, data, thread count and precision give "
                       "the same model.", lo=0, hi=2**63 - 1)
    device: str = opt("auto", "Training device ('auto': CUDA when present, else CPU; its "
                              "arithmetic: precision).", choices=("auto", "cpu", "cuda"))
    precision: str = opt("auto", "Arithmetic of the training's forward pass: 'fp32', "
                                 "'bf16' (autocast to bfloat16; the loss, the contact "
                                 "projection and the weights stay fp32) or 'auto' (bf16 on "
                                 "CUDA; on a CPU with AMX-BF16 or AVX-512 BF16 the faster of "
                                 "the two by a timed training step of each, bf16 only when "
                                 "10 % faster, a resumed training the checkpoint's; fp32 on "
                                 "other CPUs; train's first line and meta.json say which and "
                                 "the steps; docs/network.md). Inference has its own "
                                 "arithmetic: [network] runtime.",
                         choices=("auto", "fp32", "bf16"))
    threads: int = opt(0, "CPU threads for training and inference (0: the idle cores, "
                          "measured when it starts).", lo=0, hi=1024)
    baseline: str = opt("linear-elastic", "Physics baseline: 'linear-elastic' (the network "
                                          "learns only the residual of the case's linearised FE "
                                          "model moved at the contact nodes; see "
                                          "docs/network.md) or 'none' (the network predicts the "
                                          "whole displacement).",
                        choices=("linear-elastic", "none"))
    contact_projection: bool = opt(True, "Predictions move the contact points exactly by "
                                         "their measured displacement: the part of the "
                                         "network's residual the points see is replaced by the "
                                         "linear-elastic field of the rest (training, tracker "
                                         "and Table 1; needs the linear-elastic baseline and "
                                         "the elastic contact input; a model trained through "
                                         "it is always projected). Measured on the phantom: "
                                         "mean / max e 0.0420 / 0.498 mm trained through it, "
                                         "0.0475 / 0.619 projected after training, 0.0509 / "
                                         "0.668 without (docs/network.md).")
    prior: str = opt("none", "A pretrained network of another breast the training starts "
                             "from (its weights, this case's normalisation; "
                             "biopsynav.prior_registry): 'none' (from scratch), 'auto' (the "
                             "first packaged prior of the same architecture whose surface is "
                             "not this case's: the UC Davis breast for the phantom and any "
                             "patient, the phantom for the UC Davis breast) or a prior's name. "
                             "Not used with init_from. With a prior, set iterations = 4000: "
                             "measured on the phantom and the UC Davis breast, the mean "
                             "held-out error of 12,500 from scratch and the tracking network "
                             "within 5 % of its distance from the independent truth, in a "
                             "third of the training time, but the largest held-out error 1.5-2 "
                             "times larger (phantom 0.318 against 0.165 mm, over the paper's "
                             "0.27): not the default (docs/network.md, 'Starting from a "
                             "prior').",
                     choices=prior_choices)
    init_from: str = opt("", "A trained model folder (absolute, or relative to the case "
                             "folder) training starts from: its best weights and its "
                             "normalisation, the same network and grid required. For "
                             "multi-fidelity training: a model taught by many samples of the "
                             "case grid, trained further on a few of a finer teacher "
                             "([dataset] teacher_refine). '' (default): from scratch.")
    runtime: str = opt("auto", "Inference runtime of the exported model: 'torchscript' "
                               "(frozen, optimize_for_inference, fp32), 'openvino' (fp32 "
                               "forced), 'openvino-bf16' (bfloat16 on a CPU with AMX-BF16 "
                               "or AVX-512 BF16: a tracker update 30-45 % faster on the "
                               "larger MRI breasts, lesions within 0.02 mm of fp32's) or "
                               "'auto' (the fastest installed: OpenVINO, in bf16 on a CPU "
                               "with bf16 arithmetic where timed predictions of both are "
                               "10 % faster in bf16, else in fp32; else torchscript; "
                               "docs/network.md 'Inference runtimes'). Table 1 is measured "
                               "with the runtime and arithmetic chosen, and says why.",
                       choices=runtime_choices)


@dataclass
class RefineSection:
    samples: int = opt(1000, "Multi-fidelity training (docs/experiments.md, 'Trained further on a "
                           "finer teacher'): after the case-grid network, this many rigid-probe "
                           "pushes are solved by the refine teacher (teacher_refine, "
                           "extrapolation; by default the case grid itself with the elastic "
                           "contact of [tracker] fem_contact) and the network is trained "
                           "further on them; the tracker then uses that model "
                           "(CASE_DIR/refine/model). They live in their own case folder, "
                           "CASE_DIR/refine, with the same anatomy and grid. 1,000 (default, "
                           "with iterations = 16,000): at 30 mm pushes the phantom's lesions "
                           "nearer the independent truth, and UC Davis's worst lesion, than "
                           "with 300 pushes and 4,000 iterations (docs/experiments.md, '1,000 "
                           "pushes and 16,000 iterations': accuracy and time). Raising it on a "
                           "refined case keeps the fine pushes already solved and adds the "
                           "rest. 0: off; the case-grid network is the model.",
                       lo=0, hi=10**6)
    held_out: int = opt(20, "Of those samples, held out to choose the best weights (mean e "
                            "against the refine teacher).", lo=1, hi=10**6)
    teacher_refine: float = opt(1.0, "The refine teacher's cells are [grid] cell_size_mm "
                                     "divided by this ([dataset] teacher_refine of the refine "
                                     "case): 1 (default), the case grid itself, whose rigid "
                                     "pushes with elastic contact are 0.2 mm from the truth at "
                                     "10 mm pushes; 1.46 turns 7.3 mm cells into 5 mm (with "
                                     "extrapolation = 2: the teacher of cases made on "
                                     "2026-11-27, about five times the cost).",
                                lo=1.0, hi=4.0)
    teacher: str = opt(GRID_TEACHER, "The refine pushes' FE code ([dataset] teacher of the "
                                     "refine case): 'grid' (default), the hexahedral FE of "
                                     "teacher_refine; 'p2', the P2 tetrahedral FE of Table 2's "
                                     "truth on its own mesh (teacher_size_mm, "
                                     "teacher_fine_mm; docs/dataset.md, 'The P2 teacher'). "
                                     "One material only.", choices=teacher_names)
    teacher_size_mm: float = opt(10.0, "With teacher = 'p2': [dataset] teacher_size_mm of the "
                                       "refine case.", lo=0.5, hi=200.0)
    teacher_push_limit_s: float = opt(1800.0, "With teacher = 'p2': [dataset] "
                                              "teacher_push_limit_s of the refine case (0: no "
                                              "limit).", lo=0.0, hi=1e6)
    teacher_fine_mm: float = opt(4.0, "With teacher = 'p2': [dataset] teacher_fine_mm of the "
                                      "refine case.", lo=0.5, hi=200.0)
    extrapolation: float = opt(0.0, "Richardson extrapolation order of the refine pushes "
                                    "([dataset] teacher_extrapolation of the refine case), "
                                    "with teacher_refine > 1: each is solved on the case grid "
                                    "too and extrapolated from the two (docs/experiments.md, 'An "
                                    "extrapolated teacher'). 0 (default): the teacher's "
                                    "solution alone. A [refine] table that names "
                                    "teacher_refine but not this key was written before it "
                                    "existed, and reads as 0 (its fine data stay valid).",
                               lo=0.0, hi=8.0)
    lesion_share: float = opt(0.0, "Share of the fine pushes centred near a lesion ([probe] "
                                   "lesion_share of the refine case; lesion_reach_mm from "
                                   "[probe]).", lo=0.0, hi=1.0)
    max_push_mm: float = opt(35.0, "Deepest fine push (mm of probe displacement); depths are "
                                   "uniform up to it (less by [probe] max_chest_compression), "
                                   "tilts within [probe] rigid_max_tilt_deg.", lo=1.0,
                             hi=200.0)
    material_model: str = opt("neo-hookean-split-sri-inner",
                              "Hyperelastic law of the refine teacher's rigid pushes ([material] "
                              "model of the refine case), and so of every solve that stands for "
                              "the tracking model's teacher: the FE engine, Table 2's FE method, "
                              "the contact compliance of the tracker's elastic input and its "
                              "linear baseline (with samples = 0 they follow [material] model). "
                              "'neo-hookean-split-sri-inner' (default): nearer the independent "
                              "P2 truth than 'neo-hookean' at 10, 20 and 30 mm pushes on both "
                              "built-in cases (docs/experiments.md, 'Two laws: the mixed recipe'). "
                              "A "
                              "case.toml biopsynav wrote before this key existed reads it "
                              "as its [material] model (one law, as it was made).",
                              choices=material_law_names)
    fictitious_stiffness: float = opt(0.0, "[material] fictitious_stiffness of the refine "
                                           "teacher, and so of every solve that material_model "
                                           "governs (the FE engine, Table 2's FE method, the "
                                           "tracker's contact compliance). 0 (default): none. "
                                           "0.05 brings the FE engine's lesions nearer the "
                                           "independent P2 truth at 30 mm pushes on both "
                                           "built-in cases (every push answered by the springs "
                                           "as asked, the 1,000 pushes solved in half the "
                                           "time), but the network it teaches is no nearer "
                                           "(docs/experiments.md, 'The fictitious domain'). A "
                                           "case.toml "
                                           "biopsynav wrote before this key existed reads it "
                                           "as its [material] fictitious_stiffness.",
                                      lo=0.0, hi=1.0)
    iterations: int = opt(16000, "Training iterations on the fine pushes, from the case-grid "
                                 "network's best weights.", lo=1, hi=10**8)
    learning_rate: float = opt(3e-4, "Peak learning rate of that training (100 warm-up "
                                     "steps, then cosine decay).", lo=1e-7, hi=1.0)
    batch_size: int = opt(4, "Batch size of that training. 4: on the phantom, 4,000 "
                             "iterations at batch 16 (the same samples) left the tracking "
                             "network 17 % further from the independent truth at 30 mm pushes "
                             "than 16,000 at batch 4 (docs/experiments.md, 'Cost and "
                             "settings of the chain'). A [refine] table written before this "
                             "key existed reads it as [network] batch_size (as it trained).",
                          lo=1, hi=1024)


@dataclass
class TrackerSection:
    engine: str = opt("net", "Default engine: 'net' (U-Net) or 'fem' (finite elements).",
                      choices=("net", "fem"))
    envelope_margin: float = opt(1.1, "Contact displacements up to this factor of the largest "
                                      "trained one, and probe displacements (their mean norm) "
                                      "up to this factor of the deepest trained push, and "
                                      "compressions of the tissue before the chest wall up to "
                                      "this factor of [probe] max_chest_compression, are "
                                      "accepted; beyond, the answer is out_of_envelope.",
                                 lo=1.0, hi=10.0)
    rigid_tolerance: float = opt(1e-3, "Largest deviation of a pose rotation from orthonormal.",
                                 lo=1e-9, hi=1.0)
    fem_contact: str = opt("elastic", "How the FE engine (and Table 2's FE method and ground "
                                      "truth, and rigid-probe pushes in training data) "
                                      "prescribes the probe's motion "
                                      "(biopsynav.contact.constraints registry): 'elastic' "
                                      "(every contact point tied to the face by a spring, "
                                      "contact_stiffness; the default: 0.2 mm from the "
                                      "independent P2 truth at 10 mm pushes where 'points' is "
                                      "1.9 mm, docs/fem.md 'Elastic contact'), 'points' "
                                      "(every contact point met) or 'cell_average' (the mean "
                                      "of the contact points of each grid cell met).",
                           choices=contact_constraint_names)
    contact_stiffness: float = opt(14.0, "beta of fem_contact = 'elastic': each contact point "
                                         "is tied to the face by a spring of beta E A / h "
                                         "N/mm (E the Young's modulus of its cell, MPa; A the "
                                         "skin area it stands for, mm^2; h the cell size, mm), "
                                         "the penalty int beta E / h |u - g|^2 dA over the "
                                         "contact (docs/contact.md, 'Elastic contact'). 14 is "
                                         "measured with the default [refine] "
                                         "material_model, the law of the solves these "
                                         "springs serve; 10 was the default with "
                                         "'neo-hookean' throughout.",
                                   lo=0.1, hi=1e6)
    spring_budget: int = opt(80, "Elastic contact in the FE engine and in Table 2's FE method, "
                                 "on the case grid (a grid r times finer, such as Table 2's "
                                 "ground truth or a refined teacher's, gets r times as many: "
                                 "converging solves took up to 110 on 2 times finer cells): "
                                 "Newton iterations after which the "
                                 "springs as asked give way to springs 4 times stiffer (then "
                                 "to the points met). Solves that converge take far fewer "
                                 "(at most 42 over 40 phantom pushes to 35 mm); those past a "
                                 "limit point ran 94-319 before failing (docs/contact.md, 'Deep "
                                 "pushes and the fallback'). 0: no limit. Data generation "
                                 "uses [dataset] newton_budget instead.", lo=0, hi=100000)
    contact_follows_pose: bool = opt(False, "Skin that the probe face reaches during a push "
                                            "(behind the face plane in the deformed state, "
                                            "in cells apart from the rest contact) is held on "
                                            "the plane, free to slide, and the answer "
                                            "repeated: the FE engine solves again "
                                            "(frictionless; held skin that elastic "
                                            "contact's springs pull is let go), the network "
                                            "engine predicts "
                                            "again with that skin in its contact set (a grown "
                                            "set is built once per rest pose, then looked "
                                            "up). Off (the default): only the skin touched at "
                                            "the rest pose follows the probe; on, fewer 35 mm "
                                            "FE pushes converge, and against the independent "
                                            "truth it moved lesions further, not nearer "
                                            "(docs/fem.md); on a clinical breast each grown "
                                            "set takes up to a second to build (MRI exam 31 "
                                            "left, 20 mm pushes: the network engine's update "
                                            "11 / 1,179 ms median / p99), which holds up a "
                                            "100 Hz stream.")


@dataclass
class IgtlSection:
    tracker: str = opt("127.0.0.1:18944", "OpenIGTLink server that streams the probe "
                                          "(PLUS); biopsynav connects to it as a client.")
    listen: str = opt("127.0.0.1:18945", "Address where biopsynav listens for 3D Slicer and "
                                         "other clients.")
    probe_device: str = opt("ProbeToReference", "Device name of the probe TRANSFORM.")
    max_body_bytes: int = opt(1 << 20, "Largest accepted message body.", lo=64, hi=1 << 30)
    max_clients: int = opt(32, "Most listening clients at once. When full, a new client "
                               "takes the slot of the client idle longest (no complete "
                               "message from it and no reply taken by it for the longest "
                               "time), so idle or trickling connections never lock a real "
                               "client out.", lo=1, hi=4096)
    client_backlog_bytes: int = opt(4 << 20, "Unsent reply bytes held for one client; a "
                                             "client that does not read beyond this is "
                                             "dropped.", lo=1024, hi=1 << 30)
    max_poses_per_read: int = opt(4, "Probe poses tracked per read of one connection; older "
                                     "poses of the same read are skipped (coalesced) so that "
                                     "a backlog never delays the newest pose by more than "
                                     "this many updates.", lo=1, hi=10**6)
    reconnect_max_s: float = opt(2.0, "Longest wait between attempts to reach the tracker "
                                      "server (exponential backoff from 0.05 s).",
                                 lo=0.05, hi=60.0)
    stall_timeout_s: float = opt(5.0, "A message must arrive whole within this long of its "
                                      "first byte, or its connection is dropped (a stalled, "
                                      "half-dead or trickling peer never holds a partial "
                                      "message for longer, however it paces its bytes).",
                                 lo=0.1, hi=3600.0)
    reply_header_version: str = opt("auto", "OpenIGTLink header version of the replies: "
                                             "'auto' answers each client in version 1 until it "
                                             "sends a version-2 message (then in version 2, with "
                                             "status metadata), '1' or '2' for every client.",
                                     choices=("auto", "1", "2"))
    probe_timeout_s: float = opt(0.5, "A probe pose not received for this long (after the "
                                      "first) gives the status probe_not_tracked.",
                                 lo=0.02, hi=600.0)
    status_keepalive_s: float = opt(1.0, "TrackingStatus is sent when the status changes, and "
                                         "again after this long while it stays the same.",
                                    lo=0.05, hi=3600.0)
    lesion_model_rate_hz: float = opt(20.0, "Rate of the lesion surface POLYDATA models (at "
                                            "most one per tracked pose; 0: never).",
                                      lo=0.0, hi=1000.0)
    skin_model_rate_hz: float = opt(2.0, "Rate of the deformed breast skin POLYDATA "
                                         "(BreastSkin; each costs one full-field prediction, "
                                         "made after the lesion reply went out; 0: never).",
                                    lo=0.0, hi=100.0)
    skin_model_triangles: int = opt(2000, "Most triangles of the decimated skin model sent to "
                                          "clients.", lo=50, hi=10**6)
    rest_pose_on_reconnect: str = opt("clear", "What a lost tracker-server connection does to "
                                               "the rest pose: 'clear' (taken again at the next "
                                               "contact; the tracker's frame may have changed) "
                                               "or 'keep'.", choices=("clear", "keep"))
    inference_threads: int = opt(2, "CPU threads of the served tracker's network (0: the idle "
                                    "cores when the service starts, as [network] threads; "
                                    "never more than the machine has). On the 2-core "
                                    "development VM at 100 Hz, 2 threads gave a 3.6 ms median "
                                    "round trip against 5.8-6.0 ms with 1, and 0 picked 1 "
                                    "there while the benchmark's own processes started "
                                    "(docs/igtl.md); set 1 where the cores "
                                    "are "
                                    "busy with other work.", lo=0, hi=1024)


@dataclass
class EvaluateSection:
    timed_predictions: int = opt(1000, "Batch-1 predictions timed for Table 1's prediction "
                                       "time (median, p99).", lo=10, hi=10**6)
    deformations_per_lesion: int = opt(4, "Probe pushes per lesion in Table 2 by simulation "
                                          "(the paper: four of increasing extent).", lo=1, hi=50)
    max_push_mm: float = opt(32.0, "Deepest probe push in Table 2 by simulation: the push "
                                   "depths are spread from 10/32 to 30/32 of it (10 ... 30 mm, "
                                   "the centres of the paper's bins D10 ... D30, by default; "
                                   "docs/evaluation.md).", lo=1.0, hi=200.0)
    reference_refinement: float = opt(2.0, "The ground-truth FE grid of Table 2 has cells this "
                                           "many times smaller than the training grid (2: half "
                                           "the cell size, about 8 times the elements).",
                                      lo=1.0, hi=4.0)
    max_lesions: int = opt(0, "Lesions evaluated in Table 2 by simulation (0: all; else this "
                              "many, spread over the lesion list) to bound the run time.",
                           lo=0, hi=10000)
    reference: str = opt("auto", "Ground truth of Table 2 by simulation "
                                 "(biopsynav.evaluate.references registry): 'auto' ('stored' "
                                 "where a stored independent truth serves the case, the "
                                 "built-in phantom's and UC Davis as one material's, else "
                                 "'fine_grid'; Table 2 says which and why) or 'fine_grid' "
                                 "(this FE on a grid reference_refinement times finer: the "
                                 "teacher's own code, not independent) or 'p2' (an "
                                 "independent FE: quadratic tetrahedra of a gmsh mesh, one "
                                 "homogeneous material; minutes per push, kept in eval/ and "
                                 "resumed; needs gmsh) or 'stored' (that independent FE's "
                                 "answers computed once by benchmarks/truth.py and kept: "
                                 "truth_file, or the one shipped for the built-in phantom and "
                                 "the UC Davis breast as one material; the lesions pushed to "
                                 "its depths; seconds; docs/evaluation.md).",
                         choices=reference_names)
    truth_file: str = opt("", "The stored truth of reference = 'stored', relative to the case "
                              "folder (a --reference file of benchmarks/truth.py); empty: the "
                              "truth shipped with biopsynav whose anatomy, material and probe "
                              "are this case's.")
    p2_size_mm: float = opt(10.0, "P2 reference: tetrahedron size away from the probe.",
                            lo=1.0, hi=100.0)
    p2_fine_mm: float = opt(4.0, "P2 reference: tetrahedron size within 35 mm of the probe.",
                            lo=0.5, hi=100.0)
    p2_friction: str = opt("stick", "P2 reference: how the probe face holds the skin: 'stick' "
                                    "(the skin it touches at rest moves with it, as the "
                                    "tracker's contact points; skin it reaches later slides "
                                    "on it) or 'slip' (all of it slides without friction, as "
                                    "on ultrasound gel).", choices=P2_FRICTIONS)
    p2_rim_mm: float = opt(0.0, "P2 reference: tetrahedron size along the edge of the probe "
                                "face at rest: the outline of the skin held at rest, which "
                                "otherwise follows the mesh (0: no finer rim, the shipped "
                                "truths'; 1: converged to 0.1 mm at 10 mm on the phantom, "
                                "twice the unknowns; docs/evaluation.md, 'The truth "
                                "against a second FE code').",
                           lo=0.0, hi=100.0)
    p2_edge_radius_mm: float = opt(0.0, "P2 reference: the probe a rigid body whose face's "
                                        "edges are rounded by this radius, mm, with sides "
                                        "that no skin passes (below half the footprint's "
                                        "short side); 0: a flat face with sharp edges and no "
                                        "sides, the shipped truths' (2.5 mm moves phantom "
                                        "lesion 1 by 0.04 / 0.11 / 0.19 mm at 10 / 20 / 30 mm "
                                        "pushes; with p2_rim_mm = 1 a 10 mm push solves in 5 "
                                        "min instead of 28; docs/evaluation.md, 'The truth "
                                        "against a second FE code').",
                                   lo=0.0, hi=100.0)


SECTIONS: dict[str, type] = {
    "case": CaseSection,
    "anatomy": AnatomySection,
    "grid": GridSection,
    "material": MaterialSection,
    "solver": SolverSection,
    "probe": ProbeSection,
    "dataset": DatasetSection,
    "network": NetworkSection,
    "refine": RefineSection,
    "tracker": TrackerSection,
    "igtl": IgtlSection,
    "evaluate": EvaluateSection,
}


@dataclass
class CaseConfig:
    """The whole of ``case.toml``."""

    case: CaseSection = field(default_factory=CaseSection)
    anatomy: AnatomySection = field(default_factory=AnatomySection)
    grid: GridSection = field(default_factory=GridSection)
    material: MaterialSection = field(default_factory=MaterialSection)
    solver: SolverSection = field(default_factory=SolverSection)
    probe: ProbeSection = field(default_factory=ProbeSection)
    dataset: DatasetSection = field(default_factory=DatasetSection)
    network: NetworkSection = field(default_factory=NetworkSection)
    refine: RefineSection = field(default_factory=RefineSection)
    tracker: TrackerSection = field(default_factory=TrackerSection)
    igtl: IgtlSection = field(default_factory=IgtlSection)
    evaluate: EvaluateSection = field(default_factory=EvaluateSection)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def section_dict(self, name: str) -> dict:
        """One section as a plain dict (used in fingerprints)."""
        return dataclasses.asdict(getattr(self, name))


def _check_value(section: str, f: dataclasses.Field, value: Any, where: str) -> Any:
    key = f"[{section}] {f.name}"
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    expected = type(default)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if expected is bool and not isinstance(value, bool):
        raise InputError(f"{key} must be true or false, got {value!r}", where)
    if expected is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise InputError(f"{key} must be an integer, got {value!r}", where)
    if not isinstance(value, expected):
        raise InputError(f"{key} must be of type {expected.__name__}, got {value!r}", where)
    meta = f.metadata
    if meta.get("choices") and value not in field_choices(meta):
        raise InputError(f"{key} must be one of {', '.join(field_choices(meta))}; got {value!r}",
                         where)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise InputError(f"{key} must be a finite number, got {value!r}", where)
        if meta.get("lo") is not None and value < meta["lo"]:
            raise InputError(f"{key} = {value} is below its minimum {meta['lo']}", where)
        if meta.get("hi") is not None and value > meta["hi"]:
            raise InputError(f"{key} = {value} is above its maximum {meta['hi']}", where)
    return value


def label_item(item: int | str) -> int | str:
    """A label value (an integer, sign included) or a segment name (stripped) from ``item``,
    as the command line, case.toml and a segmentation spell it."""
    if isinstance(item, int) and not isinstance(item, bool):
        return item
    text = str(item).strip()
    return int(text) if re.fullmatch(r"[+-]?\d+", text) else text


def is_finite_number(value: Any) -> bool:
    """A finite int or float, not a boolean."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def _check_teachers(cfg: CaseConfig, where: str) -> None:
    """InputError for a teacher other than the grid's asked with a finer grid or force
    patches, which it does not solve."""
    for key, teacher, refine, rigid in (
            ("[dataset]", cfg.dataset.teacher, cfg.dataset.teacher_refine,
             cfg.probe.rigid_share),
            ("[refine]", cfg.refine.teacher, cfg.refine.teacher_refine, 1.0)):
        if teacher == GRID_TEACHER:
            continue
        if refine != 1:
            raise InputError(f"{key} teacher = {teacher!r} solves its own mesh: teacher_refine "
                             f"(now {refine:g}) is the grid teacher's; set it to 1", where)
        if rigid < 1:
            raise InputError(f"{key} teacher = {teacher!r} solves rigid pushes only: set "
                             f"[probe] rigid_share = 1 (now {rigid:g})", where)


def _check_tetrahedron_sizes(cfg: CaseConfig, where: str) -> None:
    """InputError where a P2 mesh's tetrahedra near the probe would be larger than those
    away from it (``fine_mm`` > ``size_mm``: the refinement reversed)."""
    for key, size, fine in (
            ("[evaluate] p2_", cfg.evaluate.p2_size_mm, cfg.evaluate.p2_fine_mm),
            ("[dataset] teacher_", cfg.dataset.teacher_size_mm, cfg.dataset.teacher_fine_mm),
            ("[refine] teacher_", cfg.refine.teacher_size_mm, cfg.refine.teacher_fine_mm)):
        if fine > size:
            raise InputError(f"{key}fine_mm ({fine:g} mm, the tetrahedra near the probe) must "
                             f"not exceed {key}size_mm ({size:g} mm, those away from it)", where)


def _check_special(cfg: CaseConfig, where: str) -> None:
    fp = cfg.probe.footprint_mm
    if len(fp) != 2 or not all(is_finite_number(v) and 0 < v < 1e3 for v in fp):
        raise InputError(f"[probe] footprint_mm must be two positive lengths (finite, mm), got "
                         f"{fp!r}", where)
    _check_edge_radius(cfg, where)
    if cfg.refine.samples and cfg.refine.held_out >= cfg.refine.samples:
        raise InputError(f"[refine] held_out ({cfg.refine.held_out}) must be smaller than "
                         f"samples ({cfg.refine.samples})", where)
    if cfg.dataset.teacher_extrapolation > 0 and cfg.dataset.teacher_refine == 1:
        raise InputError("[dataset] teacher_extrapolation extrapolates from the case grid and "
                         "a finer teacher: set teacher_refine > 1 too (1.46 for 5 mm cells on "
                         "a 7.3 mm grid), or teacher_extrapolation = 0", where)
    if cfg.refine.extrapolation > 0 and cfg.refine.teacher_refine == 1:
        raise InputError("[refine] extrapolation extrapolates from the case grid and a finer "
                         "teacher: set [refine] teacher_refine > 1 too, or extrapolation = 0 "
                         "(the case grid's own rigid pushes)", where)
    _check_teachers(cfg, where)
    _check_tetrahedron_sizes(cfg, where)
    if cfg.probe.rigid_share > 0 and cfg.probe.max_push_mm <= 0:
        raise InputError("[probe] rigid_share > 0 draws rigid push depths in [0, max_push_mm]: "
                         "set [probe] max_push_mm to the deepest push (mm), not 0", where)
    for key, law_name in (("[material] model", cfg.material.model),
                          ("[refine] material_model", cfg.refine.material_model)):
        law = MATERIAL_LAWS[law_name]
        for name, tissue in cfg.material.tissues.items():
            problem = law.tissue_problem(tissue)
            if problem:
                raise InputError(f"[material.tissues.{name}] {problem}, of {key}; both laws "
                                 "read these tissues (give them laws with the same "
                                 "parameters)", where)
    if cfg.material.default_tissue not in cfg.material.tissues:
        raise InputError(f"[material] default_tissue {cfg.material.default_tissue!r} is not in "
                         "[material.tissues]", where)
    for key in ("breast_labels", "lesion_labels", "chest_labels"):
        for item in getattr(cfg.anatomy, key):
            if isinstance(item, bool) or not isinstance(item, (int, str)) or item == "":
                raise InputError(f"[anatomy] {key} holds {item!r}: give integer label values "
                                 "or segment names", where)
    for label, tissue in cfg.anatomy.tissue_labels.items():
        if tissue not in cfg.material.tissues:
            raise InputError(f"[anatomy] tissue_labels maps {label} to unknown tissue "
                             f"{tissue!r}", where)
    cw = cfg.anatomy.chest_wall
    valid_axes = {f"{s}-{m}" for s in "xyz" for m in ("min", "max")}
    if cw != "auto" and cw not in valid_axes and not cw.startswith("plane:"):
        raise InputError(f"[anatomy] chest_wall must be auto, x-min ... z-max or "
                         f"plane:px,py,pz,nx,ny,nz; got {cw!r}", where)
    if cw.startswith("plane:"):
        try:
            vals = [float(v) for v in cw[6:].split(",")]
        except ValueError:
            vals = []
        if len(vals) != 6 or sum(v * v for v in vals[3:]) == 0:
            raise InputError(f"[anatomy] chest_wall plane needs six numbers px,py,pz,nx,ny,nz "
                             f"with a non-zero normal; got {cw!r}", where)
    for addr_key in ("tracker", "listen"):
        try:
            parse_address(getattr(cfg.igtl, addr_key), f"[igtl] {addr_key}")
        except InputError as exc:
            raise InputError(str(exc), where) from None


def _check_edge_radius(cfg: CaseConfig, where: str) -> None:
    """InputError when ``[evaluate] p2_edge_radius_mm`` does not fit the probe's face
    (:meth:`~biopsynav.footprint.Footprint.rounded_core`)."""
    radius = cfg.evaluate.p2_edge_radius_mm
    if radius:
        try:
            cfg.probe.footprint.rounded_core(radius)
        except ValueError as exc:
            raise InputError(f"[evaluate] p2_edge_radius_mm = {radius:g} does not fit the "
                             f"probe face: {exc}", where) from None


def parse_address(text: str, where: str = "address") -> tuple[str, int]:
    """Parse ``HOST:PORT`` (an IPv6 host in brackets: ``[::1]:18945``) into a tuple; raise
    InputError naming ``where`` when malformed."""
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise InputError(f"an IPv6 address needs brackets, [HOST]:PORT; got {text!r}", where)
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"expected HOST:PORT with a port in 1..65535, got {text!r}", where)
    return host, int(port)


def config_from_dict(data: dict, where: str = CASE_FILE) -> CaseConfig:
    """Build and validate a configuration; unknown sections or keys are errors."""
    cfg = CaseConfig()
    for section, values in data.items():
        if section not in SECTIONS:
            raise InputError(f"unknown section [{section}]; known: {', '.join(SECTIONS)}", where)
        if not isinstance(values, dict):
            raise InputError(f"[{section}] must be a table", where)
        cls = SECTIONS[section]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        kwargs = {}
        for key, value in values.items():
            if key not in fields:
                raise InputError(f"unknown key {key!r} in [{section}]; known: "
                                 f"{', '.join(fields)}", where)
            kwargs[key] = _check_value(section, fields[key], value, where)
        if section == "refine" and "teacher_refine" in kwargs and "extrapolation" not in kwargs:
            kwargs["extrapolation"] = 0.0  # written before it existed: the fitted teacher
        if section == "material" and "tissues" in kwargs and _default_parameters(kwargs):
            merged = CaseConfig().material.tissues  # the built-in tissues, unless redefined
            merged.update(kwargs["tissues"])
            kwargs["tissues"] = merged
        setattr(cfg, section, cls(**kwargs))
    _check_special(cfg, where)
    return cfg


def _default_parameters(material: dict) -> bool:
    """Whether the ``[material]`` being read uses a law with the default law's tissue
    parameters (then its tissues extend the built-in ones)."""
    law = MATERIAL_LAWS.get(material.get("model", MaterialSection().model))
    return law is not None and set(law.parameters) == set(
        MATERIAL_LAWS[MaterialSection().model].parameters)


HEADER_LINE = "# biopsynav case. Units: mm, N, MPa (1 kPa = 1e-3 MPa), s."
#: Second line of a case.toml written by biopsynav since the end line exists; such a file must
#: end with :data:`END_LINE` (files written before it are read as they are).
ENDED_LINE = ("# Every key is documented in docs/case_toml.md. This file ends with an end line "
              "(a truncation check).")
END_LINE = "# end of case.toml: biopsynav checks this line to detect a truncated file"


def load_config(case_dir: str | Path) -> CaseConfig:
    """Read and validate ``CASE_DIR/case.toml``.

    A file written by biopsynav (its second line is :data:`ENDED_LINE`) must still end with
    :data:`END_LINE`: a truncated case.toml is refused rather than read with defaults for
    what it lost. Other files (written by hand, or before the end line) are read as they
    are. A file biopsynav wrote before ``[refine]`` existed (no such table) reads as
    ``[refine] samples = 0``: its case's model stays the tracker's; one written before
    ``[refine] material_model`` (``fictitious_stiffness``, ``batch_size``) existed reads it as
    its ``[material]`` value (``[network] batch_size``)."""
    path = Path(case_dir) / CASE_FILE
    if not Path(case_dir).is_dir():
        raise InputError("case folder does not exist", str(case_dir))
    if not path.is_file():
        raise InputError("no case.toml here; create the case with `biopsynav init`", str(path))
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML: {exc}", str(path)) from None
    _check_whole(text, str(path))
    if _written_whole(text) and "refine" not in data:
        # biopsynav writes every section: a case.toml of its own without [refine] is from
        # before the stage existed, and its model is the one its tracker used then
        data["refine"] = {"samples": 0}
    if _written_whole(text):
        _refine_keys_before_they_existed(data)
    return config_from_dict(data, str(path))


def _refine_keys_before_they_existed(data: dict) -> None:
    """A case.toml biopsynav wrote before ``[refine] material_model`` (or ``[refine]
    fictitious_stiffness``, ``batch_size``) existed (its ``[refine]`` table, which biopsynav
    writes whole, lacks the key) was made with one law and refined at the case network's
    batch: its ``[material]`` value is then the refine teacher's too, and its ``[network]
    batch_size`` the refine training's (in place)."""
    refine, material = data.get("refine"), data.get("material")
    if not (isinstance(refine, dict) and isinstance(material, dict)):
        return
    refine.setdefault("material_model", material.get("model", "neo-hookean"))
    refine.setdefault("fictitious_stiffness", material.get("fictitious_stiffness", 0.0))
    network = data.get("network")
    if isinstance(network, dict) and "batch_size" in network:
        refine.setdefault("batch_size", network["batch_size"])  # as its refine trained


def _written_whole(text: str) -> bool:
    """Whether biopsynav wrote this case.toml (its second line is :data:`ENDED_LINE`)."""
    lines = text.splitlines()
    return len(lines) > 1 and lines[1].strip() == ENDED_LINE


def _check_whole(text: str, where: str) -> None:
    """Refuse an empty case.toml, and one written by biopsynav that lost its end."""
    if not text.strip():
        raise InputError("case.toml is empty; restore it, or rebuild the case with "
                         "`biopsynav init --overwrite`", where)
    lines = text.rstrip().splitlines()
    if _written_whole(text) and lines[-1].strip() != END_LINE:
        raise InputError(f"case.toml is truncated (its last line, {END_LINE!r}, is missing); "
                         "restore it, or rebuild the case with `biopsynav init --overwrite`",
                         where)


def save_config(case_dir: str | Path, cfg: CaseConfig) -> Path:
    """Write ``case.toml`` atomically, with a header naming the units and an end line."""
    header = f"{HEADER_LINE}\n{ENDED_LINE}\n\n"
    body = tomli_w.dumps(_drop_none(cfg.to_dict()))
    return write_text_atomic(Path(case_dir) / CASE_FILE, f"{header}{body}\n{END_LINE}\n")


def _drop_none(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop_none(v) for k, v in obj.items() if v is not None}
    return obj


def recipe_lines() -> list[str]:
    """Markdown lines naming the values each recipe (:mod:`biopsynav.recipes`) writes over the
    defaults below."""
    from .recipes import DEFAULT_RECIPE, RECIPES

    lines = ["`init` and `demo` write a recipe's values over the defaults below into a new "
             "case's case.toml (`--recipe`, `biopsynav.recipes`; docs/pipeline.md, "
             "\"Recipes\"):", ""]
    for recipe in RECIPES.values():
        values = "; ".join(f"[{section}] " + ", ".join(f"{k} = {v!r}" for k, v in keys.items())
                           for section, keys in recipe.overrides.items())
        default = " (default)" if recipe.name == DEFAULT_RECIPE else ""
        lines.append(f"- `{recipe.name}`{default}: {recipe.summary}."
                     + (f" Sets {values}." if values else ""))
    return [*lines, ""]


def reference_markdown() -> str:
    """The case.toml reference (every key, default, range and meaning) as Markdown."""
    lines = ["# case.toml reference", "",
             "Units: millimetres, newtons, megapascals (1 kPa = 1e-3 MPa), seconds.", "",
             *recipe_lines()]
    defaults = CaseConfig()
    for section, cls in SECTIONS.items():
        lines += [f"## [{section}]", "", "| key | default | allowed | meaning |",
                  "|---|---|---|---|"]
        for f in dataclasses.fields(cls):
            value = getattr(getattr(defaults, section), f.name)
            meta = f.metadata
            allowed = ""
            if meta.get("choices"):
                allowed = ", ".join(field_choices(meta))
            elif meta.get("lo") is not None or meta.get("hi") is not None:
                allowed = f"[{meta.get('lo')}, {meta.get('hi')}]"
            shown = repr(value) if not isinstance(value, dict) else "see meaning"
            lines.append(f"| `{f.name}` | `{shown}` | {allowed} | {meta['doc']} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":  # python -m biopsynav.config > docs/case_toml.md
    print(reference_markdown(), end="")
