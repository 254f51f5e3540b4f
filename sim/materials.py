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
