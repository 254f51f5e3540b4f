"""The procedural ROBI-like catalog: the parts of :mod:`sim.parts` as object models."""

from __future__ import annotations

from posefuse.estimator.core.objects import Catalog, make_model


def robi_like_catalog() -> Catalog:
    """The five procedural parts as obj_ids 1..5, in metres, with their symmetries detected."""
    from posefuse.sim.parts import PARTS, build_part

    models = []
    for obj_id, (name, _) in enumerate(PARTS, start=1):
        mesh = build_part(name)
        mesh.apply_scale(1e-3)  # parts are built in millimetres
        models.append(make_model(obj_id, name, mesh))
    return Catalog(models)
