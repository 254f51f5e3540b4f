"""Writes docs/objects.md: the symmetries detected for the procedural parts and the real meshes.

python -m posefuse.bench.objects_report --out docs/objects.md
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from posefuse.estimator.core.objects import load_mesh, mesh_diameter
from posefuse.estimator.core.symmetry import (
    DEFAULT_EXACT_FRAC,
    DEFAULT_NEAR_FRAC,
    DEFAULT_TOL_FRAC,
    detect_symmetries,
)
from posefuse.evaluation.eval_points import EVAL_SPACING, derive_eval_points
from posefuse.evaluation.pose_error import bop_symmetry_transformations

REAL_MESH_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "objects"
REAL_MESHES = ("tee_fitting", "screw", "eye_bolt", "gear", "bracket")


def meshes_to_report(real_dir: Path):
    """(source, name, mesh in metres) for the procedural parts, then the real meshes found."""
    from posefuse.sim.parts import PARTS, build_part

    for name, _ in PARTS:
        mesh = build_part(name)
        mesh.apply_scale(1e-3)
        yield "procedural", name, mesh
    for name in REAL_MESHES:
        path = real_dir / f"{name}.stl"
        if path.is_file():
            yield f"`shared/objects/{name}.stl`", name, load_mesh(path, "mm")


def detect_row(source: str, name: str, mesh) -> dict:
    start = time.perf_counter()
    diameter = mesh_diameter(mesh)
    report = detect_symmetries(mesh, diameter)
    seconds = time.perf_counter() - start
    eval_points = derive_eval_points(mesh, diameter)
    eval_symmetries = bop_symmetry_transformations(
        report.discrete, [(np.asarray(c.axis), np.asarray(c.offset)) for c in report.continuous]
    )
    axes = "; ".join(
        f"{'continuous' if a.order == 0 else f'{a.order}-fold'} "
        f"[{', '.join(f'{c:+.3f}' for c in a.axis)}] ({a.residual * 100:.2f}%, margin "
        f"{report.margin(a) * 100:.2f}%)"
        for a in report.axes
    )
    alternatives = "; ".join(f"{a.name()} ({a.residual * 100:.2f}%)" for a in report.alternatives)
    return {
        "source": source,
        "name": name,
        "diameter_mm": diameter * 1000,
        "faces": len(mesh.faces),
        "watertight": mesh.is_watertight,
        "symmetries": report.describe(),
        "n_discrete": len(report.discrete),
        "axes": axes or "-",
        "alternatives": alternatives or "-",
        "flagged": "yes" if report.flags else "no",
        "seconds": seconds,
        "eval_points": len(eval_points),
        "eval_symmetries": len(eval_symmetries),
    }


def render_markdown(rows: list[dict]) -> str:
    lines = [
        "# Object symmetries",
        "",
        "Produced by `python -m posefuse.bench.objects_report --out docs/objects.md`; checked by",
        "`tests/estimator/core/test_objects_catalog.py`.",
        "",
        "A rotation is accepted as a symmetry when the 95th percentile of the distances from",
        f"the rotated surface samples to the surface is at most {DEFAULT_TOL_FRAC:.1%} of the",
        "diameter (see `estimator/core/symmetry.py` for why), and a group only when every element",
        "passes. The residual in brackets is that percentile for the worst element generated",
        "by the axis, as a fraction of the diameter; the margin is the tolerance minus it.",
        f"Where an axis carries an exact group (every element within {DEFAULT_EXACT_FRAC:.0%})",
        "and a larger group passes only the looser tolerance, the exact one is claimed and the",
        "larger one listed as an alternative. Flagged: a claim with a margin under",
        f"{DEFAULT_NEAR_FRAC:.0%} of the diameter, or an alternative; `posefuse onboard` draws",
        "these on the contact sheet, and `--symmetry NAME=SPEC` decides.",
        "Discrete counts exclude the identity; a continuous axis is stored as BOP",
        "`symmetries_continuous` and any flip perpendicular to it as one discrete symmetry.",
        "",
        "Pose errors (`evaluation/pose_error.py`, equal to bop_toolkit's) use the evaluation",
        "points (`evaluation/eval_points.py`: the mesh's vertices, subdivided and thinned to one",
        f"point per {EVAL_SPACING:g} x diameter, stored as `models_eval/` with a catalog) and",
        "the symmetry transformations of bop_toolkit's `get_symmetry_transformations` with",
        "`max_sym_disc_step = 0.01` (identity included).",
        "",
        "| source | name | diameter (mm) | faces | watertight | symmetries | discrete"
        " | axes (residual, margin) | alternatives not claimed | flagged | eval points"
        " | error symmetries | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['source']} | {r['name']} | {r['diameter_mm']:.1f} | {r['faces']} | "
            f"{'yes' if r['watertight'] else 'no'} | {r['symmetries']} | {r['n_discrete']} | "
            f"{r['axes']} | {r['alternatives']} | {r['flagged']} | {r['eval_points']} | "
            f"{r['eval_symmetries']} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/objects.md")
    parser.add_argument("--real-dir", default=str(REAL_MESH_DIR))
    args = parser.parse_args(argv)
    rows = [detect_row(*item) for item in meshes_to_report(Path(args.real_dir))]
    text = render_markdown(rows)
    Path(args.out).write_text(text)
    print(text)
    np.set_printoptions()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
