"""Files shipped with the project, found beside the packages in a checkout: the procedural
catalog, the front end trained on it and the demo recording. Read-only defaults: nothing
writes here unless told to explicitly."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# The procedural catalog committed with the project.
DEFAULT_CATALOG = str(REPO / "catalogs" / "robi_like")
# The front end trained on it.
DEFAULT_MODEL = str(REPO / "models" / "robi_like.onnx")
# The demo recording (3 bin scenes x 8 views of the catalog, with their ground truth).
DEFAULT_RECORDING = str(REPO / "recordings" / "demo.mcap")
