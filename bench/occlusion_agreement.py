"""How often the self-occlusion table answers differently from the camera's own rays.

python -m posefuse.bench.occlusion_agreement [--catalog DIR] [--poses 200] [--seed 1]

For each part of the catalog: random turns, the part 4 to 12 diameters in front of the camera,
and the samples that show (:func:`estimator.verification.model_edges.pose_edges`) with the
occlusion table against those with the rays of every pose (``occlusion_directions=0``). Prints,
per part, the samples the table shows that the rays hide, those it hides that the rays show, and
how many show without any occlusion test; the contour's the same way.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from posefuse.estimator.core.geometry import so3_exp
from posefuse.estimator.verification.edge_maps import EdgeConfig
from posefuse.estimator.verification.model_edges import model_edges, pose_edges


def agreement(model, n_poses: int, seed: int) -> dict[str, int]:
    """Counts over ``n_poses`` random poses of one catalog model (see the module docstring)."""
    rng = np.random.default_rng(seed)
    edges = model_edges(model.mesh, model.diameter, EdgeConfig())
    exact = replace(edges, occlusion=None)
    bare = replace(edges, occlusion=None, mesh=None)
    R = np.array([so3_exp(v) for v in rng.normal(0.0, 2.0, (n_poses, 3))])
    t = np.column_stack(
        [rng.uniform(-0.05, 0.05, (n_poses, 2)), rng.uniform(4, 12, n_poses) * model.diameter]
    )
    _, _, active, contour = pose_edges(edges, R, t)
    _, _, active_rays, contour_rays = pose_edges(exact, R, t)
    facing = pose_edges(bare, R, t)[2]
    return {
        "facing": int(facing.sum()),
        "shown, rays hide": int((active & ~active_rays).sum()),
        "hidden, rays show": int((active_rays & ~active).sum()),
        "contour": int(contour_rays.sum()),
        "contour shown, rays hide": int((contour & ~contour_rays).sum()),
        "contour hidden, rays show": int((contour_rays & ~contour).sum()),
    }


def main(argv: list[str] | None = None) -> int:
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.service.resources import DEFAULT_CATALOG

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--catalog", default=str(DEFAULT_CATALOG))
    parser.add_argument("--poses", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    catalog = load_catalog(args.catalog)
    keys = None
    for obj_id in sorted(catalog):
        model = catalog[obj_id]
        row = agreement(model, args.poses, args.seed + obj_id)
        if keys is None:
            keys = list(row)
            print("| part | " + " | ".join(keys) + " | differ |")
            print("|---" * (len(keys) + 2) + "|")
        differ = (row["shown, rays hide"] + row["hidden, rays show"]) / max(row["facing"], 1)
        cells = " | ".join(str(row[k]) for k in keys)
        print(f"| {model.name} | {cells} | {100 * differ:.2f}% |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
