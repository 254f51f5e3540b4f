"""What a part is rendered in: its own colour when its mesh has one, else machined metal.

Every render of parts (``synth``, the training sets, onboarding's validation, the active-vision
simulator, a dataset's twin) asks :func:`part_material`, so a part onboarded from a coloured
mesh (vertex colours, as LM-O's and many scanned models have) is seen in training as it will
be seen by the camera.
"""

from __future__ import annotations

import numpy as np

from posefuse.estimator.core.objects import ObjectModel
from posefuse.estimator.rotation.render import CHROME, METAL, Material


def has_colour(model: ObjectModel) -> bool:
    """The mesh carries vertex colours that are not all one grey default."""
    visual = model.mesh.visual
    return getattr(visual, "kind", None) == "vertex"


def plastic_of(model: ObjectModel) -> Material:
    """Matte plastic of the mesh's mean vertex colour (linear RGB), or METAL without one."""
    if not has_colour(model):
        return METAL
    srgb = np.asarray(model.mesh.visual.vertex_colors, np.float64)[:, :3].mean(axis=0) / 255.0
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return Material(
        color=tuple(float(c) for c in linear),
        diffuse=0.85,
        specular=0.25,
        shininess=30.0,
        reflect=0.03,
        fresnel0=0.04,
    )


def part_material(model: ObjectModel) -> Material:
    """Plastic of its colour when the mesh has one; chrome for screws (as ROBI's are); bare
    machined metal otherwise."""
    if has_colour(model):
        return plastic_of(model)
    return CHROME if "screw" in model.name else METAL


def random_material(rng: np.random.Generator) -> Material:
    """A material drawn from what factory parts are made of, for training renders of the shape
    family: bare machined metal, chrome, dark oxide or zinc, painted metal and coloured matte
    plastic, each with its gloss drawn too (linear RGB)."""
    kind = rng.choice(
        ["metal", "chrome", "oxide", "painted", "plastic"], p=[0.3, 0.15, 0.15, 0.15, 0.25]
    )
    if kind == "metal":
        grey = rng.uniform(0.45, 0.8)
        tint = rng.uniform(-0.04, 0.04, 3)
        return Material(
            color=tuple(float(c) for c in np.clip(grey + tint, 0, 1)),
            diffuse=float(rng.uniform(0.15, 0.45)),
            specular=float(rng.uniform(0.5, 1.0)),
            shininess=float(rng.uniform(20, 90)),
            reflect=float(rng.uniform(0.3, 0.7)),
            fresnel0=float(rng.uniform(0.4, 0.7)),
        )
    if kind == "chrome":
        return Material(
            color=(0.8, 0.8, 0.82),
            diffuse=float(rng.uniform(0.05, 0.12)),
            specular=float(rng.uniform(0.9, 1.3)),
            shininess=float(rng.uniform(80, 160)),
            reflect=float(rng.uniform(0.75, 0.9)),
            fresnel0=float(rng.uniform(0.6, 0.8)),
        )
    if kind == "oxide":
        grey = rng.uniform(0.04, 0.15)
        return Material(
            color=(float(grey), float(grey), float(grey * rng.uniform(0.9, 1.1))),
            diffuse=float(rng.uniform(0.5, 0.8)),
            specular=float(rng.uniform(0.2, 0.6)),
            shininess=float(rng.uniform(15, 50)),
            reflect=float(rng.uniform(0.05, 0.2)),
            fresnel0=float(rng.uniform(0.04, 0.2)),
        )
    colour = rng.uniform(0.02, 0.8, 3) ** 1.5
    glossy = kind == "painted"
    return Material(
        color=tuple(float(c) for c in colour),
        diffuse=float(rng.uniform(0.7, 0.95)),
        specular=float(rng.uniform(0.2, 0.6) if glossy else rng.uniform(0.02, 0.3)),
        shininess=float(rng.uniform(20, 60) if glossy else rng.uniform(5, 30)),
        reflect=float(rng.uniform(0.02, 0.1) if glossy else 0.0),
        fresnel0=0.04,
    )
