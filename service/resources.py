"""Files shipped with the project: the procedural catalog, the front end trained on it and the
demo recording. They are package data of ``posefuse`` (``catalogs/``, ``models/`` and
``recordings/`` at the root of the package), found through ``importlib.resources``: in a
checkout (``pip install -e .``) the folders of the repository, in an installed wheel those
under ``site-packages/posefuse/``. Read-only defaults: nothing writes here unless told to
explicitly."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def shipped(*parts: str) -> Path:
    """The path of a shipped file or folder (``shipped("models", "robi_like.onnx")``). pip
    installs a wheel unpacked, so every resource is a plain file on disk; the models' crop
    networks and cards are found beside them by name."""
    return Path(str(files("posefuse").joinpath(*parts)))


# The procedural catalog committed with the project.
DEFAULT_CATALOG = str(shipped("catalogs", "robi_like"))
# The front end trained on it (its card, crop model and checkpoint beside it in models/).
DEFAULT_MODEL = str(shipped("models", "robi_like.onnx"))
# The generalist front end, trained on the procedural part family (``posefuse catalog
# --family``) to say "a part" of any shape; onboarding starts from its checkpoint when shipped.
GENERALIST_MODEL = str(shipped("models", "generalist.onnx"))
# The demo recording (3 bin scenes x 8 views of the catalog, with their ground truth).
DEFAULT_RECORDING = str(shipped("recordings", "demo.mcap"))
