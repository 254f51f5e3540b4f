"""The learning curve of a front-end checkpoint: recall, precision and center error on the
tuning sets against cumulative CPU hours, as a table and a plot.

python -m posefuse.bench.training_curve --checkpoint models/robi_like.ckpt
    [--plot docs/training_curve.png] [--markdown]

The points are the ones the training run scored at its checkpoints (``posefuse train --tune``).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def load_curve(checkpoint: str | Path) -> list[dict]:
    """The checkpoint's points, after those of the checkpoints it was fine-tuned from
    (``posefuse train --init``): steps and hours then count from the first run's start, and
    each point says which run (1, 2, ...) it belongs to."""
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    return lineage_curve(state)


def _totals(record: dict | None) -> dict:
    """Step, CPU and wall hours at the end of ``record`` (a checkpoint or an ``init_from``),
    counted from the first run's start."""
    if not record:
        return {"step": 0, "cpu_hours": 0.0, "wall_hours": 0.0}
    before = _totals(record.get("init_from"))
    return {
        "step": before["step"] + (record.get("step") or 0),
        "cpu_hours": before["cpu_hours"] + (record.get("cpu_seconds") or 0.0) / 3600,
        "wall_hours": before["wall_hours"] + (record.get("wall_seconds") or 0.0) / 3600,
    }


def lineage_curve(state: dict) -> list[dict]:
    """(see load_curve) ``state``: a checkpoint, or its ``init_from`` record."""
    depth, record = 0, state.get("init_from")
    while record:
        depth, record = depth + 1, record.get("init_from")
    base = state.get("init_from")
    before = lineage_curve(base) if base else []
    offset = _totals(base)
    return before + [
        {**p, "run": depth + 1, **{k: p[k] + offset[k] for k in offset}}
        for p in state.get("curve", [])
    ]


def curve_table(curve: list[dict]) -> str:
    sets = sorted({name for p in curve for name in p.get("tuning", {})})
    head = "| run | step | CPU h | wall h | " + " | ".join(
        f"{s}: recall / precision / median px / NEES" for s in sets
    )
    lines = [head + " |", "|" + "---|" * (4 + len(sets))]
    for p in curve:
        cells = []
        for s in sets:
            t = p.get("tuning", {}).get(s)
            cells.append(
                f"{t['recall']:.3f} / {t['precision']:.3f} / {t['median_center_error_px']:.2f} / "
                f"{t['mean_nees']:.2f}"
                if t
                else "-"
            )
        lines.append(
            f"| {p.get('run', 1)} | {p['step']} | {p['cpu_hours']:.2f} | {p['wall_hours']:.2f} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def plot_curve(curve: list[dict], path: str | Path) -> None:
    import cv2
    import numpy as np

    sets = sorted({name for p in curve for name in p.get("tuning", {})})
    W, H, m = 900, 420, 60
    img = np.full((H, W, 3), 255, np.uint8)
    pts = [p for p in curve if p.get("tuning")]
    if not pts:
        raise ValueError("the checkpoint's curve has no tuning scores (train with --tune)")
    xmax = max(p["cpu_hours"] for p in pts) * 1.05 or 1.0

    def xy(x, y):
        return int(m + x / xmax * (W - 2 * m)), int(H - m - y * (H - 2 * m))

    cv2.rectangle(img, xy(0, 0), xy(xmax, 1), (0, 0, 0), 1)
    for y in (0.25, 0.5, 0.75, 0.9, 0.95):
        cv2.line(img, xy(0, y), xy(xmax, y), (220, 220, 220), 1)
        cv2.putText(
            img, f"{y:.2f}", (5, xy(0, y)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1
        )
    colors = [(200, 60, 0), (0, 120, 220), (0, 160, 0), (160, 0, 160)]
    legend = 0
    for k, s in enumerate(sets):
        for key, style in (("recall", 0), ("precision", 1)):
            line = [xy(p["cpu_hours"], p["tuning"][s][key]) for p in pts if s in p["tuning"]]
            color = colors[k % len(colors)]
            for a, b in zip(line, line[1:], strict=False):
                if style == 0:
                    cv2.line(img, a, b, color, 2)
                else:
                    cv2.line(img, a, b, color, 1, cv2.LINE_AA)
            for q in line:
                cv2.circle(img, q, 3, color, -1)
            cv2.putText(
                img,
                f"{s} {key}" + (" (thick)" if style == 0 else " (thin)"),
                (m + 10, m - 40 + 14 * legend),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.4,
                color,
                1,
            )
            legend += 1
    cv2.putText(
        img,
        "cumulative CPU hours",
        (W // 2 - 70, H - 20),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.5,
        (0, 0, 0),
        1,
    )
    for x in np.linspace(0, xmax, 6):
        cv2.putText(
            img,
            f"{x:.1f}",
            (xy(x, 0)[0] - 10, H - m + 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
        )
    cv2.imwrite(str(path), img)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--plot", default=None, help="PNG to write")
    args = parser.parse_args(argv)
    curve = load_curve(args.checkpoint)
    print(curve_table(curve))
    if args.plot:
        plot_curve(curve, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
