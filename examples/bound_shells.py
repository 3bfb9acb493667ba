"""Draw what a Slicer client receives from `biopsynav serve` for one probe push: the deformed
skin, each lesion model and its 95 % shell (POLYDATA ``Lesion<id>Bound``, docs/igtl.md).

    python examples/bound_shells.py CASE_DIR [--lesion 0] [--depth 20] [--out shells.png]

CASE_DIR: a case with a trained model (`biopsynav run`). The probe is placed over lesion
``--lesion`` (an index into the case's lesions) as Table 2 places it, its rest pose set, then
pushed ``--depth`` mm along its beam; the service's session (the same code `serve` runs, without
the sockets) answers the pose, its messages are packed and decoded as a client decodes them,
and the POLYDATA they hold are drawn with matplotlib (3D Slicer is not needed: the picture is of
the messages, not of Slicer's view).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def served_models(case_dir, lesion: int, depth_mm: float) -> dict:
    """device name -> (points (k, 3) mm, triangles (m, 3)) of every POLYDATA the service sends
    for the push, decoded from its packed messages; ``case_dir``: the case's folder or the
    loaded case."""
    import pyigtl

    from biopsynav.case import as_case
    from biopsynav.config import IgtlSection
    from biopsynav.evaluate.placement import place_case_probe
    from biopsynav.igtl.protocol import MessageReader, pack
    from biopsynav.igtl.session import IgtlSession
    from biopsynav.tracker import Tracker

    case = as_case(case_dir)
    rest = place_case_probe(case, lesion).pose
    pushed = rest.copy()
    pushed[:3, 3] += depth_mm * rest[:3, 2]
    settings = IgtlSection(skin_model_rate_hz=1000.0, lesion_model_rate_hz=1000.0)
    session = IgtlSession(Tracker.load(case), settings=settings, clock=iter(range(10**6)).__next__)
    session.add_peer("slicer")
    plus = session.add_peer("plus", True)
    models = {}
    for pose in (rest, pushed):
        (msg,) = MessageReader().feed(pack(pyigtl.TransformMessage(pose,
                                                                   device_name="ProbeToReference")))
        for _, batch in session.on_messages(plus, [msg]):
            for got in MessageReader().feed(b"".join(m.packed(1) for m in batch)):
                if got.type == "POLYDATA":
                    models[got.device] = (np.asarray(got.body.points),
                                          np.asarray(got.body.triangles))
    return models


def draw(models: dict, focus: str, out: Path, title: str) -> None:
    """Two views of the skin (light), the lesions (red) and their shells (blue, translucent):
    the whole breast, and close up round lesion model ``focus`` (e.g. ``Lesion1``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, 5.5), dpi=90)
    whole = np.vstack([models["BreastSkin"][0]]) if "BreastSkin" in models else \
        np.vstack([pts for pts, _ in models.values()])
    near = models[focus][0].mean(axis=0)
    shell = models[focus + "Bound"][0] - models[focus][0]
    views = ((whole.mean(axis=0), float(np.ptp(whole, axis=0).max()) / 2, "the breast"),
             (near, 14.0, f"{focus} close up: its shell {np.linalg.norm(shell, axis=1).mean():.1f}"
                          " mm out"))
    for k, (centre, half, label) in enumerate(views):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        _add_models(ax, models, centre, half)
        for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            set_lim(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.set_title(label, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out)


def _add_models(ax, models: dict, centre: np.ndarray, half: float) -> None:
    """Each model's triangles whose centroid lies in the cube of ``half`` round ``centre``."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    for name, (points, tris) in sorted(models.items()):
        if name == "BreastSkin":
            style = {"facecolor": (0.85, 0.75, 0.65, 0.15), "edgecolor": (0.5, 0.4, 0.3, 0.2)}
        elif name.endswith("Bound"):
            style = {"facecolor": (0.2, 0.4, 0.9, 0.2), "edgecolor": (0.2, 0.4, 0.9, 0.35)}
        else:
            style = {"facecolor": (0.85, 0.1, 0.1, 0.9), "edgecolor": (0.5, 0.0, 0.0, 0.5)}
        faces = points[tris]
        inside = np.all(np.abs(faces.mean(axis=1) - centre) <= half, axis=1)
        if inside.any():
            ax.add_collection3d(Poly3DCollection(faces[inside], linewidths=0.3, **style))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("case_dir", type=Path)
    p.add_argument("--lesion", type=int, default=0)
    p.add_argument("--depth", type=float, default=20.0)
    p.add_argument("--out", type=Path, default=Path("shells.png"))
    args = p.parse_args(argv)
    from biopsynav.case import as_case
    from biopsynav.errors import BiopsynavError

    if not np.isfinite(args.depth):
        p.error(f"--depth {args.depth}: a push depth in mm")
    try:
        case = as_case(args.case_dir)
        if not 0 <= args.lesion < len(case.anatomy.lesions):
            p.error(f"--lesion {args.lesion}: {args.case_dir} has lesions 0 to "
                    f"{len(case.anatomy.lesions) - 1} (an index into its lesion list)")
        models = served_models(case, args.lesion, args.depth)
    except BiopsynavError as exc:
        print(f"bound_shells.py: error: {exc}", file=sys.stderr)
        return 2
    if not any(name.endswith("Bound") for name in models):
        print("no 95 % shell was sent (no bound for this push)", file=sys.stderr)
        return 1
    focus = f"Lesion{case.anatomy.lesions[args.lesion].id}"
    draw(models, focus, args.out, f"{args.case_dir.name}: what `serve` sends for a "
                                  f"{args.depth:g} mm push over {focus}; red: the lesions, "
                                  "blue: their 95 % shells (Lesion<id>Bound)")
    print(f"wrote {args.out} ({', '.join(sorted(models))})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
