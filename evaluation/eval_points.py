"""The points every pose error is evaluated on, as BOP's ``models_eval`` holds them.

BOP evaluates errors on the vertices of a resampled model whose vertices are spread uniformly
over the surface (``models_eval``), so that a part's finely tessellated fillets do not outweigh
its flat faces. We derive such a set from the mesh itself, deterministically:

1. subdivide every triangle until no edge is longer than a third of the spacing
   (``trimesh.remesh.subdivide_to_size``: every new vertex lies on the surface);
2. Poisson-disk thinning of those vertices: visit them in a seeded random order and keep a
   vertex when no kept vertex lies within the spacing. A maximal set of points at least one
   spacing apart has the same density everywhere, whatever the tessellation.

The spacing is ``EVAL_SPACING`` (1/40) of the diameter: 500-3,100 points for our parts. On
random rotations, ADD on these points differs from ADD on 100,000 area-uniform surface samples
by at most 1.1% of the diameter for every part but the threaded screws (2.5% and 5.3%: the
thread's folded surface has much area within one spacing, which area sampling counts and a
uniform-density set does not). The points are stored with the catalog as
``models_eval/obj_XXXXXX.ply`` (millimetres), and a catalog without them derives them on load.
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from posefuse.estimator.core.objects import (  # noqa: F401  (the catalog's file layout)
    EVAL_DIR,
    Catalog,
    ObjectModel,
    eval_points_path,
    read_eval_points,
    write_eval_points,
)

EVAL_SPACING = 0.025  # of the diameter
EVAL_SEED = 0
_DERIVED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> (M, 3)


def derive_eval_points(mesh: trimesh.Trimesh, diameter: float) -> np.ndarray:
    """(N, 3) surface points of uniform density, in the mesh's unit, in vertex order."""
    spacing = EVAL_SPACING * float(diameter)
    if not np.isfinite(spacing) or spacing <= 0:
        raise ValueError(f"diameter must be positive and finite, got {diameter!r}")
    vertices, _ = trimesh.remesh.subdivide_to_size(
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces),
        max_edge=spacing / 3,
        max_iter=64,
    )
    vertices = np.unique(vertices, axis=0)  # sorted: independent of the face order
    tree = cKDTree(vertices)
    removed = np.zeros(len(vertices), dtype=bool)
    keep = []
    for i in np.random.default_rng(EVAL_SEED).permutation(len(vertices)):
        if not removed[i]:
            keep.append(i)
            removed[tree.query_ball_point(vertices[i], spacing)] = True
    return vertices[np.sort(keep)]


def eval_points(model: ObjectModel) -> np.ndarray:
    """(M, 3) metres: the points every pose error of ``model`` is evaluated on, the catalog's
    stored ``models_eval`` points or else derived (:func:`derive_eval_points`, once per model)."""
    if model.stored_eval_points is not None:
        return model.stored_eval_points
    cached = _DERIVED.get(model)
    if cached is None:
        cached = _DERIVED[model] = derive_eval_points(model.mesh, model.diameter)
    return cached


def with_eval_points(models: Catalog | list[ObjectModel]) -> list[ObjectModel]:
    """The models, each carrying its evaluation points (``stored_eval_points``), so that
    :func:`posefuse.estimator.core.objects.write_catalog` stores them as ``models_eval``."""
    items = list(models.values()) if isinstance(models, Catalog) else list(models)
    return [dataclasses.replace(m, stored_eval_points=eval_points(m)) for m in items]
