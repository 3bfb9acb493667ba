"""The ``biopsynav`` command line: a thin layer over the pipeline stages.

Every bad input ends as one line ``biopsynav: error: WHERE: WHAT`` and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from .errors import BiopsynavError, InputError
from .fileio import json_default
from .layout import CasePaths
from .reference_registry import reference_names

LABEL_OPTIONS = ("--breast-labels", "--lesion-labels", "--chest-labels", "--tissue-labels")


def _label_list(text: str) -> list[int | str]:
    """Comma-separated label values (any integer, negative included) or segment names."""
    from .config import label_item

    items = [v.strip() for v in text.split(",") if v.strip()]
    if not items:
        raise argparse.ArgumentTypeError(f"expected label values or segment names, got {text!r}")
    return [label_item(v) for v in items]


def _tissue_map(text: str) -> dict[str, str]:
    """``LABEL=TISSUE,...`` (a label value, negative included, or a segment name), or a table
    file of ``LABEL,TISSUE`` rows (``#`` starts a comment) such as a graded segmentation's."""
    from .config import label_item

    if "=" not in text and Path(text).is_file():
        return _tissue_table(Path(text))
    pairs = [item.split("=", 1) for item in text.split(",") if item.strip()]
    if not pairs or any(len(p) != 2 or not p[0].strip() or not p[1].strip() for p in pairs):
        raise argparse.ArgumentTypeError(f"expected LABEL=TISSUE,... or a table file, got "
                                         f"{text!r}")
    return {str(label_item(k)): v.strip() for k, v in pairs}


def _tissue_table(path: Path) -> dict[str, str]:
    """``LABEL,TISSUE`` rows of a table file (commas, tabs or spaces between)."""
    import re

    from .config import label_item

    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise argparse.ArgumentTypeError(f"{path}: not a readable LABEL,TISSUE table "
                                         f"({type(exc).__name__})") from None
    table = {}
    for number, line in enumerate(text.splitlines(), start=1):
        row = [c for c in re.split(r"[,\t ]+", line.split("#", 1)[0].strip()) if c]
        if not row:
            continue
        if len(row) != 2:
            raise argparse.ArgumentTypeError(f"{path}: line {number}: expected LABEL,TISSUE, "
                                             f"got {line.strip()!r}")
        table[str(label_item(row[0]))] = row[1]
    if not table:
        raise argparse.ArgumentTypeError(f"{path}: no LABEL,TISSUE rows")
    return table


def breast_labels_of(args: argparse.Namespace) -> list:
    """``--breast-labels``, or else the labels ``--tissue-labels`` maps that are neither
    lesion nor chest labels (a graded segmentation's table names its breast tissue)."""
    from .config import label_item

    if args.breast_labels or not args.tissue_labels:
        return args.breast_labels or []
    other = {str(v) for v in (args.lesion_labels or []) + (args.chest_labels or [])}
    return [label_item(k) for k in args.tissue_labels if k not in other]


def join_label_values(argv: list[str]) -> list[str]:
    """``--breast-labels -2,1`` as ``--breast-labels=-2,1``: argparse takes a value starting
    with '-' for an option unless it is one negative number."""
    out: list[str] = []
    for token in argv:
        if out and out[-1] in LABEL_OPTIONS and token.startswith("-") \
                and not token.startswith("--"):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def cmd_init(args: argparse.Namespace) -> int:
    from .anatomy.modelled import modelled_lines
    from .case import init_case
    from .config import CaseConfig, config_from_dict
    from .fileio import read_json
    from .recipes import recipe_overrides

    cfg = CaseConfig()
    overrides: dict = {**recipe_overrides(args.recipe), "anatomy": {}}
    if args.phantom:
        if args.surface or args.labelmap:
            raise InputError("--phantom takes no --surface or --labelmap", "init")
        from .anatomy.phantom import PHANTOM_DESCRIPTION

        overrides["anatomy"]["source"] = "phantom"
        overrides["case"] = {"name": "phantom", "description": PHANTOM_DESCRIPTION}
    elif args.surface:
        overrides["anatomy"]["source"] = "surface"
    elif args.labelmap:
        overrides["anatomy"].update(source="labelmap", breast_labels=breast_labels_of(args),
                                    lesion_labels=args.lesion_labels or [],
                                    chest_labels=args.chest_labels or [], side=args.side or "")
    else:
        raise InputError("give --phantom, --surface FILE or --labelmap FILE", "init")
    if not args.labelmap and (args.chest_labels or args.side):
        raise InputError("--chest-labels and --side need --labelmap", "init")
    overrides["anatomy"]["chest_wall"] = args.chest_wall
    overrides["anatomy"]["input_frame"] = args.frame
    if args.tissue_labels:
        overrides["anatomy"]["tissue_labels"] = args.tissue_labels
    if args.cell_size is not None:
        overrides.setdefault("grid", {})["cell_size_mm"] = args.cell_size
    if args.config:
        import tomllib

        try:
            extra = tomllib.loads(Path(args.config).read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read: {exc}", args.config) from None
        for section, values in extra.items():
            overrides.setdefault(section, {}).update(values)
    cfg = config_from_dict(overrides, "command line")
    anatomy_file = args.surface or args.labelmap
    case = init_case(args.case_dir, cfg, {"anatomy": anatomy_file, "lesions": args.lesions},
                     overwrite=args.overwrite)
    print(f"case written to {case.dir} ({case.grid.active_cells.sum()} active cells, "
          f"{len(case.anatomy.lesions)} lesions)")
    print("\n".join(modelled_lines(read_json(case.paths.facts, "", missing_ok=True) or {})))
    kept = CasePaths(case.dir).outputs()
    if kept:
        print(f"kept from before: {', '.join(p.name for p in kept)}; each is checked against "
              "the rebuilt case when it is used (a data set or model of another anatomy, grid "
              "or protocol is refused; 'generate --overwrite' starts the data again)")
    return 0


def loaded_case(args: argparse.Namespace):
    """The case folder of the command line, loaded once (``biopsynav.case.Case``) and handed to
    the stage it runs."""
    from .case import Case

    return Case.load(args.case_dir)


def cmd_info(args: argparse.Namespace) -> int:
    from .info import case_summary, format_summary

    summary = case_summary(loaded_case(args))
    print(json.dumps(summary) if args.json else format_summary(summary))
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from .fileio import check_output_path
    from .show import render_case

    if args.out:
        check_output_path(args.out, "--out")
        if Path(args.out).suffix.lower() != ".png":
            raise InputError(f"{args.out}: the picture is a PNG; name a .png file", "--out")
    out = render_case(loaded_case(args), args.out)
    print(f"picture written to {out}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from .simulate import format_simulation, simulate

    out = Path(args.out) if args.out else Path(args.case_dir) / "simulate"
    result = simulate(loaded_case(args), args.force, args.at, out)
    print(json.dumps(result, indent=2, default=json_default) if args.json
          else format_simulation(result))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from .dataset.generate import format_run_summary, generate_case

    summary = generate_case(loaded_case(args), workers=args.workers, scheduler=args.scheduler,
                            overwrite=args.overwrite)
    print(json.dumps(summary, indent=2, default=json_default) if args.json
          else format_run_summary(summary))
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from .network.train import train_case

    s = train_case(loaded_case(args), preset=args.preset, iterations=args.iterations,
                   device=args.device)
    state = "finished" if s.finished else "stopped; run again to resume"
    print(f"training {state}: {s.iterations_done} of {s.iterations} iterations, best held-out "
          f"mean e {s.best_val_e_mm:.4f} mm at iteration {s.best_iteration}, "
          f"{s.n_parameters:,} parameters; model in {s.model_dir}")
    return 0


def cmd_refine(args: argparse.Namespace) -> int:
    from .pipeline import refine_stage

    case = loaded_case(args)
    summary = refine_stage(case, args.workers)
    if summary:
        print(f"fine pushes: {summary.get('count', 0)} of {summary.get('requested', 0)} "
              f"(deepest {summary.get('max_probe_disp_mm', 0.0):.1f} mm) in "
              f"{case.paths.refine}; the tracker uses {case.tracking_model}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluate import evaluate_case

    case = loaded_case(args)
    if args.reference is not None:  # this run only; case.toml keeps its own
        case.cfg.evaluate.reference = args.reference
    evaluate_case(case, table2=not args.table1_only, measured=args.measured, poses=args.poses,
                  workers=args.workers)
    return 0


def cmd_track(args: argparse.Namespace) -> int:
    from .tracker.csvtrack import track_csv, track_summary

    case = loaded_case(args)
    counts = track_csv(case, args.poses, args.out, engine=args.engine)
    print(track_summary(counts, len(case.anatomy.lesions), args.out))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import logging

    from .igtl.service import configure_logging, serve

    configure_logging(logging.WARNING if args.quiet else logging.DEBUG if args.verbose
                      else logging.INFO)
    serve(loaded_case(args), tracker_addr=args.tracker, listen_addr=args.listen, device=args.device)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from .report import write_report

    paths = write_report(args.case_dir)
    print("report written to " + ", ".join(str(p) for p in paths))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import run_case

    run_case(args.case_dir, workers=args.workers)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .pipeline import run_demo

    run_demo(args.case_dir, quick=args.quick, workers=args.workers, recipe=args.recipe)
    return 0


def _version() -> str:
    """The installed package's version ("unknown" when run from a source tree without an
    install)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("biopsynav")
    except PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="biopsynav",
        description="Real-time breast lesion tracking for ultrasound-guided biopsy. "
                    "Units: mm, N, MPa.")
    parser.add_argument("--version", action="version", version=f"biopsynav {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, func: Callable, help_: str) -> argparse.ArgumentParser:
        # argparse expands "%" in a help (not in a description)
        p = sub.add_parser(name, help=help_.replace("%", "%%"), description=help_)
        p.set_defaults(func=func)
        return p

    p = add("init", cmd_init, "Create a case folder from anatomy files or the built-in phantom.")
    p.add_argument("case_dir", type=Path)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--phantom", action="store_true", help="built-in CIRS 073-like phantom")
    src.add_argument("--surface", type=Path, help="closed surface (STL/OBJ/PLY/VTK/VTU) or "
                     "tetrahedral volume mesh (VTK/VTU) of the breast, mm")
    src.add_argument("--labelmap", type=Path, help="segmented label map (NRRD/NIfTI/MHA)")
    p.add_argument("--lesions", type=Path, help="lesion CSV (id,x,y,z,radius_mm), Slicer "
                   "markups (.mrk.json) or a folder of lesion surface meshes")
    p.add_argument("--breast-labels", type=_label_list, help="label values (negative "
                   "included) or segment names of breast tissue, e.g. fat,gland,skin or -2,1 "
                   "(default: the labels --tissue-labels maps, lesion and chest labels aside)")
    p.add_argument("--lesion-labels", type=_label_list, help="label values or segment names "
                   "of lesions")
    p.add_argument("--chest-labels", type=_label_list, help="label values or segment names "
                   "of the pectoral muscle: the chest wall is the interface with them")
    p.add_argument("--side", choices=("left", "right"), help="the patient's breast to take "
                   "from a bilateral label map")
    p.add_argument("--tissue-labels", type=_tissue_map, help="map labels to tissues, e.g. "
                   "1=fat,2=gland,-3=skin, or a table file of LABEL,TISSUE rows for a graded "
                   "segmentation (segments named fat, gland, skin, tumour map themselves)")
    p.add_argument("--frame", choices=("ras", "lps"), default="ras", help="frame of a surface "
                   "mesh and a lesion CSV (default ras, Slicer's); label maps and markups "
                   "carry their own")
    p.add_argument("--chest-wall", default="auto", help="auto | x-min ... z-max | "
                   "plane:px,py,pz,nx,ny,nz (default auto)")
    p.add_argument("--cell-size", type=float, help="grid cell size, mm")
    p.add_argument("--config", type=Path, help="a TOML file with case.toml sections to set")
    _recipe_option(p)
    p.add_argument("--overwrite", action="store_true", help="rebuild an existing case")

    p = add("info", cmd_info, "Print the case summary.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--json", action="store_true", help="one JSON object")

    p = add("show", cmd_show, "Write a PNG of anatomy, lesions, chest wall and grid.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--out", type=Path, help="PNG path (default CASE_DIR/anatomy.png)")

    p = add("simulate", cmd_simulate, "One finite-element probe push.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--force", type=float, nargs=3, required=True, metavar=("FX", "FY", "FZ"),
                   help="total probe force, N")
    p.add_argument("--at", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"),
                   help="probe centre near the skin, mm")
    p.add_argument("--out", type=Path, help="output folder (default CASE_DIR/simulate)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (as in "
                   "simulate.json)")

    p = add("generate", cmd_generate, "Generate the training data (random probe pushes).")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--workers", type=int, default=0, help="local worker processes (0: all "
                   "cores); the force calibration uses them with --scheduler too")
    p.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT")
    p.add_argument("--overwrite", action="store_true", help="discard data made for another "
                   "anatomy, grid or protocol")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (as in "
                   "CASE_DIR/dataset_summary.json)")

    p = add("train", cmd_train, "Train the U-Net surrogate (resumable).")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--preset", choices=("default", "paper", "custom"))
    p.add_argument("--iterations", type=int)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"))

    p = add("refine", cmd_refine, "Train the network further on a finer teacher's rigid "
            "pushes ([refine] samples > 0; resumable).")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--workers", type=int, default=0, help="local worker processes (0: all "
                   "cores)")

    p = add("evaluate", cmd_evaluate,
            "The paper's Table 1, each lesion's self-check (its 95 % bound) and Table 2.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--table1-only", action="store_true",
                   help="skip Table 2 and the lesion self-check")
    p.add_argument("--poses", type=Path, help="poses CSV of a measured experiment")
    p.add_argument("--measured", type=Path, help="measured lesion positions CSV "
                   "(frame,lesion_id,x,y,z) for Table 2 from user data")
    p.add_argument("--reference", choices=reference_names(),
                   help="ground truth of Table 2 by simulation for this run (default: [evaluate] "
                        "reference): auto, stored where a stored truth serves the case, else "
                        "fine_grid; fine_grid, biopsynav's FE on a finer grid; p2, an "
                        "independent tetrahedral FE; or stored, that FE's answers computed once "
                        "and kept")
    p.add_argument("--workers", type=int, default=0, help="local processes that solve the "
                   "self-check's, the FE teacher's and a fine-grid ground truth's pushes "
                   "(default 0: one per core; 1: in this process)")

    p = add("track", cmd_track, "Track lesions along a CSV of probe poses.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--poses", type=Path, required=True, help="CSV frame,sequence,m00..m23")
    p.add_argument("--out", type=Path, required=True, help="output CSV")
    p.add_argument("--engine", choices=("net", "fem"), default="net")

    p = add("serve", cmd_serve, "Serve lesion positions to 3D Slicer over OpenIGTLink.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--tracker", help="probe tracker server HOST:PORT (PLUS; default "
                   "127.0.0.1:18944)")
    p.add_argument("--listen", help="listen for clients on HOST:PORT (default "
                   "127.0.0.1:18945)")
    p.add_argument("--device", help="probe TRANSFORM device name (default ProbeToReference)")
    level = p.add_mutually_exclusive_group()
    level.add_argument("--quiet", action="store_true", help="log warnings and errors only")
    level.add_argument("--verbose", action="store_true", help="log every decision (debug)")

    p = add("report", cmd_report, "Write report.html and report.md.")
    p.add_argument("case_dir", type=Path)

    p = add("run", cmd_run, "Run every missing stage of a case.")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--workers", type=int, default=0, help="local worker processes of "
                   "every stage (0: one per core)")

    p = add("demo", cmd_demo, "The whole pipeline on the built-in phantom.")
    p.add_argument("case_dir", type=Path, nargs="?", default=Path("demo-case"))
    p.add_argument("--quick", action="store_true", help="reduced sizes, a few minutes")
    p.add_argument("--workers", type=int, default=0, help="local worker processes of "
                   "every stage (0: one per core)")
    _recipe_option(p)
    return parser


def _recipe_option(p: argparse.ArgumentParser) -> None:
    """``--recipe``: the training data's recipe of a new case (biopsynav.recipes)."""
    from .recipes import DEFAULT_RECIPE, RECIPES

    p.add_argument("--recipe", choices=sorted(RECIPES), default=DEFAULT_RECIPE,
                   help="what teaches the tracking network (a new case's case.toml values): "
                   + "; ".join(f"{r.name}: {r.summary}" for r in RECIPES.values())
                   + f" (default {DEFAULT_RECIPE}; docs/pipeline.md)")


#: Commands that write into the case folder: each holds the case's lock while it runs.
WRITING_COMMANDS = ("init", "show", "simulate", "generate", "train", "refine", "evaluate",
                    "report", "run", "demo")


def _run_command(args: argparse.Namespace) -> int:
    """Run the command, holding the case's write lock when it writes into an existing case."""
    from .caselock import case_lock

    case_dir = getattr(args, "case_dir", None)
    if args.command not in WRITING_COMMANDS or case_dir is None or not case_dir.is_dir():
        return int(args.func(args) or 0)
    with case_lock(case_dir, args.command):
        return int(args.func(args) or 0)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(join_label_values(sys.argv[1:] if argv is None else list(argv)))
    try:
        status = _run_command(args)
        sys.stdout.flush()  # a reader that closed the pipe is met here, not at exit
        return status
    except BrokenPipeError:  # `biopsynav info CASE | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except BiopsynavError as exc:
        print(f"biopsynav: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("biopsynav: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except OSError as exc:  # the system refused (permissions, full disk): name the file
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"biopsynav: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: one line, the traceback on request
        if os.environ.get("BIOPSYNAV_DEBUG"):
            raise
        print(f"biopsynav: internal error: {type(exc).__name__}: {exc} (set BIOPSYNAV_DEBUG=1 "
              "for the traceback, and please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
